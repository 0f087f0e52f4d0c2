/* The flat Adam update kernel over the host's emulated grid (kernel/launch.rs, kernel/emulate.h). */
#include "../../kernel/emulate.h"
#include "adam.cu"

int pma_emu_adam(const char *name, unsigned int blocks, unsigned int threads, void **p)
{
    if (PMA_IS(name, "pma_adam_f32")) {
        PMA_GRID(blocks, threads, pma_adam_f32(PMA_IN_F32(0), PMA_IN_F32(1), PMA_IN_F32(2), PMA_IN_F32(3), PMA_OUT_F32(4), PMA_OUT_F32(5), PMA_OUT_F32(6), PMA_IN_U32(7), PMA_IN_F32(8), PMA_IN_F32(9), PMA_IN_U8(10), PMA_IN_U8(11), PMA_IN_F32(12), PMA_I32(13), PMA_U32(14), PMA_F32(15), PMA_F32(16), PMA_F32(17), PMA_F32(18)));
        return 0;
    }
    return -1;
}
