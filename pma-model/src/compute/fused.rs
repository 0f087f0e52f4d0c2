//! CPU kernels that replace the places where candle's generic autograd costs most (in a
//! profile of a paper-config training step):
//!
//! * **Bias add** of every linear layer. candle differentiates `broadcast_add` with a
//!   strided reduction over the rows that runs element by element; [`add_bias`] computes the
//!   same column sums in one contiguous pass.
//! * **The window's max-pool** `m = max_j (q_j + g_j) · w^p_j`. In plain ops this builds two
//!   [N,24,128] tensors forward and about ten passes over that size backward (equality mask,
//!   casts, products, candle's zero-then-add accumulation). [`window_pool`] reads `q` once
//!   forward, keeps the arg-max joints when the graph tracks gradients, and scatters the
//!   gradient to them backward.
//! * **The FiLM-sine layers** of the modulator, reading Θ and Φ out of the pose extractor's
//!   head ([`FilmHead`]).
//! * **Every linear layer** `x Wᵀ + b` as one op ([`linear`]): candle keeps each op's inputs
//!   alive until the graph is dropped, so a product followed by a bias add kept the product,
//!   a second [rows,out] tensor per layer that no backward reads. One op keeps only its
//!   output: the largest cut of a training step's peak memory, on every device.
//!
//! All compute the same f32 operations in the same order as the plain path, so forward
//! values are bit-identical and gradients identical except on exact ties of the max, where
//! the gradient goes to the first maximal joint (PyTorch's rule, the reference) instead of
//! to every tied joint (candle's rule). Ties only occur where w^p = 0, so both give 0 there.
//! What a backward needs from its forward (the arg-max, cos of the sine's argument) is kept
//! once and used once; a second backward over the same graph computes it again.
//!
//! They run in f32 when the network's [`Numerics::fused`] is on: on the CPU as written here,
//! on CUDA through the kernels of [`crate::compute::cuda`] (the linear layer through cuBLAS
//! and candle's bias-add kernel), and in a CPU run accounted as CUDA
//! ([`crate::compute::account`]) as the CPU code counted as those kernels. Other dtypes take
//! the plain path.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Shape, Storage, Tensor};

#[cfg(feature = "cuda")]
use candle_core::cuda_backend::cudarc::driver::CudaSlice;

use crate::compute::numerics::Numerics;
use crate::compute::ops::f32_slice;
use crate::error::Result;

/// The fused kernels are CPU-only: tensors elsewhere, and runs accounted as CUDA, take the
/// plain ops.
fn applies(k: Numerics, ts: &[&Tensor]) -> bool {
    k.fused && cpu_f32(ts)
}

/// Whether `ts` are f32 tensors on the CPU's route.
fn cpu_f32(ts: &[&Tensor]) -> bool {
    !crate::compute::account::emulates_cuda()
        && ts
            .iter()
            .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}

/// `x Wᵀ + b`: x: [rows,in], W: [out,in] (PyTorch's layout), b: [out] -> [rows,out], as one
/// op that keeps only its output for the backward (see the module docs): the same product
/// (candle's, under the network's TF32 choice) and the same bias add, so values and
/// gradients are those of [`add_bias`] after the product. Counted as what it launches: the
/// product, then the bias add.
pub fn linear(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    let plain =
        || -> Result<Tensor> { add_bias(&crate::compute::numerics::matmul(x, &w.t()?, k)?, b, k) };
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?;
    let on_route = cpu_f32(&[x, w, b]) || cuda_f32(&[x, w, b]) || modeled_f32(&[x, w, b]);
    if !(k.fused && fits && on_route) {
        return plain();
    }
    let (x, w, b) = (x.contiguous()?, w.contiguous()?, b.contiguous()?);
    let op = Linear {
        cpu_route: cpu_f32(&[&x]),
    };
    Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
        k.tf32,
        || x.apply_op3(&w, &b, op),
    )?)
}

/// `y + b` broadcast over rows: y: [rows,out], b: [out] -> [rows,out].
pub fn add_bias(y: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    if !applies(k, &[y, b]) || y.rank() != 2 || b.rank() != 1 {
        return Ok(y.broadcast_add(b)?);
    }
    Ok(y.contiguous()?.apply_op2(&b.contiguous()?, BiasAdd)?)
}

/// `max_j (q[n,j,:] + g[p(n),j,:]) · w_p[n,j]`: q: [N,J,H], g: [P,J,H], w_p: [N,J] -> [N,H],
/// the N points grouped by pose in P equal blocks (point n belongs to pose `n / (N/P)`).
/// No gradient flows to `w_p` (the reference detaches the spatial window).
pub fn window_pool(q: &Tensor, g: &Tensor, w_p: &Tensor, k: Numerics) -> Result<Tensor> {
    let (n, j, h) = q.dims3()?;
    let p = g.dim(0)?;
    if g.dims() != [p, j, h] || p == 0 || n % p != 0 {
        return Err(crate::error::ModelError::shape(
            "window pool: g",
            format!("[P,{j},{h}] with P dividing {n}"),
            g.dims(),
        ));
    }
    let plain = || -> Result<Tensor> {
        let part = q
            .reshape((p, n / p, j, h))?
            .broadcast_add(&g.unsqueeze(1)?)?
            .reshape((n, j, h))?;
        Ok(part
            .broadcast_mul(&w_p.unsqueeze(candle_core::D::Minus1)?)?
            .max(1)?)
    };
    let modeled = models_cuda(k, &[q, g, w_p]);
    if !(applies(k, &[q, g, w_p]) || applies_cuda(k, &[q, g, w_p]) || modeled) {
        return plain();
    }
    let (q, g) = (q.contiguous()?, g.contiguous()?);
    let tracked = q.track_op() || g.track_op();
    let op = WindowPool {
        arg: crate::compute::ops::Kept::new(tracked),
        modeled,
        held: Mutex::new(None),
        #[cfg(feature = "cuda")]
        arg_dev: crate::compute::ops::Kept::new(tracked),
    };
    let out = q.apply_op3(&g, &w_p.detach().contiguous()?, op)?;
    if modeled {
        // The CUDA kernel also writes the arg-max (u32 [N,H]); the custom op's count has
        // its one launch and the max.
        candle_core::account::record(
            true,
            candle_core::account::Op {
                name: "pma-window-pool",
                launches: 0,
                param_uploads: 0,
                bytes_read: 0,
                bytes_written: (out.elem_count() * 4) as u64,
                flops: 0,
            },
        );
    }
    Ok(out)
}

/// [`window_pool`] of `q = e · Wᵀ` (e: [N·J,Ce], W: [H,Ce] in PyTorch's layout, viewed as
/// [N,J,H]) as one op that computes the product and pools it without keeping q: the pool's
/// backward needs only its arg-max, and a [N,J,H] product kept alive until the backward was
/// the largest single tensor of a training step. The same product and pool as the two ops,
/// so the same values and gradients.
pub fn window_pool_of(
    e: &Tensor,
    w: &Tensor,
    g: &Tensor,
    w_p: &Tensor,
    k: Numerics,
) -> Result<Tensor> {
    let (nj, ce) = e.dims2()?;
    let (h, ce2) = w.dims2()?;
    let (p, j, h2) = g.dims3()?;
    if ce2 != ce || h2 != h || j == 0 || nj % j != 0 {
        return Err(crate::error::ModelError::shape(
            "window pool: e, W and g",
            format!("e [N·{j},Ce], W [{h2},Ce]"),
            e.dims(),
        ));
    }
    let n = nj / j;
    let on = [e, w, g, w_p];
    let fused = applies(k, &on) || applies_cuda(k, &on) || models_cuda(k, &on);
    if !fused || p == 0 || n % p != 0 {
        let q = crate::compute::numerics::matmul(e, &w.t()?, k)?.reshape((n, j, h))?;
        return window_pool(&q, g, w_p, k);
    }
    let (e, w, g) = (e.contiguous()?, w.contiguous()?, g.contiguous()?);
    let tracked = e.track_op() || w.track_op() || g.track_op();
    let op = WindowPoolOf {
        inner: WindowPool {
            arg: crate::compute::ops::Kept::new(tracked),
            modeled: models_cuda(k, &on),
            held: Mutex::new(None),
            #[cfg(feature = "cuda")]
            arg_dev: crate::compute::ops::Kept::new(tracked),
        },
        w_p: w_p.detach().contiguous()?,
        j,
    };
    Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
        k.tf32,
        || e.apply_op3(&w, &g, op),
    )?)
}

/// [`window_pool_of`]'s op on (e, W, g), the spatial window held (no gradient flows to it).
struct WindowPoolOf {
    inner: WindowPool,
    w_p: Tensor,
    j: usize,
}

impl WindowPoolOf {
    /// Count the op as its two kernels: this op is the product; the pool is recorded beside
    /// it (reading q, g and the window; writing the max, and the arg-max when kept).
    fn report(&self, cpu: bool, (n, j, h, ce): (usize, usize, usize, usize), g_len: usize) {
        let (nj, h64, ce) = ((n * j) as u64, h as u64, ce as u64);
        candle_core::account::report_launches(1, 0);
        candle_core::account::report_bytes(4 * (nj * ce + h64 * ce), 4 * nj * h64);
        candle_core::account::report_flops(2 * nj * h64 * ce);
        let kept = u64::from(self.inner.arg.wanted());
        let nh = (n * h) as u64;
        candle_core::account::record(
            cpu,
            candle_core::account::Op {
                name: "pma-window-pool",
                launches: 1,
                param_uploads: 0,
                bytes_read: 4 * (nj * h64 + g_len as u64 + nj),
                bytes_written: 4 * nh * (1 + kept),
                flops: 0,
            },
        );
    }

