//! `pma forward`: run the model on a ray batch stored as npz (the parity hook for outside
//! tools). The batch holds the golden `input/*` arrays without the prefix: per-ray copies of
//! the pose data, as the reference's data loader delivers them.
//!
//! No gradient is needed here, so by default the batch runs on the inference path
//! (`Mode::Infer`: detached, chunked, on the data-parallel workers), which writes the same
//! bytes as the graph-keeping path (`--grad`, `Mode::Train`/`Mode::Eval`) that this command
//! ran before; `tests/cli/forward.rs` compares the two output files byte for byte.

use std::collections::HashMap;
use std::io::{BufWriter, Write as _};
use std::path::PathBuf;

use anyhow::{Context, Result};

use super::{refuse, Refused};
use candle_core::Tensor;
use pma_data::dataset::npz::{MemberData, NpyData, NpzReader, NpzWriter};
use pma_data::fsio::AtomicFile;
use pma_model::network::checkpoint;
use pma_model::render::avatar::{Avatar, Mode, Outputs, Poses, Rays};

#[derive(clap::Args)]
pub struct Args {
    /// Model checkpoint (.safetensors), or a run directory (its newest complete model).
    #[arg(long)]
    model: PathBuf,
    /// Load a model with NaN or infinite weights (refused otherwise), to see what it computes.
    #[arg(long)]
    allow_non_finite: bool,
    /// Ray batch npz: rays_o, rays_d [R,3], kp3d [R,24,3], skts [R,24,4,4], bones [R,24,3],
    /// cyls [R,5], cam_idxs [R], bgs [R,3], rest_pose [24,3]; optional N_unique.
    #[arg(long)]
    batch: PathBuf,
    /// Output npz.
    #[arg(long)]
    out: PathBuf,
    /// safetensors whose tensors replace the model's (e.g. the golden `dense` case's sigma head).
    #[arg(long)]
    sigma_override: Option<PathBuf>,
    /// Frame codes as in training: looked up by index, and a batch whose indices are all −1 is
    /// refused (with `false`, as in evaluation, such a batch gets the mean code). No density
    /// noise either way.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    train_mode: bool,
    /// Keep the autograd graph (the pass gradients would need): one network call per pose
    /// instead of the inference path's detached chunks on all cores. Same outputs, slower.
    #[arg(long)]
    grad: bool,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// TF32 matrix products on CUDA: faster, changes results (see docs/numerics.md, "Low
    /// precision"); refused on other devices.
    #[arg(long)]
    tf32: bool,
    /// After the forward whose outputs are written, run this many more and print their
    /// median wall time (the first call pays one-off costs such as GPU kernel loading).
    #[arg(long, default_value_t = 0)]
    time: usize,
}

struct Batch {
    file: String,
    arrays: HashMap<String, (Vec<usize>, NpyData)>,
}

impl Batch {
    fn get(&self, key: &str, shape: &[Option<usize>]) -> Result<(&[usize], &NpyData)> {
        let (s, d) = self
            .arrays
            .get(key)
            .ok_or_else(|| Refused::new(format!("{}: missing key `{key}`", self.file)))?;
        let ok =
            s.len() == shape.len() && s.iter().zip(shape).all(|(a, b)| b.is_none_or(|b| *a == b));
        if !ok {
            let want: Vec<String> = shape
                .iter()
                .map(|d| d.map_or("*".into(), |v| v.to_string()))
                .collect();
            refuse!(
                "{}: key `{key}`: expected shape [{}], found {s:?}",
                self.file,
                want.join(",")
            );
        }
        Ok((s, d))
    }

    fn f32(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<f32>> {
        let (_, d) = self.get(key, shape)?;
        let v = match d {
            NpyData::F32(v) => v.clone(),
            NpyData::F64(v) => v.iter().map(|x| *x as f32).collect(),
            other => refuse!(
                "{}: key `{key}`: expected float32, found {:?}",
                self.file,
                other.elem()
            ),
        };
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            refuse!(
                "{}: key `{key}`: non-finite value at flat index {i}",
                self.file
            );
        }
        Ok(v)
    }

