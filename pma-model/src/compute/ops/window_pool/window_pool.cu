// The window max-pool of pma's feature window and its gradient (pma-model/src/compute/ops/window_pool,
// `window_pool`), for f32 on CUDA. Compiled at run time with NVRTC (no includes), checked
// with nvcc by scripts/check-cuda-kernels.sh, and compiled for the host's emulated grid
// (emu.c), where the tests run it against the CPU op.
//
// Shapes: q [N,J,H], g [P,J,H] (point n belongs to pose n / per_pose), w [N,J];
// out and arg [N,H]. Every kernel is a grid-stride loop with one thread per output
// element, no shared memory and no atomics: any grid covers the work, and every sum runs in
// the CPU op's order, so values and gradients are the CPU's bits.
//
// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

// Products and sums go through __fmul_rn/__fadd_rn so that the compiler never contracts
// them into an FMA (which would round once where the CPU rounds twice).

// out[n,k] = max_j (q[n,j,k] + g[p(n),j,k]) * w[n,j] and arg[n,k] the first j reaching it;
// a NaN wins and stays (PyTorch's max propagates it).
PMA_KERNEL void pma_window_pool_f32(
    const float *q, const float *g, const float *w, float *out, unsigned int *arg,
    unsigned int n, unsigned int j, unsigned int h, unsigned int per_pose)
{
    PMA_FOR_EACH(i, (unsigned long long)n * h) {
        const unsigned long long row = i / h;
        const unsigned int k = (unsigned int)(i % h);
        const float *qr = q + row * j * h + k;
        const float *gr = g + (row / per_pose) * j * h + k;
        const float *wr = w + row * j;
        float best = __fmul_rn(__fadd_rn(qr[0], gr[0]), wr[0]);
        unsigned int a = 0;
        for (unsigned int jj = 1; jj < j; ++jj) {
            const float v = __fmul_rn(__fadd_rn(qr[(unsigned long long)jj * h],
                                                gr[(unsigned long long)jj * h]), wr[jj]);
            const bool take = v > best || (v != v && best == best);
            best = take ? v : best;
            a = take ? jj : a;
        }
        out[i] = best;
        arg[i] = a;
    }
}

// grad_q[n,j,k] = grad[n,k] * w[n,j] at the arg-max joint, 0 elsewhere (every element
// written: no zeroed buffer needed).
PMA_KERNEL void pma_window_pool_grad_q_f32(
    const float *grad, const float *w, const unsigned int *arg, float *grad_q,
    unsigned int n, unsigned int j, unsigned int h)
{
    const unsigned long long jh = (unsigned long long)j * h;
    PMA_FOR_EACH(i, (unsigned long long)n * jh) {
        const unsigned long long row = i / jh;
        const unsigned int jj = (unsigned int)((i % jh) / h);
        const unsigned int k = (unsigned int)(i % h);
        grad_q[i] = arg[row * h + k] == jj ? __fmul_rn(grad[row * h + k], w[row * j + jj]) : 0.0f;
    }
}

// grad_g[p,j,k] = the sum over pose p's points n, in point order from +0, of
// grad[n,k] * w[n,j] where arg[n,k] == j: the CPU's order, without atomics.
PMA_KERNEL void pma_window_pool_grad_g_f32(
    const float *grad, const float *w, const unsigned int *arg, float *grad_g,
    unsigned int p, unsigned int j, unsigned int h, unsigned int per_pose)
{
    const unsigned long long jh = (unsigned long long)j * h;
    PMA_FOR_EACH(i, (unsigned long long)p * jh) {
        const unsigned long long pose = i / jh;
        const unsigned int jj = (unsigned int)((i % jh) / h);
        const unsigned int k = (unsigned int)(i % h);
        float acc = 0.0f;
        for (unsigned long long row = pose * per_pose; row < (pose + 1) * per_pose; ++row) {
            if (arg[row * h + k] == jj) {
                acc = __fadd_rn(acc, __fmul_rn(grad[row * h + k], w[row * j + jj]));
            }
        }
        grad_g[i] = acc;
    }
}
