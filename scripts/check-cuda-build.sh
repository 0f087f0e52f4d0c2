#!/bin/bash
# Build pma with `--features cuda` on a machine without a GPU, so the CUDA code paths keep
# compiling, and leave what scripts/gpu-check.sh needs on a GPU machine:
#
#   scripts/check-cuda-build.sh [TOOLCHAIN_DIR]   # default /tmp/cuda-tc; needs network once
#
#   target-cuda/gpu-check/pma            the CUDA build of the CLI (stripped)
#   target-cuda/gpu-check/model-tests    with MODEL_TESTS=1: the model tests (PMA_TEST_DEVICE=
#                                        cuda); `pma doctor` already runs the golden forward,
#                                        gradients and Adam step on the device
#   target-cuda/gpu-kit.tar.xz           both, plus (with OFFICIAL=DIR) the official code and
#                                        the wheels it needs beyond the GPU image's packages:
#                                        what a GPU session carries (its limit is 64 MiB, the
#                                        working tree included: scripts/gpu-session.sh)
#
# Steps: the nvcc toolchain from NVIDIA's wheels (scripts/cuda-toolchain-from-wheels.sh,
# skipped when DIR/env.sh exists), nvcc on pma's own kernels (scripts/check-cuda-kernels.sh),
# then the two release builds and the kit. Prints the time of each step. CI runs the cheaper
# scripts/ci-cuda-check.sh (type-check and lint, no codegen, nothing linked) instead.
set -euo pipefail
cd "$(dirname "$0")/.."
TC=$(realpath -m "${1:-/tmp/cuda-tc}")
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$PWD/target-cuda}
t() { local s; s=$(date +%s); "$@"; echo "   ($(( $(date +%s) - s )) s: $*)"; }

echo "== toolchain ($TC)"
[ -f "$TC/env.sh" ] || t scripts/cuda-toolchain-from-wheels.sh "$TC"
# shellcheck disable=SC1091
. "$TC/env.sh"
export CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}

echo "== pma's kernels (nvcc --ptx)"
t scripts/check-cuda-kernels.sh "$CUDA_COMPUTE_CAP"

echo "== pma --features cuda (release)"
t cargo build --release --locked -p pma --features cuda

kit="$CARGO_TARGET_DIR/gpu-check"
mkdir -p "$kit"
strip -o "$kit/pma" "$CARGO_TARGET_DIR/release/pma"
if [ "${MODEL_TESTS:-0}" = 1 ]; then
  echo "== pma-model model tests --features cuda (release)"
  t cargo test --release --locked -p pma-model --features cuda,train --test model --no-run
  bin=$(cargo test --release --locked -p pma-model --features cuda,train --test model --no-run \
    --message-format json 2>/dev/null \
    | python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "model" and m.get("executable"):
        print(m["executable"])' | tail -1)
  strip -o "$kit/model-tests" "$bin"
else
  rm -f "$kit/model-tests"
fi
ls -la "$kit"

echo "== kit (xz)"
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
cp "$kit"/* "$stage/"
if [ -n "${OFFICIAL:-}" ]; then
  # The official code without its history, and hydra/omegaconf (pure Python; the GPU image
  # has torch, numpy, safetensors and pyyaml but not these).
  mkdir -p "$stage/official" "$stage/wheels"
  tar -C "$OFFICIAL" --exclude=.git -cf - . | tar -C "$stage/official" -xf -
  t python3 -m pip wheel -q --no-deps -w "$stage/wheels" \
    hydra-core==1.3.2 omegaconf==2.3.0 antlr4-python3-runtime==4.9.3
fi
t sh -c "tar -C '$stage' -cf - . | xz -9e -T0 > '$CARGO_TARGET_DIR/gpu-kit.tar.xz.tmp'"
mv "$CARGO_TARGET_DIR/gpu-kit.tar.xz.tmp" "$CARGO_TARGET_DIR/gpu-kit.tar.xz"
bytes=$(stat -c %s "$CARGO_TARGET_DIR/gpu-kit.tar.xz")
echo "kit: $CARGO_TARGET_DIR/gpu-kit.tar.xz, $bytes bytes ($(( bytes / 1048576 )) MiB; unpacked $(du -sm "$stage" | cut -f1) MiB)"
if [ "$bytes" -gt $(( 64 * 1048576 )) ]; then
  echo "check-cuda-build: the kit is over the 64 MiB a GPU session can carry" >&2
  exit 1
fi
echo "== ok: carry target-cuda/gpu-kit.tar.xz; scripts/gpu-check.sh unpacks it (run it from the repo root)"
