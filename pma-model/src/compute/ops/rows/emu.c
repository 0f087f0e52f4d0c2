/* The row-gather kernels over the host's emulated grid (kernel/launch.rs, kernel/emulate.h). */
#include "../../kernel/emulate.h"
#include "rows.cu"

int pma_emu_rows(const char *name, unsigned int blocks, unsigned int threads, void **p)
{
    if (PMA_IS(name, "pma_gather_rows_f32")) {
        PMA_GRID(blocks, threads, pma_gather_rows_f32(PMA_IN_F32(0), PMA_IN_U32(1), PMA_OUT_F32(2), PMA_U32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6)));
        return 0;
    }
    if (PMA_IS(name, "pma_scatter_add_rows_f32")) {
        PMA_GRID(blocks, threads, pma_scatter_add_rows_f32(PMA_IN_F32(0), PMA_IN_U32(1), PMA_OUT_F32(2), PMA_U32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6)));
        return 0;
    }
    if (PMA_IS(name, "pma_scatter_add_rows_ordered_f32")) {
        PMA_GRID(blocks, threads, pma_scatter_add_rows_ordered_f32(PMA_IN_F32(0), PMA_IN_U32(1), PMA_OUT_F32(2), PMA_U32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6)));
        return 0;
    }
    return -1;
}
