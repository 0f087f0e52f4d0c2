// One FiLM-sine layer of the modulated stack and its gradient (pma-model/src/compute/ops/film_sine,
// `FilmHead`), for f32 on CUDA: h = sin(pre * (theta * mul + add) + phi), with theta and phi
// layer k's blocks of the pose extractor's head o [N, 2*K*F] = [theta_0..theta_{K-1},
// phi_0..phi_{K-1}]. Compiled at run time with NVRTC (no includes), checked with nvcc by
// scripts/check-cuda-kernels.sh, and compiled for the host's emulated grid (emu.c), where
// the tests run it against the CPU op.
//
// One thread per element of [N,F], grid-stride, no shared memory, no atomics. Products and
// sums are rounded separately (__fmul_rn/__fadd_rn, never an FMA), in the CPU op's order;
// sinf/cosf are the device's (within 2 ulp of the correctly rounded value; the host build
// takes the C library's, which the CPU op reproduces bit for bit).

// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

// out = sin(a) and, when keep_cos, cos_out = cos(a) for the backward.
PMA_KERNEL void pma_film_sine_f32(
    const float *pre, const float *o, float *out, float *cos_out,
    unsigned int n, unsigned int f, unsigned int k, unsigned int n_layers,
    float mul, float add, int keep_cos)
{
    const unsigned long long w = 2ULL * n_layers * f;
    PMA_FOR_EACH(i, (unsigned long long)n * f) {
        const unsigned long long row = i / f;
        const unsigned int c = (unsigned int)(i % f);
        const float theta = o[row * w + (unsigned long long)k * f + c];
        const float phi = o[row * w + (unsigned long long)(n_layers + k) * f + c];
        const float a = __fadd_rn(__fmul_rn(pre[i], __fadd_rn(__fmul_rn(theta, mul), add)), phi);
        out[i] = sinf(a);
        if (keep_cos) {
            cos_out[i] = cosf(a);
        }
    }
}

// The layer's gradients from the upstream gradient: g_pre [N,F], and layer k's two blocks
// of the head gradient g_o [N, 2*K*F] (its other columns are left as they are: the layers
// of one stack fill one head gradient). cos(a) from the forward when have_cos, else again.
PMA_KERNEL void pma_film_sine_grad_f32(
    const float *grad, const float *pre, const float *o, const float *cos_in, float *g_pre,
    float *g_o, unsigned int n, unsigned int f, unsigned int k, unsigned int n_layers,
    float mul, float add, int have_cos)
{
    const unsigned long long w = 2ULL * n_layers * f;
    PMA_FOR_EACH(i, (unsigned long long)n * f) {
        const unsigned long long row = i / f;
        const unsigned int c = (unsigned int)(i % f);
        const unsigned long long t_at = row * w + (unsigned long long)k * f + c;
        const unsigned long long p_at = row * w + (unsigned long long)(n_layers + k) * f + c;
        const float gamma = __fadd_rn(__fmul_rn(o[t_at], mul), add);
        const float cs = have_cos ? cos_in[i] : cosf(__fadd_rn(__fmul_rn(pre[i], gamma), o[p_at]));
        // The plain graph's steps, each gradient from the zero accumulator: g_a = grad cos;
        // the add passes it to the product and to phi; the product gives pre g_a gamma and
        // gamma g_a pre; the affine gives theta (g_gamma mul) + 0.
        const float ga = __fmul_rn(grad[i], cs);
        const float gt = __fadd_rn(0.0f, ga);
        g_pre[i] = __fmul_rn(gt, gamma);
        const float gg = __fadd_rn(0.0f, __fmul_rn(gt, pre[i]));
        g_o[t_at] = __fadd_rn(__fmul_rn(gg, mul), 0.0f);
        g_o[p_at] = __fadd_rn(0.0f, ga);
    }
}
