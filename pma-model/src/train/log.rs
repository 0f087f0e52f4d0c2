//! `log.csv`: one row per log interval.
//!
//! Columns: `iter, wall_s, loss, train_psnr, eval_psnr, eval_ssim, eval_lpips, lr, skipped`.
//! `loss` and `train_psnr` are means over the interval's finite steps; `eval_*` are empty
//! unless a held-out evaluation ran at that iteration (`eval_lpips` also when the held-out
//! images are under LPIPS's 31×31 minimum); `skipped` is the run's running count of
//! non-finite steps. Logs from before `eval_lpips` existed ([`HEADER_NO_LPIPS`]) still read,
//! so such runs resume; they are rewritten with the new header. The whole file is rewritten atomically at each row (it is small), so a
//! reader never sees a torn line and a resumed run can drop the rows after its checkpoint.

use std::fmt::Write as _;
use std::path::Path;

use super::{write_atomic, TrainError};

pub const HEADER: &str = "iter,wall_s,loss,train_psnr,eval_psnr,eval_ssim,eval_lpips,lr,skipped";
/// The header of logs written before LPIPS was computed.
pub const HEADER_NO_LPIPS: &str = "iter,wall_s,loss,train_psnr,eval_psnr,eval_ssim,lr,skipped";

#[derive(Debug, Clone, PartialEq)]
pub struct LogRow {
    pub iter: u64,
    pub wall_s: f64,
    pub loss: f64,
    pub train_psnr: f64,
    pub eval_psnr: Option<f64>,
    pub eval_ssim: Option<f64>,
    pub eval_lpips: Option<f64>,
    /// Learning rate of the "other" group for the next step.
    pub lr: f64,
    pub skipped: u64,
}

#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrainLog {
    pub rows: Vec<LogRow>,
}

