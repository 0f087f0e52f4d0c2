/* The FiLM-sine kernels over the host's emulated grid (kernel/launch.rs, kernel/emulate.h). */
#include "../../kernel/emulate.h"
#include "film_sine.cu"

int pma_emu_film_sine(const char *name, unsigned int blocks, unsigned int threads, void **p)
{
    if (PMA_IS(name, "pma_film_sine_f32")) {
        PMA_GRID(blocks, threads, pma_film_sine_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_OUT_F32(2), PMA_OUT_F32(3), PMA_U32(4), PMA_U32(5), PMA_U32(6), PMA_U32(7), PMA_F32(8), PMA_F32(9), PMA_I32(10)));
        return 0;
    }
    if (PMA_IS(name, "pma_film_sine_grad_f32")) {
        PMA_GRID(blocks, threads, pma_film_sine_grad_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_IN_F32(3), PMA_OUT_F32(4), PMA_OUT_F32(5), PMA_U32(6), PMA_U32(7), PMA_U32(8), PMA_U32(9), PMA_F32(10), PMA_F32(11), PMA_I32(12)));
        return 0;
    }
    return -1;
}
