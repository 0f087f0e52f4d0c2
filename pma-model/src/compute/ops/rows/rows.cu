// Row gather and its gradient (pma-model/src/compute/ops/rows). Compiled at run time with
// NVRTC (no includes allowed), checked ahead of time by scripts/check-cuda-kernels.sh with
// nvcc --ptx, and compiled for the host's emulated grid (emu.c beside this file).
//
// Shapes: x [B,N,C], ids [B,M] (u32, indices into N), out [B,M,C].
// One thread per output element (b, m, c): no serial loop over the indices.
//
// PMA_KERNEL is `extern "C" __global__` on CUDA; the host build defines it away.
#ifndef PMA_KERNEL
#define PMA_KERNEL extern "C" __global__
#endif

PMA_KERNEL void pma_gather_rows_f32(
    const float *x, const unsigned int *ids, float *out,
    unsigned int b_size, unsigned int n, unsigned int m, unsigned int c)
{
    const unsigned long long total = (unsigned long long)b_size * m * c;
    for (unsigned long long i = (unsigned long long)blockIdx.x * blockDim.x + threadIdx.x;
         i < total; i += (unsigned long long)blockDim.x * gridDim.x) {
        const unsigned long long row = i / c;  // b * m + j
        const unsigned int col = (unsigned int)(i % c);
        const unsigned long long b = row / m;
        const unsigned int idx = ids[row];
        // Indices are checked on the host before upload; an out-of-range one reads as 0
        // rather than outside the buffer.
        out[i] = idx < n ? x[(b * n + idx) * c + col] : 0.0f;
    }
}

// grad_x [B,N,C] (zeroed by the caller) += grad_out [B,M,C] scattered by ids.
// atomicAdd per element: rows that share an index (every ray of an image shares its frame
// code) are summed in parallel, in no fixed order.
PMA_KERNEL void pma_scatter_add_rows_f32(
    const float *grad, const unsigned int *ids, float *grad_x,
    unsigned int b_size, unsigned int n, unsigned int m, unsigned int c)
{
    const unsigned long long total = (unsigned long long)b_size * m * c;
    for (unsigned long long i = (unsigned long long)blockIdx.x * blockDim.x + threadIdx.x;
         i < total; i += (unsigned long long)blockDim.x * gridDim.x) {
        const unsigned long long row = i / c;
        const unsigned int col = (unsigned int)(i % c);
        const unsigned long long b = row / m;
        const unsigned int idx = ids[row];
        if (idx < n) {
            atomicAdd(&grad_x[(b * n + idx) * c + col], grad[i]);
        }
    }
}

// The same sum in a fixed order (Numerics::deterministic): one thread per element of
// grad_x [B,N,C] scans ids[b, 0..M] and adds the matching rows in index order from +0, as
// the CPU does. No atomics, so a run repeats bit for bit; costs M index reads per element.
PMA_KERNEL void pma_scatter_add_rows_ordered_f32(
    const float *grad, const unsigned int *ids, float *grad_x,
    unsigned int b_size, unsigned int n, unsigned int m, unsigned int c)
{
    const unsigned long long total = (unsigned long long)b_size * n * c;
    for (unsigned long long i = (unsigned long long)blockIdx.x * blockDim.x + threadIdx.x;
         i < total; i += (unsigned long long)blockDim.x * gridDim.x) {
        const unsigned long long row = i / c;  // b * n + idx
        const unsigned int col = (unsigned int)(i % c);
        const unsigned long long b = row / n;
        const unsigned int idx = (unsigned int)(row % n);
        float acc = 0.0f;
        for (unsigned int j = 0; j < m; ++j) {
            if (ids[b * m + j] == idx) {
                acc += grad[(b * m + j) * c + col];
            }
        }
        grad_x[i] = acc;
    }
}
