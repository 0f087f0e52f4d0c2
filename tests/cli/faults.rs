//! Fault injection: every way a run was lost, a machine taken down or an error misreported
//! is reproduced at small scale (the `tiny` preset on a 24 px synthetic scene) and must now
//! end cleanly: full disks (a 3 MB tmpfs where the test can mount one, and
//! `PMA_FSIO_FAIL_AFTER`, the atomic writer's injected write error, everywhere), `kill -9`
//! at random points while checkpointing, two trainers on one run directory, outputs naming
//! inputs, FIFOs and devices as inputs, unbounded sizes and flags, signals, and refusals
//! that must be one line with exit status 2.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

#[cfg(unix)]
use crate::run::mkfifo;
use crate::run::{exits, kill, ok, pma_env, pma_within, refused, s, tiny_scene, wait_for};
use crate::train::newest;

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Stopped by a signal: exit status `code`, the needles in the last stderr line (the
/// handler's "stopping" notice comes before it), no panic.
fn interrupted(out: &Output, code: i32, needles: &[&str]) {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "expected exit {code}: {err}");
    let last = err.trim_end().lines().last().unwrap_or("");
    for n in needles {
        assert!(last.contains(n), "last stderr line lacks {n:?}: {err}");
    }
    assert!(!err.contains("panicked"), "{err}");
}

/// `preset = "tiny"` with a checkpoint after every iteration.
fn ck1(dir: &Path) -> PathBuf {
    let p = dir.join("ck1.toml");
    std::fs::write(&p, "preset = \"tiny\"\n[train]\nckpt_every = 1\n").unwrap();
    p
}

fn train_cmd(data: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let mut v: Vec<String> = ["train", "--workers", "1", "--quiet", "--data", s(data)]
        .iter()
        .chain(&["--out", s(out)])
        .map(|x| x.to_string())
        .collect();
    v.extend(extra.iter().map(|x| x.to_string()));
    v
}

fn run(args: &[String], env: &[(&str, &str)]) -> Output {
    pma_env(&args.iter().map(String::as_str).collect::<Vec<_>>(), env)
}

/// `pma train --data DATA --out OUT EXTRA...` (see [`train_cmd`]), ended within 60 s.
fn train_within(data: &Path, out: &Path, extra: &[&str]) -> Output {
    let args = train_cmd(data, out, extra);
    pma_within(&args.iter().map(String::as_str).collect::<Vec<_>>(), 60)
}

/// [`train_within`] refused: exit 2, one line holding every needle.
fn train_refused(data: &Path, out: &Path, extra: &[&str], needles: &[&str]) {
    refused(&train_within(data, out, extra), needles);
}

/// A fresh run in `out` with the `cfg` from [`ck1`], up to `iters`; it must succeed.
fn train_ck1(data: &Path, cfg: &Path, out: &Path, iters: &str) {
    ok(run(
        &train_cmd(data, out, &["--config", s(cfg), "--iters", iters]),
        &[],
    ));
}

/// `--resume` of the run in `out` up to `iters`, with `env`.
fn resume(data: &Path, out: &Path, iters: &str, env: &[(&str, &str)]) -> Output {
    run(&train_cmd(data, out, &["--resume", "--iters", iters]), env)
}

/// In `tmp`: a tiny scene, the [`ck1`] config, and the model of a run straight to `iters`,
/// which a resumed run must end with byte for byte.
fn straight_run(tmp: &Path, iters: &str) -> (PathBuf, PathBuf, Vec<u8>) {
    let data = tiny_scene(&tmp.join("scene"), 2);
    let cfg = ck1(tmp);
    let straight = tmp.join("straight");
    train_ck1(&data, &cfg, &straight, iters);
    let want = std::fs::read(straight.join("model.safetensors")).unwrap();
    (data, cfg, want)
}

fn spawn(args: &[String]) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// A small xorshift generator: the loops' random choices, reproducible from the printed seed.
struct Rng(u64);

impl Rng {
    fn from_time() -> Self {
        let seed = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos() as u64
            | 1;
        eprintln!("fault-injection seed {seed}");
        Rng(seed)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0 % n.max(1)
    }
}

/// A small SMPL-parameter motion (4 frames).
fn smpl_motion(path: &Path) {
    use pma_data::dataset::npz::{MemberData, NpzWriter};
    let mut w = NpzWriter::new(std::fs::File::create(path).unwrap(), false, "m");
    w.add("poses", &[4, 72], MemberData::F32(&[0.1; 4 * 72]))
        .unwrap();
    w.add("trans", &[4, 3], MemberData::F32(&[0.0; 12]))
        .unwrap();
    w.finish().unwrap();
}

/// A trained `tiny` model (one iteration) and its run directory.
fn tiny_model(dir: &Path, data: &Path) -> PathBuf {
    let run_dir = dir.join("model_run");
    ok(run(
        &train_cmd(data, &run_dir, &["--preset", "tiny", "--iters", "1"]),
        &[],
    ));
    run_dir.join("model.safetensors")
}

/// A temporary directory with a tiny scene (`scene/`) and a model trained on it
/// ([`tiny_model`]): the training split's path and the model's.
fn scene_and_model() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let model = tiny_model(tmp.path(), &data);
    (tmp, data, model)
}

/// Copies a safetensors file, editing its metadata and its data bytes.
fn rewrite_safetensors(
    from: &Path,
    to: &Path,
    edit_meta: impl FnOnce(&mut serde_json::Map<String, serde_json::Value>),
    edit_data: impl FnOnce(&serde_json::Value, &mut [u8]),
) {
    let bytes = std::fs::read(from).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let mut data = bytes[8 + n..].to_vec();
    edit_data(&header, &mut data);
    edit_meta(header["__metadata__"].as_object_mut().unwrap());
    let mut h = serde_json::to_vec(&header).unwrap();
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.extend_from_slice(&data);
    std::fs::write(to, out).unwrap();
}

