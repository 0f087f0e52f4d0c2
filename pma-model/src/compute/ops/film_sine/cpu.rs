//! A FiLM-sine layer on the CPU: the same f32 operations as candle's ops, in their order.

use candle_core::{CpuStorage, Layout, Tensor};

use crate::compute::kernel::storage::{f32_slice, with_f32, Kept};

/// Layer `k` of `n_layers`: γ = mul·Θ + add; the sine libm's or the vectorised one (`fast`,
/// fixed when the graph is built, so the backward matches its forward).
#[derive(Debug, Clone, Copy)]
pub(super) struct Layer {
    pub k: usize,
    pub n_layers: usize,
    pub mul: f32,
    pub add: f32,
    pub fast: bool,
}

impl Layer {
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
        for (i, prow) in pre.chunks_exact(f.max(1)).enumerate() {
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
}

/// The layer's sine of pre [N,F] with o [N,2KF]; cos too, into `cos`, when it is wanted.
pub(super) fn forward(
    layer: &Layer,
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
    f: usize,
    cos: &Kept<Vec<f32>>,
) -> candle_core::Result<CpuStorage> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let (pre, o) = (
        f32_slice(s1, l1, "film sine: pre")?,
        f32_slice(s2, l2, "film sine: o")?,
    );
    let a = layer.argument(pre, o, f);
    let sin = if cos.wanted() {
        let (sin, c) = crate::compute::fast_sine::trig_pair(&a, layer.fast);
        cos.put(c);
        sin
    } else {
        crate::compute::fast_sine::trig(&a, 0, layer.fast)
    };
    Ok(CpuStorage::F32(sin))
}

/// The gradient of pre [N,F] and the head gradient [N,2KF] with this layer's blocks written
/// (into `head`, the stack's shared one, when given); cos from the forward when it kept it.
pub(super) fn backward(
    layer: &Layer,
    grad: &Tensor,
    pre: &Tensor,
    o: &Tensor,
    cos: Option<Vec<f32>>,
    head: Option<Vec<f32>>,
) -> candle_core::Result<(Tensor, Vec<f32>)> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let (n, f) = pre.dims2()?;
    let w = 2 * layer.n_layers * f;
    let mut g_o = head.unwrap_or_else(|| vec![0f32; n * w]);
    if g_o.len() != n * w {
        candle_core::bail!("film sine: shared head gradient has the wrong size")
    }
    let g_pre = with_f32([pre, o, grad], "film sine", |[p, oo, d]| {
        let cos = match cos {
            Some(c) if c.len() == n * f => c,
            _ => crate::compute::fast_sine::trig(&layer.argument(p, oo, f), 1, layer.fast),
        };
        layer.grad_rows(p, oo, d, &cos, &mut g_o, f)
    })?;
    Ok((Tensor::from_vec(g_pre, (n, f), pre.device())?, g_o))
}
