//! A training run as the page follows it: the curves of `RUN/log.csv` and which checkpoint
//! is newest.
//!
//! `pma train` rewrites `log.csv` atomically at each row, so every read sees whole rows.
//! Columns are found by their header names (`iter`, `wall_s`, `loss`, `eval_psnr`; see
//! `pma_model::train::log`), so the reader needs no training code and keeps working when
//! columns are added.

use std::path::Path;

use serde::Serialize;

use crate::renderer::{run_model_file, stamp, Stamp};

/// The run's log file.
pub const LOG_FILE: &str = "log.csv";
/// Largest log read (a run logs a few dozen bytes per interval; this is far beyond any run).
pub const MAX_LOG_BYTES: u64 = 32 << 20;
/// At most this many points per curve go to the page (evenly thinned, the last kept).
pub const MAX_POINTS: usize = 2000;

/// `GET /api/run`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RunStatus {
    /// (iteration, training loss) per logged interval.
    pub loss: Vec<(u64, f64)>,
    /// (iteration, held-out PSNR) where an evaluation ran.
    pub eval_psnr: Vec<(u64, f64)>,
    /// Last logged iteration and its wall time, seconds.
    pub last_iter: Option<u64>,
    pub wall_s: Option<f64>,
    /// The newest checkpoint file's stamp (`None`: none written yet).
    pub checkpoint: Option<Stamp>,
    /// Why the log could not be read, if it could not.
    pub log_error: Option<String>,
}

/// The status of run directory `dir` now.
pub fn status(dir: &Path) -> RunStatus {
    let mut st = RunStatus {
        checkpoint: stamp(&run_model_file(dir)),
        ..Default::default()
    };
    let path = dir.join(LOG_FILE);
    match read_log(&path) {
        Ok(Some(text)) => match parse(&text) {
            Ok(log) => {
                st.last_iter = log.last_iter;
                st.wall_s = log.wall_s;
                st.loss = thin(log.loss);
                st.eval_psnr = thin(log.eval_psnr);
            }
            Err(e) => st.log_error = Some(format!("{}: {e}", path.display())),
        },
        Ok(None) => {}
        Err(e) => st.log_error = Some(format!("{}: {e}", path.display())),
    }
    st
}

/// The log's text, `None` before the run wrote one. Opened with `fsio::open_input`: a FIFO or
/// a device in its place is an error, never a read that blocks.
fn read_log(path: &Path) -> std::io::Result<Option<String>> {
    use std::io::Read as _;
    let f = match pma_data::fsio::open_input(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let mut text = String::new();
    f.take(MAX_LOG_BYTES).read_to_string(&mut text)?;
    Ok(Some(text))
}

/// The curves of a log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Curves {
    pub loss: Vec<(u64, f64)>,
    pub eval_psnr: Vec<(u64, f64)>,
    pub last_iter: Option<u64>,
    pub wall_s: Option<f64>,
}

/// Parse `log.csv` text. Empty and non-finite fields are left out of the curves.
pub fn parse(text: &str) -> Result<Curves, String> {
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let Some(header) = lines.next() else {
        return Ok(Curves::default());
    };
    let cols: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |name: &str| {
        cols.iter()
            .position(|c| *c == name)
            .ok_or_else(|| format!("no column {name:?} in the header {header:?}"))
    };
    let (it, wall, loss) = (col("iter")?, col("wall_s")?, col("loss")?);
    let eval = col("eval_psnr").ok();
    let mut out = Curves::default();
    for (k, line) in lines.enumerate() {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != cols.len() {
            return Err(format!(
                "row {}: {} fields, the header has {}",
                k + 2,
                f.len(),
                cols.len()
            ));
        }
        let iter: u64 = f[it]
            .parse()
            .map_err(|_| format!("row {}: iter {:?} is not an integer", k + 2, f[it]))?;
        let num = |i: usize| f[i].parse::<f64>().ok().filter(|v| v.is_finite());
        if let Some(v) = num(loss) {
            out.loss.push((iter, v));
        }
        if let Some(v) = eval.and_then(num) {
            out.eval_psnr.push((iter, v));
        }
        out.last_iter = Some(iter);
        out.wall_s = num(wall).or(out.wall_s);
    }
    Ok(out)
}

/// At most [`MAX_POINTS`] of `v`, evenly spread, the last always kept.
fn thin(v: Vec<(u64, f64)>) -> Vec<(u64, f64)> {
    if v.len() <= MAX_POINTS {
        return v;
    }
    let n = v.len();
    (0..MAX_POINTS)
        .map(|k| v[k * (n - 1) / (MAX_POINTS - 1)])
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_both_headers_by_column_name() {
        let text = "iter,wall_s,loss,train_psnr,eval_psnr,eval_ssim,eval_lpips,lr,skipped\n\
                    10,1.5,0.25,12.0,,,,0.001,0\n\
                    20,3.0,0.125,14.0,15.5,0.8,,0.001,0\n";
        let c = parse(text).unwrap();
        assert_eq!(c.loss, vec![(10, 0.25), (20, 0.125)]);
        assert_eq!(c.eval_psnr, vec![(20, 15.5)]);
        assert_eq!(c.last_iter, Some(20));
        assert_eq!(c.wall_s, Some(3.0));
        let old =
            "iter,wall_s,loss,train_psnr,eval_psnr,eval_ssim,lr,skipped\n5,0.5,nan,1,,,0.1,1\n";
        let c = parse(old).unwrap();
        assert!(c.loss.is_empty());
        assert_eq!(c.last_iter, Some(5));
        assert_eq!(parse("").unwrap(), Curves::default());
    }

    #[test]
    fn refuses_torn_or_foreign_files() {
        assert!(parse("a,b,c\n1,2,3\n").is_err());
        assert!(parse("iter,wall_s,loss\n1,2\n").is_err());
        assert!(parse("iter,wall_s,loss\nx,2,3\n").is_err());
    }

    #[test]
    fn thinning_keeps_ends_and_bound() {
        let v: Vec<(u64, f64)> = (0..10_000).map(|i| (i, i as f64)).collect();
        let t = thin(v);
        assert_eq!(t.len(), MAX_POINTS);
        assert_eq!(t[0], (0, 0.0));
        assert_eq!(*t.last().unwrap(), (9_999, 9_999.0));
    }
}
