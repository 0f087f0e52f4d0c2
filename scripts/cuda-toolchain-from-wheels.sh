#!/bin/bash
# Build-time CUDA toolchain for `cargo build --features cuda` on a machine without a CUDA
# toolkit (no GPU needed): nvcc and headers from NVIDIA's PyPI wheels, plus link stubs.
#
#   scripts/cuda-toolchain-from-wheels.sh DIR      # once; needs pip, gcc/g++, network
#   . DIR/env.sh && cargo build --release -p pma --features cuda
#
# Why each piece:
# * nvcc 13.0 exactly: PTX from a newer nvcc has a PTX ISA version that a CUDA 13.0 driver
#   (R580) cannot load. Pick the nvcc minor that matches the oldest driver you target.
# * candle-core turns on cudarc's `dynamic-linking`, so the linker needs libcuda, libcublas,
#   libcublasLt, libcurand and libnvrtc. Only the real libcudart comes in a small wheel; the
#   others are replaced by stub libraries that export the same symbols under the real
#   SONAMEs. At run time the real libraries are loaded (the driver's libcuda.so.1 and the
#   cu13 libraries, e.g. from the nvidia-* pip wheels that PyTorch installs), so the binary
#   needs them on the library path even for `--device cpu`.
# * candle-kernels also compiles GGUF/MoE quantized-matmul kernels into a static library
#   that pma never calls; they take most of the build time. An nvcc wrapper replaces those
#   translation units with stubs that abort if ever called (PMA_FULL_CANDLE_KERNELS=1 at
#   build time compiles them for real).
set -euo pipefail
DIR=$(realpath -m "${1:?usage: $0 DIR}")
CUDA_VER=${CUDA_VER:-13.0}
mkdir -p "$DIR/wheels"
PIP_PLAT="--no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
# Versions that go together for CUDA 13.0 (runtime 13.0.96 is the newest 13.0 patch).
# Exit 3 when the wheels cannot be fetched (no network or no pip), so that a caller can tell
# "no toolchain here" apart from a broken build.
python3 -m pip download -q $PIP_PLAT -d "$DIR/wheels" \
  nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88 \
  nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85 \
  || { echo "cuda-toolchain-from-wheels: could not download NVIDIA's toolchain wheels" >&2; exit 3; }
tmp=$(mktemp -d)
for w in "$DIR"/wheels/*.whl; do unzip -q -o "$w" -d "$tmp"; done
cp -a "$tmp"/nvidia/cu13/. "$DIR"/
rm -rf "$tmp"
ln -sf libcudart.so.13 "$DIR/lib/libcudart.so"

# Link stubs: every function cudarc declares for a library, under that library's SONAME.
SRC=$(cargo metadata --format-version 1 --features cuda --manifest-path "$(dirname "$0")/../Cargo.toml" \
  | python3 -c 'import json,sys; m=json.load(sys.stdin); print("\n".join(p["manifest_path"] for p in m["packages"] if p["name"] in ("cudarc","candle-kernels")))')
CUDARC=$(dirname "$(echo "$SRC" | grep /cudarc-)")/src
KERNELS=$(dirname "$(echo "$SRC" | grep /candle-kernels-)")/src
mkdir -p "$DIR/lib/stubs"
stub() { # sys-module soname link-name
  grep -oE '^\s*fn [A-Za-z_0-9]+\(' "$CUDARC/$1/sys/mod.rs" | sed -E 's/^\s*fn ([A-Za-z_0-9]+)\(/\1/' \
    | sort -u | awk '{print "void "$1"(void){}"}' > "$DIR/lib/stubs/$3.c"
  gcc -shared -fPIC -o "$DIR/lib/stubs/$2" -Wl,-soname,"$2" "$DIR/lib/stubs/$3.c"
  ln -sf "$2" "$DIR/lib/stubs/lib$3.so"
}
stub driver libcuda.so.1 cuda
stub cublas libcublas.so.13 cublas
stub cublaslt libcublasLt.so.13 cublasLt
stub curand libcurand.so.10 curand
stub nvrtc libnvrtc.so.13 nvrtc

# nvcc wrapper that leaves out the unused GGUF/MoE kernels.
grep -oE 'pub fn [A-Za-z0-9_]+' "$KERNELS/ffi.rs" | awk '{print $3}' > "$DIR/candle_ffi_symbols.txt"
[ -f "$DIR/bin/nvcc.real" ] || mv "$DIR/bin/nvcc" "$DIR/bin/nvcc.real"
cat > "$DIR/bin/nvcc" <<'WRAP'
#!/bin/bash
# Replaces candle-kernels' GGUF/MoE sources (unused by pma) with stubs; see the script above.
here="$(cd "$(dirname "$0")" && pwd)"
real="$here/nvcc.real"
last="${@: -1}"
compile=0
for a in "$@"; do [ "$a" = "-c" ] && compile=1; done
if [ -z "${PMA_FULL_CANDLE_KERNELS:-}" ] && [ $compile = 1 ]; then
  case "$last" in
    */moe/*.cu|*/mmq_gguf/*.cu|*/mmvq_gguf.cu)
      stub="$(mktemp --suffix=.cu)"
      printf '#include <cstdio>\n#include <cstdlib>\n' > "$stub"
      # One translation unit defines every symbol; the others stay empty (no duplicates).
      if [ "$(basename "$last")" = moe_gguf.cu ]; then
        while read -r s; do
          printf 'extern "C" void %s(void) { std::fprintf(stderr, "candle GGUF/MoE kernel %s was left out of this build\\n"); std::abort(); }\n' "$s" "$s" >> "$stub"
        done < "$here/../candle_ffi_symbols.txt"
      fi
      "$real" "${@:1:$#-1}" "$stub"; rc=$?
      rm -f "$stub"; exit $rc;;
  esac
fi
exec "$real" "$@"
WRAP
chmod +x "$DIR/bin/nvcc"

cat > "$DIR/env.sh" <<ENV
# Source before: cargo build --release -p pma --features cuda
export CUDA_HOME=$DIR
export PATH=$DIR/bin:\$PATH
export CUDA_COMPUTE_CAP=\${CUDA_COMPUTE_CAP:-90}
export RUSTFLAGS="-L native=$DIR/lib -L native=$DIR/lib/stubs"
ENV
"$DIR/bin/nvcc" --version | tail -1
echo "toolchain ready: . $DIR/env.sh"
