#!/usr/bin/env bash
# Step accounting of the official PM-Avatars code and of pma in one run, side by side: what
# one training step would launch, upload and wait for on a GPU, counted on this machine
# (no GPU needed), with estimated GPU times from the same cost model (docs/gpu.md, "Step
# accounting").
#
#   bench/official/account.sh --official DIR [--python PY] [--preset default] [--rays 3072]
#       [--chunk-rays 0[,3072]] [--extrapolate-from N] [--account-as cuda] [--official-rays 256]
#       [--pma BIN] [--out DIR]
#
# Needs the release build (cargo build --release -p pma) and a Python with torch, numpy,
# safetensors, hydra-core, omegaconf and the modules the official code imports
# (opencv-python-headless, pillow, scipy). DIR is a checkout of the official code (imported
# at run time, never copied). CI does not run this.
#
# The official step is counted first (count_official.py). Its op and sync counts do not
# depend on the batch size, its bytes and FLOPs grow linearly, and a 3,072-ray step needs
# some 20 GiB on the CPU: with --official-rays N below --rays it counts steps of N, 2N and
# 3N rays and extrapolates to --rays (refused unless every op is exactly affine; 768 rays
# peak near 5.5 GiB). Then `pma bench --account` runs once per --chunk-rays value and
# prints both columns. A one-pass pma step too large for memory (--chunk-rays >= --rays) is
# accounted with --extrapolate-from N (N, 2N, 3N rays).
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
official=""
python="${PYTHON:-python3}"
preset=default
rays=3072
chunks=0
extrapolate=""
account_as=cuda
official_rays=256
pma="$repo/target/release/pma"
out=""
while [ $# -gt 0 ]; do
    case "$1" in
        --official) official="$2"; shift 2 ;;
        --python) python="$2"; shift 2 ;;
        --preset) preset="$2"; shift 2 ;;
        --rays) rays="$2"; shift 2 ;;
        --chunk-rays) chunks="$2"; shift 2 ;;
        --extrapolate-from) extrapolate="$2"; shift 2 ;;
        --account-as) account_as="$2"; shift 2 ;;
        --official-rays) official_rays="$2"; shift 2 ;;
        --pma) pma="$2"; shift 2 ;;
        --out) out="$2"; shift 2 ;;
        -h|--help) sed -n 2,20p "$0"; exit 0 ;;
        *) echo "account.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
[ -n "$official" ] || { echo "account.sh: --official DIR is required" >&2; exit 2; }
[ -x "$pma" ] || { echo "account.sh: $pma missing; run cargo build --release -p pma" >&2; exit 2; }
[ -n "$out" ] || out="$(mktemp -d)"
mkdir -p "$out"

start=$(date +%s)
extra=()
[ "$official_rays" -lt "$rays" ] && extra=(--extrapolate-to "$rays")
"$python" "$here/count_official.py" --official "$official" --rays "$official_rays" "${extra[@]}" \
    --json "$out/official_account.json"
echo "official count: $(( $(date +%s) - start )) s"

for chunk in ${chunks//,/ }; do
    dir="$out/pma-chunk-$chunk"
    mkdir -p "$dir"
    args=(bench --account --quiet --preset "$preset" --rays "$rays" --chunk-rays "$chunk"
          --account-as "$account_as" --official-json "$out/official_account.json" --out "$dir")
    # A one-pass step (chunks of at least --rays) is extrapolated when asked to.
    if [ -n "$extrapolate" ] && [ "$chunk" -ge "$rays" ]; then
        args+=(--extrapolate-from "$extrapolate")
    fi
    echo
    echo "== pma bench --account --chunk-rays $chunk"
    start=$(date +%s)
    # One pma worker (the CUDA route runs one anyway), so candle's ops use every core.
    "$pma" --workers 1 "${args[@]}"
    echo "pma account: $(( $(date +%s) - start )) s (files in $dir)"
done
