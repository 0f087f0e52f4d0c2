#!/bin/bash
# One run on a CUDA machine (H100/H200, PyTorch installed, no network) that prints what pma's
# GPU work needs measured (docs/gpu.md). Builds nothing: the binaries come from a build
# machine: scripts/check-cuda-build.sh leaves them packed in target-cuda/gpu-kit.tar.xz, which
# a GPU session carries over (an ignored path) and this script unpacks into
# target-cuda/gpu-check/ (the binaries; official/ and wheels/ when the kit has them). The
# session sends the working tree too, and the tracked files alone are over its 64 MiB: run
# `scripts/gpu-session.sh leave` before the device call and `restore` after it.
#
#   scripts/gpu-check.sh                       # everything, under 8 minutes
#
# It starts with `pma doctor --device "$DEVICE"` and prints its table; it goes on only if every check
# of the doctor passes (KEEP_GOING=1 goes on regardless, to measure what still runs).
#
# Environment (all optional):
#   PMA_BIN      CUDA build of pma                      (default target-cuda/gpu-check/pma)
#   PMA_TESTBIN  CUDA build of pma-model's `model` test binary: golden forward + gradient
#                parity on CUDA (default target-cuda/gpu-check/model-tests; skipped if absent)
#   OFFICIAL     official PM-Avatars checkout: its training it/s via bench/official/run_official.py
#                (default: the kit's copy, target-cuda/gpu-check/official, when there is one)
#   OUT          output directory                       (default runs/gpu-check)
#   MINUTES      wall-clock minutes per timed training run (default 0.4)
#   KEEP_GOING   1: go on after a failed doctor
#   DEVICE       the device every phase runs on (default cuda; cpu tries the script itself)
#   PYTHON       python with PyTorch                    (default python3)
#
# Prints one summary at the end (also OUT/summary.txt). Each phase's peak GPU memory comes from
# nvidia-smi sampled every 200 ms while it runs.
set -uo pipefail
cd "$(dirname "$0")/.."
KIT=target-cuda/gpu-check
if [ -f target-cuda/gpu-kit.tar.xz ] && [ ! -x "$KIT/pma" ]; then
  mkdir -p "$KIT" && tar -C "$KIT" -xJf target-cuda/gpu-kit.tar.xz \
    || { echo "gpu-check: could not unpack target-cuda/gpu-kit.tar.xz" >&2; exit 1; }
