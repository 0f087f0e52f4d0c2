//! Step accounting: what a training step or an inference pass would launch on a GPU and
//! wait for, counted on any device, the CPU included (docs/gpu.md, "Step accounting").
//!
//! The counting happens in the vendored candle-core (`candle_core::account`), at its storage
//! dispatch point: every storage operation with the kernel launches, dims/strides uploads and
//! bytes that candle's CUDA backend would use for it, matmul FLOPs, each device → host read
//! (a sync on a GPU) and each explicit upload. This module turns those events into
//! [`Counts`] per stage (the stage names of [`crate::compute::profile`]'s marks) and per op
//! name, and ([`cost`]) into an estimated step time on a named GPU ([`Gpu`], [`estimate`]).
//! It also keeps the distinct signatures of the run's ops ([`Issued`]): what candle's CUDA
//! backend must implement for the run (docs/gpu.md, "What candle's CUDA backend must
//! implement").
//!
//! While an [`Account`] is open on a CPU run with [`Route::Cuda`], pma takes the route a
//! CUDA device would take: no fused CPU kernels, candle's own sine where CUDA uses it, one
//! worker (so training chunks as on a GPU). The route belongs to the accounted run (the
//! thread that opened it and the workers it hands work to), not to the process: other
//! threads keep theirs. Outside an accounted run the check costs one relaxed atomic load.

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::thread::ThreadId;

use candle_core::account::{self as hook, Event, Sink};
use candle_core::Device;
use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};

pub mod cost;
pub use cost::{
    estimate, estimates, gpu, Estimate, Gpu, GpuEstimate, Link, Topology, GPUS, INFINIBAND_NDR,
    LAUNCH_S, NVLINK4, PCIE4, PCIE5, SYNC_S,
};

/// The backend whose route an accounted run takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Route {
    /// As on a CUDA device (the only route of a CUDA run).
    Cuda,
    /// pma's CPU route: fused kernels, libm sine, data-parallel workers.
    Cpu,
}

impl std::str::FromStr for Route {
    type Err = ModelError;
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cuda" => Ok(Self::Cuda),
            "cpu" => Ok(Self::Cpu),
            _ => Err(ModelError::Input(format!(
                "account route `{s}`: expected `cuda` or `cpu`"
            ))),
        }
    }
}

impl std::fmt::Display for Route {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Cuda => "cuda",
            Self::Cpu => "cpu",
        })
    }
}

/// Counts of one stage, one op name or a whole run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counts {
    /// candle storage operations (custom ops included).
    pub ops: u64,
    /// Kernel launches, memcpys and memsets they make on a CUDA device.
    pub launches: u64,
    /// Device → host reads: each one a sync on a GPU.
    pub syncs: u64,
    pub sync_bytes: u64,
    /// Explicit host → device uploads of tensor data.
    pub uploads: u64,
    pub upload_bytes: u64,
    /// Implicit uploads of dims and strides (strided layouts, reductions, index_select, where).
    pub param_uploads: u64,
    /// Bytes the ops read and wrote (device memory traffic).
    pub bytes_read: u64,
    pub bytes_written: u64,
    /// Matmul FLOPs.
    pub flops: u64,
    /// Collectives among data-parallel ranks ([`record_collective`]): all-reduces and the
    /// bytes each rank contributes to them (its buffer), all-gathers and theirs. Each also
    /// counts as one op and one launch; their link time is
    /// [`cost::Topology::collective_s`]'s.
    #[serde(default)]
    pub all_reduces: u64,
    #[serde(default)]
    pub all_reduce_bytes: u64,
    #[serde(default)]
    pub all_gathers: u64,
    #[serde(default)]
    pub all_gather_bytes: u64,
}

/// A collective among the ranks of a data-parallel group, as [`record_collective`] counts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Collective {
    /// Every rank ends with the sum of every rank's buffer of this many bytes.
    AllReduce { bytes: u64 },
    /// Every rank ends with every rank's buffer of this many bytes, in rank order.
    AllGather { bytes: u64 },
}

impl Counts {
    /// Add one event.
    pub fn add(&mut self, e: &Event) {
        match *e {
            Event::Op(op, _) => {
                self.ops += 1;
                self.launches += u64::from(op.launches);
                self.param_uploads += u64::from(op.param_uploads);
                self.bytes_read += op.bytes_read;
                self.bytes_written += op.bytes_written;
                self.flops += op.flops;
            }
            Event::Read { bytes } => {
                self.syncs += 1;
                self.sync_bytes += bytes;
            }
            Event::Upload { bytes } => {
                self.uploads += 1;
                self.upload_bytes += bytes;
            }
        }
    }

    /// Add one collective (its op and launch come as an [`Event::Op`]).
    pub fn add_collective(&mut self, c: Collective) {
        match c {
            Collective::AllReduce { bytes } => {
                self.all_reduces += 1;
                self.all_reduce_bytes += bytes;
            }
            Collective::AllGather { bytes } => {
                self.all_gathers += 1;
                self.all_gather_bytes += bytes;
            }
        }
    }

