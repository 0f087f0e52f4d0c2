//! pma-model's CUDA kernels (`pma-model/src/compute/cuda/kernels/*.cu`) compiled for the
//! host and run over an emulated grid: every (block, thread) pair of a [`Grid`] runs the
//! kernel body once, in sequence. The kernels are grid-stride loops without shared memory,
//! barriers or atomics, so the result is what any launch of that grid computes on a GPU,
//! up to the device's own library functions: `sinf`/`cosf` here are the C library's, on a
//! GPU CUDA's (within 2 ulp).
//!
//! A test-only crate: the tests in `tests/` run each kernel against pma-model's CPU op on
//! random shapes. pma itself launches the same sources through NVRTC (`cuda` feature).

use std::os::raw::{c_int, c_uint};

/// A launch shape: `blocks` blocks of `threads` threads (x only).
#[derive(Debug, Clone, Copy)]
pub struct Grid {
    pub blocks: u32,
    pub threads: u32,
}

impl Grid {
    /// The launch pma uses for `elements` outputs: `threads` per block, enough blocks
    /// for one element per thread up to `max_blocks` (the grid-stride loop does the rest).
    pub fn covering(elements: usize, threads: u32, max_blocks: u32) -> Self {
        let blocks = elements
            .div_ceil(threads as usize)
            .clamp(1, max_blocks as usize) as u32;
        Self { blocks, threads }
    }
}

