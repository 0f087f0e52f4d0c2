//! Time to quality (`pma bench --time-to-quality`): held-out PSNR against training time for
//! parity, culling with the grid, each other training option alone, the fast recipe and
//! all of them together, on synthetic scenes of seeds the options were not tuned on, and
//! the minutes each needs to reach the held-out PSNR parity has after each mark (1, 2 and 5
//! minutes by default).
//!
//! For each scene seed every run trains from the same initialisation, and the runs take
//! turns of [`TURN_SECONDS`] of training until each has spent its budget, so a machine whose
//! speed drifts slows them alike. Only training counts against a budget: at fixed points
//! of its own training time (every `last mark / points`, and at each mark) a run is scored
//! on the same held-out images (the novel views `pma eval --max-images` picks, foreground
//! PSNR as it scores them, a parity render), and the scoring is not timed.
//!
//! An option whose learning rates anneal over the run's budget ([`QualityOption::budgeted`])
//! has a run per mark, each annealed over that mark; its quality at a mark is the end of
//! that run, and its time to a quality is read from those end points. Every other option
//! has one run of the last mark and its time to a quality is read from its curve (the pose
//! side's boost comes down over that run: its row is the curve of a run of the last mark's
//! budget). Times between two scored points are interpolated linearly.

use std::path::PathBuf;
use std::time::Instant;

use candle_core::Device;
use pma_data::synth::SynthConfig;
use serde::{Deserialize, Serialize};

use super::measure::{prepare_scene, Scene};
use super::{BenchObserver, Result};
use crate::eval::{evaluate, EvalOptions};
use crate::network::occupancy::OccupancyConfig;
use crate::train::average::AverageConfig;
use crate::train::{recipe, Preset, RunConfig, Trainer};
use pma_data::error_map::ErrorMapConfig;

/// Seconds of training each run does before the next takes its turn.
pub const TURN_SECONDS: f64 = 2.0;

/// Rays per render chunk of the held-out scores.
const CHUNK: usize = 4096;

/// One configuration compared: how it changes a preset's run for a budget of `minutes`.
#[derive(Debug, Clone)]
pub struct QualityOption {
    /// Its name on the command line (`pma bench --ttq-options`).
    pub key: &'static str,
    pub name: String,
    pub setup: fn(&mut RunConfig, f64),
    /// Its schedule follows the budget: one run per mark.
    pub budgeted: bool,
}

/// Parity, culling at 0.6 with the grid, each of the other options alone (the error map;
/// the annealed rates; coarse samples from the grid, which needs the grid; stratified
/// samples; averaged weights; the pose side's rate `lr_freq` ×4, and ×4 coming down to ×1
/// over the budget), the fast recipe without that boost (as a run by iterations has it),
/// the recipe, and all of them together.
pub fn quality_options() -> Vec<QualityOption> {
    fn culled(run: &mut RunConfig) {
        recipe::cull_with_grid(run);
    }
    fn anneal(run: &mut RunConfig, minutes: f64) {
        run.train.anneal_over(Some(minutes * 60.0))
    }
    fn pose_boost(run: &mut RunConfig, minutes: f64) {
        run.train.boost_pose_over(Some(minutes * 60.0))
    }
    let option = |key, name: &str, setup: fn(&mut RunConfig, f64), budgeted| QualityOption {
        key,
        name: name.into(),
        setup,
        budgeted,
    };
    vec![
        option("parity", "parity", |_, _| {}, false),
        option("cull-grid", "cull 0.6 + grid", |run, _| culled(run), false),
        option(
            "error-map",
            "error map",
            |run, _| run.train.error_map = Some(ErrorMapConfig::default()),
            false,
        ),
        option("anneal", "anneal over the budget", anneal, true),
        option(
            "coarse-from-grid",
            "grid + coarse from grid",
            |run, _| {
                run.train.occupancy = Some(OccupancyConfig::default());
                run.train.coarse_from_grid = true;
            },
            false,
        ),
        option(
            "jitter",
            "stratified samples",
            |run, _| run.train.jitter = true,
            false,
        ),
        option(
            "average",
            "averaged weights",
            |run, _| run.train.average = Some(AverageConfig::default()),
            false,
        ),
        option(
            "lr-freq",
            "pose-side rate x4",
            |run, _| run.train.lr_freq *= 4.0,
            false,
        ),
        option("pose-boost", "pose-side rate x4 -> x1", pose_boost, true),
        option(
            "recipe-no-boost",
            "the fast recipe without the boost",
            |run, _| {
                recipe::fast(run, None);
            },
            false,
        ),
        option(
            "recipe",
            "the fast recipe",
            |run, minutes| {
                recipe::fast(run, Some(minutes * 60.0));
            },
            true,
        ),
        option(
            "all",
            "all options together",
            |run, minutes| {
                recipe::fast(run, Some(minutes * 60.0));
                run.train.coarse_from_grid = true;
                run.train.jitter = true;
                run.train.error_map = Some(ErrorMapConfig::default());
                run.train.average = Some(AverageConfig::default());
                anneal(run, minutes);
            },
            true,
        ),
    ]
}

