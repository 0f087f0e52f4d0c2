//! `pma synth`: render the built-in synthetic multi-view scene (`pma_data::synth`) into
//! `OUT/{train,novel_view,novel_pose}.npz` (pma-npz v1), `OUT/scene.json` and
//! `OUT/preview.png`. The same settings and seed always give byte-identical files.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use pma_data::synth::{generate, SynthConfig};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Output directory.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = SynthConfig::default().res)]
    pub res: usize,
    /// Training cameras on the ring.
    #[arg(long, default_value_t = SynthConfig::default().train_cams)]
    pub train_cams: usize,
    /// Held-out cameras (the novel-view split).
    #[arg(long, default_value_t = SynthConfig::default().test_cams)]
    pub test_cams: usize,
    /// Training frames (poses of the CMU walk).
    #[arg(long, default_value_t = SynthConfig::default().frames)]
    pub frames: usize,
    /// Step through the 30 fps walk (2 = 15 fps poses).
    #[arg(long, default_value_t = SynthConfig::default().frame_stride)]
    pub frame_stride: usize,
    /// The novel-view split takes every k-th training frame.
    #[arg(long, default_value_t = SynthConfig::default().novel_view_stride)]
    pub novel_view_stride: usize,
    /// Motion of the novel-pose split: walk frames after the training span.
    #[arg(long, default_value_t = SynthConfig::default().novel_pose_walk)]
    pub novel_pose_walk: usize,
    /// Motion of the novel-pose split: AIST++ dance frames (poses far from the walk).
    #[arg(long, default_value_t = SynthConfig::default().novel_pose_dance)]
    pub novel_pose_dance: usize,
    /// Sampling-mask margin around the silhouette, pixels.
    #[arg(long, default_value_t = SynthConfig::default().sampling_margin)]
    pub sampling_margin: usize,
    /// Seed of colours, glyphs and camera jitter (the motion is fixed).
    #[arg(long, default_value_t = SynthConfig::default().seed)]
    pub seed: u64,
    /// Store the npz members uncompressed (larger files, memory-mappable pixels).
    #[arg(long)]
    pub stored: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

impl Args {
    fn config(&self) -> SynthConfig {
        SynthConfig {
            res: self.res,
            train_cams: self.train_cams,
            test_cams: self.test_cams,
            frames: self.frames,
            frame_stride: self.frame_stride,
            novel_view_stride: self.novel_view_stride,
            novel_pose_walk: self.novel_pose_walk,
            novel_pose_dance: self.novel_pose_dance,
            sampling_margin: self.sampling_margin,
            seed: self.seed,
            compress: !self.stored,
        }
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = args.config();
    super::check_paths(pma_data::fsio::PathCheck::new().output_dir(
        "--out",
        &args.out,
        [
            "train.npz",
            "novel_view.npz",
            "novel_pose.npz",
            "scene.json",
            "preview.png",
        ],
    ))?;
    let bar = super::progress::bar(args.quiet, 0, "rendering images");
    let start = Instant::now();
    let summary = generate(&cfg, &args.out, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("synthesising the scene into {}", args.out.display()))?;
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    println!(
        "{}x{} px, {} training + {} held-out cameras, seed {}",
        cfg.res, cfg.res, cfg.train_cams, cfg.test_cams, cfg.seed
    );
    for s in &summary.splits {
        println!(
            "  {:<11} {:>5} images  {:>4} poses  cameras {:?}  {:>10} bytes  {}",
            s.name,
            s.images,
            s.poses,
            s.cameras,
            s.bytes,
            s.path.display()
        );
    }
    println!(
        "wrote {} bytes in {secs:.2} s (+ {} and {})",
        summary.total_bytes(),
        summary.scene_json.display(),
        summary.preview.display()
    );
    Ok(())
}