    /// Add another set of counts.
    pub fn merge(&mut self, o: &Counts) {
        self.ops += o.ops;
        self.launches += o.launches;
        self.syncs += o.syncs;
        self.sync_bytes += o.sync_bytes;
        self.uploads += o.uploads;
        self.upload_bytes += o.upload_bytes;
        self.param_uploads += o.param_uploads;
        self.bytes_read += o.bytes_read;
        self.bytes_written += o.bytes_written;
        self.flops += o.flops;
        self.all_reduces += o.all_reduces;
        self.all_reduce_bytes += o.all_reduce_bytes;
        self.all_gathers += o.all_gathers;
        self.all_gather_bytes += o.all_gather_bytes;
    }

    /// Device memory traffic of the ops: bytes read plus bytes written.
    pub fn bytes(&self) -> u64 {
        self.bytes_read + self.bytes_written
    }

    /// Host → device copies of every kind (explicit and dims/strides).
    pub fn all_uploads(&self) -> u64 {
        self.uploads + self.param_uploads
    }
}

/// One distinct operation of an accounted run as candle's CUDA backend picks its kernel:
/// the op's name and its signature (input dtypes and layouts, output dtype, kernel variant,
/// empty grid). Custom ops are pma's own; the kernels they [`record`](hook::record) beside
/// themselves have none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Issued {
    pub op: &'static str,
    pub sig: hook::Sig,
}

/// `[custom ]op[/variant][ dtype:layout,...] -> dtype[ (empty)]`, layouts by
/// [`hook::Lay::letter`]: `matmul f32:n,f32:t -> f32`, `reduce-sum/small f32:s -> f32`,
/// `zeros -> f32`.
impl std::fmt::Display for Issued {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = &self.sig;
        if s.custom {
            f.write_str("custom ")?;
        }
        f.write_str(self.op)?;
        if !s.variant.is_empty() {
            write!(f, "/{}", s.variant)?;
        }
        let inputs: Vec<String> = s
            .inputs
            .iter()
            .flatten()
            .map(|(d, l)| format!("{}:{}", d.as_str(), l.letter()))
            .collect();
        if !inputs.is_empty() {
            write!(f, " {}", inputs.join(","))?;
        }
        write!(f, " -> {}", s.output.as_str())?;
        if s.empty {
            f.write_str(" (empty)")?;
        }
        Ok(())
    }
}

/// One op as the cost model sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Cost {
    /// The op's name (candle's op name or a pma kernel's); not part of a recorded file.
    #[serde(skip)]
    pub op: &'static str,
    pub launches: u32,
    pub bytes: u64,
    pub flops: u64,
}

/// The counts between two stage marks (summed over every time the stage ran).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stage {
    pub name: String,
    /// How many times the stage was closed (once per chunk for the per-chunk stages).
    pub times: u64,
    pub counts: Counts,
    /// Each op of the stage, for [`estimate`].
    #[serde(skip)]
    pub costs: Vec<Cost>,
}

/// Everything an accounted run counted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub route: Route,
    pub total: Counts,
    /// In the order the stages first closed; work after the last mark is the stage `other`.
    pub stages: Vec<Stage>,
    /// Per op name.
    pub ops: BTreeMap<String, Counts>,
    #[serde(default)]
    /// The most bytes of memory allocated during the run that were alive at once: the
    /// run's activations, gradients and new state. What existed before it started (the
    /// parameters, the optimizer's moments) is not included.
    pub peak_live_bytes: u64,
    /// The live bytes after every allocation of the run, in order (for [`Self::extrapolate`]).
    #[serde(skip)]
    pub live_trace: Vec<u64>,
    /// The run's distinct op signatures, in the order of their text.
    #[serde(skip)]
    pub issued: Vec<Issued>,
}

/// `issued` without repeats, in the order of their text.
fn distinct(issued: impl IntoIterator<Item = Issued>) -> Vec<Issued> {
    let set: HashSet<Issued> = issued.into_iter().collect();
    let mut v: Vec<(String, Issued)> = set.into_iter().map(|i| (i.to_string(), i)).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v.into_iter().map(|(_, i)| i).collect()
}

impl Report {
    /// Every op of the run, for [`estimate`].
    pub fn costs(&self) -> impl Iterator<Item = &Cost> + Clone {
        self.stages.iter().flat_map(|s| &s.costs)
    }

    /// The run's estimated time on `gpu` ([`estimate`]).
    pub fn estimate(&self, gpu: &Gpu, tf32: bool) -> Estimate {
        estimate(self.costs(), &self.total, gpu, tf32)
    }
}

/// `v[0] + k·(v[1] − v[0])` when the three values are equally spaced (exactly affine in a
/// size that grows by the same step from one to the next); `None` otherwise.
fn affine(v: [u64; 3], k: u64) -> Option<u64> {
    let [a, b, c] = v.map(i128::from);
    if c - b != b - a {
        return None;
    }
    u64::try_from(a + (b - a) * i128::from(k)).ok()
}

