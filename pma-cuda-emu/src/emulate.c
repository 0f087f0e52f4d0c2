/* pma-model's CUDA kernels as host C: the qualifiers are defined away, the grid variables
 * are globals, and each pma_emu_* entry point runs its kernel once per (block, thread) of
 * the grid it is given, sequentially (the kernels use no shared memory, no barriers and no
 * atomics, so this is every interleaving's result). */
#include <math.h>
#include <stdbool.h>

typedef struct {
    unsigned int x, y, z;
} pma_dim3;

static pma_dim3 blockIdx, threadIdx, blockDim, gridDim;

#define PMA_KERNEL static
static inline float __fmul_rn(float a, float b) { return a * b; }
static inline float __fadd_rn(float a, float b) { return a + b; }
static inline float __fsub_rn(float a, float b) { return a - b; }
static inline float __fdiv_rn(float a, float b) { return a / b; }
static inline float __fsqrt_rn(float a) { return sqrtf(a); }

#include "adam.cu"
#include "bias_act.cu"
#include "film_sine.cu"
#include "sine_linear.cu"
#include "window_pool.cu"

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

void pma_emu_window_pool_f32(const float *q, const float *g, const float *w, float *out,
                             unsigned int *arg, unsigned int n, unsigned int j,
                             unsigned int h, unsigned int per_pose, unsigned int blocks,
                             unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_window_pool_f32(q, g, w, out, arg, n, j, h, per_pose));
}

void pma_emu_window_pool_grad_q_f32(const float *grad, const float *w,
                                    const unsigned int *arg, float *grad_q, unsigned int n,
                                    unsigned int j, unsigned int h, unsigned int blocks,
                                    unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_window_pool_grad_q_f32(grad, w, arg, grad_q, n, j, h));
}

void pma_emu_window_pool_grad_g_f32(const float *grad, const float *w,
                                    const unsigned int *arg, float *grad_g, unsigned int p,
                                    unsigned int j, unsigned int h, unsigned int per_pose,
                                    unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_window_pool_grad_g_f32(grad, w, arg, grad_g, p, j, h, per_pose));
}

void pma_emu_film_sine_f32(const float *pre, const float *o, float *out, float *cos_out,
                           unsigned int n, unsigned int f, unsigned int k,
                           unsigned int n_layers, float mul, float add, int keep_cos,
                           unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_film_sine_f32(pre, o, out, cos_out, n, f, k, n_layers, mul, add, keep_cos));
}

void pma_emu_film_sine_grad_f32(const float *grad, const float *pre, const float *o,
                                const float *cos_in, float *g_pre, float *g_o, unsigned int n,
                                unsigned int f, unsigned int k, unsigned int n_layers,
                                float mul, float add, int have_cos, unsigned int blocks,
                                unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_film_sine_grad_f32(grad, pre, o, cos_in, g_pre, g_o, n, f, k, n_layers, mul,
                                    add, have_cos));
}

void pma_emu_adam_f32(const float *g, const float *p_old, const float *m_old,
                      const float *v_old, float *p, float *m, float *v,
                      const unsigned int *slot_of, const float *step_size,
                      const float *inv_bias2, const unsigned char *has,
                      const unsigned char *ok, const float *coef, int clip, unsigned int n,
                      float one_minus_b1, float b2, float one_minus_b2, float eps,
                      unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_adam_f32(g, p_old, m_old, v_old, p, m, v, slot_of, step_size, inv_bias2, has,
                          ok, coef, clip, n, one_minus_b1, b2, one_minus_b2, eps));
}

void pma_emu_sine_linear_f32(const float *x, const float *wb, const float *sc, float *y,
                             unsigned int rows, unsigned int in, unsigned int outs,
                             unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_sine_linear_f32(x, wb, sc, y, rows, in, outs));
}

void pma_emu_sine_linear_grad_part_f32(const float *grad, const float *x, const float *wb,
                                       const float *sc, float *part, unsigned int rows,
                                       unsigned int in, unsigned int outs,
                                       unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_sine_linear_grad_part_f32(grad, x, wb, sc, part, rows, in, outs));
}

void pma_emu_sine_linear_grad_rows_f32(const float *grad, const float *x, const float *wb,
                                       const float *sc, float *g_rows, unsigned int rows,
                                       unsigned int in, unsigned int outs,
                                       unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads,
             pma_sine_linear_grad_rows_f32(grad, x, wb, sc, g_rows, rows, in, outs));
}

void pma_emu_sine_linear_grad_sum_f32(const float *part, float *g, unsigned int n_blocks,
                                      unsigned int in, unsigned int outs, unsigned int blocks,
                                      unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_sine_linear_grad_sum_f32(part, g, n_blocks, in, outs));
}

unsigned int pma_emu_sine_linear_rows(void) { return PMA_SINE_LINEAR_ROWS; }

void pma_emu_bias_relu_f32(const float *z, const float *b, float *y, unsigned int rows,
                           unsigned int outs, unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_bias_relu_f32(z, b, y, rows, outs));
}

void pma_emu_bias_sine_f32(const float *z, const float *b, float *y, unsigned int rows,
                           unsigned int outs, unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_bias_sine_f32(z, b, y, rows, outs));
}

void pma_emu_act_grad_f32(const float *grad, const float *kept, const float *b, float *gz,
                          float *part, unsigned int rows, unsigned int outs, int sine,
                          unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_act_grad_f32(grad, kept, b, gz, part, rows, outs, sine));
}

void pma_emu_bias_grad_sum_f32(const float *part, float *gb, unsigned int n_blocks,
                               unsigned int outs, unsigned int blocks, unsigned int threads)
{
    PMA_GRID(blocks, threads, pma_bias_grad_sum_f32(part, gb, n_blocks, outs));
}

unsigned int pma_emu_bias_act_rows(void) { return PMA_BIAS_ACT_ROWS; }
