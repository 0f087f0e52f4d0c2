/* The window max-pool kernels over the host's emulated grid (kernel/launch.rs, kernel/emulate.h). */
#include "../../kernel/emulate.h"
#include "window_pool.cu"

int pma_emu_window_pool(const char *name, unsigned int blocks, unsigned int threads, void **p)
{
    if (PMA_IS(name, "pma_window_pool_f32")) {
        PMA_GRID(blocks, threads, pma_window_pool_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_OUT_F32(3), PMA_OUT_U32(4), PMA_U32(5), PMA_U32(6), PMA_U32(7), PMA_U32(8)));
        return 0;
    }
    if (PMA_IS(name, "pma_window_pool_grad_q_f32")) {
        PMA_GRID(blocks, threads, pma_window_pool_grad_q_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_U32(2), PMA_OUT_F32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6)));
        return 0;
    }
    if (PMA_IS(name, "pma_window_pool_grad_g_f32")) {
        PMA_GRID(blocks, threads, pma_window_pool_grad_g_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_U32(2), PMA_OUT_F32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6), PMA_U32(7)));
        return 0;
    }
    return -1;
}
