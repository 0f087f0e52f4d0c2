//! The estimated step time of data-parallel training on N GPUs, from step accounting and
//! the cost model with interconnects ([`crate::compute::account::cost::Topology`]). Every
//! figure here is an estimate; none is measured.
//!
//! A rank of N computes the one-pass step of its slice, rays / N (accounted by
//! extrapolation from the same three one-pass steps as the full step), plus the ray casting
//! of the rest of the batch (every rank casts the whole batch; the difference of the `cast`
//! stage between the full step and the rank's step is added), then exchanges the flat
//! gradient and the step's numbers ([`crate::train::parallel::group::step_collectives`]) as rings
//! over the topology, after its backward and before its update (no overlap assumed).

use serde::Serialize;

use crate::compute::account::cost::{Gpu, Link, Topology};
use crate::compute::account::{estimate, Counts, Report, LAUNCH_S};
use crate::train::account::Extrapolated;
use crate::train::TrainError;

/// GPUs per node of the topologies estimated (an 8-GPU HGX/DGX node).
pub const GPUS_PER_NODE: usize = 8;

/// One row of the scaling table: a group of `gpus` GPUs. Every time is an estimate.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingRow {
    pub gpus: usize,
    pub nodes: usize,
    pub gpu: &'static str,
    pub intra: &'static str,
    pub inter: &'static str,
    /// Rays of a step of the whole group, and of each rank's share.
    pub global_rays: usize,
    pub rays_per_rank: usize,
    /// Per rank and step: the collectives and the bytes each rank contributes.
    pub all_reduces: u64,
    pub all_reduce_bytes: u64,
    /// Per rank and step, the collectives included.
    pub launches: u64,
    /// The rank's compute (its slice's step and the rest of the batch's casting), FP32
    /// matmuls.
    pub est_compute_s: f64,
    /// The collectives over the links.
    pub est_link_s: f64,
    pub est_step_s: f64,
    /// The group's rays per second over one GPU's (for the same global batch: one GPU's step
    /// time over the group's).
    pub est_speedup: f64,
    /// `est_speedup / gpus`.
    pub est_efficiency: f64,
}

/// What a group trains: trainable tensors and their elements.
#[derive(Debug, Clone, Copy)]
pub struct Model {
    pub params: usize,
    pub elems: usize,
}

/// The `cast` stage's estimated seconds on `gpu` in `r` (0 when it has none).
fn cast_s(r: &Report, gpu: &Gpu) -> f64 {
    r.stages
        .iter()
        .find(|st| st.name == "cast")
        .map_or(0.0, |st| {
            estimate(st.costs.iter(), &st.counts, gpu, false).est_s
        })
}

/// How a group's batch relates to one GPU's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Batch {
    /// The same global batch split over the ranks: the run one GPU trains (strong scaling).
    Split,
    /// Each rank a whole batch: a global batch N times larger, another run (weak scaling).
    PerRank,
}

/// The estimated scaling rows for each count of `gpus` (with [`Batch::Split`] each must
/// divide the step's rays into multiples of the rays accounted), on `gpu` with `intra`
/// within a node and `inter` between nodes of [`GPUS_PER_NODE`]. The first count must be 1.
pub fn scaling(
    e: &Extrapolated,
    model: Model,
    gpus: &[usize],
    batch: Batch,
    gpu: &Gpu,
    intra: &'static Link,
    inter: &'static Link,
) -> Result<Vec<ScalingRow>, TrainError> {
    let full_cast = cast_s(&e.report, gpu);
    let mut rows: Vec<ScalingRow> = Vec::with_capacity(gpus.len());
    let mut one = None;
    for &n in gpus {
        if n == 0 || (batch == Batch::Split && e.rays % n != 0) {
            return Err(TrainError::Config(format!(
                "{n} GPUs cannot split a step of {} rays evenly",
                e.rays
            )));
        }
        let (rays, global) = match batch {
            Batch::Split => (e.rays / n, e.rays),
            Batch::PerRank => (e.rays, e.rays * n),
        };
        let rank = e.at(rays)?;
        let topo = Topology::of(n, GPUS_PER_NODE, intra, inter);
        let mut coll = Counts::default();
        for c in
            crate::train::parallel::group::step_collectives(n, model.elems, model.params, false)
        {
            coll.add_collective(c);
        }
        let compute = rank.estimate(gpu, false).est_s
            + (full_cast - cast_s(&rank, gpu)).max(0.0)
            + coll.all_reduces as f64 * LAUNCH_S;
        let link = topo.collective_s(&coll);
        let step = compute + link;
        let base = *one.get_or_insert(if n == 1 { step } else { f64::NAN });
        let speedup = (global as f64 / step) / (e.rays as f64 / base);
        rows.push(ScalingRow {
            gpus: n,
            nodes: topo.nodes,
            gpu: gpu.name,
            intra: intra.name,
            inter: inter.name,
            global_rays: global,
            rays_per_rank: rays,
            all_reduces: coll.all_reduces,
            all_reduce_bytes: coll.all_reduce_bytes,
            launches: rank.total.launches + coll.all_reduces,
            est_compute_s: compute,
            est_link_s: link,
            est_step_s: step,
            est_speedup: speedup,
            est_efficiency: speedup / n as f64,
        });
    }
    Ok(rows)
}
