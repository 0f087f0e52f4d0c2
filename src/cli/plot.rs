//! The PNG plots of the command line, drawn with plotters on a bundled font.

use std::path::Path;

use anyhow::Context as _;
use plotters::coord::Shift;
use plotters::prelude::*;

/// Bundled font for plot text: plotters has no fonts of its own without system libraries.
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

fn register_font() {
    static REGISTER: std::sync::Once = std::sync::Once::new();
    REGISTER.call_once(|| {
        // A font that fails to parse leaves text unrendered; the curves are still drawn.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

fn plot_err(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("plot: {e}")
}

/// A white `w`×`h` picture drawn by `draw`, written atomically as a PNG.
fn picture(
    (w, h): (u32, u32),
    path: &Path,
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    register_font();
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        draw(&root)?;
        root.present().map_err(plot_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).context("plot buffer has the wrong size")?;
    super::write_png(&img, path)
}

/// The series' names in a box at `at`.
fn legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    at: SeriesLabelPosition,
) -> anyhow::Result<()> {
    chart
        .configure_series_labels()
        .position(at)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .draw()
        .map_err(plot_err)
}

#[cfg(feature = "train")]
type PsnrChart<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

/// A chart of PSNR (dB) against wall-clock minutes on `root` whose axes hold every finite
/// point of `pts` (seconds, dB), with `title` and the x axis's `x_desc`.
#[cfg(feature = "train")]
fn psnr_chart<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    pts: &[(f64, f64)],
    title: &str,
    x_desc: &str,
    y_desc: &str,
) -> anyhow::Result<PsnrChart<'a, 'b>> {
    let finite = pts.iter().filter(|p| p.0.is_finite() && p.1.is_finite());
    let x_max = finite
        .clone()
        .map(|p| p.0 / 60.0)
        .fold(0.0f64, f64::max)
        .max(1e-3)
        * 1.02;
    let (mut y_min, mut y_max) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
        (lo.min(p.1), hi.max(p.1))
    });
    if !y_min.is_finite() {
        (y_min, y_max) = (0.0, 30.0);
    }
    let pad = ((y_max - y_min) * 0.08).max(0.5);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..x_max, (y_min - pad)..(y_max + pad))
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(plot_err)?;
    Ok(chart)
}

#[cfg(feature = "train")]
/// Plot held-out PSNR (and, lighter, training PSNR) against wall-clock time and write it
/// atomically as a PNG.
pub fn plot_psnr_vs_time(
    eval: &[(f64, f64)],
    eval_label: &str,
    train: &[(f64, f64)],
    title: &str,
    path: &Path,
) -> anyhow::Result<()> {
    picture((900, 540), path, |root| {
        let finite = |v: &&(f64, f64)| v.0.is_finite() && v.1.is_finite();
        let all: Vec<(f64, f64)> = eval.iter().chain(train).copied().collect();
        let minutes = |s: f64| s / 60.0;
        let mut chart = psnr_chart(root, &all, title, "wall-clock time [min]", "PSNR [dB]")?;
        let train_colour = RGBColor(150, 150, 150);
        if !train.is_empty() {
            chart
                .draw_series(LineSeries::new(
                    train.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                    train_colour.stroke_width(1),
                ))
                .map_err(plot_err)?
                .label("training batch PSNR")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], train_colour));
        }
        if !eval.is_empty() {
            let blue = RGBColor(31, 90, 180);
            chart
                .draw_series(LineSeries::new(
                    eval.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                    blue.stroke_width(2),
                ))
                .map_err(plot_err)?
                .label(eval_label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(2))
                });
            chart
                .draw_series(
                    eval.iter()
                        .filter(finite)
                        .map(|p| Circle::new((minutes(p.0), p.1), 3, blue.filled())),
                )
                .map_err(plot_err)?;
        }
        legend(&mut chart, SeriesLabelPosition::LowerRight)
    })
}