/// Edits the model config JSON held in a pma checkpoint's metadata.
fn with_config(from: &Path, to: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    rewrite_safetensors(
        from,
        to,
        |meta| {
            let mut cfg: serde_json::Value =
                serde_json::from_str(meta["config"].as_str().unwrap()).unwrap();
            edit(&mut cfg);
            meta.insert("config".into(), cfg.to_string().into());
        },
        |_, _| {},
    );
}

/// Case 1: a full disk while checkpointing (and a crash between the pair's files) never
/// leaves a run that `--resume` refuses; the resumed run continues bit for bit.
#[test]
fn checkpoints_survive_a_full_disk() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, cfg, want) = straight_run(tmp.path(), "6");
    // Budgets from nothing to more than one checkpoint: every cut lands somewhere else in
    // the model, the state, the config, the log, the plot or the published model.
    let budgets = [
        0u64, 1, 4_000, 60_000, 120_000, 200_000, 330_000, 520_000, 900_000,
    ];
    let mut failed = 0;
    for (k, budget) in budgets.iter().enumerate() {
        let out = tmp.path().join(format!("run{k}"));
        train_ck1(&data, &cfg, &out, "3");
        let full = resume(
            &data,
            &out,
            "6",
            &[("PMA_FSIO_FAIL_AFTER", &budget.to_string())],
        );
        if !full.status.success() {
            failed += 1;
            exits(&full, 1, &["No space left on device"]);
        }
        ok(resume(&data, &out, "6", &[]));
        assert_eq!(
            std::fs::read(out.join("model.safetensors")).unwrap(),
            want,
            "budget {budget}: the resumed run differs from the straight one"
        );
    }
    assert!(failed >= 5, "only {failed} budgets hit the full disk");
    tmpfs_full_disk(tmp.path(), &data, &cfg, &want);
}

/// The issue's reproduction where a small filesystem can be mounted (root): the run lives on
/// a 3 MB tmpfs filled up to ~150 KB free.
fn tmpfs_full_disk(tmp: &Path, data: &Path, cfg: &Path, want: &[u8]) {
    let mnt = tmp.join("tmpfs");
    std::fs::create_dir_all(&mnt).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=3m", "tmpfs", s(&mnt)])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|st| st.success());
    if !mounted {
        eprintln!("tmpfs: cannot mount here (not root?); the injected full disk covers it");
        return;
    }
    struct Unmount<'a>(&'a Path);
    impl Drop for Unmount<'_> {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg(self.0).status();
        }
    }
    let _guard = Unmount(&mnt);
    let out = mnt.join("run");
    train_ck1(data, cfg, &out, "3");
    // Fill the disk up to ~150 KB free.
    let free = || {
        let o = Command::new("df")
            .args(["-B1", "--output=avail", s(&mnt)])
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .nth(1)
            .unwrap()
            .trim()
            .parse::<u64>()
            .unwrap()
    };
    let filler = mnt.join("filler");
    std::fs::write(&filler, vec![0u8; free().saturating_sub(150_000) as usize]).unwrap();
    let full = resume(data, &out, "6", &[]);
    exits(&full, 1, &["No space left on device"]);
    std::fs::remove_file(&filler).unwrap();
    ok(resume(data, &out, "6", &[]));
    assert_eq!(std::fs::read(out.join("model.safetensors")).unwrap(), want);
    eprintln!("tmpfs: full disk at ~150 KB free: exit 1, then resumed bit for bit");
}

