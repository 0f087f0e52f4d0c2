//! `pma inspect FILE`: a pma-npz dataset's members (dtype, shape, storage), counts, pose and
//! camera ranges, and the result of validating it (see `docs/conventions.md`, "Validation") for a use
//! profile.
//! An invalid file prints its error and exits non-zero.
//!
//! A model checkpoint (`.safetensors`) gets its config and, per tensor, its shape, range
//! and count of NaN/infinite values: the one place that loads a checkpoint with
//! non-finite weights (every other command refuses it).

use std::path::{Path, PathBuf};

use anyhow::Context as _;

use super::Refused;
use pma_data::dataset::npz::NpzReader;
use pma_data::dataset::{frames_path_for, Dataset, Profile, ReadOptions};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The dataset (`.npz`, or a `.scene.npz` with its `.frames.npz`), or a model
    /// checkpoint (`.safetensors`).
    pub file: PathBuf,
    /// Profile to validate against: motion, render, eval, train, or auto (the most demanding
    /// one whose keys the file has).
    #[arg(long, default_value = "auto")]
    pub profile: String,
    /// Accept `rest_pose[0]` away from the origin.
    #[arg(long)]
    pub allow_offset_root: bool,
    /// Accept 0/255 masks (values >= 2 count as foreground).
    #[arg(long)]
    pub binarize_masks: bool,
    /// Accept RGBA images by dropping alpha.
    #[arg(long)]
    pub drop_alpha: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::check_paths(pma_data::fsio::PathCheck::new().input("file", &args.file))?;
    if args
        .file
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("safetensors"))
    {
        return inspect_checkpoint(&args.file);
    }
    let mut keys = Vec::new();
    list_members(&args.file, &mut keys)?;
    if let Some(frames) = frames_path_for(&args.file).filter(|f| f.is_file()) {
        list_members(&frames, &mut keys)?;
    }
    let profile = match args.profile.as_str() {
        "auto" => auto_profile(&keys),
        p => p.parse()?,
    };
    println!(
        "profile: {profile}{}",
        if args.profile == "auto" {
            " (auto)"
        } else {
            ""
        }
    );
    let mut opts = ReadOptions::new(profile);
    opts.allow_offset_root = args.allow_offset_root;
    opts.binarize_masks = args.binarize_masks;
    opts.drop_alpha = args.drop_alpha;
    let ds = match Dataset::read(&args.file, &opts) {
        Ok(ds) => ds,
        Err(e) => {
            println!("validation: FAILED");
            return Err(Refused::new(format!("invalid dataset ({profile} profile): {e}")).into());
        }
    };
    summary(&ds);
    println!("validation: ok ({profile} profile)");
    Ok(())
}

/// A checkpoint's config and tensors, non-finite values included; refused (exit 2) after
/// the listing when a tensor holds any.
fn inspect_checkpoint(path: &Path) -> anyhow::Result<()> {
    use pma_model::network::checkpoint::{load_with, LoadOptions};
    let opts = LoadOptions {
        allow_non_finite: true,
    };
    let ck = load_with(path, &candle_core::Device::Cpu, &opts)?;
    let c = &ck.config;
    println!(
        "{}: pma checkpoint{}, trunk {}x{}, n_pm {}, gnn width {}, n_framecodes {}, samples {} + {}",
        path.display(),
        if ck.meta.config_inferred {
            " (config inferred from the shapes)"
        } else {
            ""
        },
        c.trunk_depth,
        c.trunk_width,
        c.n_pm,
        c.gnn_width,
        c.n_framecodes,
        c.n_samples,
        c.n_importance
    );
    println!(
        "  {:<44} {:<16} {:>12} {:>12} {:>10}",
        "tensor", "shape", "min", "max", "non-finite"
    );
    let mut names: Vec<&String> = ck.tensors.keys().collect();
    names.sort();
    let mut bad = Vec::new();
    for name in names {
        let t = &ck.tensors[name];
        let v = t.flatten_all()?.to_vec1::<f32>()?;
        let finite = v.iter().copied().filter(|x| x.is_finite());
        let (lo, hi) = range(finite).unwrap_or((f64::NAN, f64::NAN));
        let n_bad = v.iter().filter(|x| !x.is_finite()).count();
        if n_bad > 0 {
            bad.push(name.clone());
        }
        println!(
            "  {:<44} {:<16} {:>12.4e} {:>12.4e} {:>10}",
            name,
            format!("{:?}", t.dims()),
            lo,
            hi,
            n_bad
        );
    }
    if let Some(first) = bad.first() {
        println!("validation: FAILED");
        return Err(Refused::new(format!(
            "{}: {} tensor(s) hold NaN or infinite values (the first: `{first}`); other commands refuse this model",
            path.display(),
            bad.len()
        ))
        .into());
    }
    println!("validation: ok");
    Ok(())
}

