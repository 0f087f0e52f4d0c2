//! A group of processes started by a launcher (Slurm's `srun`, `mpirun`, `torchrun`): where
//! this process sits in it, read from the launcher's environment, and the rendezvous that
//! carries NCCL's unique id from rank 0 to the others: a file on a filesystem every rank
//! sees (the run directory's, which resuming needs shared anyway).
//!
//! Nothing here touches a GPU: the tests run it on the CPU.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::train::TrainError;

/// This process's place in a launched group.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Launch {
    pub rank: usize,
    pub size: usize,
    /// Rank among the processes of this machine: the GPU this process takes.
    pub local_rank: usize,
    /// Which launcher's variables said so.
    pub launcher: &'static str,
    /// What tells this job from an earlier one on the same run directory, if the launcher
    /// says (names the default rendezvous file).
    pub job: Option<String>,
}

/// The variables of each launcher: rank, size, local rank, then those naming the job.
const LAUNCHERS: [(&str, [&str; 3], &[&str]); 4] = [
    (
        "torchrun",
        ["RANK", "WORLD_SIZE", "LOCAL_RANK"],
        &["TORCHELASTIC_RUN_ID", "MASTER_ADDR", "MASTER_PORT"],
    ),
    (
        "Slurm",
        ["SLURM_PROCID", "SLURM_NTASKS", "SLURM_LOCALID"],
        &["SLURM_JOB_ID", "SLURM_STEP_ID"],
    ),
    (
        "Open MPI",
        [
            "OMPI_COMM_WORLD_RANK",
            "OMPI_COMM_WORLD_SIZE",
            "OMPI_COMM_WORLD_LOCAL_RANK",
        ],
        &["OMPI_MCA_orte_ess_jobid", "PMIX_NAMESPACE"],
    ),
    (
        "MPICH",
        ["PMI_RANK", "PMI_SIZE", "MPI_LOCALRANKID"],
        &["PMI_JOBID"],
    ),
];

impl Launch {
    /// From the environment read by `var` (the first launcher whose rank and size are set).
    /// Refused when none is, or when what they say is inconsistent.
    pub fn from_env(var: impl Fn(&str) -> Option<String>) -> Result<Self, TrainError> {
        for (launcher, [rank, size, local], job) in LAUNCHERS {
            let (Some(r), Some(s)) = (var(rank), var(size)) else {
                continue;
            };
            let num = |name: &str, v: &str| {
                v.trim().parse::<usize>().map_err(|_| {
                    TrainError::Config(format!(
                        "{launcher}: {name}={v:?} is not a non-negative integer"
                    ))
                })
            };
            let (rank_n, size_n) = (num(rank, &r)?, num(size, &s)?);
            let local_n = match var(local) {
                Some(l) => num(local, &l)?,
                None => 0,
            };
            if size_n == 0 || rank_n >= size_n {
                return Err(TrainError::Config(format!(
                    "{launcher}: {rank}={rank_n} is not a rank of {size}={size_n}"
                )));
            }
            let parts: Vec<String> = job.iter().filter_map(|k| var(k)).collect();
            return Ok(Self {
                rank: rank_n,
                size: size_n,
                local_rank: local_n,
                launcher,
                job: (!parts.is_empty()).then(|| parts.join("-")),
            });
        }
        let names: Vec<String> = LAUNCHERS
            .iter()
            .map(|(l, [r, s, _], _)| format!("{r}/{s} ({l})"))
            .collect();
        Err(TrainError::Config(format!(
            "--distributed: no launcher's rank and size in the environment (expected {})",
            names.join(", ")
        )))
    }

    /// The rendezvous file of this job in run directory `out` (`.rendezvous-<job>`); refused
    /// when the launcher names no job (pass `--rendezvous FILE`, a new path per job).
    pub fn default_rendezvous(&self, out: &Path) -> Result<PathBuf, TrainError> {
        let Some(job) = &self.job else {
            return Err(TrainError::Config(format!(
                "--distributed: {} names no job to tell this one's rendezvous from an earlier \
                 one's; pass --rendezvous FILE (a new path per job, on a filesystem every rank sees)",
                self.launcher
            )));
        };
        let safe: String = job
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        Ok(out.join(format!(".rendezvous-{safe}")))
    }
}

/// The first line of a rendezvous file.
const MAGIC: &str = "pma-rendezvous 1";

/// What rank 0 publishes: the group's size, a payload (NCCL's id) or why it could not start.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Posted {
    Ready { size: usize, payload: Vec<u8> },
    Refused(String),
}

/// Rank 0: write `posted` to `path` atomically (a rank never reads half a file).
pub fn publish(path: &Path, posted: &Posted) -> Result<(), TrainError> {
    let text = match posted {
        Posted::Ready { size, payload } => {
            let hex: String = payload.iter().map(|b| format!("{b:02x}")).collect();
            format!("{MAGIC}\nsize {size}\nid {hex}\n")
        }
        Posted::Refused(why) => format!("{MAGIC}\nrefused {}\n", why.replace('\n', " ")),
    };
    crate::train::write_atomic(path, text.as_bytes())
}