/// Case 1: `kill -9` at random points, half of them while a checkpoint is being written;
/// every killed run resumes (or, killed before its first checkpoint, starts afresh) and
/// ends bit for bit where a run that was never killed ends.
#[test]
fn kill_9_while_checkpointing_never_leaves_a_run_unresumable() {
    const TRIES: usize = 32;
    const ITERS: &str = "8";
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let cfg = ck1(tmp.path());
    let straight = tmp.path().join("straight");
    let t0 = Instant::now();
    train_ck1(&data, &cfg, &straight, ITERS);
    let run_ms = t0.elapsed().as_millis() as u64;
    let want = std::fs::read(straight.join("model.safetensors")).unwrap();
    let mut rng = Rng::from_time();
    let (mut mid_checkpoint, mut before_first, mut finished, mut unresumable) = (0, 0, 0, 0);
    for i in 0..TRIES {
        let out = tmp.path().join(format!("k{i}"));
        let mut child = spawn(&train_cmd(
            &data,
            &out,
            &["--config", s(&cfg), "--iters", ITERS],
        ));
        let deadline = Instant::now() + Duration::from_secs(120);
        let until = |ready: &dyn Fn() -> bool, child: &mut std::process::Child| {
            while !ready() && Instant::now() < deadline {
                if child.try_wait().unwrap().is_some() {
                    return;
                }
                std::thread::sleep(Duration::from_micros(200));
            }
        };
        let complete =
            || pma_model::network::run_dir::newest_checkpoint(&out).is_ok_and(|c| c.is_some());
        let writing = || {
            std::fs::read_dir(&out).is_ok_and(|r| {
                r.filter_map(Result::ok)
                    .any(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
            })
        };
        match i % 4 {
            // Anywhere in the run (start-up included).
            0 => std::thread::sleep(Duration::from_millis(rng.below(run_ms))),
            // Anywhere once training runs.
            1 => {
                until(&complete, &mut child);
                std::thread::sleep(Duration::from_millis(rng.below(run_ms / 2)));
            }
            // Inside the first checkpoint's transaction.
            2 => until(&writing, &mut child),
            // Inside a later one (publishing the model, removing older checkpoints).
            _ => {
                until(&complete, &mut child);
                std::thread::sleep(Duration::from_millis(rng.below(run_ms / 4)));
                until(&writing, &mut child);
            }
        }
        if i % 4 >= 2 {
            std::thread::sleep(Duration::from_micros(rng.below(3000)));
        }
        let _ = child.kill();
        let st = child.wait().unwrap();
        if st.success() {
            finished += 1;
        }
        let left_tmp = std::fs::read_dir(&out).is_ok_and(|r| {
            r.filter_map(Result::ok)
                .any(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        });
        if left_tmp {
            mid_checkpoint += 1;
        }
        let has_ckpt = pma_model::network::run_dir::newest_checkpoint(&out)
            .unwrap()
            .is_some();
        let again = if has_ckpt {
            resume(&data, &out, ITERS, &[])
        } else {
            before_first += 1;
            run(
                &train_cmd(&data, &out, &["--config", s(&cfg), "--iters", ITERS]),
                &[],
            )
        };
        let same = std::fs::read(out.join("model.safetensors")).ok().as_deref() == Some(&want[..]);
        if !again.status.success() || !same {
            unresumable += 1;
            eprintln!("try {i}: not resumed bit for bit: {}", stderr(&again));
        }
    }
    eprintln!(
        "kill -9 loop: {TRIES} tried, {mid_checkpoint} killed with a checkpoint half-written, \
         {before_first} before the first checkpoint, {finished} finished before the kill, \
         {unresumable} unresumable"
    );
    assert_eq!(unresumable, 0);
    assert!(mid_checkpoint > 0, "no kill landed inside a checkpoint");
}

/// Case 2: a second trainer on the same run directory is refused naming the holder's PID,
/// and the lock of a killed trainer does not block.
#[test]
fn one_trainer_per_run_directory() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let cfg = ck1(tmp.path());
    let out = tmp.path().join("run");
    let mut first = spawn(&train_cmd(
        &data,
        &out,
        &["--config", s(&cfg), "--iters", "100000", "--seed", "1"],
    ));
    wait_for("a first checkpoint", 120, || {
        pma_model::network::run_dir::newest_checkpoint(&out).is_ok_and(|c| c.is_some())
    });
    let second = run(
        &train_cmd(
            &data,
            &out,
            &["--config", s(&cfg), "--iters", "4", "--seed", "2"],
        ),
        &[],
    );
    refused(&second, &["in use", &format!("PID {}", first.id())]);
    let resumed = run(&train_cmd(&data, &out, &["--resume", "--iters", "4"]), &[]);
    refused(&resumed, &[&format!("PID {}", first.id())]);
    first.kill().unwrap();
    first.wait().unwrap();
    // flock dies with its process: the killed trainer's lock is gone.
    let it = pma_model::network::run_dir::newest_checkpoint(&out)
        .unwrap()
        .unwrap()
        .iteration;
    let target = (it + 1).to_string();
    ok(run(
        &train_cmd(&data, &out, &["--resume", "--iters", &target]),
        &[],
    ));
    let seed = std::fs::read_to_string(newest(&out).join("config.toml")).unwrap();
    assert!(seed.contains("seed = 1"), "{seed}");
}

/// Case 3: no command may write over one of its inputs, whatever the spelling (another
/// path, a hard link); the input is left as it was.
#[test]
fn outputs_never_overwrite_inputs() {
    let (tmp, data, model) = scene_and_model();
    let dir = tmp.path();
    let before = std::fs::read(&model).unwrap();
    let other_spelling = model.parent().unwrap().join(".").join("model.safetensors");
    let link = dir.join("link.safetensors");
    std::fs::hard_link(&model, &link).unwrap();
    let motion = dir.join("motion.npz");
    std::fs::copy(&data, &motion).unwrap();
    let th = dir.join("c.th");
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/convert/tiny_views.th"),
        &th,
    )
    .unwrap();
    let th_before = std::fs::read(&th).unwrap();
    let smpl = dir.join("smpl.npz");
    smpl_motion(&smpl);
    let smpl_before = std::fs::read(&smpl).unwrap();
    let scene = dir.join("scene");
    for args in [
        vec![
            "mesh",
            "--model",
            s(&model),
            "--out",
            s(&model),
            "--res",
            "8",
        ],
        vec!["mesh", "--model", s(&model), "--out", s(&other_spelling)],
        vec!["mesh", "--model", s(&link), "--out", s(&model)],
        vec![
            "mesh",
            "--model",
            s(&model),
            "--poses",
            s(&motion),
            "--out",
            s(&motion),
        ],
        vec![
            "mesh",
            "--model",
            s(&model),
            "-o",
            s(&dir.join("m.ply")),
            "--preview",
            s(&model),
        ],
        vec![
            "eval",
            "--model",
            s(&model),
            "--data",
            s(&scene),
            "--freq-png",
            s(&model),
        ],
        vec![
            "forward",
            "--model",
            s(&model),
            "--batch",
            s(&motion),
            "--out",
            s(&motion),
        ],
        vec!["convert", "dataset", s(&motion), "-o", s(&motion)],
        vec!["convert", "checkpoint", s(&th), "-o", s(&th)],
        vec!["convert", "motion", s(&smpl), "-o", s(&smpl)],
    ] {
        refused(&pma_env(&args, &[]), &["would overwrite the input"]);
    }
    // A fresh run would write its resolved config over the TOML it was given.
    let fresh = dir.join("fresh");
    std::fs::create_dir_all(&fresh).unwrap();
    let user_cfg = fresh.join("config.toml");
    std::fs::write(&user_cfg, "preset = \"tiny\"\n").unwrap();
    train_refused(
        &data,
        &fresh,
        &["--config", s(&user_cfg)],
        &["would overwrite the input --config"],
    );
    assert_eq!(std::fs::read(&user_cfg).unwrap(), b"preset = \"tiny\"\n");
    assert_eq!(std::fs::read(&model).unwrap(), before, "the model changed");
    assert_eq!(
        std::fs::read(&th).unwrap(),
        th_before,
        "the checkpoint changed"
    );
    assert_eq!(
        std::fs::read(&smpl).unwrap(),
        smpl_before,
        "the motion changed"
    );
    assert_eq!(
        std::fs::read(&motion).unwrap(),
        std::fs::read(&data).unwrap()
    );
}

