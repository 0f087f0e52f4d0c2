//! Step accounting (a pma change, see PATCH.md): what a run would launch on a CUDA device and
//! wait for, counted at the storage dispatch point so it can be measured on any device.
//!
//! A thread that has entered a [`Sink`] sends one [`Event`] to the sink's [`Observer`] per
//! storage operation (with the launches, dims/strides uploads and bytes that candle's CUDA
//! backend would use for it), per device → host read (`to_vec*`, `to_scalar`,
//! `to_device(Cpu)`) and per explicit host → device upload (tensors made from host data,
//! `to_device` onto a device). When no thread has a sink, each hook is one relaxed atomic
//! load.
//!
//! Each storage operation's event also carries its [`Sig`]: the dtypes and layouts candle's
//! CUDA backend picks its kernel by, so that a run's distinct signatures can be checked
//! against what that backend implements.
//!
//! On a real device, operations on CPU storage are host work and are not counted. A sink
//! made with `host_as_device` counts CPU storage as if it were the device instead: every
//! operation, every copy out of a tensor into host memory (`to_vec*`, `to_scalar`) and every
//! tensor made from host data. That is how a run on the CPU shows what it would cost on a GPU.

use std::any::Any;
use std::cell::{Cell, RefCell};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};

use crate::{DType, Layout, Shape};

/// Threads that currently have a sink entered (any session).
static ENTERED: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    static SINK: RefCell<Option<Sink>> = const { RefCell::new(None) };
    /// Launches and parameter uploads a custom op reported for itself while it ran.
    static REPORTED: Cell<Option<(u32, u32)>> = const { Cell::new(None) };
    /// Bytes read and written a custom op reported for itself while it ran.
    static REPORTED_BYTES: Cell<Option<(u64, u64)>> = const { Cell::new(None) };
    /// Matmul FLOPs a custom op reported for itself while it ran.
    static REPORTED_FLOPS: Cell<u64> = const { Cell::new(0) };
    /// Inside [`host_only`]: CPU storage is host memory even for a `host_as_device` sink.
    static HOST_ONLY: Cell<bool> = const { Cell::new(false) };
    /// Inside [`uncounted`]: nothing is counted.
    static UNCOUNTED: Cell<bool> = const { Cell::new(false) };
}

/// One storage operation, as candle's CUDA backend would run it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Op {
    /// The operation (`"matmul"`, `"add"`, `"reduce-sum"`, a custom op's name, ...).
    pub name: &'static str,
    /// Kernel launches, memcpys and memsets on the stream.
    pub launches: u32,
    /// Implicit host → device uploads of dims and strides (strided layouts, reductions,
    /// `index_select`, `where_cond`).
    pub param_uploads: u32,
    /// Bytes of the inputs (elements behind a broadcast stride are counted once).
    pub bytes_read: u64,
    /// Bytes of the output.
    pub bytes_written: u64,
    /// Floating-point operations of a matmul (2·b·m·n·k); 0 for everything else.
    pub flops: u64,
}

/// How candle's CUDA backend sees an input's layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Lay {
    /// Row-major from its start offset: the kernels' fast path, and the only layout the
    /// indexing kernels take for everything but `index_select`'s indices (`index_select`'s
    /// and `gather`'s source, `gather`'s indices, and the destination, indices and source of
    /// `index_add`, `scatter` and `scatter_add`).
    Contiguous,
    /// Anything else: element-wise kernels index it through the uploaded dims and strides.
    /// A matmul operand is `Strided` when cuBLAS can read it neither as stored nor
    /// transposed (the backend refuses it).
    Strided,
    /// A matmul operand cuBLAS reads as stored (`CUBLAS_OP_N`).
    Normal,
    /// A matmul operand cuBLAS reads transposed (`CUBLAS_OP_T`).
    Transposed,
}

impl Lay {
    /// One letter per layout (`c`, `s`, `n`, `t`).
    pub fn letter(self) -> char {
        match self {
            Lay::Contiguous => 'c',
            Lay::Strided => 's',
            Lay::Normal => 'n',
            Lay::Transposed => 't',
        }
    }
}