    fn dims(&self, l1: &Layout, l2: &Layout) -> candle_core::Result<(usize, usize, usize, usize)> {
        let (nj, ce) = l1.shape().dims2()?;
        let (h, ce2) = l2.shape().dims2()?;
        if ce2 != ce || nj % self.j != 0 {
            candle_core::bail!(
                "window pool: e {:?} and W {:?} do not agree",
                l1.shape(),
                l2.shape()
            )
        }
        Ok((nj / self.j, self.j, h, ce))
    }
}

impl CustomOp3 for WindowPoolOf {
    fn name(&self) -> &'static str {
        "matmul"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        use candle_core::backend::BackendStorage;
        let (n, j, h, ce) = self.dims(l1, l2)?;
        self.report(true, (n, j, h, ce), l3.shape().elem_count());
        // The product exactly as `Tensor::matmul` calls it for e · Wᵀ; freed on return.
        let q = s1.matmul(s2, (1, n * j, h, ce), l1, &l2.transpose(0, 1)?)?;
        let (wp, wl) = self.w_p.storage_and_layout();
        let Storage::Cpu(wp) = &*wp else {
            candle_core::bail!("window pool: the window is not on the CPU")
        };
        self.inner
            .cpu_fwd(&q, &Layout::contiguous((n, j, h)), s3, l3, wp, wl)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        use candle_core::backend::BackendStorage;
        let (n, j, h, ce) = self.dims(l1, l2)?;
        self.report(false, (n, j, h, ce), l3.shape().elem_count());
        let p = l3.shape().dims3()?.0;
        let q = s1.matmul(s2, (1, n * j, h, ce), l1, &l2.transpose(0, 1)?)?;
        let (wp, wl) = self.w_p.storage_and_layout();
        let Storage::Cuda(wp) = &*wp else {
            candle_core::bail!("window pool: the window is not on the GPU")
        };
        let (out, arg) = crate::compute::cuda::window_pool(
            &q,
            &Layout::contiguous((n, j, h)),
            s3,
            l3,
            wp,
            wl,
            [n, j, h, n / p],
        )?;
        self.inner.arg_dev.put(arg);
        Ok((out, Shape::from((n, h))))
    }

    fn bwd(
        &self,
        e: &Tensor,
        w: &Tensor,
        g: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let q = QSource::Product { e, w, j: self.j };
        let (gq, gg) = self.inner.grads(&q, g, &self.w_p, grad)?;
        // candle's matmul backward for e · (Wᵀ) on the [N·J,H] view, then the transpose's.
        let gq = gq.reshape((e.dim(0)?, w.dim(0)?))?;
        let wt = w.t()?;
        let ge = gq.matmul(&wt.t()?)?;
        let gw = e.t()?.matmul(&gq)?.t()?;
        Ok((Some(ge), Some(gw), Some(gg)))
    }
}

/// Whether a CPU run accounted as CUDA ([`crate::compute::account`]) should count the
/// CUDA kernel of [`crate::compute::cuda`] rather than candle's plain ops: the fused ops
/// then run on the CPU and count what their kernel launches, reads and writes.
pub(crate) fn models_cuda(k: Numerics, ts: &[&Tensor]) -> bool {
    k.fused && modeled_f32(ts)
}

/// Whether `ts` are f32 tensors on the CPU of a run accounted as CUDA.
fn modeled_f32(ts: &[&Tensor]) -> bool {
    crate::compute::account::emulates_cuda()
        && ts
            .iter()
            .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}

/// Whether `ts` are f32 tensors on CUDA and the network asks for fused kernels: the
/// kernels of [`crate::compute::cuda`] (which exist in a `cuda` build only).
pub(crate) fn applies_cuda(k: Numerics, ts: &[&Tensor]) -> bool {
    k.fused && cuda_f32(ts)
}

/// Whether `ts` are f32 tensors on CUDA in a `cuda` build.
fn cuda_f32(ts: &[&Tensor]) -> bool {
    cfg!(feature = "cuda")
        && ts
            .iter()
            .all(|t| t.device().is_cuda() && t.dtype() == DType::F32)
}

/// The pose extractor's head `o` = [Θ_0..Θ_{K-1}, Φ_0..Φ_{K-1}] (each block `f` wide), as
/// read by the K FiLM-SIREN layers `sin(pre ⊙ (m·Θ_k + c) + Φ_k)` of one forward pass.
///
/// The plain path is four ops forward per layer (a strided affine, a product, a strided add,
/// the sine) and, backward, about a dozen passes over [N,f] plus two zero-padded [N,2Kf]
/// gradients for the narrowed blocks, which candle then adds. Here a layer is one pass each
/// way, computed with the same f32 operations in the same order (sine and cosine from libm,
/// or from [`crate::compute::fast_sine`] when that is on), so values and gradients are bit-identical.
/// When the graph tracks gradients the forward keeps cos of the argument (the sine kernel
/// computes it anyway), so the backward evaluates no trigonometry.
///
/// Through [`FilmHead::stack`] the layers also share one head gradient: layers 1..K write
/// their columns into it and layer 0, whose backward necessarily runs last (every later
/// layer's input depends on its output), hands it to candle. The sum candle formed of K
/// zero-padded gradients had the same bits: every entry the kernel writes already carries
/// the `+ 0` of the plain graph's accumulation.
pub struct FilmHead {
    o: Tensor,
    n_layers: usize,
    mul: f64,
    add: f64,
    fast: bool,
    fused: bool,
    /// A CPU run accounted as CUDA: the CPU kernels run and count as the CUDA ones.
    modeled: bool,
    grad: Arc<Mutex<HeadGrad>>,
}

/// The head gradient the layers of one [`FilmHead::stack`] fill in.
#[derive(Default)]
struct HeadGrad {
    /// The buffer of the CPU route's backward.
    buf: Option<Vec<f32>>,
    /// The buffer of a device backward (CUDA, or a CPU run accounted as CUDA).
    dev: Option<HeadBuf>,
    /// Layer 0 has handed the buffer over: a later backward pass over the same graph makes
    /// every layer return its own gradient.
    taken: bool,
}

/// A device backward's head gradient while the layers fill it: on CUDA the device buffer; in
/// a CPU run accounted as CUDA a host buffer whose bytes are held live on the modeled device.
enum HeadBuf {
    Modeled(Vec<f32>, candle_core::account::Held),
    #[cfg(feature = "cuda")]
    Cuda(CudaSlice<f32>),
}

impl FilmHead {
    /// `o`: [N,2·K·f] for K = `n_layers`; γ = `mul`·Θ + `add`.
    pub fn new(o: &Tensor, n_layers: usize, (mul, add): (f64, f64), k: Numerics) -> Self {
        let modeled = models_cuda(k, &[o]);
        let fused = applies(k, &[o]) || applies_cuda(k, &[o]) || modeled;
        let mut head = Self::with(o, n_layers, (mul, add), k.fast_sine, fused);
        head.modeled = modeled;
        head
    }

    /// [`Self::new`] with the sine flavour and the kernel choice made by the caller.
    fn with(o: &Tensor, n_layers: usize, (mul, add): (f64, f64), fast: bool, fused: bool) -> Self {
        Self {
            o: o.clone(),
            n_layers,
            mul,
            add,
            fast,
            fused,
            modeled: false,
            grad: Arc::default(),
        }
    }

    /// Layer `k` on its own: pre: [N,f] -> [N,f].
    pub fn layer(&self, pre: &Tensor, k: usize) -> Result<Tensor> {
        self.apply(pre, k, false)
    }

    /// The whole modulated stack: `h_k = layer_k(linear(k, h_{k-1}))` from `h_{-1} = x` for
    /// the head's `n_layers` layers; returns every `h_k`.
    pub fn stack(
        &self,
        x: &Tensor,
        linear: impl Fn(usize, &Tensor) -> Result<Tensor>,
    ) -> Result<Vec<Tensor>> {
        let mut h = x.clone();
        let mut outs = Vec::with_capacity(self.n_layers);
        for k in 0..self.n_layers {
            h = self.apply(&linear(k, &h)?, k, true)?;
            outs.push(h.clone());
        }
        Ok(outs)
    }