/// Case 6: FIFOs, devices and directories as inputs are refused at once (no hang, no
/// endless read).
#[cfg(unix)]
#[test]
fn fifos_devices_and_directories_are_refused_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let data = tiny_scene(&dir.join("scene"), 2);
    let fifo = |name: &str| {
        let p = dir.join(name);
        mkfifo(&p);
        p
    };
    let (npz, st, th, png, toml) = (
        fifo("f.npz"),
        fifo("f.safetensors"),
        fifo("f.th"),
        fifo("f.png"),
        fifo("f.toml"),
    );
    let scene = dir.join("scene");
    let o = dir.join("o");
    std::fs::create_dir_all(&o).unwrap();
    let cases: Vec<Vec<String>> = vec![
        vec!["inspect", s(&npz)],
        vec!["inspect", s(&scene)],
        vec!["eval", "--model", s(&st), "--data", s(&scene)],
        vec!["eval", "--model", "/dev/zero", "--data", s(&scene)],
        vec!["mesh", "--model", s(&st), "-o", "/tmp/never.ply"],
        vec!["convert", "dataset", s(&npz), "-o", "/tmp/never.npz"],
        vec![
            "convert",
            "checkpoint",
            s(&th),
            "-o",
            "/tmp/never.safetensors",
        ],
        vec!["convert", "motion", s(&npz), "-o", "/tmp/never.npz"],
        vec!["metrics", s(&png), s(&png)],
    ]
    .into_iter()
    .map(|v| v.into_iter().map(String::from).collect())
    .chain([
        train_cmd(&npz, &o.join("r1"), &["--preset", "tiny"]),
        train_cmd(&data, &o.join("r2"), &["--config", s(&toml)]),
        train_cmd(&data, &o.join("r3"), &["--config", "/dev/zero"]),
    ])
    .collect();
    for args in cases {
        let out = pma_within(&args.iter().map(String::as_str).collect::<Vec<_>>(), 60);
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(
            err.contains("FIFO") || err.contains("device") || err.contains("directory"),
            "{args:?}: {err}"
        );
    }
}

/// Cases 5 and 7: sizes from files and flags are bounded before anything is allocated.
#[test]
fn unbounded_sizes_and_flags_are_refused_before_allocating() {
    let (tmp, data, model) = scene_and_model();
    let dir = tmp.path();
    let deep = dir.join("deep.safetensors");
    with_config(&model, &deep, |c| {
        c["trunk_depth"] = 1_000_000_000u64.into()
    });
    for args in [
        vec!["eval", "--model", s(&deep), "--data", s(&dir.join("scene"))],
        vec!["mesh", "--model", s(&deep), "-o", s(&dir.join("m.ply"))],
        vec!["inspect", s(&deep)],
    ] {
        refused(
            &pma_within(&args, 60),
            &["deep.safetensors", "trunk_depth", "over the limit"],
        );
    }
    for (body, key) in [
        ("[model]\ntrunk_width = 1000000\n", "trunk_width"),
        ("[model]\nn_samples = 1000000000\n", "n_samples"),
        ("[train]\nrays_per_step = 1000000000\n", "rays_per_step"),
    ] {
        let cfg = dir.join(format!("{key}.toml"));
        std::fs::write(&cfg, format!("preset = \"tiny\"\n{body}")).unwrap();
        let out = dir.join(format!("r_{key}"));
        train_refused(
            &data,
            &out,
            &["--config", s(&cfg)],
            &[key, "over the limit"],
        );
    }
    let motion = dir.join("motion.npz");
    std::fs::copy(&data, &motion).unwrap();
    let r = dir.join("r");
    for (args, needle) in [
        (
            vec![
                "render",
                "--model",
                s(&model),
                "--camera",
                "bullet",
                "--views",
                "1000000000",
                "--out",
                s(&dir.join("b")),
            ],
            "--views",
        ),
        (
            vec![
                "convert",
                "motion",
                s(&motion),
                "-o",
                s(&dir.join("m.npz")),
                "--fps",
                "1000000",
            ],
            "--fps",
        ),
        (vec!["--workers", "20000", "inspect", s(&data)], "--workers"),
        (
            vec![
                "eval",
                "--model",
                s(&model),
                "--data",
                s(&dir.join("scene")),
                "--chunk",
                "1000000000",
            ],
            "--chunk",
        ),
    ] {
        refused(&pma_within(&args, 60), &[needle]);
    }
    // Flags of a run: the value named as given, short (1e300, not 300 digits).
    for (flag, needles) in [
        ("--minutes=1e300", ["--minutes 1e300", "(0, 1000000]"]),
        ("--minutes=-1", ["--minutes -1", "(0, 1000000]"]),
        ("--minutes=nan", ["--minutes NaN", "(0, 1000000]"]),
        (
            "--iters=18446744073709551615",
            ["--iters 18446744073709551615", "at most 1000000000000"],
        ),
        (
            "--seed=18446744073709551615",
            ["--seed 18446744073709551615", "at most 9223372036854775807"],
        ),
    ] {
        let out = train_within(&data, &r, &["--preset", "tiny", flag]);
        let err = stderr(&out);
        assert!(err.len() < 200, "{flag}: {err}");
        refused(&out, &needles);
        assert!(!r.exists(), "{flag}: the refused run left {}", r.display());
    }
}