/// The options named by `keys` ([`QualityOption::key`]), in the order of
/// [`quality_options`]; parity, the target, is always the first. An unknown key is an
/// error naming the known ones.
pub fn select_options(keys: &[String]) -> std::result::Result<Vec<QualityOption>, String> {
    let all = quality_options();
    if let Some(k) = keys
        .iter()
        .find(|k| !all.iter().any(|o| o.key == k.as_str()))
    {
        let known: Vec<&str> = all.iter().map(|o| o.key).collect();
        return Err(format!(
            "unknown option `{k}` (expected one of {})",
            known.join(", ")
        ));
    }
    Ok(all
        .into_iter()
        .filter(|o| o.key == "parity" || keys.iter().any(|k| k == o.key))
        .collect())
}

/// What to measure.
#[derive(Debug, Clone)]
pub struct QualityRequest {
    pub preset: Preset,
    /// Where the scenes go (`scene-seed<N>/`).
    pub out: PathBuf,
    /// The synthetic scene; each of `seeds` replaces its seed.
    pub scene: SynthConfig,
    pub seeds: Vec<u64>,
    /// Minutes of training at which parity's quality is the target (ascending).
    pub marks: Vec<f64>,
    /// Scored points of a curve over the last mark (besides the marks themselves).
    pub points: usize,
    /// Held-out images scored at each point (evenly spread over the novel views).
    pub eval_images: usize,
    pub options: Vec<QualityOption>,
    pub device: Device,
    pub numerics: crate::compute::numerics::Numerics,
}

/// One run: its budget, its scored points and what it trained.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunCurve {
    pub budget_s: f64,
    /// (seconds of training, held-out PSNR), the initial model first.
    pub curve: Vec<(f64, f64)>,
    pub iterations: u64,
    /// Mean training ms per step.
    pub ms_per_step: f64,
    /// Network points per step, on average.
    pub points_per_step: f64,
}

/// An option on one scene seed.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SeedQuality {
    pub seed: u64,
    /// One run, or one per mark for a budgeted option.
    pub runs: Vec<RunCurve>,
    /// Held-out PSNR at each mark.
    pub psnr_at_marks: Vec<f64>,
    /// Minutes to reach parity's PSNR at each mark on this seed (`None`: not within the
    /// last mark).
    pub minutes_to_parity: Vec<Option<f64>>,
}

/// An option over all seeds (a row of the table).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OptionQuality {
    pub name: String,
    pub budgeted: bool,
    pub seeds: Vec<SeedQuality>,
    /// Mean over the seeds of the PSNR at each mark.
    pub psnr_at_marks: Vec<f64>,
    /// Mean over the seeds of the minutes to parity's PSNR at each mark (`None` where a
    /// seed did not reach it).
    pub minutes_to_parity: Vec<Option<f64>>,
}

/// `quality.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct QualityReport {
    pub preset: String,
    pub seeds: Vec<u64>,
    pub marks_minutes: Vec<f64>,
    pub eval_images: usize,
    pub options: Vec<OptionQuality>,
    /// Wall seconds of the whole measurement, scoring included.
    pub wall_s: f64,
}

