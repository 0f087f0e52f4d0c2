#!/bin/bash
# CI's guard of the `cuda` feature on a machine without a GPU or a CUDA toolkit: nvcc and
# headers come from NVIDIA's wheels (scripts/cuda-toolchain-from-wheels.sh), then
#
#   1. pma's own kernels compile with nvcc, warnings as errors (scripts/check-cuda-kernels.sh);
#   2. clippy type-checks and lints every crate and test with `cuda` and `nccl` on (-D
#      warnings; cudarc carries NCCL's bindings and nothing is linked, so no NCCL library
#      or header is needed); its build scripts compile candle's CUDA kernels, so a
#      candle/CUDA mismatch shows here too.
#
# Nothing is linked: a full CUDA build takes far longer than CI's budget on 2 cores
# (scripts/check-cuda-build.sh does it). Prints the time of each step.
#
#   scripts/ci-cuda-check.sh        # toolchain in target-cuda/toolchain, build in target-cuda/
#
# Exit 0 when every step passed or when the toolchain wheels could not be downloaded (said on
# stderr as SKIPPED: no CUDA toolchain here is not a CUDA bug); non-zero on any check that
# failed.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$PWD/target-cuda}
TC=$(realpath -m "${PMA_CUDA_TOOLCHAIN:-$CARGO_TARGET_DIR/toolchain}")
export CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}
t() { local s; s=$(date +%s); "$@"; echo "   ($(( $(date +%s) - s )) s: $*)"; }

echo "== cuda toolchain ($TC)"
if [ ! -f "$TC/env.sh" ]; then
  need=()
  python3 -m pip --version >/dev/null 2>&1 || need+=(python3-pip)
  command -v unzip >/dev/null || need+=(unzip)
  if [ ${#need[@]} -gt 0 ] && command -v apt-get >/dev/null; then
    echo "install ${need[*]}"
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -qq && apt-get install -y -qq "${need[@]}" >/dev/null; } || true
  fi
  rc=0; t scripts/cuda-toolchain-from-wheels.sh "$TC" || rc=$?
  if [ $rc = 3 ]; then
    echo "ci-cuda-check: SKIPPED: no CUDA toolchain could be downloaded; the cuda feature is unchecked" >&2
    exit 0
  fi
  [ $rc = 0 ] || exit 1
fi
# shellcheck disable=SC1091
. "$TC/env.sh"

echo "== pma's kernels (nvcc --ptx -Werror, compute_$CUDA_COMPUTE_CAP)"
t scripts/check-cuda-kernels.sh "$CUDA_COMPUTE_CAP"

echo "== clippy --features cuda,nccl (every crate and test; candle's kernels compiled by nvcc)"
t cargo clippy --locked --workspace --all-targets \
  --features pma/cuda,pma/nccl,pma-model/cuda,pma-model/nccl,pma-model/train,pma-infer/cuda \
  -- -D warnings
echo "== cuda check ok"
