// What every kernel source of pma (compute/ops/*/*.cu) is compiled after: NVRTC allows no
// #include, so `kernel_module!` puts this text before the source it hands NVRTC,
// scripts/check-cuda-kernels.sh does the same for nvcc, and emulate.h includes it for the
// host build (having defined PMA_KERNEL first).

// A kernel: `extern "C" __global__` on CUDA.
#ifndef PMA_KERNEL
#define PMA_KERNEL extern "C" __global__
#endif

// Every i in [0, count) once, whatever the grid: a grid-stride loop.
#define PMA_FOR_EACH(i, count)                                                             \
    for (unsigned long long i = (unsigned long long)blockIdx.x * blockDim.x + threadIdx.x; \
         i < (count); i += (unsigned long long)blockDim.x * gridDim.x)