impl Counts {
    /// Every field by [`affine`]; `None` if one is not affine.
    fn affine(c: [&Counts; 3], k: u64) -> Option<Counts> {
        let f = |g: fn(&Counts) -> u64| affine(c.map(g), k);
        Some(Counts {
            ops: f(|c| c.ops)?,
            launches: f(|c| c.launches)?,
            syncs: f(|c| c.syncs)?,
            sync_bytes: f(|c| c.sync_bytes)?,
            uploads: f(|c| c.uploads)?,
            upload_bytes: f(|c| c.upload_bytes)?,
            param_uploads: f(|c| c.param_uploads)?,
            bytes_read: f(|c| c.bytes_read)?,
            bytes_written: f(|c| c.bytes_written)?,
            flops: f(|c| c.flops)?,
            all_reduces: f(|c| c.all_reduces)?,
            all_reduce_bytes: f(|c| c.all_reduce_bytes)?,
            all_gathers: f(|c| c.all_gathers)?,
            all_gather_bytes: f(|c| c.all_gather_bytes)?,
        })
    }
}

impl Report {
    /// The run of size `n + k·d`, from three runs of sizes n, n + d, n + 2d (say rays per
    /// step) that made the same ops in the same order and whose every count, per op, per
    /// stage and per op name, is exactly affine in the size (checked: equal steps between
    /// the three). Refused when anything differs, so a count is never extrapolated from a
    /// shape it does not have.
    pub fn extrapolate(runs: [&Report; 3], k: u64) -> Result<Report> {
        let bad = |what: String| {
            ModelError::Input(format!(
                "cannot extrapolate the account: {what} is not the same or not affine in the size"
            ))
        };
        let [a, b, c] = runs;
        if a.route != b.route || b.route != c.route {
            return Err(bad("the route".into()));
        }
        let total = Counts::affine([&a.total, &b.total, &c.total], k)
            .ok_or_else(|| bad("the total".into()))?;
        if a.stages.len() != b.stages.len() || b.stages.len() != c.stages.len() {
            return Err(bad("the list of stages".into()));
        }
        let mut stages = Vec::with_capacity(a.stages.len());
        for ((sa, sb), sc) in a.stages.iter().zip(&b.stages).zip(&c.stages) {
            if sa.name != sb.name
                || sb.name != sc.name
                || sa.times != sb.times
                || sb.times != sc.times
            {
                return Err(bad(format!("stage `{}`", sa.name)));
            }
            if sa.costs.len() != sb.costs.len() || sb.costs.len() != sc.costs.len() {
                return Err(bad(format!("the ops of stage `{}`", sa.name)));
            }
            let costs = sa
                .costs
                .iter()
                .zip(&sb.costs)
                .zip(&sc.costs)
                .map(|((x, y), z)| {
                    if x.op != y.op || y.op != z.op {
                        return None;
                    }
                    Some(Cost {
                        op: x.op,
                        launches: u32::try_from(affine(
                            [x, y, z].map(|c| u64::from(c.launches)),
                            k,
                        )?)
                        .ok()?,
                        bytes: affine([x, y, z].map(|c| c.bytes), k)?,
                        flops: affine([x, y, z].map(|c| c.flops), k)?,
                    })
                })
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| bad(format!("an op of stage `{}`", sa.name)))?;
            stages.push(Stage {
                name: sa.name.clone(),
                times: sa.times,
                counts: Counts::affine([&sa.counts, &sb.counts, &sc.counts], k)
                    .ok_or_else(|| bad(format!("stage `{}`", sa.name)))?,
                costs,
            });
        }
        if !a.ops.keys().eq(b.ops.keys()) || !b.ops.keys().eq(c.ops.keys()) {
            return Err(bad("the set of op names".into()));
        }
        let mut ops = BTreeMap::new();
        for (name, ca) in &a.ops {
            let counts = Counts::affine([ca, &b.ops[name], &c.ops[name]], k)
                .ok_or_else(|| bad(format!("op `{name}`")))?;
            ops.insert(name.clone(), counts);
        }
        // The peak is the largest live size after an allocation. Each of those is affine in
        // the size when the runs allocate alike, but which one is largest can change with
        // the size: extrapolate every point, then take the largest.
        let same_len =
            a.live_trace.len() == b.live_trace.len() && b.live_trace.len() == c.live_trace.len();
        if !same_len {
            return Err(bad("the sequence of allocations".into()));
        }
        let live_trace = (0..a.live_trace.len())
            .map(|i| {
                affine(
                    [&a.live_trace, &b.live_trace, &c.live_trace].map(|t| t[i]),
                    k,
                )
            })
            .collect::<Option<Vec<u64>>>()
            .ok_or_else(|| bad("the live memory after an allocation".into()))?;
        Ok(Report {
            route: a.route,
            total,
            stages,
            ops,
            peak_live_bytes: live_trace.iter().copied().max().unwrap_or(0),
            live_trace,
            // What sizes decide (a small sum's kernel, an empty grid) can differ between
            // sizes: every signature of the three runs.
            issued: distinct([a, b, c].iter().flat_map(|r| r.issued.iter().copied())),
        })
    }
}