extern "C" {
    fn pma_emu_sine_linear_f32(
        x: *const f32,
        wb: *const f32,
        sc: *const f32,
        y: *mut f32,
        rows: c_uint,
        inp: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_sine_linear_grad_part_f32(
        grad: *const f32,
        x: *const f32,
        wb: *const f32,
        sc: *const f32,
        part: *mut f32,
        rows: c_uint,
        inp: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_sine_linear_grad_rows_f32(
        grad: *const f32,
        x: *const f32,
        wb: *const f32,
        sc: *const f32,
        g_rows: *mut f32,
        rows: c_uint,
        inp: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_sine_linear_grad_sum_f32(
        part: *const f32,
        g: *mut f32,
        n_blocks: c_uint,
        inp: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_bias_relu_f32(
        z: *const f32,
        b: *const f32,
        y: *mut f32,
        rows: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_bias_sine_f32(
        z: *const f32,
        b: *const f32,
        y: *mut f32,
        rows: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_act_grad_f32(
        grad: *const f32,
        kept: *const f32,
        b: *const f32,
        gz: *mut f32,
        part: *mut f32,
        rows: c_uint,
        outs: c_uint,
        sine: c_int,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_bias_grad_sum_f32(
        part: *const f32,
        gb: *mut f32,
        n_blocks: c_uint,
        outs: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_bias_act_rows() -> c_uint;
    fn pma_emu_sine_linear_rows() -> c_uint;
    fn pma_emu_adam_f32(
        g: *const f32,
        p_old: *const f32,
        m_old: *const f32,
        v_old: *const f32,
        p: *mut f32,
        m: *mut f32,
        v: *mut f32,
        slot_of: *const c_uint,
        step_size: *const f32,
        inv_bias2: *const f32,
        has: *const u8,
        ok: *const u8,
        coef: *const f32,
        clip: c_int,
        n: c_uint,
        one_minus_b1: f32,
        b2: f32,
        one_minus_b2: f32,
        eps: f32,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_film_sine_f32(
        pre: *const f32,
        o: *const f32,
        out: *mut f32,
        cos_out: *mut f32,
        n: c_uint,
        f: c_uint,
        k: c_uint,
        n_layers: c_uint,
        mul: f32,
        add: f32,
        keep_cos: c_int,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_film_sine_grad_f32(
        grad: *const f32,
        pre: *const f32,
        o: *const f32,
        cos_in: *const f32,
        g_pre: *mut f32,
        g_o: *mut f32,
        n: c_uint,
        f: c_uint,
        k: c_uint,
        n_layers: c_uint,
        mul: f32,
        add: f32,
        have_cos: c_int,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_window_pool_f32(
        q: *const f32,
        g: *const f32,
        w: *const f32,
        out: *mut f32,
        arg: *mut c_uint,
        n: c_uint,
        j: c_uint,
        h: c_uint,
        per_pose: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_window_pool_grad_q_f32(
        grad: *const f32,
        w: *const f32,
        arg: *const c_uint,
        grad_q: *mut f32,
        n: c_uint,
        j: c_uint,
        h: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
    fn pma_emu_window_pool_grad_g_f32(
        grad: *const f32,
        w: *const f32,
        arg: *const c_uint,
        grad_g: *mut f32,
        p: c_uint,
        j: c_uint,
        h: c_uint,
        per_pose: c_uint,
        blocks: c_uint,
        threads: c_uint,
    );
}

/// Sizes of one window pool: N points in P poses of `n / p` points, J joints, H features.
#[derive(Debug, Clone, Copy)]
pub struct PoolDims {
    pub n: usize,
    pub p: usize,
    pub j: usize,
    pub h: usize,
}

impl PoolDims {
    fn check(&self) -> [c_uint; 5] {
        let Self { n, p, j, h } = *self;
        assert!(
            p > 0 && j > 0 && n % p == 0,
            "window pool: bad dims {self:?}"
        );
        [n, p, j, h, n / p].map(|v| c_uint::try_from(v).expect("dims fit the kernel's u32"))
    }
}

/// `window_pool.cu`'s forward: (max [N,H], arg-max joint [N,H]).
pub fn window_pool(
    q: &[f32],
    g: &[f32],
    w: &[f32],
    d: PoolDims,
    grid: Grid,
) -> (Vec<f32>, Vec<u32>) {
    let [n, p, j, h, per_pose] = d.check();
    assert_eq!(q.len(), d.n * d.j * d.h, "q");
    assert_eq!(g.len(), d.p * d.j * d.h, "g");
    assert_eq!(w.len(), d.n * d.j, "w");
    let _ = p;
    let mut out = vec![f32::NAN; d.n * d.h];
    let mut arg = vec![u32::MAX; d.n * d.h];
    // SAFETY: every buffer has the length the kernel indexes for these dims (checked above).
    unsafe {
        pma_emu_window_pool_f32(
            q.as_ptr(),
            g.as_ptr(),
            w.as_ptr(),
            out.as_mut_ptr(),
            arg.as_mut_ptr(),
            n,
            j,
            h,
            per_pose,
            grid.blocks,
            grid.threads,
        )
    };
    (out, arg)
}

/// `window_pool.cu`'s backward: (grad q [N,J,H], grad g [P,J,H]) from the upstream
/// gradient [N,H] and the forward's arg-max.
pub fn window_pool_grad(
    grad: &[f32],
    w: &[f32],
    arg: &[u32],
    d: PoolDims,
    grid_q: Grid,
    grid_g: Grid,
) -> (Vec<f32>, Vec<f32>) {
    let [n, p, j, h, per_pose] = d.check();
    assert_eq!(grad.len(), d.n * d.h, "grad");
    assert_eq!(arg.len(), d.n * d.h, "arg");
    assert_eq!(w.len(), d.n * d.j, "w");
    // Poisoned, so that an element no thread writes shows.
    let mut gq = vec![f32::NAN; d.n * d.j * d.h];
    let mut gg = vec![f32::NAN; d.p * d.j * d.h];
    // SAFETY: every buffer has the length the kernels index for these dims (checked above).
    unsafe {
        pma_emu_window_pool_grad_q_f32(
            grad.as_ptr(),
            w.as_ptr(),
            arg.as_ptr(),
            gq.as_mut_ptr(),
            n,
            j,
            h,
            grid_q.blocks,
            grid_q.threads,
        );
        pma_emu_window_pool_grad_g_f32(
            grad.as_ptr(),
            w.as_ptr(),
            arg.as_ptr(),
            gg.as_mut_ptr(),
            p,
            j,
            h,
            per_pose,
            grid_g.blocks,
            grid_g.threads,
        );
    }
    (gq, gg)
}

/// One FiLM-sine layer: N rows of F features, layer `k` of `n_layers`, γ = `mul`·Θ + `add`.
#[derive(Debug, Clone, Copy)]
pub struct FilmDims {
    pub n: usize,
    pub f: usize,
    pub k: usize,
    pub n_layers: usize,
    pub mul: f32,
    pub add: f32,
}

impl FilmDims {
    fn check(&self, pre: usize, o: usize) -> [c_uint; 4] {
        let Self {
            n, f, k, n_layers, ..
        } = *self;
        assert!(k < n_layers, "film sine: layer {k} of {n_layers}");
        assert_eq!(pre, n * f, "pre");
        assert_eq!(o, n * 2 * n_layers * f, "o");
        [n, f, k, n_layers].map(|v| c_uint::try_from(v).expect("dims fit the kernel's u32"))
    }
}

/// `film_sine.cu`'s forward: (sin of the argument [N,F], its cosine when `keep_cos`).
pub fn film_sine(
    pre: &[f32],
    o: &[f32],
    d: FilmDims,
    keep_cos: bool,
    grid: Grid,
) -> (Vec<f32>, Option<Vec<f32>>) {
    let [n, f, k, layers] = d.check(pre.len(), o.len());
    let mut out = vec![f32::NAN; pre.len()];
    let mut cos = vec![f32::NAN; if keep_cos { pre.len() } else { 1 }];
    // SAFETY: the buffers have the lengths the kernel indexes for these dims (checked).
    unsafe {
        pma_emu_film_sine_f32(
            pre.as_ptr(),
            o.as_ptr(),
            out.as_mut_ptr(),
            cos.as_mut_ptr(),
            n,
            f,
            k,
            layers,
            d.mul,
            d.add,
            c_int::from(keep_cos),
            grid.blocks,
            grid.threads,
        )
    };
    (out, keep_cos.then_some(cos))
}

/// `film_sine.cu`'s backward: g_pre [N,F], and layer k's blocks written into `g_o`
/// [N, 2·K·F] (its other entries left as they are). `cos`: the forward's, or `None` to
/// compute it again.
pub fn film_sine_grad(
    grad: &[f32],
    pre: &[f32],
    o: &[f32],
    cos: Option<&[f32]>,
    g_o: &mut [f32],
    d: FilmDims,
    grid: Grid,
) -> Vec<f32> {
    let [n, f, k, layers] = d.check(pre.len(), o.len());
    assert_eq!(grad.len(), pre.len(), "grad");
    assert_eq!(g_o.len(), o.len(), "g_o");
    if let Some(c) = cos {
        assert_eq!(c.len(), pre.len(), "cos");
    }
    let dummy = [0f32];
    let mut g_pre = vec![f32::NAN; pre.len()];
    // SAFETY: the buffers have the lengths the kernel indexes for these dims (checked);
    // `cos_in` is read only when `have_cos`.
    unsafe {
        pma_emu_film_sine_grad_f32(
            grad.as_ptr(),
            pre.as_ptr(),
            o.as_ptr(),
            cos.unwrap_or(&dummy).as_ptr(),
            g_pre.as_mut_ptr(),
            g_o.as_mut_ptr(),
            n,
            f,
            k,
            layers,
            d.mul,
            d.add,
            c_int::from(cos.is_some()),
            grid.blocks,
            grid.threads,
        )
    };
    g_pre
}

/// What one flat Adam update reads besides the element buffers: per slot (parameter) its
/// step size `lr / (1 − b1^t)` and `1 / sqrt(1 − b2^t)` (f32) and whether it has a
/// gradient; the device flag that the step applies at all; the clip factor if any.
#[derive(Debug, Clone)]
pub struct AdamStep {
    pub slot_of: Vec<u32>,
    pub step_size: Vec<f32>,
    pub inv_bias2: Vec<f32>,
    pub has: Vec<bool>,
    pub ok: bool,
    pub coef: Option<f32>,
    pub betas: [f64; 2],
    pub eps: f64,
}

/// `adam.cu`'s update of the flat gradient `g`: (parameters, first moments, second moments)
/// from the old ones.
pub fn adam(
    g: &[f32],
    p_old: &[f32],
    m_old: &[f32],
    v_old: &[f32],
    s: &AdamStep,
    grid: Grid,
) -> [Vec<f32>; 3] {
    let n = g.len();
    for (what, len) in [("p", p_old.len()), ("m", m_old.len()), ("v", v_old.len())] {
        assert_eq!(len, n, "{what}");
    }
    assert_eq!(s.slot_of.len(), n, "slot_of");
    let slots = s.step_size.len();
    assert!(
        s.inv_bias2.len() == slots && s.has.len() == slots,
        "per-slot lengths"
    );
    assert!(
        s.slot_of.iter().all(|&i| (i as usize) < slots),
        "slot index"
    );
    let has: Vec<u8> = s.has.iter().map(|&h| h as u8).collect();
    let ok = [s.ok as u8];
    let coef = [s.coef.unwrap_or(1.0)];
    let [b1, b2] = s.betas;
    let mut out = [vec![f32::NAN; n], vec![f32::NAN; n], vec![f32::NAN; n]];
    let [p, m, v] = &mut out;
    // SAFETY: every buffer has the length the kernel indexes (checked above).
    unsafe {
        pma_emu_adam_f32(
            g.as_ptr(),
            p_old.as_ptr(),
            m_old.as_ptr(),
            v_old.as_ptr(),
            p.as_mut_ptr(),
            m.as_mut_ptr(),
            v.as_mut_ptr(),
            s.slot_of.as_ptr(),
            s.step_size.as_ptr(),
            s.inv_bias2.as_ptr(),
            has.as_ptr(),
            ok.as_ptr(),
            coef.as_ptr(),
            c_int::from(s.coef.is_some()),
            c_uint::try_from(n).expect("n fits the kernel's u32"),
            (1.0 - b1) as f32,
            b2 as f32,
            (1.0 - b2) as f32,
            s.eps as f32,
            grid.blocks,
            grid.threads,
        )
    };
    out
}

/// Sizes of one narrow-input SIREN layer: `rows` rows of `inp` inputs, `out` outputs.
#[derive(Debug, Clone, Copy)]
pub struct SineLinearDims {
    pub rows: usize,
    pub inp: usize,
    pub out: usize,
}

impl SineLinearDims {
    fn check(&self, x: usize, wb: usize, sc: usize) -> [c_uint; 3] {
        assert!(
            (1..=4).contains(&self.inp),
            "sine linear: bad dims {self:?}"
        );
        assert_eq!(x, self.rows * self.inp, "x");
        assert_eq!(wb, self.out * (self.inp + 1), "[W|b]");
        assert_eq!(sc, self.rows, "s");
        [self.rows, self.inp, self.out]
            .map(|v| c_uint::try_from(v).expect("dims fit the kernel's u32"))
    }
}

/// The kernel's rows per partial sum (`PMA_SINE_LINEAR_ROWS`).
pub fn sine_linear_rows() -> usize {
    // SAFETY: a constant getter without arguments.
    unsafe { pma_emu_sine_linear_rows() as usize }
}

/// `sine_linear.cu`'s forward: s_r sin(x Wᵀ + b) [rows,out], with wb = [W|b] [out,in+1].
pub fn sine_linear(x: &[f32], wb: &[f32], sc: &[f32], d: SineLinearDims, grid: Grid) -> Vec<f32> {
    let [rows, inp, out] = d.check(x.len(), wb.len(), sc.len());
    let mut y = vec![f32::NAN; d.rows * d.out];
    // SAFETY: the buffers have the lengths the kernel indexes for these dims (checked).
    unsafe {
        pma_emu_sine_linear_f32(
            x.as_ptr(),
            wb.as_ptr(),
            sc.as_ptr(),
            y.as_mut_ptr(),
            rows,
            inp,
            out,
            grid.blocks,
            grid.threads,
        )
    };
    y
}

/// `sine_linear.cu`'s backward: ([W|b]'s gradient [out, in+1], from two launches; per row
/// [rows, in+1], x's gradient and s's, from one) for the upstream gradient [rows,out].
pub fn sine_linear_grad(
    grad: &[f32],
    x: &[f32],
    wb: &[f32],
    sc: &[f32],
    d: SineLinearDims,
    [grid_part, grid_sum, grid_rows]: [Grid; 3],
) -> (Vec<f32>, Vec<f32>) {
    let [rows, inp, out] = d.check(x.len(), wb.len(), sc.len());
    assert_eq!(grad.len(), d.rows * d.out, "grad");
    let n_blocks = d.rows.div_ceil(sine_linear_rows());
    let width = d.inp + 1;
    // Poisoned, so that an element no thread writes shows.
    let mut part = vec![f32::NAN; (n_blocks * d.out * width).max(1)];
    let mut g = vec![f32::NAN; d.out * width];
    let mut g_rows = vec![f32::NAN; d.rows * width];
    let nb = c_uint::try_from(n_blocks).expect("blocks fit the kernel's u32");
    // SAFETY: `part` holds [blocks, out, in+1], `g` [out, in+1] and `g_rows` [rows, in+1],
    // as the kernels index them.
    unsafe {
        pma_emu_sine_linear_grad_part_f32(
            grad.as_ptr(),
            x.as_ptr(),
            wb.as_ptr(),
            sc.as_ptr(),
            part.as_mut_ptr(),
            rows,
            inp,
            out,
            grid_part.blocks,
            grid_part.threads,
        );
        pma_emu_sine_linear_grad_sum_f32(
            part.as_ptr(),
            g.as_mut_ptr(),
            nb,
            inp,
            out,
            grid_sum.blocks,
            grid_sum.threads,
        );
        pma_emu_sine_linear_grad_rows_f32(
            grad.as_ptr(),
            x.as_ptr(),
            wb.as_ptr(),
            sc.as_ptr(),
            g_rows.as_mut_ptr(),
            rows,
            inp,
            out,
            grid_rows.blocks,
            grid_rows.threads,
        );
    }
    (g, g_rows)
}

/// The kernel's rows per partial sum of the bias gradient (`PMA_BIAS_ACT_ROWS`).
pub fn bias_act_rows() -> usize {
    // SAFETY: a constant getter without arguments.
    unsafe { pma_emu_bias_act_rows() as usize }
}

/// `bias_act.cu`'s forward: max(z + b, 0), or sin(z + b) when `sine`, [rows, b.len()].
pub fn bias_act(z: &[f32], b: &[f32], sine: bool, grid: Grid) -> Vec<f32> {
    let out = b.len();
    let rows = z.len().checked_div(out).unwrap_or(0);
    assert_eq!(z.len(), rows * out, "z");
    let mut y = vec![f32::NAN; z.len()];
    let c = |v: usize| c_uint::try_from(v).expect("dims fit the kernel's u32");
    let f = if sine {
        pma_emu_bias_sine_f32
    } else {
        pma_emu_bias_relu_f32
    };
    // SAFETY: z and y are [rows, out], b [out].
    unsafe {
        f(
            z.as_ptr(),
            b.as_ptr(),
            y.as_mut_ptr(),
            c(rows),
            c(out),
            grid.blocks,
            grid.threads,
        )
    };
    y
}

/// `bias_act.cu`'s backward, its two launches: (the product's gradient [rows,out], the bias
/// gradient [out]) from the upstream gradient and what the forward kept (the ReLU's output,
/// or the sine's product z).
pub fn act_grad(
    grad: &[f32],
    kept: &[f32],
    b: &[f32],
    sine: bool,
    grid_rows: Grid,
    grid_sum: Grid,
) -> (Vec<f32>, Vec<f32>) {
    let out = b.len();
    let rows = kept.len().checked_div(out).unwrap_or(0);
    assert_eq!(grad.len(), kept.len(), "grad");
    let n_blocks = rows.div_ceil(bias_act_rows());
    let mut gz = vec![f32::NAN; kept.len()];
    let mut part = vec![f32::NAN; (n_blocks * out).max(1)];
    let mut gb = vec![f32::NAN; out];
    let c = |v: usize| c_uint::try_from(v).expect("dims fit the kernel's u32");
    // SAFETY: grad, kept and gz are [rows, out], b [out], part [blocks, out], gb [out].
    unsafe {
        pma_emu_act_grad_f32(
            grad.as_ptr(),
            kept.as_ptr(),
            b.as_ptr(),
            gz.as_mut_ptr(),
            part.as_mut_ptr(),
            c(rows),
            c(out),
            c_int::from(sine),
            grid_rows.blocks,
            grid_rows.threads,
        );
        pma_emu_bias_grad_sum_f32(
            part.as_ptr(),
            gb.as_mut_ptr(),
            c(n_blocks),
            c(out),
            grid_sum.blocks,
            grid_sum.threads,
        );
    }
    (gz, gb)
}
