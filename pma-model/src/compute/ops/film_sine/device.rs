//! The FiLM-sine layer on a device: `film_sine.cu`'s kernels, launched on a GPU or on the
//! emulated grid.

use std::sync::Mutex;

use candle_core::{Layout, Shape, Tensor};

use super::cpu::Layer;
use super::MODULE;
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::op::{Kernel, Op};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;

/// N rows, F features, layer k of K, and γ's mul and add: the kernels' scalar arguments.
#[derive(Debug, Clone, Copy)]
pub(super) struct Dims {
    n: usize,
    f: usize,
    layer: Layer,
}

impl Layer {
    pub(super) fn dims(&self, n: usize, f: usize) -> Dims {
        Dims { n, f, layer: *self }
    }
}

impl Dims {
    fn args(&self) -> candle_core::Result<[Arg<'static>; 6]> {
        Ok([
            Arg::U32(u32_of(self.n, "N")?),
            Arg::U32(u32_of(self.f, "F")?),
            Arg::U32(u32_of(self.layer.k, "layer")?),
            Arg::U32(u32_of(self.layer.n_layers, "layers")?),
            Arg::F32(self.layer.mul),
            Arg::F32(self.layer.add),
        ])
    }
}

/// sin of the layer's argument, [N,F] (the cosine is not kept: the backward recomputes it).
/// One launch.
pub(super) fn forward(exec: &Exec, pre: Src, o: Src, d: Dims) -> candle_core::Result<Buf> {
    let len = d.n * d.f;
    let mut out = exec.output(len)?;
    let mut unused = exec.output(1)?;
    let mut args = vec![
        Arg::Src(pre),
        Arg::Src(o),
        Arg::Dst(&mut out),
        Arg::Dst(&mut unused),
    ];
    args.extend(d.args()?);
    args.push(Arg::I32(0));
    launch(exec, &MODULE, "pma_film_sine_f32", len, &mut args)?;
    drop(args);
    Ok(out)
}

/// The layer's backward: the gradient of pre (a tensor), and the head gradient with this
/// layer's blocks written: `head`, or (the layer starts it) a zeroed [N,2KF] buffer whose
/// bytes are held live in an accounted run.
pub(super) fn backward(
    layer: &Layer,
    grad: &Tensor,
    pre: &Tensor,
    o: &Tensor,
    head: Option<(Buf, candle_core::account::Held)>,
) -> candle_core::Result<(Tensor, (Buf, candle_core::account::Held))> {
    let op = Op(FilmGrad {
        layer: *layer,
        head: Mutex::new(head),
    });
    let g_pre = grad.apply_op3_no_bwd(pre, o, &op)?;
    let head = op.0.head.into_inner().unwrap_or_else(|e| e.into_inner());
    let head = head.ok_or_else(|| candle_core::Error::Msg("film sine: no head gradient".into()))?;
    Ok((g_pre, head))
}

/// A finished head gradient as a tensor of `like`'s device, counted as the hand-over (no
/// launch, nothing moved).
pub(super) fn hand_over(
    like: &Tensor,
    head: (Buf, candle_core::account::Held),
    shape: &Shape,
) -> candle_core::Result<Tensor> {
    like.apply_op1_no_bwd(&Op(HeadOut {
        buf: Mutex::new(Some(head)),
        shape: shape.clone(),
    }))
}

/// A layer's backward on (grad, pre, o): `film_sine.cu`'s gradient kernel, writing the
/// gradient of pre and the layer's blocks of `head` (zeroed first when `None`).
struct FilmGrad {
    layer: Layer,
    head: Mutex<Option<(Buf, candle_core::account::Held)>>,
}

impl Kernel<3> for FilmGrad {
    fn name(&self) -> &'static str {
        "pma-film-sine-grad"
    }

    fn device(
        &self,
        exec: &Exec,
        [grad, pre, o]: [Src; 3],
        l: [&Layout; 3],
    ) -> candle_core::Result<(Buf, Shape)> {
        let (n, f) = l[1].shape().dims2()?;
        let w = 2 * self.layer.n_layers * f;
        if l[0].shape().dims2()? != (n, f) || l[2].shape().dims2()? != (n, w) {
            candle_core::bail!("film sine gradient: shapes do not agree with [{n}, {f}]")
        }
        let mut head = self.head.lock().unwrap_or_else(|e| e.into_inner());
        let starts = head.is_none();
        // Reads the upstream gradient, pre, Θ_k and Φ_k (to recompute the cosine); writes
        // pre's gradient, the layer's two blocks, and the head's memset when it starts it.
        let nf = (n * f * 4) as u64;
        let memset = if starts { (n * w * 4) as u64 } else { 0 };
        candle_core::account::report_launches(if starts { 2 } else { 1 }, 0);
        candle_core::account::report_bytes(4 * nf, 3 * nf + memset);
        if starts {
            let buf = exec.zeros(n * w)?;
            let held = candle_core::account::hold(exec.is_host(), buf.bytes());
            *head = Some((buf, held));
        }
        let (g_o, _) = head.as_mut().expect("made above");
        let mut g_pre = exec.output(n * f)?;
        let unused = exec.output(1)?;
        // No kept cosine (have_cos 0): its pointer is never read.
        let mut args = vec![
            Arg::Src(grad),
            Arg::Src(pre),
            Arg::Src(o),
            Arg::Src(unused.src()),
            Arg::Dst(&mut g_pre),
            Arg::Dst(g_o),
        ];
        args.extend(self.layer.dims(n, f).args()?);
        args.push(Arg::I32(0));
        launch(exec, &MODULE, "pma_film_sine_grad_f32", n * f, &mut args)?;
        drop(args);
        drop(unused);
        Ok((g_pre, Shape::from((n, f))))
    }
}

/// Hands a finished head gradient to candle as a tensor (no launch, nothing moved).
struct HeadOut {
    buf: Mutex<Option<(Buf, candle_core::account::Held)>>,
    shape: Shape,
}

impl Kernel<1> for HeadOut {
    fn name(&self) -> &'static str {
        "pma-film-head-grad"
    }

    /// The buffer; its held bytes end here (the storage made of it counts from now on).
    fn device(&self, _: &Exec, _: [Src; 1], _: [&Layout; 1]) -> candle_core::Result<(Buf, Shape)> {
        candle_core::account::report_launches(0, 0);
        candle_core::account::report_bytes(0, 0);
        let buf = self.buf.lock().unwrap_or_else(|e| e.into_inner()).take();
        let (buf, _) = buf
            .ok_or_else(|| candle_core::Error::Msg("film sine: head gradient used twice".into()))?;
        Ok((buf, self.shape.clone()))
    }
}
