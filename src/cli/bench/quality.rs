//! `pma bench --time-to-quality`: held-out PSNR against training time per option on scene
//! seeds the options were not tuned on (`pma_model::bench::quality` measures). Prints the
//! table and writes `quality.json`, `quality.md` and `time_to_quality.png`.

use std::fmt::Write as _;

use candle_core::Device;
use pma_model::bench::quality::{select_options, time_to_quality, QualityReport, QualityRequest};
use pma_model::train::Preset;

use super::super::plot::plot_curves;
use super::super::progress::Phases;
use super::super::{refuse, write_json};
use super::Args;

pub fn run(args: &Args, dev: &Device) -> anyhow::Result<()> {
    let preset: Preset = args.preset.parse()?;
    let marks = &args.ttq_marks;
    if marks.is_empty()
        || marks
            .iter()
            .any(|m| !(m.is_finite() && *m > 0.0 && *m <= 1e4))
        || marks.windows(2).any(|w| w[0] >= w[1])
    {
        refuse!("--ttq-marks: expected ascending minutes in (0, 1e4], found {marks:?}");
    }
    if args.ttq_seeds.is_empty() {
        refuse!("--ttq-seeds: name at least one scene seed");
    }
    if !(1..=1000).contains(&args.ttq_points) {
        refuse!(
            "--ttq-points must be in 1..=1000, found {}",
            args.ttq_points
        );
    }
    let options = match select_options(&args.ttq_options) {
        Ok(o) => o,
        Err(e) => refuse!("--ttq-options: {e}"),
    };
    let scene = super::scene(args);
    let req = QualityRequest {
        preset,
        out: args.out.clone(),
        scene,
        seeds: args.ttq_seeds.clone(),
        marks: marks.clone(),
        points: args.ttq_points,
        eval_images: args.eval_images,
        options,
        device: dev.clone(),
        numerics: super::super::numerics(),
    };
    let report = time_to_quality(&req, &mut Phases::new(args.quiet))?;
    let md = table(&report);
    println!("{md}");
    write_json(&report, &args.out.join("quality.json"))?;
    pma_data::fsio::write_atomic(&args.out.join("quality.md"), md.as_bytes())?;
    plot_curves(
        &curves(&report),
        &format!(
            "pma bench --time-to-quality ({}, seeds {:?}, mean)",
            report.preset, report.seeds
        ),
        "training time [min]",
        &args.out.join("time_to_quality.png"),
    )?;
    println!(
        "wrote {}, quality.md and time_to_quality.png",
        args.out.join("quality.json").display()
    );
    Ok(())
}

/// The table: per option the mean PSNR at each mark and the mean minutes to parity's
/// PSNR at each mark ("> M": some seed did not reach it within the last mark).
pub fn table(r: &QualityReport) -> String {
    let mut s = String::new();
    let marks: Vec<String> = r.marks_minutes.iter().map(|m| format!("{m}")).collect();
    let _ = writeln!(
        s,
        "# pma bench --time-to-quality: preset `{}`, scene seeds {:?}, held-out PSNR over {} \
         novel-view image(s), mean over the seeds ({:.0} s wall)\n",
        r.preset, r.seeds, r.eval_images, r.wall_s
    );
    let mut head = String::from("| option |");
    let mut rule = String::from("|---|");
    for m in &marks {
        let _ = write!(head, " PSNR at {m} min |");
        rule.push_str("---|");
    }
    for m in &marks {
        let _ = write!(head, " min to parity's {m}-min PSNR |");
        rule.push_str("---|");
    }
    head.push_str(" iterations | ms/step | network points/step |");
    rule.push_str("---|---|---|");
    let _ = writeln!(s, "{head}\n{rule}");
    let last = r.marks_minutes.last().copied().unwrap_or(f64::NAN);
    for o in &r.options {
        let mut row = format!(
            "| {}{} |",
            o.name,
            if o.budgeted { " (a run per mark)" } else { "" }
        );
        for p in &o.psnr_at_marks {
            let _ = write!(row, " {p:.2} |");
        }
        for t in &o.minutes_to_parity {
            match t {
                Some(t) => {
                    let _ = write!(row, " {t:.2} |");
                }
                None => {
                    let _ = write!(row, " > {last} |");
                }
            }
        }
        // The longest run of each seed: iterations, step time, points.
        let longest: Vec<_> = o.seeds.iter().filter_map(|s| s.runs.last()).collect();
        let n = longest.len().max(1) as f64;
        let mean = |f: &dyn Fn(&pma_model::bench::quality::RunCurve) -> f64| {
            longest.iter().map(|c| f(c)).sum::<f64>() / n
        };
        let _ = writeln!(
            row,
            " {:.0} | {:.1} | {:.0} |",
            mean(&|c| c.iterations as f64),
            mean(&|c| c.ms_per_step),
            mean(&|c| c.points_per_step)
        );
        s.push_str(&row);
    }
    let _ = writeln!(
        s,
        "\nPer seed (minutes to parity's PSNR at each mark; `-`: not reached):\n"
    );
    for o in &r.options {
        for sq in &o.seeds {
            let times: Vec<String> = sq
                .minutes_to_parity
                .iter()
                .map(|t| t.map_or("-".into(), |t| format!("{t:.2}")))
                .collect();
            let psnr: Vec<String> = sq.psnr_at_marks.iter().map(|p| format!("{p:.2}")).collect();
            let _ = writeln!(
                s,
                "* {} seed {}: PSNR {} dB; minutes {}",
                o.name,
                sq.seed,
                psnr.join(" / "),
                times.join(" / ")
            );
        }
    }
    s
}

/// One curve per option, the mean over the seeds point by point (of each seed's longest
/// run); a budgeted option adds the ends of its runs.
fn curves(r: &QualityReport) -> Vec<(String, Vec<(f64, f64)>)> {
    let mut out = Vec::new();
    for o in &r.options {
        let longest: Vec<&Vec<(f64, f64)>> = o
            .seeds
            .iter()
            .filter_map(|s| s.runs.last().map(|c| &c.curve))
            .collect();
        let len = longest.iter().map(|c| c.len()).min().unwrap_or(0);
        let n = longest.len().max(1) as f64;
        let mean: Vec<(f64, f64)> = (0..len)
            .map(|i| {
                let t = longest.iter().map(|c| c[i].0).sum::<f64>() / n;
                let p = longest.iter().map(|c| c[i].1).sum::<f64>() / n;
                (t, p)
            })
            .collect();
        out.push((o.name.clone(), mean));
        if o.budgeted {
            let ends: Vec<(f64, f64)> = r
                .marks_minutes
                .iter()
                .zip(&o.psnr_at_marks)
                .map(|(m, p)| (m * 60.0, *p))
                .collect();
            out.push((format!("{} (end of each run)", o.name), ends));
        }
    }
    out
}