/// What [`Report::summary`] writes: counts and estimates per stage, per op and in total.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    pub route: Route,
    pub total: Counts,
    /// [`Report::peak_live_bytes`].
    pub peak_live_bytes: u64,
    pub stages: Vec<StageSummary>,
    pub ops: BTreeMap<String, Counts>,
    /// Estimated times on every GPU of [`GPUS`].
    pub est: Vec<GpuEstimate>,
}

/// One stage of a [`Summary`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageSummary {
    pub name: String,
    pub times: u64,
    pub counts: Counts,
    pub est: Vec<GpuEstimate>,
    /// The stage's ops by name, the most expensive on an H200 first.
    pub ops: Vec<StageOp>,
}

/// The ops of one name within a stage: where a stage's estimated time goes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageOp {
    pub name: &'static str,
    pub ops: u64,
    pub launches: u64,
    pub bytes: u64,
    pub flops: u64,
    /// Their estimated time on an H200 with FP32 matmuls (roofline and launches; the
    /// stage's uploads and syncs are not split by op).
    pub est_h200_s: f64,
}

impl Stage {
    /// [`StageSummary::ops`].
    pub fn by_op(&self) -> Vec<StageOp> {
        let h200 = gpu("h200").expect("H200 is one of the cost model's GPUs");
        let mut names: Vec<&'static str> = self.costs.iter().map(|c| c.op).collect();
        names.sort_unstable();
        names.dedup();
        let mut ops: Vec<StageOp> = names
            .into_iter()
            .map(|name| {
                let of = || self.costs.iter().filter(move |c| c.op == name);
                StageOp {
                    name,
                    ops: of().count() as u64,
                    launches: of().map(|c| u64::from(c.launches)).sum(),
                    bytes: of().map(|c| c.bytes).sum(),
                    flops: of().map(|c| c.flops).sum(),
                    est_h200_s: estimate(of(), &Counts::default(), h200, false).est_s,
                }
            })
            .collect();
        ops.sort_by(|a, b| b.est_h200_s.total_cmp(&a.est_h200_s));
        ops
    }
}

impl Report {
    /// Counts and estimates per stage, per op and in total.
    pub fn summary(&self) -> Summary {
        Summary {
            route: self.route,
            total: self.total,
            peak_live_bytes: self.peak_live_bytes,
            stages: self
                .stages
                .iter()
                .map(|s| StageSummary {
                    name: s.name.clone(),
                    times: s.times,
                    counts: s.counts,
                    est: estimates(s.costs.iter(), &s.counts),
                    ops: s.by_op(),
                })
                .collect(),
            ops: self.ops.clone(),
            est: estimates(self.costs(), &self.total),
        }
    }
}

/// Counts of a run recorded by another program in this module's layout (the official code's
/// harness, `bench/official/count_official.py`): `counts` and the per-op `costs`, plus what
/// it says about itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Recorded {
    pub what: String,
    pub rays: usize,
    /// Set when the counts were extrapolated from steps of these rays.
    #[serde(default)]
    pub extrapolated_from: Option<Vec<usize>>,
    pub counts: Counts,
    #[serde(default)]
    pub syncs_by_kind: BTreeMap<String, u64>,
    #[serde(skip_serializing)]
    pub costs: Vec<Cost>,
}

impl Recorded {
    /// Read a recorded run (JSON); errors name the file.
    pub fn read(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(pma_data::FileError::reading(path))?;
        serde_json::from_str(&text).map_err(|e| {
            ModelError::Input(format!(
                "{}: not a recorded account (expected `what`, `rays`, `counts` and `costs`                  as count_official.py writes them): {e}",
                path.display()
            ))
        })
    }

    /// Estimated times on every GPU of [`GPUS`].
    pub fn estimates(&self) -> Vec<GpuEstimate> {
        estimates(self.costs.iter(), &self.counts)
    }
}

/// The events of the threads of one accounted run.
#[derive(Default)]
struct Tally {
    inner: Mutex<TallyInner>,
    /// The free device memory a CPU run accounted as CUDA sizes its automatic chunks from.
    free_memory: std::sync::atomic::AtomicUsize,
}

#[derive(Default)]
struct TallyInner {
    total: Counts,
    ops: HashMap<&'static str, Counts>,
    /// Per thread, what happened since its last mark.
    pending: HashMap<ThreadId, (Counts, Vec<Cost>)>,
    stages: Vec<Stage>,
    issued: HashSet<Issued>,
}

impl TallyInner {
    fn close(&mut self, thread: ThreadId, name: &str) {
        let (counts, costs) = self.pending.remove(&thread).unwrap_or_default();
        let stage = match self.stages.iter_mut().position(|s| s.name == name) {
            Some(i) => &mut self.stages[i],
            None => {
                self.stages.push(Stage {
                    name: name.to_string(),
                    ..Default::default()
                });
                self.stages.last_mut().expect("just pushed")
            }
        };
        stage.times += 1;
        stage.counts.merge(&counts);
        stage.costs.extend(costs);
    }
}