/// Case 8: SIGTERM and SIGHUP stop a run like Ctrl-C: a checkpoint, exit 143/129, a run
/// that resumes; a resumed run removes the temporaries an interrupted checkpoint left.
#[cfg(unix)]
#[test]
fn sigterm_and_sighup_checkpoint_like_ctrl_c() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    for (sig, code) in [("-TERM", 143), ("-HUP", 129)] {
        let out = tmp.path().join(format!("run{code}"));
        let child = spawn(&train_cmd(
            &data,
            &out,
            &["--preset", "tiny", "--iters", "1000000"],
        ));
        wait_for("the first log row", 300, || out.join("log.csv").exists());
        kill(child.id(), sig);
        let o = child.wait_with_output().unwrap();
        interrupted(&o, code, &["interrupted at iteration"]);
        let done = pma_model::network::run_dir::newest_checkpoint(&out)
            .unwrap()
            .expect("a checkpoint")
            .iteration;
        // What a crash mid-checkpoint leaves: a temporary checkpoint and a temporary file.
        let stale_dir = out.join("ckpt-99999999.tmp");
        std::fs::create_dir_all(&stale_dir).unwrap();
        std::fs::write(stale_dir.join("model.safetensors"), b"partial").unwrap();
        std::fs::write(out.join(".pma-XXXXXX.tmp"), b"partial").unwrap();
        std::fs::write(out.join(".tmpAbC123"), b"partial").unwrap();
        let target = (done + 1).to_string();
        ok(run(
            &train_cmd(&data, &out, &["--resume", "--iters", &target]),
            &[],
        ));
        assert!(!stale_dir.exists() && !out.join(".pma-XXXXXX.tmp").exists());
        assert!(!out.join(".tmpAbC123").exists());
    }
}