/// A run while the options take turns.
struct Run {
    option: usize,
    trainer: Trainer,
    budget: f64,
    /// Training seconds at which to score, ascending (the budget last).
    due: Vec<f64>,
    next: usize,
    trained: f64,
    curve: Vec<(f64, f64)>,
}

impl Run {
    fn done(&self) -> bool {
        self.next >= self.due.len()
    }
}

/// Held-out PSNR of `trainer`'s avatar on the scene's images (parity render).
fn score(trainer: &Trainer, scene: &Scene) -> Result<f64> {
    let r = trainer.with_model(|a| {
        evaluate(
            a,
            &scene.held,
            "novel_view",
            &scene.eval_set,
            &EvalOptions::quick(CHUNK),
            &mut |_, _| {},
        )
        .map_err(crate::train::TrainError::from)
    })?;
    Ok(r.psnr)
}

/// The first time a piecewise-linear curve (ascending times) reaches `target`.
pub fn time_to_reach(curve: &[(f64, f64)], target: f64) -> Option<f64> {
    let first = curve.first()?;
    if first.1 >= target {
        return Some(first.0);
    }
    curve.windows(2).find_map(|w| {
        let ((t0, p0), (t1, p1)) = (w[0], w[1]);
        (p1 >= target).then(|| t0 + (t1 - t0) * ((target - p0) / (p1 - p0)).clamp(0.0, 1.0))
    })
}

/// The PSNR of a curve at time `t` (linear between points; its last value past its end).
fn psnr_at(curve: &[(f64, f64)], t: f64) -> f64 {
    match curve.iter().position(|p| p.0 >= t) {
        None => curve.last().map_or(f64::NAN, |p| p.1),
        Some(0) => curve[0].1,
        Some(i) => {
            let ((t0, p0), (t1, p1)) = (curve[i - 1], curve[i]);
            p0 + (p1 - p0) * ((t - t0) / (t1 - t0).max(1e-12))
        }
    }
}