    fn apply(&self, pre: &Tensor, k: usize, chained: bool) -> Result<Tensor> {
        let (o, n_layers, (mul, add)) = (&self.o, self.n_layers, (self.mul, self.add));
        let f = pre.dim(candle_core::D::Minus1)?;
        let fits = pre.rank() == 2
            && o.rank() == 2
            && k < n_layers
            && o.dim(1)? == 2 * n_layers * f
            && o.dim(0)? == pre.dim(0)?;
        let on_route = if self.modeled {
            modeled_f32(&[pre])
        } else {
            cpu_f32(&[pre]) || cuda_f32(&[pre])
        };
        if !(self.fused && fits && on_route) {
            let theta = o.narrow(1, k * f, f)?;
            let phi = o.narrow(1, (n_layers + k) * f, f)?;
            let arg = (pre * theta.affine(mul, add)?)?.add(&phi)?;
            return crate::compute::fast_sine::sin(&arg, self.fast);
        }
        let (pre, o) = (pre.contiguous()?, o.contiguous()?);
        // On the CPU the cosine is kept: libm's is the costly part of the backward. On a GPU
        // (and a CPU run accounted as one) the backward recomputes it from pre and Φ (the
        // same bytes read as a kept cosine, and a [N,f] tensor less alive from forward to
        // backward).
        let keep_cos =
            (pre.track_op() || o.track_op()) && !(self.modeled || pre.device().is_cuda());
        let op = FilmSine {
            k,
            n_layers,
            mul: mul as f32,
            add: add as f32,
            fast: self.fast,
            cos: crate::compute::ops::Kept::new(keep_cos),
            modeled: self.modeled,
            shared: chained.then(|| self.grad.clone()),
        };
        Ok(pre.apply_op2(&o, op)?)
    }
}

struct FilmSine {
    k: usize,
    n_layers: usize,
    mul: f32,
    add: f32,
    /// Sine flavour fixed when the graph is built, so the backward matches its forward.
    fast: bool,
    /// cos of the argument, kept by the CPU route's forward for its backward.
    cos: crate::compute::ops::Kept<Vec<f32>>,
    /// A CPU run accounted as CUDA ([`FilmHead`]).
    modeled: bool,
    /// The head gradient shared along a [`FilmHead::stack`].
    shared: Option<Arc<Mutex<HeadGrad>>>,
}

impl FilmSine {
    /// Row `i`'s Θ_k and Φ_k blocks inside `o`.
    fn blocks<'a>(&self, o: &'a [f32], i: usize, f: usize) -> (&'a [f32], &'a [f32]) {
        let row = &o[i * 2 * self.n_layers * f..(i + 1) * 2 * self.n_layers * f];
        let t = self.k * f;
        let p = (self.n_layers + self.k) * f;
        (&row[t..t + f], &row[p..p + f])
    }

    /// The sine's argument, `(pre · (Θ·mul + add)) + Φ`, row by row.
    fn argument(&self, pre: &[f32], o: &[f32], f: usize) -> Vec<f32> {
        let mut a = Vec::with_capacity(pre.len());
        for (i, prow) in pre.chunks_exact(f).enumerate() {
            let (theta, phi) = self.blocks(o, i, f);
            a.extend(
                prow.iter()
                    .zip(theta)
                    .zip(phi)
                    .map(|((&x, &t), &p)| x * (t * self.mul + self.add) + p),
            );
        }
        a
    }

    /// sin (`shift` 0) or cos (`shift` 1) in place, libm or the vectorised kernel.
    fn trig(&self, a: Vec<f32>, shift: u64) -> Vec<f32> {
        crate::compute::fast_sine::trig(&a, shift, self.fast)
    }

    /// Bytes `film_sine.cu`'s forward reads (pre, and the Θ_k, Φ_k blocks of o) and writes
    /// (the sine, and the cosine when it is kept).
    fn fwd_bytes(n: usize, f: usize, keep_cos: bool) -> (u64, u64) {
        let nf = (n * f * 4) as u64;
        (3 * nf, nf * (1 + u64::from(keep_cos)))
    }

    /// Bytes its backward reads (upstream gradient, pre, Θ_k, and the kept cosine or Φ_k to
    /// recompute it) and writes (pre's gradient, the layer's two head-gradient blocks, and
    /// the memset of the whole head gradient, [N,w], when this layer starts it).
    fn bwd_bytes(n: usize, f: usize, w: usize, starts_head: bool) -> (u64, u64) {
        let nf = (n * f * 4) as u64;
        let memset = if starts_head { (n * w * 4) as u64 } else { 0 };
        (4 * nf, 3 * nf + memset)
    }

    fn check(&self, l1: &Layout, l2: &Layout) -> candle_core::Result<(usize, usize)> {
        let (n, f) = l1.shape().dims2()?;
        let (n2, w) = l2.shape().dims2()?;
        if n2 != n || w != 2 * self.n_layers * f {
            candle_core::bail!(
                "film sine: o {:?} does not hold 2·{}·{f} columns for pre {:?}",
                l2.shape(),
                self.n_layers,
                l1.shape()
            )
        }
        Ok((n, f))
    }
}

impl CustomOp2 for FilmSine {
    fn name(&self) -> &'static str {
        "pma-film-sine"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (n, f) = self.check(l1, l2)?;
        let (pre, o) = (
            f32_slice(s1, l1, "film sine: pre")?,
            f32_slice(s2, l2, "film sine: o")?,
        );
        let (read, written) = Self::fwd_bytes(n, f, self.cos.wanted());
        candle_core::account::report_bytes(read, written);
        let a = self.argument(pre, o, f);
        let sin = if self.cos.wanted() {
            let (sin, cos) = crate::compute::fast_sine::trig_pair(&a, self.fast);
            self.cos.put(cos);
            sin
        } else {
            self.trig(a, 0)
        };
        Ok((CpuStorage::F32(sin), l1.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let (n, f) = self.check(l1, l2)?;
        candle_core::account::report_launches(1, 0);
        let (read, written) = Self::fwd_bytes(n, f, false);
        candle_core::account::report_bytes(read, written);
        let (out, _) = crate::compute::cuda::film_sine(s1, l1, s2, l2, self.film(n, f), false)?;
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        pre: &Tensor,
        o: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        if self.modeled || pre.device().is_cuda() {
            return self.device_bwd(pre, o, grad);
        }
        let (n, f) = pre.dims2()?;
        let w = 2 * self.n_layers * f;
        let (pre_c, o_c, d_c) = (pre.contiguous()?, o.contiguous()?, grad.contiguous()?);
        let guards = [&pre_c, &o_c, &d_c].map(|t| t.storage_and_layout());
        let [p, oo, d] = [0, 1, 2].map(|i| cpu_slice(&guards[i].0, guards[i].1));
        let (p, oo, d) = (p?, oo?, d?);
        let cos = match self.cos.take() {
            Some(c) if c.len() == n * f => c,
            _ => self.trig(self.argument(p, oo, f), 1),
        };
        // Layers after the first write into the stack's shared head gradient and return
        // none of their own; layer 0 (run last) returns it. See [`FilmHead`].
        let mut shared = self
            .shared
            .as_ref()
            .map(|s| s.lock().unwrap_or_else(|e| e.into_inner()));
        let defer = shared.as_ref().is_some_and(|s| !s.taken);
        let mut g_o = match shared.as_mut() {
            Some(s) if defer => s.buf.take().unwrap_or_else(|| vec![0f32; n * w]),
            _ => vec![0f32; n * w],
        };
        if g_o.len() != n * w {
            candle_core::bail!("film sine: shared head gradient has the wrong size")
        }
        let g_pre = self.grad_rows(p, oo, d, &cos, &mut g_o, f);
        drop(guards);
        let g_pre = Tensor::from_vec(g_pre, (n, f), pre.device())?;
        if let Some(s) = shared.as_mut().filter(|_| defer) {
            if self.k > 0 {
                s.buf = Some(g_o);
                return Ok((Some(g_pre), None));
            }
            s.taken = true;
        }
        let g_o = Tensor::from_vec(g_o, (n, w), o.device())?;
        Ok((Some(g_pre), Some(g_o)))
    }
}

impl FilmSine {
    /// The gradient of pre, and this layer's blocks of the head gradient written into `g_o`
    /// ([N,w]), from pre, o, the upstream gradient `d` and cos of the argument. The plain
    /// graph's steps, each gradient starting from candle's zero accumulator: g_a = d·cos(a);
    /// the add passes it to the product and to Φ; the product gives pre g_a·γ and γ g_a·pre;
    /// the affine gives Θ (g_γ·mul) + 0.
    fn grad_rows(
        &self,
        p: &[f32],
        oo: &[f32],
        d: &[f32],
        cos: &[f32],
        g_o: &mut [f32],
        f: usize,
    ) -> Vec<f32> {
        let n = p.len() / f.max(1);
        let w = 2 * self.n_layers * f;
        let mut g_pre = Vec::with_capacity(n * f);
        for i in 0..n {
            let (theta, _) = self.blocks(oo, i, f);
            let prow = &p[i * f..(i + 1) * f];
            let row = i * f..(i + 1) * f;
            let (dr, cr) = (&d[row.clone()], &cos[row]);
            let go = &mut g_o[i * w..(i + 1) * w];
            let (t0, p0) = (self.k * f, (self.n_layers + self.k) * f);
            for c in 0..f {
                let ga = dr[c] * cr[c];
                let gt = 0f32 + ga;
                let gamma = theta[c] * self.mul + self.add;
                g_pre.push(gt * gamma);
                let gg = 0f32 + gt * prow[c];
                go[t0 + c] = gg * self.mul + 0f32;
                go[p0 + c] = 0f32 + ga;
            }
        }
        g_pre
    }

