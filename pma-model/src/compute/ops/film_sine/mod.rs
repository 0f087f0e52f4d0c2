//! The modulator's FiLM-sine layers `sin(pre ⊙ (m·Θ_k + c) + Φ_k)`, reading Θ and Φ out of
//! the pose extractor's head, one op per layer.
//!
//! In candle's ops a layer is four ops forward (a strided affine, a product, a strided add,
//! the sine) and, backward, about a dozen passes over [N,f] plus two zero-padded [N,2Kf]
//! gradients for the narrowed blocks, which candle then adds. Here a layer is one pass each
//! way, computed with the same f32 operations in the same order (sine and cosine from
//! libm, or from [`crate::compute::fast_sine`] when that is on), so values and gradients
//! are candle's bits. On the CPU the forward keeps cos of the argument when the graph
//! tracks gradients (the sine kernel computes it anyway), so the backward evaluates no
//! trigonometry; a device recomputes it (`film_sine.cu`: no [N,f] tensor alive from
//! forward to backward).
//!
//! Through [`FilmHead::stack`] the layers also share one head gradient: layers 1..K write
//! their columns into it and layer 0, whose backward necessarily runs last (every later
//! layer's input depends on its output), hands it to candle. The sum candle formed of K
//! zero-padded gradients had the same bits: every entry the kernel writes already carries
//! the `+ 0` of the plain graph's accumulation.

mod check;
mod cpu;
mod device;

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, Layout, Shape, Tensor};

use crate::compute::kernel::mem::{Buf, Src};
use crate::compute::kernel::op::{CpuForward, Kernel, Op};
use crate::compute::kernel::storage::Kept;
use crate::compute::kernel::{self, Exec};
use crate::compute::numerics::Numerics;
use crate::error::Result;

crate::kernel_module!("film_sine", "film_sine.cu", pma_emu_film_sine, check::check);

/// The pose extractor's head `o` = [Θ_0..Θ_{K-1}, Φ_0..Φ_{K-1}] (each block `f` wide), as
/// read by the K FiLM-SIREN layers of one forward pass (see the module docs).
pub struct FilmHead {
    o: Tensor,
    n_layers: usize,
    mul: f64,
    add: f64,
    fast: bool,
    /// Whether the network asks for pma's kernels ([`Numerics::fused`]).
    fused: bool,
    grad: Arc<Mutex<HeadGrad>>,
}

/// The head gradient the layers of one [`FilmHead::stack`] fill in.
#[derive(Default)]
struct HeadGrad {
    /// The buffer of the CPU route's backward.
    buf: Option<Vec<f32>>,
    /// The buffer of a device backward, its bytes held live in an accounted run.
    dev: Option<(Buf, candle_core::account::Held)>,
    /// Layer 0 has handed the buffer over: a later backward pass over the same graph makes
    /// every layer return its own gradient.
    taken: bool,
}

impl FilmHead {
    /// `o`: [N,2·K·f] for K = `n_layers`; γ = `mul`·Θ + `add`.
    pub fn new(o: &Tensor, n_layers: usize, (mul, add): (f64, f64), k: Numerics) -> Self {
        Self::with(o, n_layers, (mul, add), k.fast_sine, k.fused)
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

    /// candle's ops for layer `k`.
    fn generic(&self, pre: &Tensor, k: usize) -> Result<Tensor> {
        let f = pre.dim(candle_core::D::Minus1)?;
        let theta = self.o.narrow(1, k * f, f)?;
        let phi = self.o.narrow(1, (self.n_layers + k) * f, f)?;
        let arg = (pre * theta.affine(self.mul, self.add)?)?.add(&phi)?;
        crate::compute::fast_sine::sin(&arg, self.fast)
    }

    fn apply(&self, pre: &Tensor, k: usize, chained: bool) -> Result<Tensor> {
        let (o, n_layers) = (&self.o, self.n_layers);
        let f = pre.dim(candle_core::D::Minus1)?;
        let fits = pre.rank() == 2
            && o.rank() == 2
            && k < n_layers
            && o.dim(1)? == 2 * n_layers * f
            && o.dim(0)? == pre.dim(0)?;
        let Some(exec) = kernel::fused_route(self.fused && fits, &MODULE, &[pre, o]) else {
            return self.generic(pre, k);
        };
        kernel::or_generic(
            &MODULE,
            || {
                let (pre, o) = (pre.contiguous()?, o.contiguous()?);
                // The CPU keeps the cosine: libm's is the costly part of its backward.
                let keep_cos = exec.is_none() && (pre.track_op() || o.track_op());
                let op = FilmSine {
                    layer: cpu::Layer {
                        k,
                        n_layers,
                        mul: self.mul as f32,
                        add: self.add as f32,
                        fast: self.fast,
                    },
                    exec: exec.clone(),
                    cos: Kept::new(keep_cos),
                    shared: chained.then(|| self.grad.clone()),
                };
                Ok(pre.apply_op2(&o, Op(op))?)
            },
            || self.generic(pre, k),
        )
    }
}

struct FilmSine {
    layer: cpu::Layer,
    /// The device kernels' executor, or `None` on the CPU's route.
    exec: Option<Exec>,
    /// cos of the argument, kept by the CPU route's forward for its backward.
    cos: Kept<Vec<f32>>,
    /// The head gradient shared along a [`FilmHead::stack`].
    shared: Option<Arc<Mutex<HeadGrad>>>,
}

impl FilmSine {
    /// Bytes `film_sine.cu`'s forward reads (pre, and the Θ_k, Φ_k blocks of o) and writes
    /// (the sine, and the cosine when it is kept).
    fn report_fwd(n: usize, f: usize, keep_cos: bool) {
        let nf = (n * f * 4) as u64;
        candle_core::account::report_bytes(3 * nf, nf * (1 + u64::from(keep_cos)));
    }