/// Measure every option on every seed (see the module docs).
pub fn time_to_quality(req: &QualityRequest, obs: &mut dyn BenchObserver) -> Result<QualityReport> {
    let start = Instant::now();
    let last = req.marks.last().copied().unwrap_or(1.0) * 60.0;
    let step = last / req.points.max(1) as f64;
    let mut per_option: Vec<Vec<SeedQuality>> = vec![Vec::new(); req.options.len()];
    for &seed in &req.seeds {
        let cfg = SynthConfig {
            seed,
            ..req.scene.clone()
        };
        let scene = prepare_scene(&req.out, &cfg, req.eval_images, obs)?;
        let mut runs = Vec::new();
        for (k, opt) in req.options.iter().enumerate() {
            let budgets: Vec<f64> = match opt.budgeted {
                true => req.marks.iter().map(|m| m * 60.0).collect(),
                false => vec![last],
            };
            for budget in budgets {
                let mut run = RunConfig::from_preset(req.preset);
                run.numerics = req.numerics;
                (opt.setup)(&mut run, budget / 60.0);
                let mut due: Vec<f64> = (1..=req.points)
                    .map(|i| i as f64 * step)
                    .chain(req.marks.iter().map(|m| m * 60.0))
                    .filter(|&t| t <= budget * (1.0 + 1e-9))
                    .collect();
                due.sort_by(f64::total_cmp);
                due.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
                runs.push(Run {
                    option: k,
                    trainer: Trainer::new(run, scene.train.clone(), &req.device)?,
                    budget,
                    due,
                    next: 0,
                    trained: 0.0,
                    curve: Vec::new(),
                });
            }
        }
        // Every run starts from the same initialisation: one score of it serves all.
        let initial = score(&runs[0].trainer, &scene)?;
        for r in &mut runs {
            r.curve.push((0.0, initial));
        }
        let total: f64 = runs.iter().map(|r| r.budget).sum();
        obs.phase(
            &format!("scene seed {seed}: runs in turns (training s)"),
            total.ceil() as u64,
        );
        let mut spent = 0.0;
        while runs.iter().any(|r| !r.done()) {
            for r in runs.iter_mut().filter(|r| !r.done()) {
                let turn_start = r.trained;
                while !r.done() && r.trained - turn_start < TURN_SECONDS {
                    if r.trained >= r.due[r.next] {
                        let p = score(&r.trainer, &scene)?;
                        r.curve.push((r.trained, p));
                        r.next += 1;
                        continue;
                    }
                    // The annealed rates follow this run's own training clock.
                    r.trainer.set_wall_s(r.trained);
                    let t = Instant::now();
                    r.trainer.step()?;
                    r.trained += t.elapsed().as_secs_f64();
                }
                spent += r.trained.min(r.budget) - turn_start.min(r.budget);
                obs.progress(
                    spent as u64,
                    &format!("{} ({:.0} s)", req.options[r.option].name, r.budget),
                );
            }
        }
        obs.phase_end();
        for (k, opt) in req.options.iter().enumerate() {
            let mine: Vec<&Run> = runs.iter().filter(|r| r.option == k).collect();
            let curves: Vec<RunCurve> = mine
                .iter()
                .map(|r| {
                    let it = r.trainer.iteration();
                    RunCurve {
                        budget_s: r.budget,
                        curve: r.curve.clone(),
                        iterations: it,
                        ms_per_step: 1e3 * r.trained / it.max(1) as f64,
                        points_per_step: r.trainer.pass_totals().points_evaluated as f64
                            / it.max(1) as f64,
                    }
                })
                .collect();
            // The quality a time buys: a budgeted option's run ends, or the one curve.
            let reached: Vec<(f64, f64)> = match opt.budgeted {
                true => std::iter::once((0.0, initial))
                    .chain(
                        curves
                            .iter()
                            .map(|c| (c.budget_s, c.curve.last().map_or(f64::NAN, |p| p.1))),
                    )
                    .collect(),
                false => curves[0].curve.clone(),
            };
            let psnr_at_marks = req
                .marks
                .iter()
                .map(|m| psnr_at(&reached, m * 60.0))
                .collect();
            per_option[k].push(SeedQuality {
                seed,
                runs: curves,
                psnr_at_marks,
                minutes_to_parity: Vec::new(),
            });
        }
    }
    // Targets: parity's PSNR at each mark, seed by seed (parity is the first option).
    let parity = per_option.first().cloned().unwrap_or_default();
    let mut options = Vec::new();
    for (opt, mut seeds) in req.options.iter().zip(per_option) {
        for (s, p) in seeds.iter_mut().zip(&parity) {
            let reached: Vec<(f64, f64)> = match opt.budgeted {
                true => std::iter::once(s.runs[0].curve[0])
                    .chain(
                        s.runs
                            .iter()
                            .map(|c| (c.budget_s, c.curve.last().map_or(f64::NAN, |x| x.1))),
                    )
                    .collect(),
                false => s.runs[0].curve.clone(),
            };
            s.minutes_to_parity = p
                .psnr_at_marks
                .iter()
                .map(|&target| time_to_reach(&reached, target).map(|t| t / 60.0))
                .collect();
        }
        let n = seeds.len().max(1) as f64;
        let psnr_at_marks = (0..req.marks.len())
            .map(|i| seeds.iter().map(|s| s.psnr_at_marks[i]).sum::<f64>() / n)
            .collect();
        let minutes_to_parity = (0..req.marks.len())
            .map(|i| {
                seeds
                    .iter()
                    .map(|s| s.minutes_to_parity[i])
                    .sum::<Option<f64>>()
                    .map(|t| t / n)
            })
            .collect();
        options.push(OptionQuality {
            name: opt.name.clone(),
            budgeted: opt.budgeted,
            seeds,
            psnr_at_marks,
            minutes_to_parity,
        });
    }
    Ok(QualityReport {
        preset: req.preset.name().to_string(),
        seeds: req.seeds.clone(),
        marks_minutes: req.marks.clone(),
        eval_images: req.eval_images,
        options,
        wall_s: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_and_values_are_read_off_the_curve() {
        let c = [(0.0, 10.0), (60.0, 14.0), (120.0, 16.0), (300.0, 15.0)];
        assert_eq!(time_to_reach(&c, 9.0), Some(0.0));
        assert_eq!(time_to_reach(&c, 12.0), Some(30.0));
        assert_eq!(time_to_reach(&c, 15.0), Some(90.0));
        assert_eq!(time_to_reach(&c, 16.5), None);
        assert_eq!(psnr_at(&c, 90.0), 15.0);
        assert_eq!(psnr_at(&c, 300.0), 15.0);
        assert_eq!(psnr_at(&c, 400.0), 15.0);
        assert_eq!(psnr_at(&c, 0.0), 10.0);
    }

    #[test]
    fn every_option_validates_and_the_budgeted_ones_follow_the_budget() {
        let opts = quality_options();
        assert_eq!(opts[0].name, "parity");
        for o in &opts {
            let mut run = RunConfig::from_preset(Preset::CpuSmall);
            (o.setup)(&mut run, 2.0);
            run.validate().unwrap_or_else(|e| panic!("{}: {e}", o.name));
            let spans = [
                run.train.anneal.as_ref().map(|a| a.seconds),
                run.train.pose_boost.as_ref().map(|b| b.seconds),
            ];
            assert_eq!(
                o.budgeted,
                spans.contains(&Some(120.0)),
                "{}: a schedule over the budget is a run per mark",
                o.name
            );
        }
        let mut parity = RunConfig::from_preset(Preset::CpuSmall);
        (opts[0].setup)(&mut parity, 5.0);
        assert_eq!(parity, RunConfig::from_preset(Preset::CpuSmall));
        // The recipe rows are `recipe::fast`, whatever it holds, with the budget and without.
        let recipe = opts.iter().find(|o| o.key == "recipe").unwrap();
        let (mut a, mut b) = (parity.clone(), parity.clone());
        (recipe.setup)(&mut a, 5.0);
        recipe::fast(&mut b, Some(300.0));
        assert_eq!(a, b);
        let steady = opts.iter().find(|o| o.key == "recipe-no-boost").unwrap();
        let (mut a, mut b) = (parity.clone(), parity.clone());
        (steady.setup)(&mut a, 5.0);
        recipe::fast(&mut b, None);
        assert_eq!(a, b);
        assert!(a.train.pose_boost.is_none());
        // The culling row is the recipe's culling part alone: no average, the preset's rates.
        let culled = opts.iter().find(|o| o.key == "cull-grid").unwrap();
        let (mut a, mut b) = (parity.clone(), parity.clone());
        (culled.setup)(&mut a, 5.0);
        recipe::cull_with_grid(&mut b);
        assert_eq!(a, b);
        assert!(a.train.average.is_none() && a.train.occupancy.is_some());
        assert_eq!(a.train.lr_freq, parity.train.lr_freq);
        // The rate row changes the pose side's rate and nothing else.
        let rate = opts.iter().find(|o| o.key == "lr-freq").unwrap();
        let mut a = parity.clone();
        (rate.setup)(&mut a, 5.0);
        assert_eq!(a.train.lr_freq, 4.0 * parity.train.lr_freq);
        a.train.lr_freq = parity.train.lr_freq;
        assert_eq!(a, parity);
        // The boost row comes down over the run it is given and changes nothing else.
        let boost = opts.iter().find(|o| o.key == "pose-boost").unwrap();
        let mut a = parity.clone();
        (boost.setup)(&mut a, 5.0);
        assert_eq!(a.train.pose_boost.take().map(|b| b.seconds), Some(300.0));
        assert_eq!(a, parity);
    }

    #[test]
    fn options_are_selected_by_key_with_parity_first() {
        let keys = |k: &[&str]| -> Vec<String> { k.iter().map(|s| s.to_string()).collect() };
        let picked = select_options(&keys(&["recipe", "average"])).unwrap();
        let picked: Vec<&str> = picked.iter().map(|o| o.key).collect();
        assert_eq!(picked, ["parity", "average", "recipe"]);
        let all = select_options(&keys(&["all", "parity"])).unwrap();
        assert_eq!(all.len(), 2);
        let err = select_options(&keys(&["nope"])).unwrap_err();
        assert!(err.contains("`nope`") && err.contains("cull-grid"), "{err}");
    }
}