fi
if [ -d "$KIT/wheels" ] && [ -n "$(ls "$KIT"/wheels/*.whl 2>/dev/null)" ]; then
  # The official code's Python packages that the GPU image lacks (no registry there).
  "${PYTHON:-python3}" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/pma-site "$KIT"/wheels/*.whl \
    && export PYTHONPATH=/tmp/pma-site${PYTHONPATH:+:$PYTHONPATH}
fi
[ -z "${OFFICIAL:-}" ] && [ -d "$KIT/official" ] && OFFICIAL=$PWD/$KIT/official
PMA_BIN=${PMA_BIN:-target-cuda/gpu-check/pma}
PMA_TESTBIN=${PMA_TESTBIN:-target-cuda/gpu-check/model-tests}
OFFICIAL=${OFFICIAL:-}
OUT=${OUT:-runs/gpu-check}
MINUTES=${MINUTES:-0.4}
PYTHON=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
mkdir -p "$OUT"
SUMMARY="$OUT/summary.txt"
: > "$SUMMARY"
say() { echo "$*" | tee -a "$SUMMARY"; }
start=$(date +%s)

# The binary dlopens libcublas(Lt).so.13, libcurand.so.10, libcudart.so.13 and libnvrtc: take
# them from the PyTorch install's nvidia-* packages.
libs=$("$PYTHON" - <<'PY' 2>/dev/null
import glob, os
try:
    import nvidia
    roots = list(nvidia.__path__)
except Exception:
    roots = []
dirs = set()
for r in roots:
    for so in glob.glob(os.path.join(r, "**", "lib*.so*"), recursive=True):
        dirs.add(os.path.dirname(so))
print(":".join(sorted(dirs)))
PY
)
export LD_LIBRARY_PATH="${libs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

[ -x "$PMA_BIN" ] || { echo "gpu-check: no pma binary at $PMA_BIN (set PMA_BIN)" >&2; exit 1; }
say "== gpu-check $(date -u +%FT%TZ)"
say "gpu: $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null | head -1)"

# phase NAME LIMIT CMD...: run CMD for at most LIMIT seconds, log to OUT/NAME.log, record wall
# seconds and peak GPU memory. A hung phase cannot take the rest of the run with it.
phase() {
  local name=$1 limit=$2; shift 2
  local mem="$OUT/$name.mem"
  nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 200 > "$mem" 2>/dev/null &
  local mon=$!
  local t0; t0=$(date +%s.%N)
  timeout -k 5 "$limit" "$@" > "$OUT/$name.log" 2>&1
  local rc=$?
  [ $rc = 124 ] && echo "gpu-check: $name stopped at its limit of $limit s" >> "$OUT/$name.log"
  local t1; t1=$(date +%s.%N)
  kill "$mon" 2>/dev/null; wait "$mon" 2>/dev/null
  local peak; peak=$(sort -n "$mem" 2>/dev/null | tail -1)
  PHASE_S=$(echo "$t1 - $t0" | bc)
  printf '%-28s rc %d  %7.1f s  peak GPU memory %s MiB\n' "$name" "$rc" "$PHASE_S" "${peak:-?}" | tee -a "$SUMMARY"
  return $rc
}
itps() { grep -oE '[0-9.]+ it/s' "$OUT/$1.log" | tail -1; }

# 0. The doctor: the device, every kernel against candle's ops, the golden case on the device's
# route, a 20-step `default` burst. Its table goes into the summary.
phase doctor 300 "$PMA_BIN" doctor --device "$DEVICE" --golden fixtures/golden --json "$OUT/doctor.json" --quiet
doctor_rc=$?
grep -vE '^report: ' "$OUT/doctor.log" | tee -a "$SUMMARY"
if [ $doctor_rc != 0 ] && [ "${KEEP_GOING:-0}" != 1 ]; then
  say "gpu-check: the doctor failed (exit $doctor_rc): stopping here (KEEP_GOING=1 goes on); logs in $OUT"
  exit 1
fi

# 1. Golden forward + gradient parity on CUDA (the tests' own tolerances). The dense case is
# left out: its 10 MB fixture stays behind when the working tree must fit a GPU session.
if [ -n "$PMA_TESTBIN" ] && [ -x "$PMA_TESTBIN" ]; then
  skip=(); [ -f fixtures/golden/dense/golden.safetensors ] || skip=(--skip dense)
  phase parity-golden 150 env PMA_TEST_DEVICE="$DEVICE" PMA_FIXTURES="$PWD/fixtures" "$PMA_TESTBIN" \
    golden:: grad:: "${skip[@]}" --test-threads 1 --nocapture
  say "  $(grep -E '^test result' "$OUT/parity-golden.log" | tail -1)"
  grep -E '^test .* (FAILED|ok)$' "$OUT/parity-golden.log" | sed 's/^/  /' | tee -a "$SUMMARY"
  grep -iE 'max (abs|rel)|worst' "$OUT/parity-golden.log" | head -12 | sed 's/^/  /' | tee -a "$SUMMARY"
else
  say "parity-golden: skipped (set PMA_TESTBIN to a --features cuda build of the model tests)"
fi

# 2. Data: the synthetic scene (CPU). Training runs read a copy of train.npz in a directory of
# its own, so no periodic held-out evaluation enters the it/s.
phase synth 120 "$PMA_BIN" synth --out "$OUT/scene"
mkdir -p "$OUT/train-only" && cp -f "$OUT/scene/train.npz" "$OUT/train-only/train.npz"
DATA="$OUT/train-only/train.npz"
printf 'preset = "cpu-small"\n[train]\nrays_per_step = 3072\n' > "$OUT/cpu-small-3072.toml"

# 3. Warm-up: the driver's JIT cache keeps candle's kernels for the runs below.
rm -rf "$OUT/warmup"
phase warmup 120 "$PMA_BIN" train --data "$DATA" --out "$OUT/warmup" --preset tiny --iters 3 --device "$DEVICE" --quiet

train() { # NAME ARGS...: a timed training run of MINUTES (on $ON when set, else $DEVICE)
  local name=$1; shift
  rm -rf "$OUT/$name"
  phase "$name" 120 "$PMA_BIN" train --data "$DATA" --out "$OUT/$name" --iters 100000 \
    --minutes "$MINUTES" --device "${ON:-$DEVICE}" --quiet "$@"
  say "  $name: $(grep -E '^done at' "$OUT/$name.log" | tail -1)"
  grep -iE 'warning|chunk' "$OUT/$name.log" | head -3 | sed 's/^/  /' | tee -a "$SUMMARY"
}

# 4. Training it/s at 3,072 rays: `default` with automatic chunks and in one chunk, with TF32,
# and `cpu-small`.
train default-auto --preset default
train default-3072 --preset default --chunk-rays 3072
train default-3072-tf32 --preset default --chunk-rays 3072 --tf32
train cpu-small-3072 --config "$OUT/cpu-small-3072.toml"

# 4b. On a machine with several GPUs: `default` on all of them, data-parallel (one process, one
# thread per GPU, NCCL: needs a kit built with `--features cuda,nccl`), beside the 1-GPU run above.
gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU ')
if [ "$DEVICE" = cuda ] && [ "${gpus:-0}" -gt 1 ]; then
  all=$(seq -s, 0 $((gpus - 1)))
  ON="cuda:$all" train "default-${gpus}gpus" --preset default
else
  say "  data-parallel: skipped (${gpus:-0} GPU(s) seen)"
fi

# 5. Peak GPU memory against the chunk size: 3 `default` steps at 256 and 1,024 rays per chunk
# (3,072 is the timed run above). The slope is the bytes a chunk's point × joint × feature
# element holds, the constant of the automatic chunk rule (compute::device::BYTES_PER_ELEMENT).
for c in 256 1024; do
  rm -rf "$OUT/chunk-$c"
  phase "chunk-$c" 90 "$PMA_BIN" train --data "$DATA" --out "$OUT/chunk-$c" --iters 3 \
    --preset default --chunk-rays "$c" --device "$DEVICE" --quiet
done

# 6. Per-stage profile of `default` steps (device syncs at every stage boundary).
rm -rf "$OUT/profile"
phase profile-default 120 env PMA_PROFILE=1 "$PMA_BIN" train --data "$DATA" --out "$OUT/profile" \
  --preset default --iters 4 --device "$DEVICE"
grep -E 'profile \(PMA_PROFILE=1\)' "$OUT/profile-default.log" | tail -2 | sed 's/^/  /' | tee -a "$SUMMARY"

# 7. A 512×512 render of a `default` avatar (the 3,072-ray run's; twice, the second is timed).
MODEL="$OUT/default-3072/model.safetensors"
for i in 1 2; do
  phase "render512-$i" 120 "$PMA_BIN" render --model "$MODEL" --data "$OUT/scene/novel_view.npz" \
    --res 512x512 --frames 0:1 --no-gif --quiet --device "$DEVICE" --out "$OUT/render512"
done
say "  512x512 render of a default avatar: ${PHASE_S} s (second run, the process's start included)"

# 8. The official code on the same GPU and batch (bench/official/run_official.py).
if [ -n "$OFFICIAL" ] && [ -f bench/official/run_official.py ]; then
  phase official-train 150 "$PYTHON" bench/official/run_official.py --official "$OFFICIAL" \
    --what train --rays 3072 --repeats 5 --device "$DEVICE" --json "$OUT/official-train.json"
  say "  official: $(tr -d '\n' < "$OUT/official-train.json" 2>/dev/null | head -c 400)"
  tail -3 "$OUT/official-train.log" | sed 's/^/  /' | tee -a "$SUMMARY"
else
  say "official-train: skipped (set OFFICIAL to the official checkout; needs bench/official/run_official.py)"
fi

say "== done in $(( $(date +%s) - start )) s; logs in $OUT"