impl hook::Observer for Tally {
    fn event(&self, e: &Event) {
        let thread = std::thread::current().id();
        let mut t = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        t.total.add(e);
        let pending = t.pending.entry(thread).or_default();
        pending.0.add(e);
        if let Event::Op(op, sig) = e {
            pending.1.push(Cost {
                op: op.name,
                launches: op.launches,
                bytes: op.bytes_read + op.bytes_written,
                flops: op.flops,
            });
            t.ops.entry(op.name).or_default().add(e);
            if let Some(sig) = sig {
                t.issued.insert(Issued {
                    op: op.name,
                    sig: *sig,
                });
            }
        }
    }
}

thread_local! {
    /// The accounted run this thread works for, and its route.
    static CURRENT: RefCell<Option<(Arc<Tally>, Route)>> = const { RefCell::new(None) };
}

/// Whether this thread works for an accounted run that takes the CUDA route on the CPU: the
/// kernel choices that differ between the CPU and CUDA ask this.
#[inline]
pub fn emulates_cuda() -> bool {
    hook::on() && CURRENT.with_borrow(|c| matches!(c, Some((_, Route::Cuda))))
}

/// The free device memory this thread's run accounted as CUDA models
/// ([`Account::model_free_memory`]), if any.
pub fn modeled_free_memory() -> Option<usize> {
    if !emulates_cuda() {
        return None;
    }
    CURRENT.with_borrow(|c| {
        c.as_ref()
            .map(|(t, _)| t.free_memory.load(std::sync::atomic::Ordering::Relaxed))
            .filter(|&b| b > 0)
    })
}

/// Whether work on `device` takes the CPU's route: on the CPU, outside a run accounted as
/// CUDA. The choices between host-side code and device tensor ops ask this.
#[inline]
pub fn cpu_route(device: &Device) -> bool {
    device.is_cpu() && !emulates_cuda()
}

/// Count collective `c` in this thread's accounted run (called by the communicators of
/// `train::parallel` where they exchange a buffer); nothing outside an accounted run.
pub fn record_collective(c: Collective) {
    if !hook::on() {
        return;
    }
    CURRENT.with_borrow(|cur| {
        if let Some((tally, _)) = cur {
            let thread = std::thread::current().id();
            let mut t = tally.inner.lock().unwrap_or_else(|e| e.into_inner());
            t.total.add_collective(c);
            t.pending.entry(thread).or_default().0.add_collective(c);
        }
    });
}

/// Close stage `name` of this thread's accounted run (called by
/// [`crate::compute::profile::mark`]).
pub(crate) fn mark(name: &str) {
    if !hook::on() {
        return;
    }
    CURRENT.with_borrow(|c| {
        if let Some((tally, _)) = c {
            let thread = std::thread::current().id();
            tally
                .inner
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .close(thread, name);
        }
    });
}

/// A thread's membership of an accounted run ([`Handoff::join`]); dropping it restores the
/// thread's previous run.
pub struct Joined {
    prev: Option<(Arc<Tally>, Route)>,
    _candle: hook::Entered,
}

impl Drop for Joined {
    fn drop(&mut self) {
        let prev = self.prev.take();
        CURRENT.with_borrow_mut(|c| *c = prev);
    }
}

fn join(sink: Sink, tally: Arc<Tally>, route: Route) -> Joined {
    let candle = hook::enter(Some(sink));
    let prev = CURRENT.with_borrow_mut(|c| c.replace((tally, route)));
    Joined {
        prev,
        _candle: candle,
    }
}

/// An accounted run on this thread (and the workers it hands work to through
/// [`crate::compute::parallel::map_ordered`]), from [`Account::start`] to [`Account::finish`].
pub struct Account {
    tally: Arc<Tally>,
    /// Where this thread's events go: it also keeps the live-memory peak.
    sink: Sink,
    route: Route,
    joined: Option<Joined>,
    /// The run belongs to the thread that opened it.
    _not_send: std::marker::PhantomData<*const ()>,
}

impl Account {
    /// Count everything this thread does on `device` from now on. On the CPU every tensor
    /// counts as device memory; `route` picks the kernels ([`Route::Cpu`] is refused for
    /// other devices, which have one route).
    pub fn start(device: &Device, route: Route) -> Result<Self> {
        if route == Route::Cpu && !device.is_cpu() {
            return Err(ModelError::Input(format!(
                "account route `cpu` on {device:?}: a GPU run takes the `cuda` route"
            )));
        }
        let tally = Arc::new(Tally::default());
        let sink = Sink::new(tally.clone(), device.is_cpu());
        let joined = join(sink.clone(), tally.clone(), route);
        Ok(Self {
            tally,
            sink,
            route,
            joined: Some(joined),
            _not_send: std::marker::PhantomData,
        })
    }

    /// A CPU run accounted as CUDA sizes its automatic chunks (training steps with
    /// `chunk_rays = 0`, inference calls) as a GPU with `bytes` of free memory would
    /// ([`crate::compute::device::free_memory`]); without this, with the CPU's budgets.
    pub fn model_free_memory(&self, bytes: usize) {
        self.tally
            .free_memory
            .store(bytes, std::sync::atomic::Ordering::Relaxed);
    }