/// What candle's CUDA backend picks an operation's kernel by: each input's dtype and layout,
/// the output's dtype, a kernel variant and whether there is any element.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Sig {
    /// A custom op (`apply_op*`, `inplace_op`): its own kernels, not the backend's.
    pub custom: bool,
    /// The inputs in the backend method's order (`where_cond`: condition, then the two
    /// branches; `index_add`, `scatter`: destination, indices, source); unused slots `None`.
    pub inputs: [Option<(DType, Lay)>; 3],
    pub output: DType,
    /// A kernel the backend picks by size: `"small"` for a sum of at most 32 elements per
    /// output (`fast_sum_small_*`); empty otherwise.
    pub variant: &'static str,
    /// The operation's kernel would run no thread (an empty grid): an empty output, or for
    /// `index_add` and `scatter*` no row of the source outside the indexed dim.
    pub empty: bool,
}

impl Sig {
    fn new(inputs: &[(DType, Lay)], output: DType, elements: usize) -> Self {
        Self {
            custom: false,
            inputs: std::array::from_fn(|i| inputs.get(i).copied()),
            output,
            variant: "",
            empty: elements == 0,
        }
    }
}

/// What an [`Observer`] is told.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// A storage operation, with its signature (none for an op [`record`]ed beside a custom
    /// op: a kernel of that op, not a backend call).
    Op(Op, Option<Sig>),
    /// A device → host copy: on a GPU the host waits for the stream (a sync).
    Read {
        bytes: u64,
    },
    /// An explicit host → device copy of tensor data.
    Upload {
        bytes: u64,
    },
}

/// Receives the events of the threads that entered its [`Sink`], on those threads.
pub trait Observer: Send + Sync {
    fn event(&self, event: &Event);
}

/// Where a thread's events go.
#[derive(Clone)]
pub struct Sink {
    observer: Arc<dyn Observer>,
    host_as_device: bool,
    live: Arc<Mutex<Live>>,
}

impl Sink {
    /// `host_as_device`: count CPU storage as the device (see the module docs).
    pub fn new(observer: Arc<dyn Observer>, host_as_device: bool) -> Self {
        Self {
            observer,
            host_as_device,
            live: Arc::default(),
        }
    }

    pub fn host_as_device(&self) -> bool {
        self.host_as_device
    }

    /// Bytes of the storages (and [`hold`]s) made while this sink counted that are alive now.
    pub fn live_bytes(&self) -> u64 {
        let mut live = self.live.lock().unwrap_or_else(|e| e.into_inner());
        live.sweep();
        live.bytes
    }

    /// The largest [`Self::live_bytes`] since the sink was made or [`Self::reset_peak`]; it
    /// is taken at every allocation, where live bytes reach their maxima.
    pub fn peak_live_bytes(&self) -> u64 {
        self.live.lock().unwrap_or_else(|e| e.into_inner()).peak
    }

    /// The live bytes right after each allocation counted so far, in order: where the peak
    /// can be. Runs that make the same allocations in the same order at different sizes
    /// give traces of the same length, so a peak can be extrapolated point by point.
    pub fn live_trace(&self) -> Vec<u64> {
        self.live.lock().unwrap_or_else(|e| e.into_inner()).trace.clone()
    }

    /// Start a new peak from the bytes alive now.
    pub fn reset_peak(&self) {
        let mut live = self.live.lock().unwrap_or_else(|e| e.into_inner());
        live.sweep();
        live.peak = live.bytes;
    }
}

/// The storages a sink has seen made, each with its bytes, while they live.
#[derive(Default)]
struct Live {
    entries: Vec<(Weak<dyn Any + Send + Sync>, u64)>,
    bytes: u64,
    peak: u64,
    trace: Vec<u64>,
}

impl Live {
    /// Forget what has been dropped.
    fn sweep(&mut self) {
        let mut freed = 0;
        self.entries.retain(|(w, b)| {
            let alive = w.strong_count() > 0;
            if !alive {
                freed += b;
            }
            alive
        });
        self.bytes -= freed;
    }

    fn add(&mut self, what: Weak<dyn Any + Send + Sync>, bytes: u64) {
        self.sweep();
        self.entries.push((what, bytes));
        self.bytes += bytes;
        self.peak = self.peak.max(self.bytes);
        self.trace.push(self.bytes);
    }
}