/// Case 8: `convert dataset` stops on Ctrl-C (exit 130) and leaves no output or temporary.
#[cfg(unix)]
#[test]
fn convert_dataset_stops_on_ctrl_c_and_leaves_nothing() {
    use ndarray::{s as sl, Array1, Array3};
    use pma_data::dataset::{Compression, WriteOptions};
    use pma_data::synth::{plan, render_split, SynthConfig};
    let tmp = tempfile::tempdir().unwrap();
    let cfg = SynthConfig::small(64, 2, 1);
    let p = plan(&cfg).unwrap();
    let mut ds = render_split(&p, &p.splits[0], &mut || {}).unwrap();
    // Tiled to many images, so that a deflated conversion takes a while.
    let n = 6000;
    let hw = 64 * 64;
    let tile = |a: &Array3<u8>, ch: usize| {
        let mut t = Array3::<u8>::zeros((n, hw, ch));
        for i in 0..n {
            t.slice_mut(sl![i, .., ..])
                .assign(&a.slice(sl![i % 2, .., ..]));
        }
        t
    };
    ds.imgs = Some(tile(ds.imgs.as_ref().unwrap(), 3));
    ds.masks = Some(tile(ds.masks.as_ref().unwrap(), 1));
    ds.sampling_masks = Some(tile(ds.sampling_masks.as_ref().unwrap(), 1));
    let cams = ds.img_pose_indices.take().unwrap();
    ds.img_shape = Some([n, 64, 64, 3]);
    ds.kp_idxs = Some(Array1::zeros(n));
    ds.img_pose_indices = Some(Array1::from_iter((0..n).map(|i| cams[i % 2])));
    ds.bkgd_idxs = Some(Array1::zeros(n));
    let big = tmp.path().join("big.npz");
    ds.write(
        &big,
        &WriteOptions {
            compression: Compression::Stored,
        },
    )
    .unwrap();
    drop(ds);
    let out_dir = tmp.path().join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let out = out_dir.join("converted.npz");
    let child = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(["convert", "dataset", s(&big), "-o", s(&out), "--compress"])
        // A slow disk, so that the signal lands mid-write however fast the machine is.
        .env("PMA_FSIO_DELAY_US", "2000")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Signal once the temporary output exists: the handler is installed and writing began.
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::fs::read_dir(&out_dir).unwrap().next().is_none() {
        assert!(
            Instant::now() < deadline,
            "convert dataset never began writing"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let sent = Instant::now();
    kill(child.id(), "-INT");
    let o = child.wait_with_output().unwrap();
    let latency = sent.elapsed();
    interrupted(&o, 130, &["interrupted"]);
    eprintln!("convert dataset: exit 130 {latency:?} after SIGINT");
    let left: Vec<_> = std::fs::read_dir(&out_dir).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// Case 9: a full disk while an npz is written exits 1 with one line naming the file.
#[test]
fn failed_npz_writes_exit_1_with_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let data = tiny_scene(&dir.join("scene"), 2);
    let full = [("PMA_FSIO_FAIL_AFTER", "20000")];
    let synth = dir.join("synth");
    let out = pma_env(
        &["synth", "--out", s(&synth), "--res", "24", "--quiet"],
        &full,
    );
    exits(&out, 1, &["No space left on device", ".npz"]);
    let converted = dir.join("c.npz");
    let out = pma_env(
        &["convert", "dataset", s(&data), "-o", s(&converted)],
        &full,
    );
    exits(&out, 1, &["No space left on device", "c.npz"]);
    assert!(!converted.exists());
    let smpl = dir.join("smpl.npz");
    smpl_motion(&smpl);
    let motion = dir.join("m.npz");
    let out = pma_env(
        &["convert", "motion", s(&smpl), "-o", s(&motion)],
        &[("PMA_FSIO_FAIL_AFTER", "100")],
    );
    exits(&out, 1, &["No space left on device", "m.npz"]);
    assert!(!motion.exists());
    // A converted `.h5` goes through a scratch file: its failure names the output too.
    let h5 = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/convert/perfcap.h5");
    for budget in ["0", "100", "3000"] {
        let out_npz = dir.join(format!("h{budget}.npz"));
        let out = pma_env(
            &["convert", "dataset", s(&h5), "-o", s(&out_npz)],
            &[("PMA_FSIO_FAIL_AFTER", budget)],
        );
        exits(&out, 1, &["No space left on device", s(&out_npz)]);
        assert!(!stderr(&out).contains(".pma-"), "{}", stderr(&out));
        assert!(!out_npz.exists());
    }
}

/// A FIFO where a dataset or a model is expected is named as one, with what was expected,
/// by `eval`, `render` and `view` alike: given itself, or as a scene directory's split file.
#[cfg(unix)]
#[test]
fn fifos_are_named_as_fifos_with_what_was_expected() {
    let (tmp, _, model) = scene_and_model();
    let dir = tmp.path();
    let npz = dir.join("f.npz");
    mkfifo(&npz);
    let scene = dir.join("fifo_scene");
    std::fs::create_dir(&scene).unwrap();
    for split in ["train", "novel_view"] {
        mkfifo(&scene.join(format!("{split}.npz")));
    }
    let st = dir.join("f.safetensors");
    mkfifo(&st);
    let r = dir.join("r");
    let m = s(&model);
    for (args, needles) in [
        (
            vec!["eval", "--model", m, "--data", s(&npz)],
            vec!["f.npz: a FIFO", "expected a pma-npz file or a directory"],
        ),
        (
            vec!["render", "--model", m, "--data", s(&npz), "--out", s(&r)],
            vec!["f.npz: a FIFO", "expected a pma-npz file or a directory"],
        ),
        (
            vec!["view", m, "--data", s(&npz), "--port", "0"],
            vec!["f.npz: a FIFO", "expected a pma-npz file or a directory"],
        ),
        (
            vec!["eval", "--model", m, "--data", s(&scene)],
            vec!["novel_view.npz: a FIFO", "expected the novel_view split's"],
        ),
        (
            vec!["view", m, "--data", s(&scene), "--port", "0"],
            vec!["train.npz: a FIFO", "expected the train split's"],
        ),
        (
            vec!["view", s(&st), "--port", "0"],
            vec![
                "f.safetensors: a FIFO",
                "expected a model file or a run directory",
            ],
        ),
    ] {
        let out = pma_within(&args, 60);
        let err = stderr(&out);
        refused(&out, &needles);
        for wrong in ["does not exist", "directory without", "no such"] {
            assert!(!err.contains(wrong), "{args:?}: {err}");
        }
    }
    assert!(!r.exists(), "the refused render left {}", r.display());
}

/// A command that fails removes what it created and nothing that was there before: a
/// refused `train` its lock file and the run directory it made; a failed `synth`, `render`
/// or `eval` the output directories it made and left empty.
#[test]
fn failed_commands_remove_what_they_created_and_nothing_else() {
    let (tmp, data, model) = scene_and_model();
    let dir = tmp.path();
    // Refused after the lock is taken: the run's settings are checked under it.
    let refuse_train = |out: &Path| {
        train_refused(
            &data,
            out,
            &["--preset", "tiny", "--chunk-rays", "100000000"],
            &["chunk_rays", "over the limit"],
        )
    };
    let made = dir.join("new").join("run");
    refuse_train(&made);
    assert!(
        !dir.join("new").exists(),
        "a refused train left its directory"
    );
    let empty = dir.join("empty");
    std::fs::create_dir(&empty).unwrap();
    refuse_train(&empty);
    assert!(empty.is_dir(), "a directory that was there went");
    assert_eq!(
        std::fs::read_dir(&empty).unwrap().count(),
        0,
        "left the lock"
    );
    // A lock file that was there before (a run's) stays.
    let run_dir = model.parent().unwrap();
    let lock = run_dir.join(pma_model::network::run_dir::LOCK_FILE);
    assert!(lock.is_file());
    let out = train_within(&data, run_dir, &["--resume", "--chunk-rays", "100000000"]);
    refused(&out, &["chunk_rays"]);
    assert!(
        lock.is_file(),
        "a refused resume removed the run's lock file"
    );

    let full = [("PMA_FSIO_FAIL_AFTER", "100")];
    let scene = dir.join("scene");
    let (m, sc) = (s(&model), s(&scene));
    let kept = dir.join("kept");
    std::fs::create_dir(&kept).unwrap();
    std::fs::write(kept.join("mine.txt"), b"mine").unwrap();
    for out_dir in [dir.join("a").join("b"), kept.join("sub"), empty.clone()] {
        let o = s(&out_dir);
        for args in [
            vec!["synth", "--out", o, "--res", "24", "--quiet"],
            vec!["render", "--model", m, "--data", sc, "--out", o],
            vec!["eval", "--model", m, "--data", sc, "--out", o],
        ] {
            exits(&pma_env(&args, &full), 1, &["No space left on device"]);
            let left = dir.join("a").exists() || kept.join("sub").exists();
            assert!(!left, "{args:?} left the directory it made");
            assert!(
                empty.is_dir(),
                "{args:?} removed a directory that was there"
            );
        }
    }
    assert_eq!(std::fs::read(kept.join("mine.txt")).unwrap(), b"mine");
}

/// A way to damage a file.
type Damage = fn(&Path);

/// Cut `path` to half its length, as a disk error after the commit might.
fn truncate(path: &Path) {
    let f = std::fs::OpenOptions::new().write(true).open(path).unwrap();
    let len = f.metadata().unwrap().len();
    f.set_len(len / 2).unwrap();
}

/// Flip one byte near the end of `path` (in a checkpoint, tensor data).
fn flip_a_byte(path: &Path) {
    let mut bytes = std::fs::read(path).unwrap();
    let k = bytes.len() - 5;
    bytes[k] ^= 0xff;
    std::fs::write(path, bytes).unwrap();
}

/// The newest checkpoint's model or train state truncated or corrupted after its commit (a
/// disk error): `--resume` continues from the previous complete checkpoint, with one warning
/// naming the one skipped and why, and ends where a run that never failed ends; with no
/// checkpoint that reads back, it is refused.
#[test]
fn resume_falls_back_to_the_newest_checkpoint_that_reads_back() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, cfg, want) = straight_run(tmp.path(), "6");
    let checkpoints = |run: &Path| pma_model::network::run_dir::checkpoints(run).unwrap();
    let damages: [(&str, Damage, &str); 3] = [
        ("model.safetensors", truncate, "does not belong to"),
        ("model.safetensors", flip_a_byte, "does not belong to"),
        (
            "train_state.safetensors",
            truncate,
            "train_state.safetensors",
        ),
    ];
    for (k, (file, damage, why)) in damages.into_iter().enumerate() {
        let out = tmp.path().join(format!("run{k}"));
        train_ck1(&data, &cfg, &out, "3");
        let all = checkpoints(&out);
        assert_eq!(all.len(), 2, "the run keeps two checkpoints");
        let (older, newest) = (&all[0], &all[1]);
        damage(&newest.path.join(file));
        let resumed = resume(&data, &out, "6", &[]);
        let err = stderr(&resumed);
        assert!(resumed.status.success(), "{file}: {err}");
        let warnings: Vec<&str> = err.lines().filter(|l| l.starts_with("warning:")).collect();
        assert_eq!(warnings.len(), 1, "{err}");
        let skipped = format!("{}: skipped", newest.path.display());
        let from = format!("resuming from {}", older.path.display());
        for needle in [skipped.as_str(), why, from.as_str()] {
            assert!(
                warnings[0].contains(needle),
                "lacks {needle:?}: {}",
                warnings[0]
            );
        }
        assert_eq!(
            std::fs::read(out.join("model.safetensors")).unwrap(),
            want,
            "{file}: the resumed run differs from the straight one"
        );
    }
    // Both checkpoints unreadable: refused, naming both.
    let out = tmp.path().join("both");
    train_ck1(&data, &cfg, &out, "3");
    let all = checkpoints(&out);
    truncate(&all[1].model());
    truncate(&all[0].state());
    let resumed = resume(&data, &out, "6", &[]);
    let names: Vec<String> = all
        .iter()
        .map(|c| c.path.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    refused(
        &resumed,
        &["no complete checkpoint reads back", &names[0], &names[1]],
    );
}

/// Case 4: `convert checkpoint --with-optimizer` on a full disk writes both files or none.
#[test]
fn converted_checkpoint_pairs_are_all_or_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let th = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/convert/ckpt_adam.th");
    let out = tmp.path().join("x.safetensors");
    let side = tmp.path().join("x.optim.safetensors");
    let mut cut = 0;
    for budget in [
        0u64,
        1000,
        100_000,
        1_000_000,
        4_000_000,
        8_000_000,
        1 << 40,
    ] {
        let o = pma_env(
            &[
                "convert",
                "checkpoint",
                s(&th),
                "-o",
                s(&out),
                "--with-optimizer",
            ],
            &[("PMA_FSIO_FAIL_AFTER", &budget.to_string())],
        );
        if o.status.success() {
            assert!(out.is_file() && side.is_file(), "budget {budget}");
            std::fs::remove_file(&out).unwrap();
            std::fs::remove_file(&side).unwrap();
        } else {
            cut += 1;
            exits(&o, 1, &["No space left on device"]);
            assert!(
                !out.exists() && !side.exists(),
                "budget {budget}: half a pair"
            );
        }
        let left = std::fs::read_dir(tmp.path()).unwrap().count();
        assert_eq!(left, 0, "budget {budget}: temporaries left");
    }
    assert!(cut >= 3, "only {cut} budgets hit the full disk");
}

