// The bias add and activation after a linear layer's product, and their gradients
// (pma-model/src/compute/ops/linear), for f32 on CUDA, with z = x W^T [R, OUT] from
// cuBLAS: y = max(z + b, 0) (ReLU: the density trunk, the colour head) or y = sin(z + b) (the
// pose extractor's SIREN layers, W and b already scaled by omega). Compiled at run time with
// NVRTC (no includes), checked with nvcc by scripts/check-cuda-kernels.sh, and compiled for
// the host's emulated grid (emu.c), where the tests run it against candle's ops.
//
// No shared memory, no atomics: the bias gradient is summed per block of PMA_BIAS_ACT_ROWS
// rows by one thread per column, then over the blocks in block order by a second launch, so
// a run repeats bit for bit.

// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

#define PMA_BIAS_ACT_ROWS 256

// y = max(z + b, 0) (a NaN becomes 0, as candle's ReLU makes it). One thread per element.
PMA_KERNEL void pma_bias_relu_f32(
    const float *z, const float *b, float *y, unsigned int rows, unsigned int outs)
{
    PMA_FOR_EACH(i, (unsigned long long)rows * outs) {
        const float a = __fadd_rn(z[i], b[i % outs]);
        y[i] = a > 0.0f ? a : 0.0f;
    }
}

// y = sin(z + b). One thread per element.
PMA_KERNEL void pma_bias_sine_f32(
    const float *z, const float *b, float *y, unsigned int rows, unsigned int outs)
{
    PMA_FOR_EACH(i, (unsigned long long)rows * outs) {
        y[i] = sinf(__fadd_rn(z[i], b[i % outs]));
    }
}

// The gradient gz of the activation's input, and part [blocks, OUT]: per block of rows and
// column, the sum of its gz in row order from zero. ReLU (sine = 0): gz = grad where the
// forward's output `kept` is > 0, else 0 (PyTorch's rule). Sine (sine = 1): gz = grad
// cos(z + b), `kept` the product z. One thread per (block, column), grid-stride;
// consecutive threads take consecutive columns.
PMA_KERNEL void pma_act_grad_f32(
    const float *grad, const float *kept, const float *b, float *gz, float *part,
    unsigned int rows, unsigned int outs, int sine)
{
    const unsigned long long blocks =
        ((unsigned long long)rows + PMA_BIAS_ACT_ROWS - 1) / PMA_BIAS_ACT_ROWS;
    PMA_FOR_EACH(i, blocks * outs) {
        const unsigned long long blk = i / outs;
        const unsigned int j = (unsigned int)(i % outs);
        const unsigned long long first = blk * PMA_BIAS_ACT_ROWS;
        unsigned long long last = first + PMA_BIAS_ACT_ROWS;
        if (last > rows) {
            last = rows;
        }
        float acc = 0.0f;
        for (unsigned long long r = first; r < last; ++r) {
            const unsigned long long at = r * outs + j;
            float v;
            if (sine) {
                v = __fmul_rn(grad[at], cosf(__fadd_rn(kept[at], b[j])));
            } else {
                v = kept[at] > 0.0f ? grad[at] : 0.0f;
            }
            gz[at] = v;
            acc = __fadd_rn(acc, v);
        }
        part[i] = acc;
    }
}

// gb [OUT] = the blocks' partial sums added in block order from zero. One thread per column.
PMA_KERNEL void pma_bias_grad_sum_f32(
    const float *part, float *gb, unsigned int blocks, unsigned int outs)
{
    PMA_FOR_EACH(j, outs) {
        float s = 0.0f;
        for (unsigned int k = 0; k < blocks; ++k) {
            s = __fadd_rn(s, part[(unsigned long long)k * outs + j]);
        }
        gb[j] = s;
    }
}