    fn i64(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<i64>> {
        let (_, d) = self.get(key, shape)?;
        Ok(match d {
            NpyData::I64(v) => v.clone(),
            NpyData::I32(v) => v.iter().map(|x| *x as i64).collect(),
            other => refuse!(
                "{}: key `{key}`: expected an integer array, found {:?}",
                self.file,
                other.elem()
            ),
        })
    }
}

pub fn run(mut args: Args) -> Result<()> {
    if args.time > 1000 {
        refuse!("--time {}: at most 1000 repetitions", args.time);
    }
    args.model = super::model_path(&args.model)?;
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input("--batch", &args.batch)
            .input_opt("--sigma-override", args.sigma_override.as_deref())
            .output("--out", &args.out),
    )?;
    let dev = super::device_tf32(&args.device, args.tf32)?;
    let file = args.batch.display().to_string();
    let b = Batch::read(&args.batch)?;
    let input = b.model_input(&dev)?;
    let avatar = load_model(&args, &input.rest, &file, &dev)?;
    let mut opts = match (args.grad, args.train_mode) {
        (true, true) => Mode::Train(None),
        (true, false) => Mode::Eval,
        (false, train_mode) => {
            if train_mode && avatar.config().use_framecodes {
                check_training_codes(&input.rays.framecodes, &file)?;
            }
            Mode::Infer
        }
    };
    let parity = pma_model::render::PassOptions::parity();
    let out = avatar.forward(&input.rays, &input.poses, &mut opts, &parity, None)?;
    if args.time > 0 {
        time_forward(&args, &avatar, &input, &mut opts, &dev)?;
    }
    write_outputs(&out, &args.out)?;
    println!(
        "wrote {} ({} rays, {} pose(s))",
        args.out.display(),
        input.rays.framecodes.len(),
        input.poses.bones.len()
    );
    Ok(())
}

/// The inference path looks frame codes up as evaluation does; the two rules differ only on
/// a batch whose indices are all negative (evaluation: the mean code; training: an error),
/// so `--train-mode` refuses that batch up front, as the graph path in training mode does.
fn check_training_codes(codes: &[i64], file: &str) -> Result<()> {
    if let Some(bad) = codes.iter().find(|&&i| i < 0) {
        refuse!(
            "{file}: key `cam_idxs`: frame-code index {bad} is negative in training mode \
             (pass `--train-mode false` for the mean code)"
        );
    }
    Ok(())
}

/// What the batch file holds, as model input.
struct Input {
    rays: Rays,
    poses: Poses,
    /// The rest pose the batch was made for.
    rest: Vec<f32>,
}

impl Batch {
    fn read(path: &std::path::Path) -> Result<Self> {
        let mut reader = NpzReader::open(path)?;
        let mut arrays = HashMap::new();
        for key in reader.keys() {
            let a = reader.read(&key)?;
            arrays.insert(key, (a.shape, a.data));
        }
        Ok(Self {
            file: path.display().to_string(),
            arrays,
        })
    }

    fn model_input(&self, dev: &candle_core::Device) -> Result<Input> {
        let file = &self.file;
        let rays_o = self.f32("rays_o", &[None, Some(3)])?;
        let r = rays_o.len() / 3;
        let n = Some(r);
        let rays_d = self.f32("rays_d", &[n, Some(3)])?;
        let bones = self.f32("bones", &[n, Some(24), Some(3)])?;
        let skts = self.f32("skts", &[n, Some(24), Some(4), Some(4)])?;
        let cyls = self.f32("cyls", &[n, Some(5)])?;
        let bgs = self.f32("bgs", &[n, Some(3)])?;
        let cam_idxs = self.i64("cam_idxs", &[n])?;
        let rest = self.f32("rest_pose", &[Some(24), Some(3)])?;
        let n_unique = match self.arrays.get("N_unique") {
            Some(_) => self
                .i64("N_unique", &[Some(1)])
                .or_else(|_| self.i64("N_unique", &[]))?[0] as usize,
            None => 1,
        };
        if r == 0 || n_unique == 0 || r % n_unique != 0 {
            refuse!(
                "{file}: {r} rays cannot be split into N_unique = {n_unique} equal per-pose blocks"
            );
        }
        let stride = r / n_unique;
        // Unique poses by striding, as the reference does.
        let pick = |v: &[f32], per: usize| -> Vec<f32> {
            (0..n_unique)
                .flat_map(|p| v[p * stride * per..(p * stride + 1) * per].to_vec())
                .collect()
        };
        let mut pose_bones = Vec::new();
        for p in 0..n_unique {
            let mut j = [[0f32; 3]; 24];
            for (k, row) in j.iter_mut().enumerate() {
                let at = (p * stride * 24 + k) * 3;
                row.copy_from_slice(&bones[at..at + 3]);
            }
            pose_bones.push(j);
        }
        Ok(Input {
            poses: Poses {
                bones: pose_bones,
                skts: Tensor::from_vec(pick(&skts, 24 * 16), (n_unique, 24, 4, 4), dev)?,
                cyls: Tensor::from_vec(pick(&cyls, 5), (n_unique, 5), dev)?,
            },
            rays: Rays {
                origins: Tensor::from_vec(rays_o, (r, 3), dev)?,
                dirs: Tensor::from_vec(rays_d, (r, 3), dev)?,
                bgs: Some(Tensor::from_vec(bgs, (r, 3), dev)?),
                framecodes: cam_idxs,
            },
            rest,
        })
    }
}