/// Cases 10 and 12: output paths are checked before any work, with the same status in every
/// command (1: an output that cannot be written where asked); unreadable inputs are refused
/// input (2).
#[test]
fn output_paths_are_checked_before_work() {
    let (tmp, data, model) = scene_and_model();
    let dir = tmp.path();
    let missing = dir.join("missing").join("a.ply");
    let th = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/convert/tiny_views.th");
    for args in [
        vec!["mesh", "--model", s(&model), "--out", s(&missing)],
        vec!["mesh", "--model", s(&model), "--out", s(dir)],
        vec!["convert", "checkpoint", s(&th), "-o", s(&missing)],
        vec!["convert", "checkpoint", s(&th), "-o", s(dir)],
        vec!["convert", "dataset", s(&data), "-o", s(&missing)],
    ] {
        let out = pma_within(&args, 60);
        exits(&out, 1, &[]);
        let err = stderr(&out);
        assert!(
            err.contains("does not exist") || err.contains("is a directory"),
            "{args:?}: {err}"
        );
    }
    #[cfg(unix)]
    {
        let a = dir.join("loop_a");
        let b = dir.join("loop_b");
        std::os::unix::fs::symlink(&a, &b).unwrap();
        std::os::unix::fs::symlink(&b, &a).unwrap();
        for args in [
            vec!["inspect", s(&a)],
            vec!["metrics", s(&a), s(&b)],
            vec!["mesh", "--model", s(&a), "-o", s(&dir.join("m.ply"))],
        ] {
            refused(&pma_within(&args, 60), &["loop_a"]);
        }
        use std::os::unix::ffi::OsStrExt;
        let bad = dir.join(std::ffi::OsStr::from_bytes(b"mesh\xff.ply"));
        let out = Command::new(env!("CARGO_BIN_EXE_pma"))
            .args(["mesh", "--model", s(&model), "--res", "512", "--out"])
            .arg(&bad)
            .output()
            .unwrap();
        refused(&out, &["not valid UTF-8"]);
        // Permission bits do not bind root, who runs CI: only checked as another user.
        // SAFETY: getuid has no preconditions.
        if unsafe { libc::getuid() } != 0 {
            use std::os::unix::fs::PermissionsExt;
            let locked = dir.join("locked.png");
            std::fs::write(&locked, b"x").unwrap();
            std::fs::set_permissions(&locked, std::fs::Permissions::from_mode(0o000)).unwrap();
            refused(
                &pma_within(&["metrics", s(&locked), s(&locked)], 60),
                &["locked.png"],
            );
            refused(&pma_within(&["inspect", s(&locked)], 60), &["locked.png"]);
        }
    }
}