impl std::fmt::Debug for Sink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sink")
            .field("host_as_device", &self.host_as_device)
            .finish_non_exhaustive()
    }
}

/// This thread's sink while it lives (see [`enter`]).
#[must_use = "the sink is left when the guard drops"]
pub struct Entered {
    prev: Option<Sink>,
    counted: bool,
}

impl Drop for Entered {
    fn drop(&mut self) {
        let prev = self.prev.take();
        SINK.with_borrow_mut(|s| *s = prev);
        if self.counted {
            ENTERED.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

/// Send this thread's events to `sink` (none: stop counting) until the guard drops, which
/// restores the previous sink.
pub fn enter(sink: Option<Sink>) -> Entered {
    let counted = sink.is_some();
    if counted {
        ENTERED.fetch_add(1, Ordering::Relaxed);
    }
    let prev = SINK.with_borrow_mut(|s| std::mem::replace(s, sink));
    Entered { prev, counted }
}

/// This thread's sink, to enter it on a worker thread.
pub fn current() -> Option<Sink> {
    if !on() {
        return None;
    }
    SINK.with_borrow(|s| s.clone())
}

/// Whether any thread counts (the only cost of a hook when none does).
#[inline(always)]
pub fn on() -> bool {
    ENTERED.load(Ordering::Relaxed) != 0
}

/// Called by a custom op while it runs: it makes `launches` launches and `param_uploads`
/// small uploads on a CUDA device (counted instead of the default: one launch, and one
/// upload when the first input is strided). On the CPU a custom op may report what its CUDA
/// forward would do.
pub fn report_launches(launches: u32, param_uploads: u32) {
    if on() {
        REPORTED.with(|r| r.set(Some((launches, param_uploads))));
    }
}

/// Called by a custom op while it runs: its kernel reads `read` and writes `written` bytes
/// (counted instead of the default: every input's footprint and the output), for a kernel
/// that reads part of an input or writes a second output.
pub fn report_bytes(read: u64, written: u64) {
    if on() {
        REPORTED_BYTES.with(|r| r.set(Some((read, written))));
    }
}

/// Called by a custom op while it runs: it makes a matrix product of `flops` FLOPs (counted
/// instead of the default, 0).
pub fn report_flops(flops: u64) {
    if on() {
        REPORTED_FLOPS.with(|r| r.set(flops));
    }
}

/// Run `f` without counting anything it does (ops, reads, uploads, allocations): for code
/// that computes what a custom kernel would, whose cost is [`record`]ed instead.
pub fn uncounted<T>(f: impl FnOnce() -> T) -> T {
    if !on() {
        return f();
    }
    let prev = UNCOUNTED.with(|u| u.replace(true));
    let out = f();
    UNCOUNTED.with(|u| u.set(prev));
    out
}

/// Count `op` as if storage of the CPU (`cpu`) or of a device had run it (a kernel that pma
/// computes another way on this device, see [`uncounted`]).
pub fn record(cpu: bool, op: Op) {
    if on() {
        emit(cpu, || Event::Op(op, None));
    }
}

/// Bytes held outside any storage while the guard lives (a custom op's state kept from its
/// forward for its backward): they count as live memory like a storage's.
#[must_use = "the bytes count as live while the guard lives"]
pub struct Held(#[allow(dead_code)] Option<Arc<dyn Any + Send + Sync>>);

/// Count `bytes` as live memory of this thread's sink (when it counts CPU storage, `cpu`,
/// or the device's) until the returned guard drops.
pub fn hold(cpu: bool, bytes: usize) -> Held {
    if !on() {
        return Held(None);
    }
    let token: Arc<dyn Any + Send + Sync> = Arc::new(());
    let weak = Arc::downgrade(&token);
    let mut kept = false;
    with_counting_sink(cpu, |s| {
        s.live
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .add(weak, bytes as u64);
        kept = true;
    });
    Held(kept.then_some(token))
}

/// A new storage of `bytes` behind `storage` (every tensor constructor that allocates).
#[inline]
pub(crate) fn alloc<T: Any + Send + Sync>(cpu: bool, storage: &Arc<T>, bytes: usize) {
    if on() {
        let weak: Weak<T> = Arc::downgrade(storage);
        with_counting_sink(cpu, |s| {
            s.live
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .add(weak, bytes as u64)
        });
    }
}

/// Run `f` with this thread's sink if it counts storage of the CPU (`cpu`) or of a device.
fn with_counting_sink(cpu: bool, f: impl FnOnce(&Sink)) {
    if UNCOUNTED.with(Cell::get) {
        return;
    }
    SINK.with_borrow(|s| {
        if let Some(s) = s {
            if !cpu || (s.host_as_device && !HOST_ONLY.with(Cell::get)) {
                f(s)
            }
        }
    })
}

/// Run `f`, host work on every device (a scalar operand's cast before its upload): its CPU
/// storage operations are not counted even by a `host_as_device` sink.
pub(crate) fn host_only<T>(f: impl FnOnce() -> T) -> T {
    if !on() {
        return f();
    }
    let prev = HOST_ONLY.with(|h| h.replace(true));
    let out = f();
    HOST_ONLY.with(|h| h.set(prev));
    out
}

fn emit(cpu: bool, event: impl FnOnce() -> Event) {
    with_counting_sink(cpu, |s| s.observer.event(&event()))
}

/// Count an operation on storage of the CPU (`cpu`) or of a device.
#[inline]
pub(crate) fn op(cpu: bool, op: impl FnOnce() -> (Op, Sig)) {
    if on() {
        emit(cpu, || {
            let (op, sig) = op();
            Event::Op(op, Some(sig))
        });
    }
}

/// Count a device → host read of `bytes`.
#[inline]
pub(crate) fn read(cpu: bool, bytes: impl FnOnce() -> usize) {
    if on() {
        emit(cpu, || Event::Read {
            bytes: bytes() as u64,
        });
    }
}

/// Count an explicit upload of `bytes` onto the CPU (`cpu`) or a device.
#[inline]
pub(crate) fn upload(cpu: bool, bytes: impl FnOnce() -> usize) {
    if on() {
        emit(cpu, || Event::Upload {
            bytes: bytes() as u64,
        });
    }
}

/// Run a custom op and count it with the launches it reported (see [`report_launches`]).
pub(crate) fn custom<T>(
    cpu: bool,
    name: &'static str,
    inputs: &[(&Layout, DType)],
    run: impl FnOnce() -> crate::Result<(T, Shape, DType)>,
) -> crate::Result<(T, Shape)> {
    if !on() {
        return run().map(|(t, s, _)| (t, s));
    }
    REPORTED.with(|r| r.set(None));
    REPORTED_BYTES.with(|r| r.set(None));
    REPORTED_FLOPS.with(|r| r.set(0));
    let (t, shape, dtype) = run()?;
    // Unreported: one kernel, with its dims/strides upload for a strided first input (the
    // rule of candle-nn's element-wise custom ops).
    let default = (1, inputs.first().map_or(0, |(l, _)| strided(l)));
    let (launches, param_uploads) = REPORTED.with(|r| r.take()).unwrap_or(default);
    let (bytes_read, bytes_written) = REPORTED_BYTES.with(|r| r.take()).unwrap_or_else(|| {
        (
            inputs.iter().map(|(l, d)| bytes(l, *d)).sum(),
            (shape.elem_count() * dtype.size_in_bytes()) as u64,
        )
    });
    let flops = REPORTED_FLOPS.with(|r| r.replace(0));
    op(cpu, || {
        let ins: Vec<(DType, Lay)> = inputs.iter().map(|(l, d)| (*d, lay(l))).collect();
        let sig = Sig {
            custom: true,
            ..Sig::new(&ins, dtype, shape.elem_count())
        };
        let op = Op {
            name,
            launches,
            param_uploads,
            bytes_read,
            bytes_written,
            flops,
        };
        (op, sig)
    });
    Ok((t, shape))
}

/// The elements a layout reads, each once: dims behind a zero stride (broadcast) count once.
pub(crate) fn footprint(l: &Layout) -> usize {
    l.dims()
        .iter()
        .zip(l.stride())
        .filter(|(_, &s)| s != 0)
        .map(|(&d, _)| d)
        .product::<usize>()
        * usize::from(l.shape().elem_count() != 0)
}

fn bytes(l: &Layout, dtype: DType) -> u64 {
    (footprint(l) * dtype.size_in_bytes()) as u64
}

fn strided(l: &Layout) -> u32 {
    u32::from(!l.is_contiguous())
}

/// [`Lay::Contiguous`] or [`Lay::Strided`].
fn lay(l: &Layout) -> Lay {
    match l.is_contiguous() {
        true => Lay::Contiguous,
        false => Lay::Strided,
    }
}

/// How cuBLAS reads a matmul operand of `rows` × `cols` (its last two dims) batched over
/// the dims before them, as the backend's GEMM setup decides: [`Lay::Normal`] when its rows
/// are consecutive (row stride `cols`, unit column stride), [`Lay::Transposed`] when its
/// columns are (unit row stride, column stride `rows`), a single row or column counting as
/// either; the batch needs one stride (any stride for one batch dim; for two, the outer a
/// multiple of the inner or one of them of size 1). Anything else is [`Lay::Strided`],
/// which the backend refuses.
fn gemm_lay(l: &Layout, rows: usize, cols: usize) -> Lay {
    let (dims, stride) = (l.dims(), l.stride());
    let r = stride.len();
    if r < 2 {
        return Lay::Strided;
    }
    let (row_s, col_s) = (stride[r - 2], stride[r - 1]);
    let batch_ok = match (&dims[..r - 2], &stride[..r - 2]) {
        ([], []) | ([_], [_]) => true,
        ([d0, d1], [s0, s1]) => *s0 == s1 * d1 || *d0 == 1 || *d1 == 1,
        _ => false,
    };
    let normal = (col_s == 1 || cols == 1) && (row_s == cols || rows == 1);
    let transposed = (col_s == rows || cols == 1) && (row_s == 1 || rows == 1);
    match (batch_ok, normal, transposed) {
        (true, true, _) => Lay::Normal,
        (true, false, true) => Lay::Transposed,
        _ => Lay::Strided,
    }
}

/// A one-input element-wise kernel (unary, affine, powf, elu, casts): dims and strides are
/// uploaded for a strided input.
pub(crate) fn map(name: &'static str, l: &Layout, input: DType, output: DType) -> (Op, Sig) {
    let n = l.shape().elem_count();
    let op = Op {
        name,
        launches: 1,
        param_uploads: strided(l),
        bytes_read: bytes(l, input),
        bytes_written: (n * output.size_in_bytes()) as u64,
        flops: 0,
    };
    (op, Sig::new(&[(input, lay(l))], output, n))
}

/// A two-input element-wise kernel (binary ops, comparisons): one upload when either input
/// is strided.
pub(crate) fn map2(
    name: &'static str,
    lhs: &Layout,
    rhs: &Layout,
    input: DType,
    output: DType,
) -> (Op, Sig) {
    let n = lhs.shape().elem_count();
    let op = Op {
        name,
        launches: 1,
        param_uploads: u32::from(!lhs.is_contiguous() || !rhs.is_contiguous()),
        bytes_read: bytes(lhs, input) + bytes(rhs, input),
        bytes_written: (n * output.size_in_bytes()) as u64,
        flops: 0,
    };
    let sig = Sig::new(&[(input, lay(lhs)), (input, lay(rhs))], output, n);
    (op, sig)
}

/// `const_set`: a fill kernel, dims and strides uploaded when strided.
pub(crate) fn fill(l: &Layout, dtype: DType) -> (Op, Sig) {
    let n = l.shape().elem_count();
    let op = Op {
        name: "const-set",
        launches: 1,
        param_uploads: strided(l),
        bytes_read: 0,
        bytes_written: (n * dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    (op, Sig::new(&[(dtype, lay(l))], dtype, n))
}

/// A reduction over `dims`: the fast reduce kernels always upload dims and strides; a sum
/// of at most 32 elements per output takes the small-sum kernel.
pub(crate) fn reduce(name: &'static str, l: &Layout, dims: &[usize], dtype: DType) -> (Op, Sig) {
    let reduced: usize = dims.iter().map(|&d| l.dims()[d]).product();
    let out = l.shape().elem_count() / reduced.max(1);
    let out_dtype = match name.starts_with("reduce-arg") {
        true => DType::U32,
        false => dtype,
    };
    let op = Op {
        name,
        launches: 1,
        param_uploads: 1,
        bytes_read: bytes(l, dtype),
        bytes_written: (out * out_dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    let sig = Sig {
        variant: match name == "reduce-sum" && reduced <= 32 {
            true => "small",
            false => "",
        },
        ..Sig::new(&[(dtype, lay(l))], out_dtype, out)
    };
    (op, sig)
}

/// `where_cond`: always uploads dims and the three stride sets.
pub(crate) fn where_cond(
    cond: &Layout,
    c: DType,
    t: &Layout,
    f: &Layout,
    dtype: DType,
) -> (Op, Sig) {
    let n = cond.shape().elem_count();
    let op = Op {
        name: "where",
        launches: 1,
        param_uploads: 1,
        bytes_read: bytes(cond, c) + bytes(t, dtype) + bytes(f, dtype),
        bytes_written: (n * dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    let sig = Sig::new(&[(c, lay(cond)), (dtype, lay(t)), (dtype, lay(f))], dtype, n);
    (op, sig)
}

/// `gather` from `src` along a dim: one thread per output element, no upload.
pub(crate) fn gather(src: &Layout, ids: &Layout, id: DType, dtype: DType) -> (Op, Sig) {
    let out = ids.shape().elem_count();
    let op = Op {
        name: "gather",
        launches: 1,
        param_uploads: 0,
        bytes_read: bytes(ids, id) + (out * dtype.size_in_bytes()) as u64,
        bytes_written: (out * dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    (op, Sig::new(&[(dtype, lay(src)), (id, lay(ids))], dtype, out))
}

/// `index_select` of `src` rows by `ids` along `dim`: uploads the ids' dims and strides.
pub(crate) fn index_select(
    src: &Layout,
    ids: &Layout,
    id: DType,
    dim: usize,
    dtype: DType,
) -> (Op, Sig) {
    let out = ids.shape().elem_count() * outside(src, dim);
    let op = Op {
        name: "index-select",
        launches: 1,
        param_uploads: 1,
        bytes_read: bytes(ids, id) + (out * dtype.size_in_bytes()) as u64,
        bytes_written: (out * dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    (op, Sig::new(&[(dtype, lay(src)), (id, lay(ids))], dtype, out))
}

/// The elements of `l` outside dim `dim`: the threads of the `index_add` and `scatter`
/// kernels.
fn outside(l: &Layout, dim: usize) -> usize {
    let d = l.dims();
    d[..dim].iter().product::<usize>() * d[dim + 1..].iter().product::<usize>()
}

/// `index_add` into a copy of `dst` along `dim`: the copy (a memcpy, or a strided copy with
/// its upload) then the adding kernel.
pub(crate) fn index_add(
    dst: &Layout,
    ids: &Layout,
    id: DType,
    src: &Layout,
    dim: usize,
    dtype: DType,
) -> (Op, Sig) {
    let s = dtype.size_in_bytes() as u64;
    let n_dst = dst.shape().elem_count() as u64;
    let n_src = src.shape().elem_count() as u64;
    let op = Op {
        name: "index-add",
        launches: 2,
        param_uploads: strided(dst),
        bytes_read: n_dst * s + bytes(ids, id) + bytes(src, dtype) + n_src * s,
        bytes_written: n_dst * s + n_src * s,
        flops: 0,
    };
    let ins = [(dtype, lay(dst)), (id, lay(ids)), (dtype, lay(src))];
    (op, Sig::new(&ins, dtype, outside(src, dim)))
}

/// `scatter`/`scatter_add` of `src` into `dst` in place along `dim`: one launch, no upload.
pub(crate) fn scatter(
    name: &'static str,
    dst: &Layout,
    ids: &Layout,
    id: DType,
    (src, dim): (&Layout, usize),
    dtype: DType,
) -> (Op, Sig) {
    let n = src.shape().elem_count();
    let s = dtype.size_in_bytes() as u64;
    let op = Op {
        name,
        launches: 1,
        param_uploads: 0,
        bytes_read: bytes(ids, id) + bytes(src, dtype) + n as u64 * s,
        bytes_written: n as u64 * s,
        flops: 0,
    };
    let ins = [(dtype, lay(dst)), (id, lay(ids)), (dtype, lay(src))];
    (op, Sig::new(&ins, dtype, outside(src, dim)))
}

/// A batched matmul (one cuBLAS call): 2·b·m·n·k FLOPs.
pub(crate) fn matmul(
    (b, m, n, k): (usize, usize, usize, usize),
    lhs: &Layout,
    rhs: &Layout,
    dtype: DType,
) -> (Op, Sig) {
    let op = Op {
        name: "matmul",
        launches: 1,
        param_uploads: 0,
        bytes_read: bytes(lhs, dtype) + bytes(rhs, dtype),
        bytes_written: (b * m * n * dtype.size_in_bytes()) as u64,
        flops: 2 * (b * m * n * k) as u64,
    };
    let ins = [(dtype, gemm_lay(lhs, m, k)), (dtype, gemm_lay(rhs, k, n))];
    (op, Sig::new(&ins, dtype, b * m * n))
}

/// `copy_strided_src`: a device memcpy for a contiguous source, else a strided copy kernel
/// with its upload. Nothing for an empty source.
pub(crate) fn copy(src: &Layout, dtype: DType) -> (Op, Sig) {
    let elements = src.shape().elem_count();
    let n = (elements * dtype.size_in_bytes()) as u64;
    let contiguous = src.is_contiguous();
    let op = Op {
        name: if contiguous { "copy" } else { "copy-strided" },
        launches: u32::from(n != 0),
        param_uploads: u32::from(n != 0 && !contiguous),
        bytes_read: n,
        bytes_written: n,
        flops: 0,
    };
    (op, Sig::new(&[(dtype, lay(src))], dtype, elements))
}

/// `copy2d` (cat and slice assignment) of `d1` rows of `d2` elements, `src_s` apart: one
/// kernel unless empty.
pub(crate) fn copy2d(d1: usize, d2: usize, src_s: usize, dtype: DType) -> (Op, Sig) {
    let n = (d1 * d2 * dtype.size_in_bytes()) as u64;
    let op = Op {
        name: "copy2d",
        launches: u32::from(n != 0),
        param_uploads: 0,
        bytes_read: n,
        bytes_written: n,
        flops: 0,
    };
    let src = match src_s == d2 || d1 <= 1 {
        true => Lay::Contiguous,
        false => Lay::Strided,
    };
    (op, Sig::new(&[(dtype, src)], dtype, d1 * d2))
}

/// A fresh buffer filled on the device: zeros (a memset), or random values.
pub(crate) fn fresh(name: &'static str, shape: &Shape, dtype: DType) -> (Op, Sig) {
    let n = shape.elem_count();
    let op = Op {
        name,
        launches: 1,
        param_uploads: 0,
        bytes_read: 0,
        bytes_written: (n * dtype.size_in_bytes()) as u64,
        flops: 0,
    };
    (op, Sig::new(&[], dtype, n))
}

/// A copy of a whole layout's storage (`Tensor::copy`).
pub(crate) fn clone(l: &Layout, dtype: DType) -> (Op, Sig) {
    let elements = l.shape().elem_count();
    let n = (elements * dtype.size_in_bytes()) as u64;
    let op = Op {
        name: "clone",
        launches: 1,
        param_uploads: 0,
        bytes_read: n,
        bytes_written: n,
        flops: 0,
    };
    (op, Sig::new(&[(dtype, lay(l))], dtype, elements))
}

/// Convolutions, pooling, upsampling: one kernel with its dims/strides upload; input bytes
/// only (pma uses none of them).
pub(crate) fn other(name: &'static str, inputs: &[(&Layout, DType)]) -> (Op, Sig) {
    let op = Op {
        name,
        launches: 1,
        param_uploads: 1,
        bytes_read: inputs.iter().map(|(l, d)| bytes(l, *d)).sum(),
        bytes_written: 0,
        flops: 0,
    };
    let ins: Vec<(DType, Lay)> = inputs.iter().map(|(l, d)| (*d, lay(l))).collect();
    let dtype = inputs.first().map_or(DType::F32, |(_, d)| *d);
    let elements = inputs.first().map_or(0, |(l, _)| l.shape().elem_count());
    (op, Sig::new(&ins, dtype, elements))
}

/// Bytes of a layout's elements (reads and uploads of whole tensors).
pub(crate) fn tensor_bytes(l: &Layout, dtype: DType) -> usize {
    l.shape().elem_count() * dtype.size_in_bytes()
}
