//! The flat Adam update on a device: `adam.cu`'s one kernel, launched on a GPU or on the
//! emulated grid.

use std::sync::Mutex;

use candle_core::{DType, Layout, Shape, Tensor};

use super::{flat_params, Update, MODULE};
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::op::{Kernel, Op};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;
use crate::error::Result;

/// The update as one launch: new (parameters, first moments, second moments).
pub(super) fn update(u: &Update) -> Result<(Tensor, Tensor, Tensor)> {
    let dev = u.g.device();
    let has: Vec<u8> = u.has.iter().map(|&h| h as u8).collect();
    let ok = match u.apply {
        Some(a) => a.to_dtype(DType::U8)?.reshape(1)?,
        None => Tensor::new(&[1u8], dev)?,
    };
    let mut others = vec![
        flat_params(u)?,
        u.m.clone(),
        u.v.clone(),
        u.slot_of.clone(),
        u.step_size.to_dtype(DType::F32)?,
        u.bias2_sqrt.recip()?.to_dtype(DType::F32)?,
        Tensor::from_vec(has, u.has.len(), dev)?,
        ok,
    ];
    others.extend(
        u.coef
            .map(|c| c.to_dtype(DType::F32)?.reshape(1))
            .transpose()?,
    );
    let op = Op(AdamOp {
        others,
        scalars: [
            (1.0 - u.b1) as f32,
            u.b2 as f32,
            (1.0 - u.b2) as f32,
            u.eps as f32,
        ],
        moments: Mutex::new(None),
    });
    let g = u.g.detach().contiguous()?;
    let p = g.apply_op1_no_bwd(&op)?;
    let (m, v) =
        op.0.moments
            .into_inner()
            .unwrap_or_else(|e| e.into_inner())
            .ok_or_else(|| candle_core::Error::Msg("adam: the kernel did not run".into()))?;
    let wrap = |b| g.apply_op1_no_bwd(&Op(Wrap(Mutex::new(Some(b)))));
    Ok((p, wrap(m)?, wrap(v)?))
}

/// The update as an op on the gradient, the other inputs held (custom ops take at most
/// three); its output is the parameters, the moments are left in `moments`.
struct AdamOp {
    /// p, m, v, slot_of; per slot the step size, 1/sqrt(1 − b2^t) and the has-gradient flag;
    /// the ok flag; the clip factor, if any.
    others: Vec<Tensor>,
    /// 1 − b1, b2, 1 − b2, eps.
    scalars: [f32; 4],
    moments: Mutex<Option<(Buf, Buf)>>,
}

impl Kernel<1> for AdamOp {
    fn name(&self) -> &'static str {
        "pma-adam"
    }

    fn device(
        &self,
        exec: &Exec,
        [g]: [Src; 1],
        [lg]: [&Layout; 1],
    ) -> candle_core::Result<(Buf, Shape)> {
        let n = lg.shape().elem_count();
        candle_core::account::report_launches(1, 0);
        // g, p, m, v, slot_of, per slot the step size, 1/sqrt(1 − b2^t) and the flag, ok,
        // the clip factor; p, m and v written.
        let slots = self.others[4].elem_count() as u64;
        let n64 = n as u64;
        candle_core::account::report_bytes(5 * 4 * n64 + 9 * slots + 5, 3 * 4 * n64);
        let others: Vec<Tensor> = self
            .others
            .iter()
            .map(|t| t.contiguous())
            .collect::<candle_core::Result<_>>()?;
        for (i, t) in others.iter().enumerate().take(4) {
            if t.elem_count() != n {
                candle_core::bail!("adam: flat input {i} does not have {n} elements")
            }
        }
        let guards: Vec<_> = others.iter().map(|t| t.storage_and_layout()).collect();
        let src = |i: usize| Src::of(&guards[i].0, guards[i].1, "adam");
        let clip = others.len() > 8;
        let (mut p, mut m, mut v) = (exec.output(n)?, exec.output(n)?, exec.output(n)?);
        let [omb1, b2, omb2, eps] = self.scalars;
        let mut args = vec![
            Arg::Src(g),
            Arg::Src(src(0)?),
            Arg::Src(src(1)?),
            Arg::Src(src(2)?),
        ];
        args.extend([Arg::Dst(&mut p), Arg::Dst(&mut m), Arg::Dst(&mut v)]);
        for i in 3..8 {
            args.push(Arg::Src(src(i)?));
        }
        // Without a clip factor the kernel never reads `coef`: any f32 buffer will do.
        args.push(Arg::Src(src(if clip { 8 } else { 4 })?));
        args.extend([
            Arg::I32(i32::from(clip)),
            Arg::U32(u32_of(n, "N")?),
            Arg::F32(omb1),
            Arg::F32(b2),
            Arg::F32(omb2),
            Arg::F32(eps),
        ]);
        launch(exec, &MODULE, "pma_adam_f32", n, &mut args)?;
        drop(args);
        *self.moments.lock().unwrap_or_else(|e| e.into_inner()) = Some((m, v));
        Ok((p, lg.shape().clone()))
    }
}

/// Hands a finished buffer to candle as a tensor of the same shape as the op's input (no
/// launch, nothing moved).
struct Wrap(Mutex<Option<Buf>>);

impl Kernel<1> for Wrap {
    fn name(&self) -> &'static str {
        "pma-wrap"
    }

    fn device(
        &self,
        _: &Exec,
        _: [Src; 1],
        [l]: [&Layout; 1],
    ) -> candle_core::Result<(Buf, Shape)> {
        candle_core::account::report_launches(0, 0);
        candle_core::account::report_bytes(0, 0);
        let buf = self.0.lock().unwrap_or_else(|e| e.into_inner()).take();
        let buf = buf.ok_or_else(|| candle_core::Error::Msg("adam: buffer used twice".into()))?;
        Ok((buf, l.shape().clone()))
    }
}
