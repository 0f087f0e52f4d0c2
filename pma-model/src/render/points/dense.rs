//! The dense routes: every sample of a stage through the network, in one call with the graph
//! kept (training, the parity hook) or in bounded chunks on the CPU workers, outputs detached
//! (inference).

use candle_core::Tensor;

use crate::error::{ModelError, Result};
use crate::network::trace::Trace;
use crate::network::{Network, PoseFeatures};

/// Points per network call in inference on the CPU: the largest per-point tensors are
/// [n,24,128] f32, 48 MiB each at 4,096 points, a handful alive per worker; many chunks also
/// keep the workers balanced. Larger chunks were no faster.
pub const INFERENCE_POINT_CHUNK: usize = 4_096;

/// Points per network call of an inference pass on `device` for a network of `cfg`: on a
/// GPU as many as its memory budget holds ([`crate::compute::device::element_budget`], a
/// point being joints × the widest per-joint feature), at least [`INFERENCE_POINT_CHUNK`]:
/// each call is ~170 kernel launches whatever its size, so a GPU wants few large calls. The
/// CPU keeps [`INFERENCE_POINT_CHUNK`].
pub fn inference_point_chunk(
    device: &candle_core::Device,
    cfg: &crate::network::config::Config,
) -> usize {
    let per_point = cfg.n_joints * cfg.win_hidden.max(cfg.point_enc_dim).max(1);
    // A real GPU's free memory is read once: the memory pool keeps what the first passes
    // allocated, which would read as used afterwards.
    static GPU_BUDGET: std::sync::OnceLock<Option<usize>> = std::sync::OnceLock::new();
    let budget = match device.is_cpu() {
        true => crate::compute::device::element_budget(device),
        false => *GPU_BUDGET.get_or_init(|| crate::compute::device::element_budget(device)),
    };
    budget.map_or(INFERENCE_POINT_CHUNK, |b| {
        (b / per_point.max(1)).max(INFERENCE_POINT_CHUNK)
    })
}

/// Every sample of the `m` rays from ray `first` on: pts [m·S,3] and the view features of
/// their rays repeated per sample.
fn ray_block(pts: &Tensor, view: &Tensor, first: usize, m: usize) -> Result<(Tensor, Tensor)> {
    let (_, s, _) = pts.dims3()?;
    let vdim = view.dim(1)?;
    let pts_b = pts.narrow(0, first, m)?.reshape((m * s, 3))?;
    let view_b = view
        .narrow(0, first, m)?
        .unsqueeze(1)?
        .broadcast_as((m, s, vdim))?
        .reshape((m * s, vdim))?;
    Ok((pts_b, view_b))
}

/// One network call for all poses of the pass, graph kept: the samples are grouped by pose
/// in equal blocks, which is what [`Network::eval_poses`] takes. The trace is in ray order.
pub(super) fn dense(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
    stage: &str,
    trace: Option<&mut Trace>,
) -> Result<(Tensor, Tensor)> {
    crate::interrupt::check()?;
    let (pts_all, view_all) = ray_block(pts, view, 0, pts.dim(0)?)?;
    let traced = trace.map(|t| (t, stage));
    net.eval_poses(pose, 0..pose.g.dim(0)?, &pts_all, &view_all, traced)
}

/// Every (pose, chunk) pair is one job for the workers; outputs stay in ray order.
pub(super) fn chunked(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let (r, s, _) = pts.dims3()?;
    let n_poses = pose.g.dim(0)?;
    let chunk = inference_point_chunk(pts.device(), net.config());
    let k = r / n_poses;
    let n = k * s;
    if chunk >= n && !crate::compute::account::cpu_route(pts.device()) {
        return pose_groups(net, pose, pts, view, (chunk / n.max(1)).clamp(1, n_poses));
    }
    let per_pose = n.div_ceil(chunk);
    let inputs = (0..n_poses)
        .map(|p| ray_block(pts, view, p * k, k))
        .collect::<Result<Vec<_>>>()?;
    let workers = crate::compute::parallel::workers_on(pts.device());
    let outs = crate::compute::parallel::map_ordered(workers, n_poses * per_pose, |i| {
        crate::interrupt::check()?;
        let (p, c) = (i / per_pose, i % per_pose);
        let (start, len) = (c * chunk, chunk.min(n - c * chunk));
        let (pts_p, view_p) = &inputs[p];
        let (rgb, sigma_raw) = net.eval_points(
            pose,
            p,
            &pts_p.narrow(0, start, len)?,
            &view_p.narrow(0, start, len)?,
            None,
        )?;
        // Detached at once: the weights are variables, so the outputs would otherwise keep
        // the chunk's whole graph alive until every chunk is done.
        Ok::<_, ModelError>((rgb.detach(), sigma_raw.detach()))
    })?;
    let (rgbs, sigmas): (Vec<_>, Vec<_>) = outs.into_iter().unzip();
    Ok((Tensor::cat(&rgbs, 0)?, Tensor::cat(&sigmas, 0)?))
}

/// On a GPU whose calls hold more than a pose's samples: one network call per `group` poses
/// (the whole pass when it fits), outputs detached at once, in ray order.
fn pose_groups(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
    group: usize,
) -> Result<(Tensor, Tensor)> {
    let n_poses = pose.g.dim(0)?;
    let k = pts.dim(0)? / n_poses;
    let (mut rgbs, mut sigmas) = (Vec::new(), Vec::new());
    for p0 in (0..n_poses).step_by(group.max(1)) {
        crate::interrupt::check()?;
        let p1 = (p0 + group).min(n_poses);
        let (pts_g, view_g) = ray_block(pts, view, p0 * k, (p1 - p0) * k)?;
        let (rgb, sigma) = net.eval_poses(pose, p0..p1, &pts_g, &view_g, None)?;
        rgbs.push(rgb.detach());
        sigmas.push(sigma.detach());
    }
    Ok((Tensor::cat(&rgbs, 0)?, Tensor::cat(&sigmas, 0)?))
}