    /// Close stage `name` (what [`crate::compute::profile::mark`] does for its stages).
    pub fn mark(&self, name: &str) {
        mark(name)
    }

    /// Stop counting. Work after the last mark of each thread is the stage `other`.
    pub fn finish(mut self) -> Report {
        self.joined = None;
        let mut t = self.tally.inner.lock().unwrap_or_else(|e| e.into_inner());
        let threads: Vec<ThreadId> = t.pending.keys().copied().collect();
        for thread in threads {
            t.close(thread, "other");
        }
        let mut ops: BTreeMap<String, Counts> = BTreeMap::new();
        for (name, c) in &t.ops {
            ops.entry(name.to_string()).or_default().merge(c);
        }
        Report {
            route: self.route,
            total: t.total,
            stages: std::mem::take(&mut t.stages),
            ops,
            peak_live_bytes: self.sink.peak_live_bytes(),
            live_trace: self.sink.live_trace(),
            issued: distinct(t.issued.drain()),
        }
    }
}

/// Run `f` as an accounted run on `device` with `route`.
pub fn measure<T, E: From<ModelError>>(
    device: &Device,
    route: Route,
    f: impl FnOnce() -> std::result::Result<T, E>,
) -> std::result::Result<(T, Report), E> {
    let account = Account::start(device, route)?;
    let out = f()?;
    Ok((out, account.finish()))
}

/// This thread's accounted run, captured to be joined on worker threads.
pub struct Handoff(Option<(Sink, Arc<Tally>, Route)>);

impl Handoff {
    /// The calling thread's run (nothing outside an accounted run).
    pub fn capture() -> Self {
        if !hook::on() {
            return Self(None);
        }
        let sink = hook::current();
        let cur = CURRENT.with_borrow(|c| c.clone());
        Self(sink.zip(cur).map(|(s, (t, r))| (s, t, r)))
    }

    /// Join the captured run on this thread until the guard drops.
    pub fn join(&self) -> Option<Joined> {
        self.0
            .as_ref()
            .map(|(s, t, r)| join(s.clone(), t.clone(), *r))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Tensor, D};

    /// [`super::measure`] with the crate's error type.
    fn measure<T>(
        dev: &Device,
        route: Route,
        f: impl FnOnce() -> Result<T>,
    ) -> Result<(T, Report)> {
        super::measure(dev, route, f)
    }