    /// The backward on CUDA, and in a CPU run accounted as CUDA shaped as that backward:
    /// one op per layer (`film_sine.cu`'s gradient kernel, its memset of the head gradient
    /// when the layer starts it), the head gradient handed over by layer 0 without a launch.
    /// The cosine is recomputed (the device routes keep none). The same values as the CPU
    /// backward, up to CUDA's `cosf`.
    fn device_bwd(
        &self,
        pre: &Tensor,
        o: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let (n, f) = pre.dims2()?;
        let w = 2 * self.n_layers * f;
        let (pre_c, o_c, d_c) = (pre.contiguous()?, o.contiguous()?, grad.contiguous()?);
        let mut shared = self
            .shared
            .as_ref()
            .map(|s| s.lock().unwrap_or_else(|e| e.into_inner()));
        let defer = shared.as_ref().is_some_and(|s| !s.taken);
        let head = match shared.as_mut() {
            Some(s) if defer => s.dev.take(),
            _ => None,
        };
        let op = FilmGrad {
            layer: self,
            head: Mutex::new(head),
        };
        let g_pre = d_c.apply_op3_no_bwd(&pre_c, &o_c, &op)?;
        let head = op.head.into_inner().unwrap_or_else(|e| e.into_inner());
        if let Some(s) = shared.as_mut().filter(|_| defer) {
            if self.k > 0 {
                s.dev = head;
                return Ok((Some(g_pre), None));
            }
            s.taken = true;
        }
        let head =
            head.ok_or_else(|| candle_core::Error::Msg("film sine: no head gradient".into()))?;
        let g_o = d_c.apply_op1_no_bwd(&HeadOut {
            buf: Mutex::new(Some(head)),
            shape: Shape::from((n, w)),
        })?;
        Ok((Some(g_pre), Some(g_o)))
    }
}

/// A FiLM-sine layer's device backward on (grad, pre, o), counted as `film_sine.cu`'s
/// gradient kernel: the gradient of pre; the layer's head-gradient blocks go into `head`
/// (made zeroed when it is `None`: on the modeled device with its bytes held live).
struct FilmGrad<'a> {
    layer: &'a FilmSine,
    head: Mutex<Option<HeadBuf>>,
}

impl FilmGrad<'_> {
    /// (N, F) of grad and pre, o [N, 2KF] checked; the op counted as the kernel and, when
    /// this layer starts the head gradient, its memset.
    fn count(
        &self,
        l1: &Layout,
        l2: &Layout,
        l3: &Layout,
        starts: bool,
    ) -> candle_core::Result<(usize, usize)> {
        let (n, f) = l2.shape().dims2()?;
        let w = 2 * self.layer.n_layers * f;
        if l1.shape().dims2()? != (n, f) || l3.shape().dims2()? != (n, w) {
            candle_core::bail!("film sine gradient: shapes do not agree with [{n}, {f}]")
        }
        candle_core::account::report_launches(if starts { 2 } else { 1 }, 0);
        let (read, written) = FilmSine::bwd_bytes(n, f, w, starts);
        candle_core::account::report_bytes(read, written);
        Ok((n, f))
    }
}

impl CustomOp3 for FilmGrad<'_> {
    fn name(&self) -> &'static str {
        "pma-film-sine-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let mut head = self.head.lock().unwrap_or_else(|e| e.into_inner());
        let (n, f) = self.count(l1, l2, l3, head.is_none())?;
        let film = self.layer;
        let w = 2 * film.n_layers * f;
        let d = f32_slice(s1, l1, "film sine gradient: grad")?;
        let p = f32_slice(s2, l2, "film sine gradient: pre")?;
        let oo = f32_slice(s3, l3, "film sine gradient: o")?;
        let g_o = match head.get_or_insert_with(|| {
            HeadBuf::Modeled(
                vec![0f32; n * w],
                candle_core::account::hold(true, n * w * 4),
            )
        }) {
            HeadBuf::Modeled(g_o, _) if g_o.len() == n * w => g_o,
            _ => candle_core::bail!("film sine: the shared head gradient is not this layer's"),
        };
        let cos = film.trig(film.argument(p, oo, f), 1);
        let g_pre = film.grad_rows(p, oo, d, &cos, g_o, f);
        Ok((CpuStorage::F32(g_pre), Shape::from((n, f))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let mut head = self.head.lock().unwrap_or_else(|e| e.into_inner());
        let (n, f) = self.count(l1, l2, l3, head.is_none())?;
        let mut buf = match head.take() {
            None => None,
            Some(HeadBuf::Cuda(b)) => Some(b),
            Some(HeadBuf::Modeled(..)) => {
                candle_core::bail!("film sine: a host head gradient for a CUDA layer")
            }
        };
        let g_pre = crate::compute::cuda::film_sine_grad(
            s1,
            l1,
            s2,
            l2,
            s3,
            l3,
            None,
            &mut buf,
            self.layer.film(n, f),
        )?;
        *head = buf.map(HeadBuf::Cuda);
        Ok((g_pre, l1.shape().clone()))
    }
}

/// Hands a finished head gradient to candle as a tensor, counted as the CUDA hand-over (no
/// launch, nothing moved).
struct HeadOut {
    buf: Mutex<Option<HeadBuf>>,
    shape: Shape,
}

impl HeadOut {
    fn take(&self) -> candle_core::Result<HeadBuf> {
        candle_core::account::report_launches(0, 0);
        candle_core::account::report_bytes(0, 0);
        let buf = self.buf.lock().unwrap_or_else(|e| e.into_inner()).take();
        buf.ok_or_else(|| candle_core::Error::Msg("film sine: head gradient used twice".into()))
    }
}

impl candle_core::CustomOp1 for HeadOut {
    fn name(&self) -> &'static str {
        "pma-film-head-grad"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        match self.take()? {
            // The held bytes end here: the storage made of the buffer counts from now on.
            HeadBuf::Modeled(buf, _held) => Ok((CpuStorage::F32(buf), self.shape.clone())),
            #[cfg(feature = "cuda")]
            HeadBuf::Cuda(_) => {
                candle_core::bail!("film sine head gradient: a CUDA buffer for a CPU tensor")
            }
        }
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        match self.take()? {
            HeadBuf::Cuda(buf) => {
                Ok((crate::compute::cuda::storage_of(buf, s), self.shape.clone()))
            }
            HeadBuf::Modeled(..) => {
                candle_core::bail!("film sine head gradient: a host buffer for a CUDA tensor")
            }
        }
    }
}

#[cfg(feature = "cuda")]
impl FilmSine {
    fn film(&self, n: usize, f: usize) -> crate::compute::cuda::Film {
        crate::compute::cuda::Film {
            n,
            f,
            k: self.k,
            n_layers: self.n_layers,
            mul: self.mul,
            add: self.add,
        }
    }
}

/// The f32 data of a contiguous CPU tensor's storage.
fn cpu_slice<'a>(s: &'a Storage, l: &Layout) -> candle_core::Result<&'a [f32]> {
    let Storage::Cpu(cpu) = s else {
        candle_core::bail!("fused kernel: tensor is not on the CPU")
    };
    f32_slice(cpu, l, "fused kernel")
}

struct BiasAdd;

/// Column sums of `grad` ([rows,out]) in row order from zero: the sums candle's reduction
/// forms, in one contiguous pass (the bias gradient).
fn row_sums(grad: &Tensor, out: usize) -> candle_core::Result<Tensor> {
    let grad_c = grad.contiguous()?;
    let (storage, layout) = grad_c.storage_and_layout();
    let mut sums = vec![0f32; out];
    for row in cpu_slice(&storage, layout)?.chunks_exact(out) {
        for (a, v) in sums.iter_mut().zip(row) {
            *a += v;
        }
    }
    drop(storage);
    Tensor::from_vec(sums, out, grad.device())
}

/// [`linear`]'s op on (x, W, b).
struct Linear {
    /// The CPU's route: the bias gradient as [`BiasAdd`] sums it. Elsewhere (CUDA, a CPU run
    /// accounted as CUDA) it is candle's reduction, as after a `broadcast_add`.
    cpu_route: bool,
}

/// A linear layer's (rows, in, out) from the layouts of x [rows,in], W [out,in], b [out],
/// checked.
pub(crate) fn linear_dims(
    l1: &Layout,
    l2: &Layout,
    l3: &Layout,
) -> candle_core::Result<(usize, usize, usize)> {
    let (rows, inn) = l1.shape().dims2()?;
    let (out, inn2) = l2.shape().dims2()?;
    if inn2 != inn || l3.shape().dims1()? != out {
        candle_core::bail!(
            "linear: x {:?}, W {:?} and b {:?} do not agree",
            l1.shape(),
            l2.shape(),
            l3.shape()
        )
    }
    Ok((rows, inn, out))
}

/// Count a linear layer's op as its two kernels: the op is the product (its launch, bytes
/// and FLOPs), its epilogue `name` (reading the product and the bias, writing the output,
/// with `params` dims uploads) is recorded beside it.
pub(crate) fn report_linear(
    cpu: bool,
    (rows, inn, out): (usize, usize, usize),
    name: &'static str,
    params: u32,
) {
    let (rows, inn, out) = (rows as u64, inn as u64, out as u64);
    candle_core::account::report_launches(1, 0);
    candle_core::account::report_bytes(4 * (rows * inn + out * inn), 4 * rows * out);
    candle_core::account::report_flops(2 * rows * out * inn);
    candle_core::account::record(
        cpu,
        candle_core::account::Op {
            name,
            launches: 1,
            param_uploads: params,
            bytes_read: 4 * (rows * out + out),
            bytes_written: 4 * rows * out,
            flops: 0,
        },
    );
}

