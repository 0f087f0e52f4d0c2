// A SIREN layer on a narrow input, each row scaled, and its gradients
// (pma-model/src/compute/ops/sine_linear), for f32 on CUDA: y = s_r sin(x W^T + b), x [R, IN]
// with IN <= 4 (the point encoders: x-bar, 3 coordinates per joint), wb = [W | b]
// [OUT, IN + 1], s [R] (the window weight of the row's joint, or ones). Compiled at run time with NVRTC (no
// includes), checked with nvcc by scripts/check-cuda-kernels.sh, and compiled for the host's
// emulated grid (emu.c), where the tests run it against candle's ops.
//
// No shared memory, no atomics: the weight and bias gradients are summed per block of
// PMA_SINE_LINEAR_ROWS rows by one thread each, then over the blocks in block order by a
// second launch, so a run repeats bit for bit. Products and sums are rounded separately
// (__fmul_rn/__fadd_rn, never an FMA), in the CPU op's order; sinf/cosf are the device's
// (within 2 ulp; the host build takes the C library's, which the CPU op reproduces).

// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

#define PMA_SINE_LINEAR_MAX_IN 4
#define PMA_SINE_LINEAR_ROWS 1024

// The sine's argument for row r, output j: ((x_0 W_j0 + x_1 W_j1) + ...) + b_j, with
// wb's row j = [W_j0 .. W_j,IN-1, b_j].
#define PMA_SINE_LINEAR_ARG(x, wb, r, j, in, out_a)                                           \
    do {                                                                                       \
        const float *w_ = (wb) + (unsigned long long)(j) * ((in) + 1);                         \
        float s_ = __fmul_rn((x)[(unsigned long long)(r) * (in)], w_[0]);                      \
        for (unsigned int c_ = 1; c_ < (in); ++c_) {                                           \
            s_ = __fadd_rn(s_, __fmul_rn((x)[(unsigned long long)(r) * (in) + c_], w_[c_]));   \
        }                                                                                      \
        (out_a) = __fadd_rn(s_, w_[(in)]);                                                     \
    } while (0)

// y [R, OUT]: one thread per element, grid-stride.
PMA_KERNEL void pma_sine_linear_f32(
    const float *x, const float *wb, const float *sc, float *y,
    unsigned int rows, unsigned int in, unsigned int outs)
{
    PMA_FOR_EACH(i, (unsigned long long)rows * outs) {
        const unsigned long long r = i / outs;
        const unsigned int j = (unsigned int)(i % outs);
        float a;
        PMA_SINE_LINEAR_ARG(x, wb, r, j, in, a);
        y[i] = __fmul_rn(sinf(a), sc[r]);
    }
}

// Per block of PMA_SINE_LINEAR_ROWS rows and output j, the sums over the block's rows of
// g_a x_c (c < IN) and of g_a (the bias), g_a = (grad s_r) cos(a) with a recomputed from x:
// part [blocks, OUT, IN + 1]. One thread per (block, j), grid-stride; consecutive threads
// read consecutive columns of grad.
PMA_KERNEL void pma_sine_linear_grad_part_f32(
    const float *grad, const float *x, const float *wb, const float *sc, float *part,
    unsigned int rows, unsigned int in, unsigned int outs)
{
    const unsigned long long blocks =
        ((unsigned long long)rows + PMA_SINE_LINEAR_ROWS - 1) / PMA_SINE_LINEAR_ROWS;
    PMA_FOR_EACH(i, blocks * outs) {
        const unsigned long long blk = i / outs;
        const unsigned int j = (unsigned int)(i % outs);
        float acc[PMA_SINE_LINEAR_MAX_IN + 1];
        for (unsigned int c = 0; c <= in; ++c) {
            acc[c] = 0.0f;
        }
        const unsigned long long first = blk * PMA_SINE_LINEAR_ROWS;
        unsigned long long last = first + PMA_SINE_LINEAR_ROWS;
        if (last > rows) {
            last = rows;
        }
        for (unsigned long long r = first; r < last; ++r) {
            float a;
            PMA_SINE_LINEAR_ARG(x, wb, r, j, in, a);
            const float ga = __fmul_rn(__fmul_rn(grad[r * outs + j], sc[r]), cosf(a));
            for (unsigned int c = 0; c < in; ++c) {
                acc[c] = __fadd_rn(acc[c], __fmul_rn(ga, x[r * in + c]));
            }
            acc[in] = __fadd_rn(acc[in], ga);
        }
        for (unsigned int c = 0; c <= in; ++c) {
            part[i * (in + 1) + c] = acc[c];
        }
    }
}

// Per row, [R, IN + 1]: x's gradient (columns 0..IN, sums over j in order from zero of
// g_a W_jc; x-bar's gradient flows on to the learned box scales) and s's (column IN, the sum
// over j of grad sin(a)). One thread per row, grid-stride.
PMA_KERNEL void pma_sine_linear_grad_rows_f32(
    const float *grad, const float *x, const float *wb, const float *sc, float *g_rows,
    unsigned int rows, unsigned int in, unsigned int outs)
{
    PMA_FOR_EACH(r, rows) {
        float acc[PMA_SINE_LINEAR_MAX_IN + 1];
        for (unsigned int c = 0; c <= in; ++c) {
            acc[c] = 0.0f;
        }
        for (unsigned int j = 0; j < outs; ++j) {
            float a;
            PMA_SINE_LINEAR_ARG(x, wb, r, j, in, a);
            const float g = grad[r * outs + j];
            const float ga = __fmul_rn(__fmul_rn(g, sc[r]), cosf(a));
            const float *w_ = wb + (unsigned long long)j * (in + 1);
            for (unsigned int c = 0; c < in; ++c) {
                acc[c] = __fadd_rn(acc[c], __fmul_rn(ga, w_[c]));
            }
            acc[in] = __fadd_rn(acc[in], __fmul_rn(g, sinf(a)));
        }
        for (unsigned int c = 0; c <= in; ++c) {
            g_rows[r * (in + 1) + c] = acc[c];
        }
    }
}

// g [OUT, IN + 1] = the blocks' partial sums added in block order from zero: columns
// 0..IN the weight gradient, column IN the bias gradient. One thread per element.
PMA_KERNEL void pma_sine_linear_grad_sum_f32(
    const float *part, float *g, unsigned int blocks, unsigned int in, unsigned int outs)
{
    const unsigned long long total = (unsigned long long)outs * (in + 1);
    PMA_FOR_EACH(i, total) {
        float s = 0.0f;
        for (unsigned int k = 0; k < blocks; ++k) {
            s = __fadd_rn(s, part[(unsigned long long)k * total + i]);
        }
        g[i] = s;
    }
}