    /// (N, F) of pre [N,F] and o [N,2KF], checked.
    fn check(&self, l1: &Layout, l2: &Layout) -> candle_core::Result<(usize, usize)> {
        let (n, f) = l1.shape().dims2()?;
        let (n2, w) = l2.shape().dims2()?;
        if n2 != n || w != 2 * self.layer.n_layers * f {
            candle_core::bail!(
                "film sine: o {:?} does not hold 2·{}·{f} columns for pre {:?}",
                l2.shape(),
                self.layer.n_layers,
                l1.shape()
            )
        }
        Ok((n, f))
    }
}

impl Kernel<2> for FilmSine {
    fn name(&self) -> &'static str {
        "pma-film-sine"
    }

    fn device(
        &self,
        exec: &Exec,
        [pre, o]: [Src; 2],
        l: [&Layout; 2],
    ) -> candle_core::Result<(Buf, Shape)> {
        let (n, f) = self.check(l[0], l[1])?;
        candle_core::account::report_launches(1, 0);
        Self::report_fwd(n, f, false);
        Ok((
            device::forward(exec, pre, o, self.layer.dims(n, f))?,
            l[0].shape().clone(),
        ))
    }

    fn cpu(&self, s: [&CpuStorage; 2], l: [&Layout; 2]) -> Option<CpuForward> {
        self.exec.is_none().then(|| {
            let (n, f) = self.check(l[0], l[1])?;
            Self::report_fwd(n, f, self.cos.wanted());
            Ok((
                cpu::forward(&self.layer, s[0], l[0], s[1], l[1], f, &self.cos)?,
                l[0].shape().clone(),
            ))
        })
    }

    fn backward(
        &self,
        [pre, o]: [&Tensor; 2],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 2]> {
        let (pre, o, grad) = (pre.contiguous()?, o.contiguous()?, grad.contiguous()?);
        // Layers after the first write into the stack's shared head gradient and return
        // none of their own; layer 0 (run last) returns it (see [`FilmHead`]).
        let mut shared = self
            .shared
            .as_ref()
            .map(|s| s.lock().unwrap_or_else(|e| e.into_inner()));
        let defer = shared.as_ref().is_some_and(|s| !s.taken);
        match &self.exec {
            Some(_) => {
                let head = match shared.as_mut() {
                    Some(s) if defer => s.dev.take(),
                    _ => None,
                };
                let (g_pre, head) = device::backward(&self.layer, &grad, &pre, &o, head)?;
                if let Some(s) = shared.as_mut().filter(|_| defer) {
                    if self.layer.k > 0 {
                        s.dev = Some(head);
                        return Ok([Some(g_pre), None]);
                    }
                    s.taken = true;
                }
                Ok([
                    Some(g_pre),
                    Some(device::hand_over(&grad, head, o.shape())?),
                ])
            }
            None => {
                let head = match shared.as_mut() {
                    Some(s) if defer => s.buf.take(),
                    _ => None,
                };
                let (g_pre, g_o) =
                    cpu::backward(&self.layer, &grad, &pre, &o, self.cos.take(), head)?;
                if let Some(s) = shared.as_mut().filter(|_| defer) {
                    if self.layer.k > 0 {
                        s.buf = Some(g_o);
                        return Ok([Some(g_pre), None]);
                    }
                    s.taken = true;
                }
                Ok([
                    Some(g_pre),
                    Some(Tensor::from_vec(g_o, o.shape(), o.device())?),
                ])
            }
        }
    }
}

#[cfg(test)]
mod tests;