/// The product x · Wᵀ on the CPU, exactly as `Tensor::matmul` calls it.
pub(crate) fn cpu_product(
    (s1, l1): (&CpuStorage, &Layout),
    (s2, l2): (&CpuStorage, &Layout),
    (rows, inn, out): (usize, usize, usize),
) -> candle_core::Result<Vec<f32>> {
    use candle_core::backend::BackendStorage;
    match s1.matmul(s2, (1, rows, out, inn), l1, &l2.transpose(0, 1)?)? {
        CpuStorage::F32(y) => Ok(y),
        _ => candle_core::bail!("linear: the product is not f32"),
    }
}

impl CustomOp3 for Linear {
    fn name(&self) -> &'static str {
        "matmul"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let d = linear_dims(l1, l2, l3)?;
        let (rows, out) = (d.0, d.2);
        report_linear(true, d, "add", 1);
        let mut y = cpu_product((s1, l1), (s2, l2), d)?;
        let b = f32_slice(s3, l3, "linear: b")?;
        for row in y.chunks_exact_mut(out.max(1)) {
            for (a, c) in row.iter_mut().zip(b) {
                *a += c;
            }
        }
        Ok((CpuStorage::F32(y), Shape::from((rows, out))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        use candle_core::backend::BackendStorage;
        let (rows, inn, out) = linear_dims(l1, l2, l3)?;
        report_linear(false, (rows, inn, out), "add", 1);
        // cuBLAS, then candle's broadcast add kernel; the product is freed on return.
        let y = s1.matmul(s2, (1, rows, out, inn), l1, &l2.transpose(0, 1)?)?;
        let y_l = Layout::contiguous((rows, out));
        let b_l = l3.broadcast_as((rows, out))?;
        let sum = y.binary_impl::<candle_core::op::Add>(s3, &y_l, &b_l)?;
        Ok((sum, Shape::from((rows, out))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        // candle's matmul backward for x · (Wᵀ), then the transpose's: the same products.
        let wt = w.t()?;
        // No product for an input that takes no gradient (the GNN's pose input).
        let gx = x.track_op().then(|| grad.matmul(&wt.t()?)).transpose()?;
        let gw = x.t()?.matmul(grad)?.t()?;
        let out = w.dim(0)?;
        let gb = match self.cpu_route {
            true => row_sums(grad, out)?,
            false => grad.sum(0)?,
        };
        Ok((gx, Some(gw), Some(gb)))
    }
}

impl CustomOp2 for BiasAdd {
    fn name(&self) -> &'static str {
        "pma-bias-add"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (y, b) = (
            f32_slice(s1, l1, "bias add: y")?,
            f32_slice(s2, l2, "bias add: b")?,
        );
        let out = b.len();
        if out == 0 || y.len() % out != 0 {
            candle_core::bail!(
                "bias add: {} values do not split into rows of {out}",
                y.len()
            )
        }
        let mut dst = Vec::with_capacity(y.len());
        for row in y.chunks_exact(out) {
            dst.extend(row.iter().zip(b).map(|(a, c)| a + c));
        }
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _y: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        // Row order, from zero: the same summation candle's reduction does.
        let gb = row_sums(grad, b.elem_count())?;
        Ok((Some(grad.clone()), Some(gb)))
    }
}

/// The fused max-pool; when the graph tracks gradients its forward keeps the arg-max joint
/// of every output for the backward, which then need not pool again.
struct WindowPool {
    arg: crate::compute::ops::Kept<Vec<u32>>,
    /// On a CPU run accounted as CUDA: count the CUDA kernels (see [`models_cuda`]).
    modeled: bool,
    /// The kept arg-max's bytes, live on the modeled device until the backward takes it.
    held: Mutex<Option<candle_core::account::Held>>,
    /// The arg-max of a CUDA forward, on the device.
    #[cfg(feature = "cuda")]
    arg_dev: crate::compute::ops::Kept<crate::compute::cuda::ArgMax>,
}

/// One point's pooled row: `best[k] = max_j (q[j,k] + g[j,k]) · w[j]` and the first joint
/// reaching it in `arg` (a NaN wins and stays, as PyTorch's max propagates it). Written with
/// selects rather than branches, so it vectorises.
fn pool_row(q: &[f32], g: &[f32], w: &[f32], best: &mut [f32], arg: &mut [u32]) {
    let h = best.len();
    for (k, (b, a)) in best.iter_mut().zip(arg.iter_mut()).enumerate() {
        *b = (q[k] + g[k]) * w[0];
        *a = 0;
    }
    for (jj, &wj) in w.iter().enumerate().skip(1) {
        let (qj, gj) = (&q[jj * h..(jj + 1) * h], &g[jj * h..(jj + 1) * h]);
        let joint = jj as u32;
        for ((b, a), (&qv, &gv)) in best.iter_mut().zip(arg.iter_mut()).zip(qj.iter().zip(gj)) {
            let v = (qv + gv) * wj;
            let take = v > *b || (v.is_nan() & !b.is_nan());
            *b = if take { v } else { *b };
            *a = if take { joint } else { *a };
        }
    }
}

impl CustomOp3 for WindowPool {
    fn name(&self) -> &'static str {
        "pma-window-pool"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (n, j, h) = l1.shape().dims3()?;
        let q = f32_slice(s1, l1, "window pool: q")?;
        let g = f32_slice(s2, l2, "window pool: g")?;
        let w = f32_slice(s3, l3, "window pool: w_p")?;
        let poses = g.len() / (j * h).max(1);
        if poses == 0 || g.len() != poses * j * h || n % poses != 0 || w.len() != n * j {
            candle_core::bail!("window pool: shapes do not agree with q [{n},{j},{h}]")
        }
        let per_pose = n / poses;
        if j > u32::MAX as usize {
            candle_core::bail!("window pool: {j} joints")
        }
        let mut dst = vec![0f32; n * h];
        // Every row's arg-max when it is kept for the backward, else one row's scratch.
        let mut arg = vec![0u32; if self.arg.wanted() { n * h } else { h }];
        for (i, m) in dst.chunks_exact_mut(h).enumerate() {
            let a = if self.arg.wanted() {
                &mut arg[i * h..(i + 1) * h]
            } else {
                &mut arg[..]
            };
            let gp = i / per_pose;
            pool_row(
                &q[i * j * h..(i + 1) * j * h],
                &g[gp * j * h..(gp + 1) * j * h],
                &w[i * j..(i + 1) * j],
                m,
                a,
            );
        }
        if self.arg.wanted() {
            if self.modeled {
                let held = candle_core::account::hold(true, arg.len() * 4);
                *self.held.lock().unwrap_or_else(|e| e.into_inner()) = Some(held);
            }
            self.arg.put(arg);
        }
        Ok((CpuStorage::F32(dst), Shape::from((n, h))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let (n, j, h) = l1.shape().dims3()?;
        let (p, j2, h2) = l2.shape().dims3()?;
        if j2 != j || h2 != h || p == 0 || n % p != 0 || l3.shape().dims2()? != (n, j) {
            candle_core::bail!("window pool: shapes do not agree with q [{n},{j},{h}]")
        }
        candle_core::account::report_launches(1, 0);
        let (out, arg) =
            crate::compute::cuda::window_pool(s1, l1, s2, l2, s3, l3, [n, j, h, n / p])?;
        self.arg_dev.put(arg);
        Ok((out, Shape::from((n, h))))
    }

    fn bwd(
        &self,
        q: &Tensor,
        g: &Tensor,
        w_p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (gq, gg) = self.grads(&QSource::Tensor(q), g, w_p, grad)?;
        Ok((Some(gq), Some(gg), None))
    }
}

/// Where a window pool's backward gets q when it must pool again (a second backward over
/// the same graph): the forward's input, or the product [`window_pool_of`] computed it from.
enum QSource<'a> {
    Tensor(&'a Tensor),
    /// q = e · Wᵀ, [N·J,Ce] · [H,Ce]ᵀ, viewed as [N,J,H].
    Product {
        e: &'a Tensor,
        w: &'a Tensor,
        j: usize,
    },
}

impl QSource<'_> {
    fn dims(&self) -> candle_core::Result<(usize, usize, usize)> {
        match self {
            Self::Tensor(q) => q.dims3(),
            Self::Product { e, w, j } => Ok((e.dim(0)? / j, *j, w.dim(0)?)),
        }
    }

    fn get(&self) -> candle_core::Result<Tensor> {
        match self {
            Self::Tensor(q) => Ok((*q).clone()),
            Self::Product { e, w, j } => {
                let (n, h) = (e.dim(0)? / j, w.dim(0)?);
                e.matmul(&w.t()?)?.reshape((n, *j, h))
            }
        }
    }
}

/// The arg-max joint of every output of a window pool on the CPU, pooling q again (a second
/// backward over the same graph, whose forward's arg-max was used by the first).
fn pool_arg_cpu(q: &QSource, g: &Tensor, w_p: &Tensor) -> candle_core::Result<Vec<u32>> {
    let (n, j, h) = q.dims()?;
    let per_pose = n / g.dim(0)?.max(1);
    let (qc, gc, wc) = (q.get()?.contiguous()?, g.contiguous()?, w_p.contiguous()?);
    let guards = [&qc, &gc, &wc].map(|t| t.storage_and_layout());
    let [qs, gs, ws] = [0, 1, 2].map(|i| cpu_slice(&guards[i].0, guards[i].1));
    let (qs, gs, ws) = (qs?, gs?, ws?);
    let mut arg = vec![0u32; n * h];
    let mut best = vec![0f32; h];
    for i in 0..n {
        let gp = (i / per_pose) * j * h;
        pool_row(
            &qs[i * j * h..(i + 1) * j * h],
            &gs[gp..gp + j * h],
            &ws[i * j..(i + 1) * j],
            &mut best,
            &mut arg[i * h..(i + 1) * h],
        );
    }
    Ok(arg)
}

impl WindowPool {
    /// The gradients of q and g: from the forward's kept arg-max, or (a second backward)
    /// from pooling q again.
    fn grads(
        &self,
        q: &QSource,
        g: &Tensor,
        w_p: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        #[cfg(feature = "cuda")]
        if g.device().is_cuda() {
            return self.cuda_bwd(q, g, w_p, grad);
        }
        if self.modeled {
            return self.modeled_bwd(q, g, w_p, grad);
        }
        let (n, j, h) = q.dims()?;
        let poses = g.dim(0)?;
        let per_pose = n / poses;
        // The forward's arg-max (used once; a second backward pools again).
        let kept = match self.arg.take().filter(|a| a.len() == n * h) {
            Some(a) => a,
            None => pool_arg_cpu(q, g, w_p)?,
        };
        let (w_c, d_c) = (w_p.contiguous()?, grad.contiguous()?);
        let guards = [&w_c, &d_c].map(|t| t.storage_and_layout());
        let [w, dm] = [0, 1].map(|i| cpu_slice(&guards[i].0, guards[i].1));
        let (w, dm) = (w?, dm?);
        let mut gq = vec![0f32; n * j * h];
        let mut gg = vec![0f32; poses * j * h];
        for i in 0..n {
            let wn = &w[i * j..(i + 1) * j];
            let gp = (i / per_pose) * j * h;
            let arg_i = &kept[i * h..(i + 1) * h];
            let dmn = &dm[i * h..(i + 1) * h];
            for k in 0..h {
                let jj = arg_i[k] as usize;
                let d = dmn[k] * wn[jj];
                gq[i * j * h + jj * h + k] = d;
                gg[gp + jj * h + k] += d;
            }
        }
        drop(guards);
        let gq = Tensor::from_vec(gq, (n, j, h), g.device())?;
        let gg = Tensor::from_vec(gg, (poses, j, h), g.device())?;
        Ok((gq, gg))
    }
}

impl WindowPool {
    /// The backward of a CPU run accounted as CUDA, as the CUDA backward runs: the kept
    /// arg-max (or the forward's kernel again), then one op per gradient, each counted as
    /// its kernel (reading the upstream gradient, the window and the arg-max).
    fn modeled_bwd(
        &self,
        q: &QSource,
        g: &Tensor,
        w_p: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let (n, j, h) = q.dims()?;
        let p = g.dim(0)?;
        let w = w_p.contiguous()?;
        let arg = match self.arg.take().filter(|a| a.len() == n * h) {
            Some(a) => a,
            None => {
                // The forward's kernel once more (its outputs: the max and the arg-max).
                let arg = pool_arg_cpu(q, g, &w)?;
                candle_core::account::record(
                    true,
                    candle_core::account::Op {
                        name: "pma-window-pool",
                        launches: 1,
                        param_uploads: 0,
                        bytes_read: ((n * j * h + g.elem_count() + n * j) * 4) as u64,
                        bytes_written: (n * h * 8) as u64,
                        flops: 0,
                    },
                );
                arg
            }
        };
        // The arg-max is the kernels' input now: live (as a tensor) until they are done.
        let arg = candle_core::account::uncounted(|| Tensor::from_vec(arg, (n, h), g.device()))?;
        let held = candle_core::account::hold(true, n * h * 4);
        self.held.lock().unwrap_or_else(|e| e.into_inner()).take();
        let grad = grad.contiguous()?;
        let gq = grad.apply_op3_no_bwd(&w, &arg, &PoolGradCpu { p, of_g: false })?;
        let gg = grad.apply_op3_no_bwd(&w, &arg, &PoolGradCpu { p, of_g: true })?;
        drop(held);
        Ok((gq, gg))
    }
}

/// One gradient of the window pool on the CPU from (upstream gradient [N,H], window [N,J],
/// arg-max [N,H] u32), as a custom op so that a CPU run accounted as CUDA counts it as the
/// kernel `window_pool.cu` runs for it: grad q [N,J,H] or (`of_g`) grad g [P,J,H], the same
/// values as the CPU backward.
struct PoolGradCpu {
    p: usize,
    of_g: bool,
}

impl CustomOp3 for PoolGradCpu {
    fn name(&self) -> &'static str {
        "pma-window-pool-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (n, h) = l1.shape().dims2()?;
        let (n2, j) = l2.shape().dims2()?;
        let dm = f32_slice(s1, l1, "window pool gradient: grad")?;
        let w = f32_slice(s2, l2, "window pool gradient: w_p")?;
        let CpuStorage::U32(arg) = s3 else {
            candle_core::bail!("window pool gradient: the arg-max is not u32")
        };
        let p = self.p;
        if n2 != n || l3.shape().dims2()? != (n, h) || p == 0 || n % p != 0 {
            candle_core::bail!("window pool gradient: shapes do not agree with [{n},{j},{h}]")
        }
        let per_pose = n / p;
        // The CPU backward's loop, keeping one of its two outputs.
        let mut out = vec![0f32; if self.of_g { p * j * h } else { n * j * h }];
        for i in 0..n {
            let gp = (i / per_pose) * j * h;
            for k in 0..h {
                let jj = arg[i * h + k] as usize;
                let d = dm[i * h + k] * w[i * j + jj];
                if self.of_g {
                    out[gp + jj * h + k] += d;
                } else {
                    out[i * j * h + jj * h + k] = d;
                }
            }
        }
        let shape = if self.of_g { (p, j, h) } else { (n, j, h) };
        Ok((CpuStorage::F32(out), Shape::from(shape)))
    }
}

#[cfg(feature = "cuda")]
impl WindowPool {
    /// The CUDA backward: the forward's arg-max (or the forward's kernel again, for a second
    /// backward), then one kernel per gradient.
    fn cuda_bwd(
        &self,
        q: &QSource,
        g: &Tensor,
        w_p: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let (n, j, h) = q.dims()?;
        let p = g.dim(0)?;
        let w = w_p.contiguous()?;
        let arg = match self.arg_dev.take() {
            Some(a) => a,
            None => {
                let (q, g) = (q.get()?.contiguous()?, g.contiguous()?);
                let guards = [&q, &g, &w].map(|t| t.storage_and_layout());
                let cuda = |i: usize| match &*guards[i].0 {
                    Storage::Cuda(c) => Ok(c),
                    _ => Err(candle_core::Error::Msg(
                        "window pool: expected CUDA tensors".into(),
                    )),
                };
                let (_, arg) = crate::compute::cuda::window_pool(
                    cuda(0)?,
                    guards[0].1,
                    cuda(1)?,
                    guards[1].1,
                    cuda(2)?,
                    guards[2].1,
                    [n, j, h, n / p],
                )?;
                arg
            }
        };
        let grad = grad.contiguous()?;
        let gq = grad.apply_op2_no_bwd(
            &w,
            &PoolGrad {
                arg: arg.clone(),
                dims: [n, p, j, h],
                of_g: false,
            },
        )?;
        let gg = grad.apply_op2_no_bwd(
            &w,
            &PoolGrad {
                arg,
                dims: [n, p, j, h],
                of_g: true,
            },
        )?;
        Ok((gq, gg))
    }
}

/// One gradient of the CUDA window pool (of q, or of g when `of_g`), from the upstream
/// gradient and the spatial window: a kernel of `window_pool.cu`.
#[cfg(feature = "cuda")]
struct PoolGrad {
    arg: crate::compute::cuda::ArgMax,
    /// N, P, J, H.
    dims: [usize; 4],
    of_g: bool,
}

#[cfg(feature = "cuda")]
impl CustomOp2 for PoolGrad {
    fn name(&self) -> &'static str {
        "pma-window-pool-grad"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        candle_core::bail!("window pool gradient: the CUDA kernel got CPU tensors")
    }

    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let [n, p, j, h] = self.dims;
        if l1.shape().dims2()? != (n, h) || l2.shape().dims2()? != (n, j) {
            candle_core::bail!("window pool gradient: shapes do not agree with [{n},{j},{h}]")
        }
        candle_core::account::report_launches(1, 0);
        if self.of_g {
            let out =
                crate::compute::cuda::window_pool_grad_g(s1, l1, s2, l2, &self.arg, self.dims)?;
            Ok((out, Shape::from((p, j, h))))
        } else {
            let out =
                crate::compute::cuda::window_pool_grad_q(s1, l1, s2, l2, &self.arg, [n, j, h])?;
            Ok((out, Shape::from((n, j, h))))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn rand(shape: &[usize], seed: u64) -> Tensor {
        // Deterministic values in [-1, 1) without an RNG dependency.
        let n: usize = shape.iter().product();
        let mut x = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let v: Vec<f32> = (0..n)
            .map(|_| {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((x >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    fn bits_of(t: &Tensor) -> Vec<u32> {
        let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// The one-op linear layer gives the product-then-bias-add bits, forward and backward
    /// (twice over the same graph), on the CPU route and counted as CUDA, where it counts
    /// as the product and the bias add it launches.
    #[test]
    fn linear_matches_product_and_bias_add_bit_for_bit() {
        use crate::compute::account::{Account, Route};
        let empty = linear(
            &Tensor::zeros((0, 4), DType::F32, &Device::Cpu).unwrap(),
            &rand(&[2, 4], 60),
            &rand(&[2], 59),
            Numerics::PARITY,
        )
        .unwrap();
        assert_eq!(empty.dims(), [0, 2]);
        for (rows, inn, out) in [(37, 5, 9), (1, 3, 64), (300, 3, 2)] {
            let x = Var::from_tensor(&rand(&[rows, inn], 61)).unwrap();
            let w = Var::from_tensor(&rand(&[out, inn], 62)).unwrap();
            let b = Var::from_tensor(&rand(&[out], 63)).unwrap();
            let up = rand(&[rows, out], 64);
            let run = |fused: bool| {
                let k = Numerics {
                    fused,
                    ..Numerics::PARITY
                };
                let y = linear(x.as_tensor(), w.as_tensor(), b.as_tensor(), k).unwrap();
                let loss = (&y * &up).unwrap().sum_all().unwrap();
                let mut all = vec![bits_of(&y)];
                for _ in 0..2 {
                    let g = loss.backward().unwrap();
                    for (i, v) in [&x, &w, &b].into_iter().enumerate() {
                        let gv = g.get(v.as_tensor());
                        assert!(gv.is_some(), "fused {fused}, rows {rows}: no gradient {i}");
                        all.push(bits_of(gv.unwrap()));
                    }
                }
                all
            };
            let plain = run(false);
            assert_eq!(run(true), plain, "[{rows},{inn}] x [{out},{inn}]");
            let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
            let counted = run(true);
            let r = account.finish();
            assert_eq!(counted, plain);
            // Forward: the product and the bias add, as two launches.
            let op = |n: &str| r.ops.get(n).copied().unwrap_or_default();
            assert_eq!(op("matmul").flops, 2 * (rows * out * inn) as u64 * 5);
            assert!(op("add").launches >= 1);
        }
    }

    /// The window pool of a product computed inside it gives the bits of the product
    /// followed by the pool (values, and gradients of e, W and g over two backward passes),
    /// on the CPU route and counted as CUDA.
    #[test]
    fn window_pool_of_a_product_matches_product_then_pool() {
        use crate::compute::account::{Account, Route};
        let (n, j, h, ce, p) = (12, 5, 7, 4, 3);
        let e = Var::from_tensor(&rand(&[n * j, ce], 71)).unwrap();
        let w = Var::from_tensor(&rand(&[h, ce], 72)).unwrap();
        let g = Var::from_tensor(&rand(&[p, j, h], 73)).unwrap();
        let wp = rand(&[n, j], 74).abs().unwrap();
        let up = rand(&[n, h], 75);
        let run = |fused_op: bool| {
            let k = Numerics::PARITY;
            let y = if fused_op {
                window_pool_of(e.as_tensor(), w.as_tensor(), g.as_tensor(), &wp, k).unwrap()
            } else {
                let q = crate::compute::numerics::matmul(e.as_tensor(), &w.t().unwrap(), k)
                    .unwrap()
                    .reshape((n, j, h))
                    .unwrap();
                window_pool(&q, g.as_tensor(), &wp, k).unwrap()
            };
            let loss = (&y * &up).unwrap().sum_all().unwrap();
            let mut all = vec![bits_of(&y)];
            for _ in 0..2 {
                let gr = loss.backward().unwrap();
                for v in [&e, &w, &g] {
                    all.push(bits_of(gr.get(v.as_tensor()).unwrap()));
                }
            }
            all
        };
        let two_ops = run(false);
        assert_eq!(run(true), two_ops);
        let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
        let counted = run(true);
        let r = account.finish();
        assert_eq!(counted, two_ops);
        // Forward: the product and the pool; the second backward pools again.
        let launches = |op: &str| r.ops.get(op).map_or(0, |c| c.launches);
        assert_eq!(launches("pma-window-pool"), 2, "{:?}", r.ops.keys());
        assert_eq!(launches("pma-window-pool-grad"), 4);
    }

    /// Counted as CUDA (the fused pool then counts as its kernels), the window pool still
    /// computes the CPU's values and gradients, bit for bit, including a second backward
    /// that finds the arg-max used.
    #[test]
    fn window_pool_counted_as_cuda_keeps_the_cpu_bits() {
        use crate::compute::account::{Account, Route};
        let (n, j, h, p) = (12, 5, 7, 3);
        let q = Var::from_tensor(&rand(&[n, j, h], 1)).unwrap();
        let g = Var::from_tensor(&rand(&[p, j, h], 2)).unwrap();
        let w = rand(&[n, j], 3).abs().unwrap();
        let up = rand(&[n, h], 4);
        let run = || {
            let y = window_pool(q.as_tensor(), g.as_tensor(), &w, Numerics::PARITY).unwrap();
            let loss = (&y * &up).unwrap().sum_all().unwrap();
            let bits = |t: &Tensor| -> Vec<u32> {
                let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                v.iter().map(|x| x.to_bits()).collect()
            };
            let mut out = vec![bits(&y)];
            for _ in 0..2 {
                let gr = loss.backward().unwrap();
                out.push(bits(gr.get(&q).unwrap()));
                out.push(bits(gr.get(&g).unwrap()));
            }
            out
        };
        let cpu = run();
        let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
        let counted = run();
        let report = account.finish();
        assert_eq!(cpu, counted);
        let launches = |op: &str| report.ops.get(op).map_or(0, |c| c.launches);
        // Forward once, the arg-max again for the second backward, two gradients each time.
        assert_eq!(launches("pma-window-pool"), 2, "{:?}", report.ops.keys());
        assert_eq!(launches("pma-window-pool-grad"), 4);
    }

    fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// Forward values and gradients of both kernels equal the plain candle ops exactly,
    /// including rows whose spatial window is 0 for every joint (all-tie rows), with one
    /// pose and with three (each block of points pooled with its own pose's g).
    #[test]
    fn fused_kernels_match_plain_ops_bit_for_bit() {
        for poses in [1, 3] {
            fused_matches_plain(poses);
        }
    }

    fn fused_matches_plain(poses: usize) {
        let (n, j, h, out) = (39, 24, 16, 9);
        let run = |fused: bool| {
            let q = Var::from_tensor(&rand(&[n, j, h], 1)).unwrap();
            let g = Var::from_tensor(&rand(&[poses, j, h], 2)).unwrap();
            // Half the rows far from every bone (w_p = 0), the rest in (0, 1).
            let mut w = rand(&[n, j], 3).abs().unwrap();
            let zero = Tensor::zeros((n / 2, j), DType::F32, &Device::Cpu).unwrap();
            w = Tensor::cat(&[&zero, &w.narrow(0, n / 2, n - n / 2).unwrap()], 0).unwrap();
            let y = Var::from_tensor(&rand(&[n, out], 4)).unwrap();
            let b = Var::from_tensor(&rand(&[out], 5)).unwrap();
            let (m, z) = if fused {
                (
                    window_pool(q.as_tensor(), g.as_tensor(), &w, Numerics::PARITY).unwrap(),
                    add_bias(y.as_tensor(), b.as_tensor(), Numerics::PARITY).unwrap(),
                )
            } else {
                let part = q
                    .as_tensor()
                    .reshape((poses, n / poses, j, h))
                    .unwrap()
                    .broadcast_add(&g.as_tensor().unsqueeze(1).unwrap())
                    .unwrap()
                    .reshape((n, j, h));
                let att = part
                    .unwrap()
                    .broadcast_mul(&w.unsqueeze(2).unwrap())
                    .unwrap();
                (
                    att.max(1).unwrap(),
                    y.as_tensor().broadcast_add(b.as_tensor()).unwrap(),
                )
            };
            // A loss with distinct weights per element, so every gradient entry is tested.
            let a = m.sin().unwrap().sum_all().unwrap();
            let c = (z.sqr().unwrap() * 0.5).unwrap().sum_all().unwrap();
            let loss = (a + c).unwrap();
            let grads = loss.backward().unwrap();
            let get = |v: &Var| grads.get(v.as_tensor()).unwrap().clone();
            // A second backward over the same graph: the pool's kept arg-max is used up, so
            // its backward pools again and must give the same gradients.
            let again = loss.backward().unwrap();
            for v in [&q, &g] {
                let (first, second) = (get(v), again.get(v.as_tensor()).unwrap().clone());
                assert_eq!(
                    max_abs(&first, &second),
                    0.0,
                    "second backward, fused={fused}"
                );
            }
            (m, z, get(&q), get(&g), get(&y), get(&b))
        };
        let a = run(true);
        let b = run(false);
        assert_eq!(max_abs(&a.0, &b.0), 0.0, "pooled");
        assert_eq!(max_abs(&a.1, &b.1), 0.0, "bias add");
        assert_eq!(max_abs(&a.2, &b.2), 0.0, "grad q");
        assert_eq!(max_abs(&a.3, &b.3), 0.0, "grad g");
        assert_eq!(max_abs(&a.4, &b.4), 0.0, "grad y");
        assert_eq!(max_abs(&a.5, &b.5), 0.0, "grad bias");
        // The kernels actually ran (they are off when disabled or for other dtypes).
        assert!(applies(Numerics::PARITY, &[&a.0]));
    }

    /// The fused FiLM-sine layer gives the plain ops' values and gradients bit for bit, with
    /// libm's sine and with the vectorised one, for every layer of a 3-layer head, including
    /// large frequencies and arguments.
    #[test]
    fn film_sine_matches_plain_ops_bit_for_bit() {
        let (n, kk, f) = (29, 3, 8);
        for fast in [false, true] {
            for k in 0..kk {
                let run = |fused: bool| {
                    let pre = Var::from_tensor(&(rand(&[n, f], 11) * 3.0).unwrap()).unwrap();
                    let o =
                        Var::from_tensor(&(rand(&[n, 2 * kk * f], 12) * 40.0).unwrap()).unwrap();
                    let y = FilmHead::with(o.as_tensor(), kk, (15.0, 30.0), fast, fused)
                        .layer(pre.as_tensor(), k)
                        .unwrap();
                    // Distinct weights per element, so every gradient entry is tested.
                    let wts = rand(&[n, f], 13);
                    let grads = (&y * &wts).unwrap().sum_all().unwrap().backward().unwrap();
                    let get = |v: &Var| grads.get(v.as_tensor()).unwrap().clone();
                    (y, get(&pre), get(&o))
                };
                let (a, b) = (run(true), run(false));
                let bits = |t: &Tensor| {
                    t.flatten_all()
                        .unwrap()
                        .to_vec1::<f32>()
                        .unwrap()
                        .iter()
                        .map(|v| v.to_bits())
                        .collect::<Vec<_>>()
                };
                assert_eq!(bits(&a.0), bits(&b.0), "values, fast={fast} k={k}");
                assert_eq!(bits(&a.1), bits(&b.1), "grad pre, fast={fast} k={k}");
                assert_eq!(bits(&a.2), bits(&b.2), "grad head, fast={fast} k={k}");
                assert!(
                    a.2.abs()
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .to_scalar::<f32>()
                        .unwrap()
                        > 0.0
                );
            }
        }
    }

    /// A whole stack with its shared head gradient against the plain ops, bit for bit:
    /// values and the gradients of the input, the head and every linear layer. A second
    /// backward pass over the same graph (the shared gradient already handed over, the kept
    /// cosines used) gives the same bits again.
    #[test]
    fn film_stack_shares_one_head_gradient_bit_for_bit() {
        let (n, kk, f) = (23, 3, 8);
        let bits = |t: &Tensor| -> Vec<u32> {
            let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            v.iter().map(|v| v.to_bits()).collect()
        };
        let run = |fused: bool| {
            let x = Var::from_tensor(&rand(&[n, f], 21)).unwrap();
            let o = Var::from_tensor(&(rand(&[n, 2 * kk * f], 22) * 4.0).unwrap()).unwrap();
            let vars: Vec<(Var, Var)> = (0..kk as u64)
                .map(|k| {
                    let w = Var::from_tensor(&rand(&[f, f], 30 + k)).unwrap();
                    let b = Var::from_tensor(&rand(&[f], 40 + k)).unwrap();
                    (w, b)
                })
                .collect();
            // What the network's linear layer computes: x Wᵀ, then the bias.
            let linear = |k: usize, h: &Tensor| {
                let (w, b) = &vars[k];
                add_bias(
                    &h.matmul(&w.as_tensor().t()?)?,
                    b.as_tensor(),
                    Numerics::PARITY,
                )
            };
            let head = FilmHead::with(o.as_tensor(), kk, (15.0, 30.0), false, fused);
            let outs = head.stack(x.as_tensor(), linear).unwrap();
            let y = Tensor::cat(&outs, 1).unwrap();
            let wts = rand(&[n, kk * f], 23);
            let loss = (&y * &wts).unwrap().sum_all().unwrap();
            let mut passes = Vec::new();
            for _ in 0..2 {
                let g = loss.backward().unwrap();
                let mut all = vec![bits(&y)];
                all.push(bits(g.get(x.as_tensor()).unwrap()));
                all.push(bits(g.get(o.as_tensor()).unwrap()));
                for (w, b) in &vars {
                    all.push(bits(g.get(w.as_tensor()).unwrap()));
                    all.push(bits(g.get(b.as_tensor()).unwrap()));
                }
                passes.push(all);
            }
            passes
        };
        let (a, b) = (run(true), run(false));
        let names = [
            "values",
            "grad x",
            "grad head",
            "w0",
            "b0",
            "w1",
            "b1",
            "w2",
            "b2",
        ];
        for pass in 0..2 {
            for (i, name) in names.iter().enumerate() {
                assert_eq!(a[pass][i], b[pass][i], "{name}, backward pass {pass}");
            }
        }
        // Every layer's block of the head gradient is there (none lost to the sharing).
        let head: Vec<f32> = a[0][2].iter().map(|&u| f32::from_bits(u)).collect();
        for block in 0..2 * kk {
            let nonzero = (0..n).any(|r| {
                head[r * 2 * kk * f + block * f..][..f]
                    .iter()
                    .any(|v| *v != 0.0)
            });
            assert!(nonzero, "head gradient block {block} is empty");
        }
    }

    /// A stack accounted as CUDA runs the CPU kernels (the same bits) and counts
    /// `film_sine.cu`'s launches and bytes: one kernel per layer each way, the head
    /// gradient's memset once, no plain ops and nothing uploaded.
    #[test]
    fn film_stack_counted_as_cuda_keeps_the_cpu_bits() {
        use crate::compute::account::{Account, Route};
        let (n, kk, f) = (19, 3, 8);
        let x = Var::from_tensor(&rand(&[n, f], 51)).unwrap();
        let o = Var::from_tensor(&(rand(&[n, 2 * kk * f], 52) * 4.0).unwrap()).unwrap();
        let wts = rand(&[n, kk * f], 53);
        let run = || {
            let head = FilmHead::new(o.as_tensor(), kk, (15.0, 30.0), Numerics::PARITY);
            let outs = head.stack(x.as_tensor(), |_, h| Ok(h.clone())).unwrap();
            let y = Tensor::cat(&outs, 1).unwrap();
            let g = (&y * &wts).unwrap().sum_all().unwrap().backward().unwrap();
            [
                y,
                g.get(x.as_tensor()).unwrap().clone(),
                g.get(o.as_tensor()).unwrap().clone(),
            ]
        };
        let bits = |ts: &[Tensor; 3]| -> Vec<Vec<u32>> {
            ts.iter()
                .map(|t| {
                    let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                    v.iter().map(|x| x.to_bits()).collect()
                })
                .collect()
        };
        let cpu = bits(&run());
        let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
        let counted = run();
        let report = account.finish();
        assert_eq!(cpu, bits(&counted));
        let op = |name: &str| report.ops.get(name).copied().unwrap_or_default();
        let nf = (n * f * 4) as u64;
        let fwd = op("pma-film-sine");
        assert_eq!((fwd.ops, fwd.launches), (kk as u64, kk as u64));
        // Pre and the layer's Θ, Φ blocks in; the sine out (the backward recomputes the
        // cosine, as on CUDA).
        assert_eq!(fwd.bytes_read, kk as u64 * 3 * nf);
        assert_eq!(fwd.bytes_written, kk as u64 * nf);
        let bwd = op("pma-film-sine-grad");
        assert_eq!((bwd.ops, bwd.launches), (kk as u64, kk as u64 + 1));
        assert_eq!(bwd.bytes_read, kk as u64 * 4 * nf);
        let head = (n * 2 * kk * f * 4) as u64;
        assert_eq!(bwd.bytes_written, kk as u64 * 3 * nf + head);
        assert_eq!(op("pma-film-head-grad").launches, 0);
        for plain in ["sin", "cos", "affine"] {
            assert_eq!(
                op(plain).ops,
                0,
                "plain op `{plain}` in {:?}",
                report.ops.keys()
            );
        }
        assert_eq!(report.total.uploads, 0);
        // The head gradient was alive with the activations.
        assert!(report.peak_live_bytes >= head);
    }

    #[test]
    fn window_pool_propagates_nan_and_falls_back_for_f64() {
        let q = rand(&[3, 4, 5], 7);
        let g = rand(&[1, 4, 5], 8);
        let mut wv = vec![0.5f32; 12];
        wv[5] = f32::NAN;
        let w = Tensor::from_vec(wv, (3, 4), &Device::Cpu).unwrap();
        let m = window_pool(&q, &g, &w, Numerics::PARITY)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        assert!(m[1].iter().all(|v| v.is_nan()), "row 1 has a NaN window");
        assert!(m[0].iter().chain(&m[2]).all(|v| v.is_finite()));
        let m64 = window_pool(
            &q.to_dtype(DType::F64).unwrap(),
            &g.to_dtype(DType::F64).unwrap(),
            &w.to_dtype(DType::F64).unwrap(),
            Numerics::PARITY,
        )
        .unwrap();
        assert_eq!(m64.dtype(), DType::F64);
    }
}
