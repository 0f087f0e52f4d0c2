#!/bin/bash
# Compile every CUDA kernel source of pma (pma-model/src/compute/ops/*/*.cu) to PTX with nvcc,
# so a kernel that no longer compiles is caught without a GPU. At run time the same sources
# go through NVRTC, which accepts the same dialect (no #include), each after
# pma-model/src/compute/kernel/prelude.cuh: nvcc here compiles that same text.
#
#   scripts/check-cuda-kernels.sh [ARCH]      # ARCH: compute capability, default 90 (H100/H200)
#
# Needs nvcc on PATH (e.g. `. DIR/env.sh` after scripts/cuda-toolchain-from-wheels.sh DIR).
set -euo pipefail
cd "$(dirname "$0")/.."
ARCH=${1:-${CUDA_COMPUTE_CAP:-90}}
command -v nvcc >/dev/null || { echo "check-cuda-kernels: nvcc not on PATH" >&2; exit 1; }
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
n=0
while IFS= read -r cu; do
  # No system headers: NVRTC compiles these without any, so nvcc must not need them either.
  if grep -qE '^\s*#\s*include' "$cu"; then
    echo "FAIL $cu: #include is not available to NVRTC at run time" >&2; exit 1
  fi
  cat pma-model/src/compute/kernel/prelude.cuh "$cu" > "$out/$(basename "$cu")"
  nvcc --ptx -arch=compute_"$ARCH" -Werror all-warnings -o "$out/$(basename "$cu" .cu).ptx" \
    "$out/$(basename "$cu")"
  # Kernels are declared `extern "C" __global__ void name` or `PMA_KERNEL void name`.
  for k in $(grep -oE '(__global__|PMA_KERNEL) void [A-Za-z0-9_]+' "$cu" | awk '{print $3}'); do
    grep -q "\.entry $k" "$out/$(basename "$cu" .cu).ptx" || { echo "FAIL $cu: no entry $k" >&2; exit 1; }
  done
  echo "ok   $cu (compute_$ARCH)"
  n=$((n + 1))
done < <(find pma-model/src -name '*.cu' | sort)
[ "$n" -gt 0 ] || { echo "check-cuda-kernels: no kernel sources found" >&2; exit 1; }
echo "check-cuda-kernels: $n file(s) compiled"
