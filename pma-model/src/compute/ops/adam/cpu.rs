//! The flat Adam update on the CPU in one pass over the elements: the tensor ops' f32
//! operations in their order, so their bits. The tensor ops take some twenty passes and a
//! tensor per intermediate, which on a small model cost more than the update's arithmetic,
//! on the step's serial path.

use candle_core::{DType, Tensor};

use super::Update;
use crate::error::Result;

pub(super) fn update(u: &Update) -> Result<(Tensor, Tensor, Tensor)> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let omb1 = (1.0 - u.b1) as f32;
    let b2 = u.b2 as f32;
    let omb2 = (1.0 - u.b2) as f32;
    let eps = u.eps as f32;
    let scalar_f32 = |t: &Tensor| -> candle_core::Result<f32> {
        Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?[0])
    };
    let coef = u.coef.map(scalar_f32).transpose()?;
    let ok = match u.apply {
        Some(a) => a.to_dtype(DType::U8)?.flatten_all()?.to_vec1::<u8>()?[0] != 0,
        None => true,
    };
    let step_size = u.step_size.to_dtype(DType::F32)?.to_vec1::<f32>()?;
    let inv_bias2 = u
        .bias2_sqrt
        .recip()?
        .to_dtype(DType::F32)?
        .to_vec1::<f32>()?;
    let g = u.g.detach().to_vec1::<f32>()?;
    let m_old = u.m.to_vec1::<f32>()?;
    let v_old = u.v.to_vec1::<f32>()?;
    let n = g.len();
    let (mut p, mut m, mut v) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    let mut offset = 0;
    for (i, param) in u.params.iter().enumerate() {
        let p_old = param.flatten_all()?.to_vec1::<f32>()?;
        let span = offset..offset + p_old.len();
        offset = span.end;
        if !(ok && u.has[i]) {
            p.extend_from_slice(&p_old);
            m.extend_from_slice(&m_old[span.clone()]);
            v.extend_from_slice(&v_old[span]);
            continue;
        }
        let (ss, ib) = (step_size[i], inv_bias2[i]);
        for (((&po, &gi), &mo), &vo) in p_old
            .iter()
            .zip(&g[span.clone()])
            .zip(&m_old[span.clone()])
            .zip(&v_old[span])
        {
            let gi = match coef {
                Some(c) => gi * c,
                None => gi,
            };
            let mi = mo + ((gi - mo) * omb1 + 0.0);
            let vi = (vo * b2 + 0.0) + ((gi * gi) * omb2 + 0.0);
            let denom = (vi.sqrt() * ib) * 1.0 + eps;
            p.push(po - (mi * ss) / denom);
            m.push(mi);
            v.push(vi);
        }
    }
    let dev = u.g.device();
    Ok((
        Tensor::from_vec(p, n, dev)?,
        Tensor::from_vec(m, n, dev)?,
        Tensor::from_vec(v, n, dev)?,
    ))
}
