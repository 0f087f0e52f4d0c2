// Row gather and its gradient (pma-model/src/compute/ops/rows). Compiled at run time with
// NVRTC (no includes allowed), checked ahead of time by scripts/check-cuda-kernels.sh with
// nvcc --ptx, and compiled for the host's emulated grid (emu.c beside this file).
//
// Shapes: x [B,N,C], ids [B,M] (u32, indices into N), out [B,M,C].
// One thread per output element (b, m, c): no serial loop over the indices.
//
// PMA_KERNEL and PMA_FOR_EACH: kernel/prelude.cuh, compiled before this source.

// Where element i of a [B,M,C] array (a gather's output, a scatter's gradient) stands in
// x [B,N,C]: row ids[b, j] of batch b, the same column; -1 for an index out of range
// (indices are checked on the host before upload; one never reaches outside the buffer).
static __device__ inline long long pma_row_at(
    const unsigned int *ids, unsigned long long i, unsigned int n, unsigned int m, unsigned int c)
{
    const unsigned long long row = i / c;  // b * m + j
    const unsigned int col = (unsigned int)(i % c);
    const unsigned long long b = row / m;
    const unsigned int idx = ids[row];
    return idx < n ? (long long)((b * n + idx) * c + col) : -1;
}

PMA_KERNEL void pma_gather_rows_f32(
    const float *x, const unsigned int *ids, float *out,
    unsigned int b_size, unsigned int n, unsigned int m, unsigned int c)
{
    PMA_FOR_EACH(i, (unsigned long long)b_size * m * c) {
        const long long at = pma_row_at(ids, i, n, m, c);
        out[i] = at >= 0 ? x[at] : 0.0f;
    }
}

// grad_x [B,N,C] (zeroed by the caller) += grad_out [B,M,C] scattered by ids.
// atomicAdd per element: rows that share an index (every ray of an image shares its frame
// code) are summed in parallel, in no fixed order.
PMA_KERNEL void pma_scatter_add_rows_f32(
    const float *grad, const unsigned int *ids, float *grad_x,
    unsigned int b_size, unsigned int n, unsigned int m, unsigned int c)
{
    PMA_FOR_EACH(i, (unsigned long long)b_size * m * c) {
        const long long at = pma_row_at(ids, i, n, m, c);
        if (at >= 0) {
            atomicAdd(&grad_x[at], grad[i]);
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
    PMA_FOR_EACH(i, (unsigned long long)b_size * n * c) {
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
