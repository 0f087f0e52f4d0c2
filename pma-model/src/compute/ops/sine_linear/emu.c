/* The point-encoder SIREN kernels over the host's emulated grid (kernel/launch.rs, kernel/emulate.h). */
#include "../../kernel/emulate.h"
#include "sine_linear.cu"

int pma_emu_sine_linear(const char *name, unsigned int blocks, unsigned int threads, void **p)
{
    if (PMA_IS(name, "pma_sine_linear_f32")) {
        PMA_GRID(blocks, threads, pma_sine_linear_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_OUT_F32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6)));
        return 0;
    }
    if (PMA_IS(name, "pma_sine_linear_grad_part_f32")) {
        PMA_GRID(blocks, threads, pma_sine_linear_grad_part_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_IN_F32(3), PMA_OUT_F32(4), PMA_U32(5), PMA_U32(6), PMA_U32(7)));
        return 0;
    }
    if (PMA_IS(name, "pma_sine_linear_grad_rows_f32")) {
        PMA_GRID(blocks, threads, pma_sine_linear_grad_rows_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_IN_F32(3), PMA_OUT_F32(4), PMA_U32(5), PMA_U32(6), PMA_U32(7)));
        return 0;
    }
    if (PMA_IS(name, "pma_sine_linear_grad_sum_f32")) {
        PMA_GRID(blocks, threads, pma_sine_linear_grad_sum_f32(PMA_IN_F32(0), PMA_OUT_F32(1), PMA_U32(2), PMA_U32(3), PMA_U32(4)));
        return 0;
    }
    return -1;
}