#[cfg(feature = "train")]
/// Error against time: one numbered point per option, x = seconds per image (log scale: the
/// options span an order of magnitude), y = held-out PSNR loss against parity (dB); the
/// numbers are listed with the options' names beside the chart, so that options with close
/// figures stay readable.
pub fn plot_error_vs_time(
    title: &str,
    pts: &[(f64, f64, &str)],
    path: &Path,
) -> anyhow::Result<()> {
    let finite: Vec<f64> = pts
        .iter()
        .map(|p| p.0)
        .filter(|x| *x > 0.0 && x.is_finite())
        .collect();
    let x_lo = finite
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min)
        .min(1.0)
        / 1.3;
    let x_hi = finite.iter().copied().fold(0.0, f64::max).max(x_lo * 10.0) * 1.3;
    let x_lo = if x_lo.is_finite() {
        x_lo.max(1e-6)
    } else {
        1e-3
    };
    let y_lo = pts.iter().map(|p| p.1).fold(0.0, f64::min) - 0.05;
    let y_hi = pts.iter().map(|p| p.1).fold(0.1, f64::max) * 1.2 + 0.05;
    picture((1320, 540), path, |root| {
        let (left, right) = root.split_horizontally(740);
        let mut chart = ChartBuilder::on(&left)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(60)
            .build_cartesian_2d((x_lo..x_hi).log_scale(), y_lo..y_hi)
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .x_desc("seconds per image (log scale)")
            .x_label_formatter(&|x| format!("{x:.2}"))
            .y_desc("held-out PSNR loss vs parity [dB]")
            .label_style(("sans-serif", 15))
            .draw()
            .map_err(plot_err)?;
        let shown: Vec<(usize, f64, f64)> = pts
            .iter()
            .enumerate()
            .filter(|(_, p)| p.0 > 0.0 && p.0.is_finite() && p.1.is_finite())
            .map(|(i, p)| (i + 1, p.0, p.1))
            .collect();
        chart
            .draw_series(
                shown
                    .iter()
                    .map(|&(_, x, y)| Circle::new((x, y), 5, BLUE.filled())),
            )
            .map_err(plot_err)?;
        // Numbers above their points, staggered so that points at the same height do not
        // print over each other.
        chart
            .draw_series(shown.iter().map(|&(k, x, y)| {
                let up = 10 + 14 * (k as i32 % 3);
                EmptyElement::at((x, y))
                    + Text::new(k.to_string(), (-4, -up), ("sans-serif", 14).into_font())
            }))
            .map_err(plot_err)?;
        for (i, p) in pts.iter().enumerate() {
            let line = format!(
                "{:>2}  {}  ({:.1} ms, {:+.3} dB)",
                i + 1,
                p.2,
                p.0 * 1e3,
                p.1
            );
            right
                .draw(&Text::new(
                    line,
                    (8, 48 + 22 * i as i32),
                    ("sans-serif", 14).into_font(),
                ))
                .map_err(plot_err)?;
        }
        Ok(())
    })
}

#[cfg(feature = "train")]
/// Several held-out PSNR curves against wall-clock time, one per labelled series.
pub fn plot_curves(
    series: &[(String, Vec<(f64, f64)>)],
    title: &str,
    x_desc: &str,
    path: &Path,
) -> anyhow::Result<()> {
    picture((900, 540), path, |root| {
        let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
        let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.1.iter().copied()).collect();
        let mut chart = psnr_chart(root, &all, title, x_desc, "held-out PSNR [dB]")?;
        for (i, (label, pts)) in series.iter().enumerate() {
            const COLOURS: [RGBColor; 9] = [
                RGBColor(31, 90, 180),
                RGBColor(214, 96, 30),
                RGBColor(44, 150, 60),
                RGBColor(190, 40, 50),
                RGBColor(120, 80, 170),
                RGBColor(110, 110, 110),
                RGBColor(200, 160, 20),
                RGBColor(20, 170, 190),
                RGBColor(0, 0, 0),
            ];
            let colour = COLOURS[i % COLOURS.len()];
            chart
                .draw_series(LineSeries::new(
                    pts.iter().filter(finite).map(|p| (p.0 / 60.0, p.1)),
                    colour.stroke_width(2),
                ))
                .map_err(plot_err)?
                .label(label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
        }
        legend(&mut chart, SeriesLabelPosition::LowerRight)
    })
}

/// The mean frequency histograms of an evaluation (render against ground truth), one line
/// each over the bin centres, log-scaled power fraction.
pub fn plot_freq_hist(
    freq: &pma_model::eval::spectrum::FreqSummary,
    title: &str,
    path: &Path,
) -> anyhow::Result<()> {
    let centres: Vec<f64> = freq
        .bin_edges
        .windows(2)
        .map(|e| 0.5 * (e[0] + e[1]))
        .collect();
    // Log axis: empty bins (a flat crop) have no point on it and are left out.
    let positive = |v: &[f64]| -> Vec<(f64, f64)> {
        centres
            .iter()
            .zip(v)
            .filter(|(_, &p)| p > 0.0 && p.is_finite())
            .map(|(&c, &p)| (c, p))
            .collect()
    };
    let (render, gt) = (positive(&freq.hist_render), positive(&freq.hist_gt));
    let (mut lo, mut hi) = render
        .iter()
        .chain(&gt)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    if !lo.is_finite() {
        (lo, hi) = (1e-6, 1.0);
    }
    let x_max = freq.bin_edges.last().copied().unwrap_or(1.0);
    picture((900, 540), path, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..x_max, (lo / 2.0..hi * 2.0).log_scale())
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .x_desc("radial frequency [cycles/pixel]")
            .y_desc("share of power (mean per bin, normalised)")
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .label_style(("sans-serif", 15))
            .draw()
            .map_err(plot_err)?;
        let series = [
            (&gt, RGBColor(40, 40, 40), "ground truth"),
            (&render, RGBColor(200, 60, 30), "render"),
        ];
        for (pts, colour, label) in series {
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
                .map_err(plot_err)?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                .map_err(plot_err)?;
        }
        legend(&mut chart, SeriesLabelPosition::UpperRight)
    })
}