    /// A known small graph: every count is worked out by hand from candle's CUDA backend.
    #[test]
    fn counts_a_known_graph_exactly() {
        let dev = Device::Cpu;
        let a = Tensor::arange(0f32, 6.0, &dev)
            .unwrap()
            .reshape((2, 3))
            .unwrap();
        let b = Tensor::ones((3, 4), DType::F32, &dev).unwrap();
        let (out, r) = measure(&dev, Route::Cuda, || {
            // matmul [2,3]x[3,4]: 2·2·4·3 = 48 FLOPs, reads 24 + 48 B, writes 32 B.
            let c = a.matmul(&b)?;
            // sin: one kernel, contiguous, 32 B in and out.
            let s = c.sin()?;
            // broadcast add of a [4] row: the row is read once (16 B), one dims upload.
            let row = Tensor::new(&[1f32, 2.0, 3.0, 4.0], &dev)?;
            mark("first");
            let t = s.broadcast_add(&row)?;
            // sum over the last dim: a reduction, always one dims upload; 8 B out.
            let total = t.sum(D::Minus1)?;
            // one read-back of [2] f32.
            Ok(total.to_vec1::<f32>()?)
        })
        .unwrap();
        assert_eq!(out.len(), 2);
        let t = r.total;
        assert_eq!(t.ops, 4, "{:?}", r.ops);
        assert_eq!(t.launches, 4);
        assert_eq!(t.flops, 48);
        assert_eq!(t.syncs, 1);
        assert_eq!(t.sync_bytes, 8);
        assert_eq!((t.uploads, t.upload_bytes), (1, 16));
        assert_eq!(t.param_uploads, 2);
        // matmul 72 + 32, sin 32 + 32, add 32 + 16 + 32, sum 32 + 8.
        assert_eq!(t.bytes_read, 72 + 32 + 48 + 32);
        assert_eq!(t.bytes_written, 32 + 32 + 32 + 8);
        assert_eq!(r.ops["matmul"].flops, 48);
        assert_eq!(r.ops["reduce-sum"].param_uploads, 1);
        assert_eq!(r.ops["add"].param_uploads, 1);
        assert_eq!(r.ops["sin"].ops, 1);
        let names: Vec<&str> = r.stages.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["first", "other"]);
        assert_eq!(r.stages[0].counts.ops, 2);
        assert_eq!(r.stages[0].counts.uploads, 1);
        assert_eq!(r.stages[1].counts.syncs, 1);
        assert_eq!(r.costs().count(), 4);
    }

    #[test]
    fn off_counts_nothing_and_other_threads_are_not_counted() {
        let dev = Device::Cpu;
        let x = Tensor::ones(8, DType::F32, &dev).unwrap();
        // Nothing is open: the hooks see no sink.
        let _ = (x.exp().unwrap() + 1.0).unwrap().to_vec1::<f32>().unwrap();
        assert!(!emulates_cuda());
        let account = Account::start(&dev, Route::Cuda).unwrap();
        assert!(emulates_cuda());
        // Another thread's work is not this run's.
        std::thread::scope(|s| {
            s.spawn(|| {
                assert!(!emulates_cuda());
                x.sqr().unwrap().to_vec1::<f32>().unwrap()
            });
        });
        let r = account.finish();
        assert_eq!(r.total, Counts::default());
        assert!(!emulates_cuda());
        // A GPU has one route.
        if let Ok(cuda) = Device::new_cuda(0) {
            assert!(Account::start(&cuda, Route::Cpu).is_err());
        }
    }

    #[test]
    fn handoff_joins_workers_and_closes_their_stages() {
        let dev = Device::Cpu;
        let x = Tensor::ones(4, DType::F32, &dev).unwrap();
        let account = Account::start(&dev, Route::Cpu).unwrap();
        let h = Handoff::capture();
        std::thread::scope(|s| {
            s.spawn(|| {
                let _g = h.join();
                let _ = x.exp().unwrap();
                mark("worker");
                let _ = x.neg().unwrap();
            });
        });
        let r = account.finish();
        assert_eq!(r.total.ops, 2);
        let names: Vec<&str> = r.stages.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["worker", "other"]);
    }

    #[test]
    fn strided_inputs_upload_dims_and_copies_are_memcpys() {
        let dev = Device::Cpu;
        let x = Tensor::ones((3, 5), DType::F32, &dev).unwrap();
        let (_, r) = measure(&dev, Route::Cuda, || {
            let t = x.t()?; // a view: no op
            let _ = t.exp()?; // strided: one upload
            let _ = t.contiguous()?; // strided copy kernel + upload
            let _ = x.contiguous()?; // already contiguous: nothing
            let _ = x.copy()?; // a device copy
            let _ = Tensor::cat(&[&x, &x], 1)?; // two copy2d kernels
            Ok(())
        })
        .unwrap();
        assert_eq!(r.total.ops, 5, "{:?}", r.ops);
        assert_eq!(r.total.param_uploads, 2);
        assert_eq!(r.ops["copy-strided"].ops, 1);
        assert_eq!(r.ops["clone"].ops, 1);
        assert_eq!(r.ops["copy2d"].ops, 2);
    }

    #[test]
    fn scalar_operands_upload_once_as_on_a_gpu() {
        let dev = Device::Cpu;
        let x = Tensor::ones(4, DType::F32, &dev).unwrap();
        let (_, r) = measure(&dev, Route::Cuda, || Ok(x.maximum(0.5)?)).unwrap();
        // On CUDA: the scalar is made and cast on the host, uploaded, then one kernel.
        assert_eq!((r.total.ops, r.total.uploads), (1, 1), "{:?}", r.ops);
        assert_eq!(r.ops["maximum"].ops, 1);
    }

    #[test]
    fn the_cuda_route_takes_candles_kernels_and_row_ops_report_two_launches() {
        let dev = Device::Cpu;
        let x = Tensor::ones((4, 3), DType::F32, &dev).unwrap();
        let b = Tensor::ones(3, DType::F32, &dev).unwrap();
        let ids = Tensor::new(&[2u32, 0], &dev).unwrap();
        let run = |route| {
            measure(&dev, route, || {
                let k = crate::compute::numerics::Numerics::PARITY;
                crate::compute::fast_sine::sin(&x, k.fast_sine)?;
                crate::compute::ops::linear::add_bias(&x, &b, k)?;
                crate::compute::ops::rows::select_rows(&x, &ids, k)?;
                Ok(crate::compute::parallel::workers_on(&dev))
            })
            .unwrap()
        };
        let (_, cpu) = run(Route::Cpu);
        let names: Vec<&str> = cpu.ops.keys().map(String::as_str).collect();
        assert_eq!(names, ["pma-bias-add", "pma-gather-rows", "pma-sin"]);
        // One worker as on a GPU, whatever the process's worker count.
        let (workers, cuda) = run(Route::Cuda);
        assert_eq!(workers, 1);
        let names: Vec<&str> = cuda.ops.keys().map(String::as_str).collect();
        assert_eq!(names, ["add", "pma-gather-rows", "sin"]);
        // The row gather: a memset and a kernel, as on CUDA.
        assert_eq!(cuda.ops["pma-gather-rows"].launches, 2);
        assert_eq!(cuda.total.launches, 4);
    }

    #[test]
    fn extrapolates_only_what_is_affine() {
        let dev = Device::Cpu;
        let run = |n: usize| {
            measure(&dev, Route::Cuda, || {
                let x = Tensor::ones((n, 8), DType::F32, &dev)?;
                let w = Tensor::ones((8, 4), DType::F32, &dev)?;
                mark("a");
                let y = x.matmul(&w)?.sum_all()?;
                Ok(y.to_scalar::<f32>()?)
            })
            .unwrap()
            .1
        };
        let (r1, r2, r3) = (run(10), run(20), run(30));
        // 10 + 4·10 = 50 rows, counted directly and by extrapolation.
        let e = Report::extrapolate([&r1, &r2, &r3], 4).unwrap();
        let direct = run(50);
        assert_eq!(e.total, direct.total);
        assert_eq!(e.peak_live_bytes, direct.peak_live_bytes);
        assert!(e.peak_live_bytes >= 50 * 8 * 4);
        assert_eq!(e.ops, direct.ops);
        assert_eq!(e.stages, direct.stages);
        // Sizes 10, 20, 40 are not equally spaced: the bytes are not affine in the step.
        let r4 = run(40);
        assert!(Report::extrapolate([&r1, &r2, &r4], 4).is_err());
        assert!(Report::extrapolate([&r1, &r2, &run_other(&dev)], 4).is_err());
    }

    /// A backward keeps the activations and the gradients in flight, not every upstream
    /// gradient a weight's gradient was computed from (candle's store keeps what it stores
    /// detached: vendor/candle-core PATCH.md, change 1).
    #[test]
    fn backward_holds_no_upstream_gradient_through_a_weight_gradient() {
        let dev = Device::Cpu;
        let (rows, width, layers) = (256usize, 32usize, 6usize);
        let x = Tensor::ones((rows, width), DType::F32, &dev).unwrap();
        let ws: Vec<candle_core::Var> = (0..layers)
            .map(|_| candle_core::Var::ones((width, width), DType::F32, &dev).unwrap())
            .collect();
        let (_, r) = measure(&dev, Route::Cuda, || {
            let mut h = x.clone();
            for w in &ws {
                h = (h.matmul(w.as_tensor())? * 0.01)?;
            }
            let g = h.sum_all()?.backward()?;
            Ok(g.get(ws[0].as_tensor()).is_some())
        })
        .unwrap();
        let act = (rows * width * 4) as u64;
        // Forward: a product and a scaled copy per layer. Backward: a few [rows,width]
        // gradients at a time, plus the weights' gradients.
        let activations = 2 * layers as u64 * act;
        let weights = (layers * width * width * 4) as u64;
        assert!(
            r.peak_live_bytes <= activations + 3 * act + weights + 4096,
            "peak {} for {activations} of activations",
            r.peak_live_bytes
        );
    }

    /// Each op's signature as candle's CUDA backend picks its kernel: dtypes, layouts (a
    /// matmul operand read as stored or transposed, over a broadcast batch, or in a batch
    /// layout cuBLAS cannot take; a strided view), the small-sum kernel, an empty grid, a
    /// custom op.
    #[test]
    fn signatures_name_dtypes_layouts_variants_and_empty_grids() {
        let dev = Device::Cpu;
        let x = Tensor::ones((3, 5), DType::F32, &dev).unwrap();
        let w = Tensor::ones((4, 5), DType::F32, &dev).unwrap();
        let wide = Tensor::ones((2, 64), DType::F32, &dev).unwrap();
        let adj = Tensor::ones((24, 24), DType::F32, &dev).unwrap();
        let feats = Tensor::ones((2, 24, 8), DType::F32, &dev).unwrap();
        // [2,3,24,24] whose two batch dims are swapped: no single batch stride.
        let swapped = Tensor::ones((3, 2, 24, 24), DType::F32, &dev)
            .unwrap()
            .transpose(0, 1)
            .unwrap();
        let per = Tensor::ones((2, 3, 24, 8), DType::F32, &dev).unwrap();
        let ids = Tensor::new(&[2u32, 0], &dev).unwrap();
        let none = Tensor::zeros((0, 3), DType::F32, &dev).unwrap();
        let (_, r) = measure(&dev, Route::Cuda, || {
            x.matmul(&w.t()?)?;
            adj.unsqueeze(0)?
                .broadcast_as((2, 24, 24))?
                .matmul(&feats)?;
            // The CPU may or may not take it; the signature is counted before it runs.
            let _ = swapped.matmul(&per);
            x.t()?.exp()?;
            x.sum(1)?;
            wide.sum(1)?;
            x.index_select(&ids, 0)?;
            none.ge(&none)?;
            x.to_dtype(DType::F64)?;
            candle_nn::ops::sigmoid(&x)?;
            Ok(())
        })
        .unwrap();
        let got: Vec<String> = r.issued.iter().map(|i| i.to_string()).collect();
        assert_eq!(
            got,
            [
                "cmp-ge f32:c,f32:c -> u8 (empty)",
                "custom sigmoid f32:c -> f32",
                "exp f32:s -> f32",
                "index-select f32:c,u32:c -> f32",
                "matmul f32:n,f32:n -> f32",
                "matmul f32:n,f32:t -> f32",
                "matmul f32:s,f32:n -> f32",
                "reduce-sum f32:c -> f32",
                "reduce-sum/small f32:c -> f32",
                "to-dtype f32:c -> f64",
            ]
        );
    }

    fn run_other(dev: &Device) -> Report {
        measure(dev, Route::Cuda, || {
            Ok(Tensor::ones(3, DType::F32, dev)?.exp()?)
        })
        .unwrap()
        .1
    }
}
