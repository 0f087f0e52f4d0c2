/* pma's CUDA kernels as host C, for the emulated grid (kernel/launch.rs). Included by each
 * op's emu.c before its .cu source: the CUDA qualifiers are defined away, the grid
 * variables are per-thread globals, and the rounding intrinsics are plain f32 operations
 * (build.rs turns FMA contraction off, so each rounds as on the GPU). An op's emu.c runs a
 * kernel once per (block, thread) of the grid, in order, with CUDA's kernelParams
 * convention: params[i] points at argument i. */
#ifndef PMA_EMULATE_H
#define PMA_EMULATE_H

#include <math.h>
#include <stdbool.h>
#include <string.h>

typedef struct {
    unsigned int x, y, z;
} pma_dim3;

static _Thread_local pma_dim3 blockIdx, threadIdx, blockDim, gridDim;

#define PMA_KERNEL static
#define __device__
#include "prelude.cuh"
static inline float __fmul_rn(float a, float b) { return a * b; }
static inline float __fadd_rn(float a, float b) { return a + b; }
static inline float __fsub_rn(float a, float b) { return a - b; }
static inline float __fdiv_rn(float a, float b) { return a / b; }
static inline float __fsqrt_rn(float a) { return sqrtf(a); }
/* Threads run one after another: an atomic add is an add, in thread order. */
static inline float atomicAdd(float *a, float v)
{
    const float old = *a;
    *a = old + v;
    return old;
}

/* Run `call` once per (block, thread) of a blocks x threads grid. */
#define PMA_GRID(blocks, threads, call)                                 \
    do {                                                                \
        gridDim.x = (blocks);                                           \
        blockDim.x = (threads);                                         \
        gridDim.y = gridDim.z = blockDim.y = blockDim.z = 1;            \
        for (unsigned int b_ = 0; b_ < (blocks); ++b_) {                \
            for (unsigned int t_ = 0; t_ < (threads); ++t_) {           \
                blockIdx.x = b_;                                        \
                threadIdx.x = t_;                                       \
                call;                                                   \
            }                                                           \
        }                                                               \
    } while (0)

/* Argument i of a launch, of type T. */
#define PMA_ARG(p, i, T) (*(T *)(p)[i])

/* The argument kinds pma's kernels take, from the params array `p`. */
#define PMA_IN_F32(i) PMA_ARG(p, i, const float *)
#define PMA_IN_U32(i) PMA_ARG(p, i, const unsigned int *)
#define PMA_IN_U8(i) PMA_ARG(p, i, const unsigned char *)
#define PMA_OUT_F32(i) PMA_ARG(p, i, float *)
#define PMA_OUT_U32(i) PMA_ARG(p, i, unsigned int *)
#define PMA_U32(i) PMA_ARG(p, i, unsigned int)
#define PMA_I32(i) PMA_ARG(p, i, int)
#define PMA_F32(i) PMA_ARG(p, i, float)

/* Whether the launch names kernel k. */
#define PMA_IS(name, k) (strcmp((name), (k)) == 0)

#endif
