// One Adam update over every parameter at once (pma-model/src/compute/ops/adam,
// called by `Adam::step_masked`), for f32 on CUDA: the flat gradient scaled by the global-norm clip
// factor, the moments and the parameters, each parameter (slot) with its own step size and
// bias correction, and the step applied only where its slot has a gradient and the
// device-side flag `ok` (a finite loss and norm) is set; elsewhere the old values are kept.
// Compiled at run time with NVRTC (no includes), checked with nvcc by
// scripts/check-cuda-kernels.sh, and compiled for the host's emulated grid (emu.c).
//
// One thread per element, grid-stride, no shared memory, no atomics. Every operation is
// the one the tensor-op update performs, rounded separately in the same order (candle's
// `x * c` by a scalar is its affine `x * c + 0`, kept here for its sign of zero), so the
// result is the CPU update's bits. The gradient norm (a reduction) is not part of it: the
// caller passes the clip factor as a device scalar.

// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

PMA_KERNEL void pma_adam_f32(
    const float *g, const float *p_old, const float *m_old, const float *v_old,
    float *p, float *m, float *v,
    const unsigned int *slot_of, const float *step_size, const float *inv_bias2,
    const unsigned char *has, const unsigned char *ok, const float *coef, int clip,
    unsigned int n, float one_minus_b1, float b2, float one_minus_b2, float eps)
{
    PMA_FOR_EACH(i, n) {
        const unsigned int s = slot_of[i];
        const float gi = clip ? __fmul_rn(g[i], coef[0]) : g[i];
        const float mo = m_old[i];
        const float vo = v_old[i];
        // m + (g - m)(1 - b1)
        const float mn = __fadd_rn(mo, __fadd_rn(__fmul_rn(__fsub_rn(gi, mo), one_minus_b1), 0.0f));
        // v b2 + g² (1 - b2)
        const float vn = __fadd_rn(__fadd_rn(__fmul_rn(vo, b2), 0.0f),
                                   __fadd_rn(__fmul_rn(__fmul_rn(gi, gi), one_minus_b2), 0.0f));
        // sqrt(v) / sqrt(1 - b2^t) + eps, then m lr / (1 - b1^t) over it
        const float denom = __fadd_rn(__fmul_rn(__fsqrt_rn(vn), inv_bias2[s]), eps);
        const float update = __fdiv_rn(__fmul_rn(mn, step_size[s]), denom);
        const float pn = __fsub_rn(p_old[i], update);
        const bool apply = has[s] != 0 && ok[0] != 0;
        p[i] = apply ? pn : p_old[i];
        m[i] = apply ? mn : mo;
        v[i] = apply ? vn : vo;
    }
}