fn list_members(path: &Path, keys: &mut Vec<String>) -> anyhow::Result<()> {
    let mut r = NpzReader::open(path).with_context(|| format!("opening {}", path.display()))?;
    println!("{}", path.display());
    println!(
        "  {:<18} {:<6} {:<22} {:>12}  storage",
        "key", "dtype", "shape", "bytes"
    );
    for key in r.keys() {
        let info = r.info(&key)?;
        let mut notes = Vec::new();
        notes.push(if info.compressed {
            "deflated"
        } else {
            "stored"
        });
        if info.big_endian {
            notes.push("big-endian");
        }
        if info.fortran_order {
            notes.push("fortran-order");
        }
        println!(
            "  {:<18} {:<6} {:<22} {:>12}  {}",
            key,
            info.descr,
            format!("{:?}", info.shape),
            info.size,
            notes.join(", ")
        );
        keys.push(key);
    }
    for other in r.other_members() {
        println!("  {other} (not an array; ignored)");
    }
    Ok(())
}

fn auto_profile(keys: &[String]) -> Profile {
    let has = |k: &str| keys.iter().any(|x| x == k);
    if has("imgs") && has("masks") && has("sampling_masks") {
        Profile::Train
    } else if has("imgs") && has("masks") {
        Profile::Eval
    } else if has("c2ws") && has("img_shape") {
        Profile::Render
    } else {
        Profile::Motion
    }
}

/// (min, max) of an iterator of f32 as f64.
fn range(values: impl Iterator<Item = f32>) -> Option<(f64, f64)> {
    values.fold(None, |acc, v| {
        let v = v as f64;
        Some(match acc {
            None => (v, v),
            Some((lo, hi)) => (lo.min(v), hi.max(v)),
        })
    })
}

fn fmt_range(r: Option<(f64, f64)>) -> String {
    match r {
        Some((lo, hi)) => format!("[{lo:.4}, {hi:.4}]"),
        None => "-".into(),
    }
}

fn summary(ds: &Dataset) {
    println!(
        "counts: P = {} poses, C = {} cameras, N = {} images, image {}x{} (W x H), B = {} background plates",
        ds.n_poses(),
        ds.n_cameras(),
        ds.n_images(),
        ds.width(),
        ds.height(),
        ds.bkgds.as_ref().map_or(0, |b| b.shape()[0])
    );
    println!("head_dir: {:?}, pose_scale: {}", ds.head_dir, ds.pose_scale);
    let angles = ds
        .bones
        .rows()
        .into_iter()
        .map(|w| (w[0].powi(2) + w[1].powi(2) + w[2].powi(2)).sqrt());
    println!("bones |w| (rad): {}", fmt_range(range(angles)));
    if let Some(kp) = &ds.kp3d {
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            let root = kp.outer_iter().map(|p| p[[0, k]]);
            let all = kp.iter().skip(k).step_by(3).copied();
            println!(
                "kp3d {axis}: root {}  all joints {}",
                fmt_range(range(root)),
                fmt_range(range(all))
            );
        }
    }
    if let Some(f) = &ds.focals {
        println!("focals (px): {}", fmt_range(range(f.iter().copied())));
    }
    if let Some(c2ws) = &ds.c2ws {
        let dist = c2ws
            .outer_iter()
            .map(|m| (m[[0, 3]].powi(2) + m[[1, 3]].powi(2) + m[[2, 3]].powi(2)).sqrt());
        println!("camera distance to the origin: {}", fmt_range(range(dist)));
    }
    if let Some(tags) = &ds.eval_tag {
        let count = |t: i8| tags.iter().filter(|&&x| x == t).count();
        println!(
            "eval_tag: {} train, {} novel view, {} novel pose, {} val",
            count(0),
            count(1),
            count(2),
            count(3)
        );
    }
    if let Some(m) = &ds.masks {
        let fg = m.iter().filter(|&&v| v > 0).count();
        println!(
            "mask foreground: {:.2}% of pixels",
            100.0 * fg as f64 / m.len().max(1) as f64
        );
    }
    if !ds.derived.is_empty() {
        println!("derived: {}", ds.derived.join("; "));
    }
    for w in &ds.warnings {
        println!("warning: {w}");
    }
}
