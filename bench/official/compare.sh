#!/usr/bin/env bash
# The official PM-Avatars code and pma side by side, in one session on one machine, so the
# ratios printed at the end compare like with like (never against figures from elsewhere).
#
#   bench/official/compare.sh --official DIR [--python PY] [--rays 1024] [--train-rays 512]
#                             [--repeats 3] [--threads 2] [--out DIR] [--skip-train]
#
# Needs the release build (cargo build --release -p pma -p pma-model --examples) and a Python
# with torch, numpy, safetensors, hydra-core and omegaconf. DIR is a checkout of the
# official code (it is imported at run time, never copied). CI does not run this.
#
# Rows: (1) the no_grad forward of one --rays batch: official `forward_rays` vs the whole
# `pma forward` process (start-up, loading, writing included; one warm-up, then the median
# of --repeats) on the same batch file, and pma's `--grad` graph path; (2) one training
# step of --train-rays rays: official `Trainer.train_batch` vs pma's `throughput` example.
# pma uses all cores it finds; pin both with taskset to compare at a fixed core count.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
official=""
python="${PYTHON:-python3}"
rays=1024
train_rays=512
repeats=3
threads=2
out=""
skip_train=0
while [ $# -gt 0 ]; do
    case "$1" in
        --official) official="$2"; shift 2 ;;
        --python) python="$2"; shift 2 ;;
        --rays) rays="$2"; shift 2 ;;
        --train-rays) train_rays="$2"; shift 2 ;;
        --repeats) repeats="$2"; shift 2 ;;
        --threads) threads="$2"; shift 2 ;;
        --out) out="$2"; shift 2 ;;
        --skip-train) skip_train=1; shift ;;
        -h|--help) sed -n 2,16p "$0"; exit 0 ;;
        *) echo "compare.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
[ -n "$official" ] || { echo "compare.sh: --official DIR is required" >&2; exit 2; }
pma="$repo/target/release/pma"
throughput="$repo/target/release/examples/throughput"
for bin in "$pma" "$throughput"; do
    [ -x "$bin" ] || { echo "compare.sh: $bin missing; run cargo build --release -p pma -p pma-model --examples" >&2; exit 2; }
done
[ -n "$out" ] || out="$(mktemp -d)"
mkdir -p "$out"
model="$repo/fixtures/golden/model.safetensors"
batch="$out/batch_$rays.npz"

# 1. Forward: the harness writes the batch, then times the official pass on it.
"$python" "$here/run_official.py" --official "$official" --what forward --rays "$rays" \
    --repeats "$repeats" --threads "$threads" --batch-out "$batch" \
    --out-npz "$out/official_forward.npz" --json "$out/official_forward.json"

# Whole `pma forward` processes: one warm-up, then the median of --repeats.
time_pma() {
    local ts=()
    for i in $(seq 0 "$repeats"); do
        local t0 t1
        t0=$(date +%s.%N)
        "$pma" forward --model "$model" --batch "$batch" --out "$out/pma_forward.npz" "$@" >/dev/null
        t1=$(date +%s.%N)
        [ "$i" -gt 0 ] && ts+=("$(echo "$t1 - $t0" | bc -l)")
    done
    printf '%s\n' "${ts[@]}" | sort -g | awk '{v[NR]=$1} END {print v[int((NR+1)/2)]}'
}
pma_grad=$(time_pma --grad)
pma_fast=$(time_pma)
off_fwd=$("$python" -c "import json,sys; print(json.load(open(sys.argv[1]))['median_s'])" "$out/official_forward.json")
# Same inputs, same outputs: the largest |Δ| of the rendered colours.
maxdiff=$("$python" - "$out/official_forward.npz" "$out/pma_forward.npz" <<'EOF'
import sys, numpy as np
a, b = np.load(sys.argv[1]), np.load(sys.argv[2])
print(max(float(np.abs(a[k] - b[k]).max()) for k in ["rgb_map", "acc_map", "rgb0"]))
EOF
)

if [ "$skip_train" = 0 ]; then
    # 2. Training step.
    "$python" "$here/run_official.py" --official "$official" --what train --rays "$train_rays" \
        --repeats "$repeats" --threads "$threads" --json "$out/official_train.json"
    pma_train=$("$throughput" --train-rays "$train_rays" --infer-rays 0 --repeats "$repeats" \
        | awk '/^training/ {for (i = 1; i <= NF; i++) if ($i == "s/step,") print $(i-1)}')
    off_train=$("$python" -c "import json,sys; print(json.load(open(sys.argv[1]))['median_s'])" "$out/official_train.json")
fi

echo
echo "same session, same machine ($(nproc) cores; official: $threads torch threads), medians of $repeats after one warm-up"
printf '%-44s %10s %10s\n' "" "seconds" "x official"
printf '%-44s %10.3f %10s\n' "official forward_rays, no_grad, $rays rays" "$off_fwd" "1.00"
printf '%-44s %10.3f %10.2f\n' "pma forward --grad (whole process)" "$pma_grad" "$(echo "$off_fwd / $pma_grad" | bc -l)"
printf '%-44s %10.3f %10.2f\n' "pma forward (whole process)" "$pma_fast" "$(echo "$off_fwd / $pma_fast" | bc -l)"
echo "max |official - pma| over rgb_map, acc_map, rgb0: $maxdiff"
if [ "$skip_train" = 0 ]; then
    printf '%-44s %10.3f %10s\n' "official train_batch, $train_rays rays" "$off_train" "1.00"
    printf '%-44s %10.3f %10.2f\n' "pma training step (throughput example)" "$pma_train" "$(echo "$off_train / $pma_train" | bc -l)"
fi
echo "files in $out"