/// The model, checked against the batch's rest pose, with `--sigma-override` applied.
fn load_model(args: &Args, rest: &[f32], file: &str, dev: &candle_core::Device) -> Result<Avatar> {
    let opts = checkpoint::LoadOptions {
        allow_non_finite: args.allow_non_finite,
    };
    let ck = checkpoint::load_with(&args.model, dev, &opts)?;
    let model_rest: Vec<f32> = ck.meta.rest_pose.iter().flatten().copied().collect();
    let rest_err = model_rest
        .iter()
        .zip(rest)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    if rest_err > 1e-5 {
        refuse!("{file}: key `rest_pose` differs from the model's rest pose by {rest_err:.2e} (the batch was made for another subject)");
    }
    let mut tensors = ck.tensors;
    if let Some(path) = &args.sigma_override {
        for (k, v) in candle_core::safetensors::load(path, dev)
            .map_err(|e| Refused::new(format!("reading {}: {e}", path.display())))?
        {
            match tensors.get(&k) {
                Some(old) if old.dims() == v.dims() => {
                    tensors.insert(k, v);
                }
                Some(old) => refuse!(
                    "{}: tensor `{k}`: expected shape {:?}, found {:?}",
                    path.display(),
                    old.dims(),
                    v.dims()
                ),
                None => refuse!("{}: tensor `{k}` is not a model tensor", path.display()),
            }
        }
    }
    Ok(Avatar::from_tensors(ck.config, tensors, dev)?)
}

/// `--time`: more forwards, and their median wall time.
fn time_forward(
    args: &Args,
    avatar: &Avatar,
    input: &Input,
    opts: &mut Mode,
    dev: &candle_core::Device,
) -> Result<()> {
    let mut secs = Vec::with_capacity(args.time);
    for _ in 0..args.time {
        // Synchronise on both sides: GPU work is queued asynchronously, so the clock
        // must not start before earlier work ends nor stop before this work does.
        dev.synchronize()?;
        let t0 = std::time::Instant::now();
        let parity = pma_model::render::PassOptions::parity();
        let o = avatar.forward(&input.rays, &input.poses, opts, &parity, None)?;
        dev.synchronize()?;
        secs.push(t0.elapsed().as_secs_f64());
        drop(o);
    }
    secs.sort_by(f64::total_cmp);
    println!(
        "forward on {}: median {:.4} s, min {:.4} s over {} runs ({} rays)",
        args.device,
        secs[secs.len() / 2],
        secs[0],
        secs.len(),
        input.rays.framecodes.len()
    );
    Ok(())
}

/// The outputs under the reference's names, as one npz written atomically.
fn write_outputs(out: &Outputs, path: &std::path::Path) -> Result<()> {
    let outputs: Vec<(&str, &Tensor)> = vec![
        ("rgb_map", &out.fine.rgb),
        ("acc_map", &out.fine.acc),
        ("disp_map", &out.fine.disp),
        ("weights", &out.fine.weights),
        ("alpha", &out.fine.alpha),
        ("rgb0", &out.coarse.rgb),
        ("acc0", &out.coarse.acc),
        ("disp0", &out.coarse.disp),
        ("alpha0", &out.coarse.alpha),
        ("z_vals", &out.z_vals),
        ("z_vals_coarse", &out.z_coarse),
        ("raw", &out.raw_coarse),
        ("raw_merged", &out.raw),
        ("vol_scale", &out.vol_scale),
    ];
    let file = AtomicFile::create(path)
        .with_context(|| format!("creating a temporary file for {}", path.display()))?;
    let mut w = NpzWriter::new(
        BufWriter::new(file.owned_writer()?),
        false,
        path.display().to_string(),
    );
    for (name, t) in outputs {
        let data = t.flatten_all()?.to_vec1::<f32>()?;
        w.add(name, t.dims(), MemberData::F32(&data))?;
    }
    w.finish()?
        .flush()
        .with_context(|| format!("writing {}", path.display()))?;
    file.commit()
        .with_context(|| format!("writing {}", path.display()))
}