/// Case 11: a refusal is one line naming the file: a checkpoint whose config does not fit
/// its tensors (the first mismatch and how many more), a bad NPY header, a TOML syntax error,
/// an unusable train state.
#[test]
fn every_refusal_is_one_line() {
    let (tmp, data, model) = scene_and_model();
    let dir = tmp.path();
    let wide = dir.join("wide.safetensors");
    with_config(&model, &wide, |c| {
        let w = c["trunk_width"].as_u64().unwrap();
        c["trunk_width"] = (w + 8).into();
    });
    let scene = dir.join("scene");
    refused(
        &pma_within(&["eval", "--model", s(&wide), "--data", s(&scene)], 60),
        &["wide.safetensors", "more problem(s)"],
    );
    // The golden export has no pma metadata: its config is inferred, and a mismatch is
    // still one line.
    let bad_npy = dir.join("bad_header.npz");
    {
        // Stored members, so the NPY header can be found and broken in place.
        let stored = dir.join("stored.npz");
        crate::convert::rewrite_npz(&data, &stored, "bones", |_| {});
        let mut bytes = std::fs::read(&stored).unwrap();
        let at = bytes
            .windows(6)
            .position(|w| w == b"\x93NUMPY")
            .expect("an NPY member");
        // Break the header dict of the first stored member.
        let dict = at + 10;
        bytes[dict..dict + 6].copy_from_slice(b"{'xx':");
        std::fs::write(&bad_npy, bytes).unwrap();
    }
    let out = pma_within(&["inspect", s(&bad_npy)], 60);
    exits(&out, 2, &["bad_header.npz"]);
    let cfg = dir.join("broken.toml");
    std::fs::write(&cfg, "preset = \"tiny\"\n[train\nlr = 1\n").unwrap();
    train_refused(
        &data,
        &dir.join("r"),
        &["--config", s(&cfg)],
        &["broken.toml", "line 2"],
    );
    // A train state that is not one.
    let run_dir = model.parent().unwrap();
    let state = newest(run_dir).join("train_state.safetensors");
    std::fs::copy(&model, &state).unwrap();
    train_refused(
        &data,
        run_dir,
        &["--resume", "--iters", "3"],
        &["train_state.safetensors"],
    );
}

/// Case 12: NaN or infinite weights are refused wherever a model is used, and `pma inspect`
/// shows them.
#[test]
fn non_finite_weights_are_refused_and_shown_by_inspect() {
    let (tmp, _, model) = scene_and_model();
    let dir = tmp.path();
    let nan = dir.join("nan.safetensors");
    rewrite_safetensors(
        &model,
        &nan,
        |_| {},
        |header, data| {
            let at = header["sigma_linear.bias"]["data_offsets"][0]
                .as_u64()
                .unwrap() as usize;
            data[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        },
    );
    let scene = dir.join("scene");
    for args in [
        vec!["eval", "--model", s(&nan), "--data", s(&scene)],
        vec!["mesh", "--model", s(&nan), "-o", s(&dir.join("m.ply"))],
        vec!["render", "--model", s(&nan), "--out", s(&dir.join("r"))],
    ] {
        refused(
            &pma_within(&args, 60),
            &["nan.safetensors", "sigma_linear.bias", "non-finite"],
        );
    }
    let out = pma_within(&["inspect", s(&nan)], 60);
    let listing = String::from_utf8_lossy(&out.stdout);
    assert!(
        listing
            .lines()
            .any(|l| l.contains("sigma_linear.bias") && l.trim_end().ends_with(" 1")),
        "{listing}"
    );
    exits(&out, 2, &["nan.safetensors", "sigma_linear.bias"]);
    ok(pma_within(&["inspect", s(&model)], 60));
}

/// Tools take a run directory for `--model`: its newest complete model
/// (`pma_model::network::run_dir::newest_model`), with `eval`'s files beside it.
#[test]
fn a_run_directory_stands_for_its_newest_model() {
    let (tmp, _, model) = scene_and_model();
    let dir = tmp.path();
    let run_dir = model.parent().unwrap();
    ok(pma_within(
        &[
            "eval",
            "--model",
            s(run_dir),
            "--data",
            s(&dir.join("scene")),
            "--max-images",
            "1",
            "--pngs",
            "0",
        ],
        300,
    ));
    assert!(run_dir.join("eval_novel_view").join("eval.json").is_file());
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    refused(
        &pma_within(
            &[
                "eval",
                "--model",
                s(&empty),
                "--data",
                s(&dir.join("scene")),
            ],
            60,
        ),
        &["holds no complete model"],
    );
}