/// Ranks other than 0: wait up to `timeout` for `path`, then read what rank 0 posted.
pub fn wait(path: &Path, timeout: Duration) -> Result<Posted, TrainError> {
    let start = Instant::now();
    loop {
        match std::fs::read_to_string(path) {
            Ok(text) => return parse(path, &text),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(pma_data::FileError::read(path, e).into()),
        }
        if start.elapsed() >= timeout {
            return Err(TrainError::Config(format!(
                "{}: rank 0 did not post the group's rendezvous within {} s (is it running, on the \
                 same --out and filesystem?)",
                path.display(),
                timeout.as_secs()
            )));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn parse(path: &Path, text: &str) -> Result<Posted, TrainError> {
    let bad = || {
        TrainError::Config(format!(
            "{}: not a rendezvous file of this pma ({MAGIC:?} and a size and id expected)",
            path.display()
        ))
    };
    let mut lines = text.lines();
    if lines.next() != Some(MAGIC) {
        return Err(bad());
    }
    let second = lines.next().ok_or_else(bad)?;
    if let Some(why) = second.strip_prefix("refused ") {
        return Ok(Posted::Refused(why.to_string()));
    }
    let size = second
        .strip_prefix("size ")
        .and_then(|s| s.parse().ok())
        .ok_or_else(bad)?;
    let hex = lines
        .next()
        .and_then(|l| l.strip_prefix("id "))
        .ok_or_else(bad)?;
    if hex.len() % 2 != 0 {
        return Err(bad());
    }
    let payload = (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16))
        .collect::<Result<Vec<u8>, _>>()
        .map_err(|_| bad())?;
    Ok(Posted::Ready { size, payload })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn env(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let map: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| map.get(k).cloned()
    }

    #[test]
    fn each_launchers_variables_are_read() {
        let t = Launch::from_env(env(&[
            ("RANK", "3"),
            ("WORLD_SIZE", "16"),
            ("LOCAL_RANK", "3"),
            ("MASTER_ADDR", "node1"),
            ("MASTER_PORT", "29500"),
        ]))
        .unwrap();
        assert_eq!(
            (t.rank, t.size, t.local_rank, t.launcher),
            (3, 16, 3, "torchrun")
        );
        assert_eq!(t.job.as_deref(), Some("node1-29500"));
        let s = Launch::from_env(env(&[
            ("SLURM_PROCID", "9"),
            ("SLURM_NTASKS", "16"),
            ("SLURM_LOCALID", "1"),
            ("SLURM_JOB_ID", "4711"),
            ("SLURM_STEP_ID", "0"),
        ]))
        .unwrap();
        assert_eq!(
            (s.rank, s.size, s.local_rank, s.launcher),
            (9, 16, 1, "Slurm")
        );
        let dir = Path::new("/runs/a");
        assert_eq!(
            s.default_rendezvous(dir).unwrap(),
            dir.join(".rendezvous-4711-0")
        );
        let m = Launch::from_env(env(&[
            ("OMPI_COMM_WORLD_RANK", "0"),
            ("OMPI_COMM_WORLD_SIZE", "2"),
        ]))
        .unwrap();
        assert_eq!(
            (m.rank, m.size, m.local_rank, m.launcher),
            (0, 2, 0, "Open MPI")
        );
        assert!(m.default_rendezvous(dir).is_err(), "no job named");
    }

    #[test]
    fn missing_or_inconsistent_variables_are_refused() {
        for pairs in [
            &[][..],
            &[("RANK", "2"), ("WORLD_SIZE", "2")][..],
            &[("RANK", "x"), ("WORLD_SIZE", "2")][..],
            &[("SLURM_PROCID", "0"), ("SLURM_NTASKS", "0")][..],
        ] {
            let e = Launch::from_env(env(pairs)).unwrap_err();
            assert!(matches!(e, TrainError::Config(_)), "{e}");
        }
    }

    #[test]
    fn a_posted_id_reaches_the_other_ranks_and_so_does_a_refusal() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(".rendezvous-1");
        let id: Vec<u8> = (0..128).map(|i| (i * 7) as u8).collect();
        let readers: Vec<_> = (0..3)
            .map(|_| {
                let p = path.clone();
                std::thread::spawn(move || wait(&p, Duration::from_secs(20)))
            })
            .collect();
        std::thread::sleep(Duration::from_millis(150));
        let posted = Posted::Ready {
            size: 4,
            payload: id.clone(),
        };
        publish(&path, &posted).unwrap();
        for r in readers {
            assert_eq!(r.join().unwrap().unwrap(), posted);
        }
        let refused = Posted::Refused("the run directory is locked\nby PID 1".into());
        publish(&path, &refused).unwrap();
        assert_eq!(
            wait(&path, Duration::from_secs(1)).unwrap(),
            Posted::Refused("the run directory is locked by PID 1".into())
        );
        std::fs::write(&path, "something else\n").unwrap();
        assert!(wait(&path, Duration::from_secs(1)).is_err());
        let start = Instant::now();
        let e = wait(&dir.path().join("never"), Duration::from_millis(300)).unwrap_err();
        assert!(e.to_string().contains("did not post"), "{e}");
        assert!(start.elapsed() < Duration::from_secs(5));
    }
}