impl TrainLog {
    /// Read a log written by [`Self::write`]; a missing file is an empty log.
    pub fn read(path: &Path) -> Result<Self, TrainError> {
        // 256 MiB is millions of rows.
        let text = match pma_data::fsio::read_input_to_string(path, 256 << 20) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Self::default()),
            Err(source) => return Err(super::error::read_err(path)(source)),
        };
        Self::parse(&text).map_err(|msg| TrainError::Config(format!("{}: {msg}", path.display())))
    }

    pub fn parse(text: &str) -> Result<Self, String> {
        let mut lines = text.lines();
        let has_lpips = match lines.next() {
            None => return Ok(Self::default()),
            Some(h) if h.trim() == HEADER => true,
            Some(h) if h.trim() == HEADER_NO_LPIPS => false,
            Some(h) => return Err(format!("unexpected header {h:?}, expected {HEADER:?}")),
        };
        let fields = if has_lpips { 9 } else { 8 };
        let mut rows = Vec::new();
        for (i, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let lineno = i + 2;
            let f: Vec<&str> = line.split(',').collect();
            if f.len() != fields {
                return Err(format!(
                    "line {lineno}: expected {fields} fields, found {}",
                    f.len()
                ));
            }
            let num = |k: usize| -> Result<f64, String> {
                f[k].trim()
                    .parse::<f64>()
                    .map_err(|_| format!("line {lineno}: field {k} = {:?} is not a number", f[k]))
            };
            let opt = |k: usize| -> Result<Option<f64>, String> {
                if f[k].trim().is_empty() {
                    Ok(None)
                } else {
                    num(k).map(Some)
                }
            };
            let int = |k: usize| -> Result<u64, String> {
                f[k].trim()
                    .parse::<u64>()
                    .map_err(|_| format!("line {lineno}: field {k} = {:?} is not an integer", f[k]))
            };
            // Fields after `eval_ssim` sit one column later when `eval_lpips` is there.
            let k = fields - 8;
            rows.push(LogRow {
                iter: int(0)?,
                wall_s: num(1)?,
                loss: num(2)?,
                train_psnr: num(3)?,
                eval_psnr: opt(4)?,
                eval_ssim: opt(5)?,
                eval_lpips: if has_lpips { opt(6)? } else { None },
                lr: num(6 + k)?,
                skipped: int(7 + k)?,
            });
        }
        Ok(Self { rows })
    }

    pub fn to_csv(&self) -> String {
        let mut s = String::with_capacity(64 * (self.rows.len() + 1));
        s.push_str(HEADER);
        s.push('\n');
        let opt = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_default();
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{},{:.3},{:.6},{:.4},{},{},{},{:.6e},{}",
                r.iter,
                r.wall_s,
                r.loss,
                r.train_psnr,
                opt(r.eval_psnr),
                opt(r.eval_ssim),
                opt(r.eval_lpips),
                r.lr,
                r.skipped
            );
        }
        s
    }

    pub fn write(&self, path: &Path) -> Result<(), TrainError> {
        write_atomic(path, self.to_csv().as_bytes())
    }

    /// Add a row, or merge it into the last one when both are for the same iteration (an
    /// evaluation that lands on a logging iteration).
    pub fn push(&mut self, row: LogRow) {
        match self.rows.last_mut() {
            Some(last) if last.iter == row.iter => {
                last.eval_psnr = row.eval_psnr.or(last.eval_psnr);
                last.eval_ssim = row.eval_ssim.or(last.eval_ssim);
                last.eval_lpips = row.eval_lpips.or(last.eval_lpips);
            }
            _ => self.rows.push(row),
        }
    }

    /// Drop rows after `iter` (a resumed run repeats those iterations).
    pub fn truncate_after(&mut self, iter: u64) {
        self.rows.retain(|r| r.iter <= iter);
    }

    /// `(wall_s, eval_psnr)` of every evaluated row: the "error against run time" curve.
    pub fn eval_curve(&self) -> Vec<(f64, f64)> {
        self.rows
            .iter()
            .filter_map(|r| r.eval_psnr.map(|p| (r.wall_s, p)))
            .collect()
    }

    /// `(wall_s, train_psnr)` of every row with a finite training PSNR.
    pub fn train_curve(&self) -> Vec<(f64, f64)> {
        self.rows
            .iter()
            .filter(|r| r.train_psnr.is_finite())
            .map(|r| (r.wall_s, r.train_psnr))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(iter: u64, eval: Option<f64>) -> LogRow {
        LogRow {
            iter,
            wall_s: iter as f64 * 0.5,
            loss: 0.25,
            train_psnr: 12.5,
            eval_psnr: eval,
            eval_ssim: eval.map(|_| 0.5),
            eval_lpips: eval.map(|_| 0.25),
            lr: 5e-4,
            skipped: 0,
        }
    }

    #[test]
    fn csv_roundtrip_and_resume_truncation() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("log.csv");
        let mut log = TrainLog::default();
        log.push(row(10, None));
        log.push(row(20, None));
        log.push(row(20, Some(18.25))); // evaluation on a logging iteration merges
        log.push(row(30, None));
        assert_eq!(log.rows.len(), 3);
        log.write(&path).unwrap();
        let back = TrainLog::read(&path).unwrap();
        assert_eq!(back.rows.len(), 3);
        assert_eq!(back.rows[1].eval_psnr, Some(18.25));
        assert_eq!(back.rows[0].eval_psnr, None);
        assert_eq!(back.eval_curve(), vec![(10.0, 18.25)]);
        let mut cut = back.clone();
        cut.truncate_after(20);
        assert_eq!(
            cut.rows.iter().map(|r| r.iter).collect::<Vec<_>>(),
            vec![10, 20]
        );
        assert!(TrainLog::read(&dir.path().join("missing.csv"))
            .unwrap()
            .rows
            .is_empty());
    }

    #[test]
    fn malformed_logs_are_reported_with_line_numbers() {
        let err = TrainLog::parse(&format!("{HEADER}\n1,2,3\n")).unwrap_err();
        assert!(err.contains("line 2"), "{err}");
        let err = TrainLog::parse("a,b\n").unwrap_err();
        assert!(err.contains("unexpected header"), "{err}");
        let err = TrainLog::parse(&format!("{HEADER}\nx,1,1,1,,,,1,0\n")).unwrap_err();
        assert!(err.contains("not an integer"), "{err}");
    }

    #[test]
    fn logs_without_the_lpips_column_still_read() {
        let old =
            format!("{HEADER_NO_LPIPS}\n10,5.000,0.250000,12.5000,18.2500,0.5000,5.000000e-4,2\n");
        let log = TrainLog::parse(&old).unwrap();
        let r = &log.rows[0];
        assert_eq!((r.iter, r.skipped), (10, 2));
        assert_eq!(
            (r.eval_psnr, r.eval_ssim, r.eval_lpips),
            (Some(18.25), Some(0.5), None)
        );
        assert_eq!(r.lr, 5e-4);
        assert!(log.to_csv().starts_with(HEADER));
        let mut with = TrainLog::default();
        with.push(row(20, Some(18.25)));
        let back = TrainLog::parse(&with.to_csv()).unwrap();
        assert_eq!(back.rows[0].eval_lpips, Some(0.25));
    }
}
