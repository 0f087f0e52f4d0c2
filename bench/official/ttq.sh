#!/usr/bin/env bash
# Time to quality of the official PM-Avatars code beside pma's, on one synthetic scene, in
# one session on one machine: held-out PSNR after --marks minutes of training at pma's
# cpu-small config, for the official code (ttq_official.py), pma parity and pma's fast recipe.
#
#   bench/official/ttq.sh --official DIR --out OUT [--pma BIN] [--python PY] [--seed 101]
#                         [--marks 1,2,5] [--eval-images 16] [--threads 2] [--workers 0]
#                         [--fast-flags "--fast"]
#
# Needs a pma release binary (--pma; default target/release/pma) and a Python (--python)
# with what the official code imports: torch, numpy, scipy, h5py, hydra-core, omegaconf,
# pillow, imageio, smplx, lpips, scikit-image, tensorboard, pytorch-msssim, safetensors, tqdm,
# six and configargparse (the set its last table ran with; pytorch3d, plotly, matplotlib and
# cv2 are stood in for). DIR is a checkout of the official code, imported at run time and
# never copied (run_official.import_official).
#
# Steps: `pma synth --seed S` (the scene `pma bench --time-to-quality` trains on for that
# seed: SynthConfig's defaults); its train and novel-view splits as h36m_zju .h5
# (export_h5.py), each checked by a round trip through `pma convert dataset`; the official
# code trained with a checkpoint at each mark; each checkpoint converted by
# `pma convert checkpoint` with cpu-small's 16 + 8 samples set in its config (and checked
# to hold the tensors and config of pma's parity run, `ttq_official.py same-model`); pma parity
# trained by `pma train --minutes` in one run resumed at each mark (`--resume`): the first
# invocation trains for the first mark, each next one for the difference, and the model each
# leaves is copied aside; the fast recipe, whose pose-side boost spans its `--minutes`
# budget, in a run of its own per mark. Every model is scored by the same
# `pma eval --split novel_view --max-images K` (a parity render, PSNR under the mask) on the
# same K evenly spread novel-view images. Prints the table (ttq_table.py) and writes
# OUT/ttq.md and OUT/ttq.json.
#
# Time counts alike: the official driver times batch loading and `train_batch` only; pma's
# runs train on a copy of train.npz with no novel_view.npz beside it (no held-out
# evaluation) and with periodic evaluation and checkpoints off (OUT/pma.toml), so their
# `--minutes` clock holds the steps and their logging; start-up, saving and scoring are not
# counted on either side. --fast-flags: the fast recipe's `pma train` flags (`--fast`:
# culling at 0.6 with the occupancy grid, averaged weights and the pose side's boost over
# the budget; for a binary whose `--fast` differs, spell it out: "--cull-rays
# --cull-samples 0.6 --occupancy --average --pose-boost"). The timings are the result: run this alone
# on the machine (e.g. `flock LOCK bench/official/ttq.sh ...`). CI does not run this.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
official=""
out=""
pma="$repo/target/release/pma"
python="${PYTHON:-python3}"
seed=101
marks="1,2,5"
eval_images=16
threads=2
workers=0
fast_flags="--fast"
while [ $# -gt 0 ]; do
    case "$1" in
        --official) official="$2"; shift 2 ;;
        --out) out="$2"; shift 2 ;;
        --pma) pma="$2"; shift 2 ;;
        --python) python="$2"; shift 2 ;;
        --seed) seed="$2"; shift 2 ;;
        --marks) marks="$2"; shift 2 ;;
        --eval-images) eval_images="$2"; shift 2 ;;
        --threads) threads="$2"; shift 2 ;;
        --workers) workers="$2"; shift 2 ;;
        --fast-flags) fast_flags="$2"; shift 2 ;;
        -h|--help) sed -n 2,33p "$0"; exit 0 ;;
        *) echo "ttq.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
[ -n "$official" ] || { echo "ttq.sh: --official DIR is required" >&2; exit 2; }
[ -n "$out" ] || { echo "ttq.sh: --out DIR is required" >&2; exit 2; }
[ -x "$pma" ] || { echo "ttq.sh: $pma missing; build it (cargo build --release -p pma) or pass --pma" >&2; exit 2; }
mkdir -p "$out"
out="$(cd "$out" && pwd)"
IFS=, read -r -a mark_list <<< "$marks"

run() { echo "+ $*" >&2; "$@"; }

# 1. The scene and its h36m_zju export, checked by a round trip.
scene="$out/scene"
[ -f "$scene/novel_view.npz" ] || run "$pma" synth --seed "$seed" --out "$scene" --quiet
mkdir -p "$out/h5"
for split in train:train novel_view:test; do
    npz="${split%%:*}" h5="$out/h5/S9_${split##*:}.h5"
    run "$python" "$here/export_h5.py" write "$scene/$npz.npz" "$h5"
    run "$pma" convert dataset "$h5" -o "$out/h5/${npz}_back.npz" --profile eval
    run "$python" "$here/export_h5.py" compare "$scene/$npz.npz" "$out/h5/${npz}_back.npz"
done

# 2. The official code, saved at each mark; converted for pma eval.
run "$python" "$here/ttq_official.py" train --official "$official" --h5 "$out/h5/S9_train.h5" \
    --out "$out/official" --marks "$marks" --threads "$threads" --workers "$workers"
for m in "${mark_list[@]}"; do
    th="$out/official/official_${m}min.th"
    run "$pma" convert checkpoint "$th" -o "$out/official/official_${m}min.safetensors"
    run "$python" "$here/ttq_official.py" samples "$out/official/official_${m}min.safetensors"
done

# 3. pma parity, one run resumed at every mark; the fast recipe, a run per mark.
mkdir -p "$out/pma-data"
cp "$scene/train.npz" "$out/pma-data/train.npz"
cat > "$out/pma.toml" <<EOF
preset = "cpu-small"
[train]
eval_every = 0
ckpt_every = 1000000000
EOF
for r in parity fast; do
    flags=()
    [ "$r" = fast ] && read -r -a flags <<< "$fast_flags"
    dir="$out/$r"
    rm -rf "$dir"
    mkdir -p "$dir/marks"
    prev=0
    for m in "${mark_list[@]}"; do
        span="$(awk -v a="$m" -v b="$prev" 'BEGIN { print a - b }')"
        if [ "$r" = fast ]; then
            rm -rf "$dir/run"
            run "$pma" train --data "$out/pma-data/train.npz" --out "$dir/run" \
                --config "$out/pma.toml" --minutes "$m" --quiet "${flags[@]}"
        elif [ "$prev" = 0 ]; then
            run "$pma" train --data "$out/pma-data/train.npz" --out "$dir/run" \
                --config "$out/pma.toml" --minutes "$span" --quiet "${flags[@]}"
        else
            run "$pma" train --data "$out/pma-data/train.npz" --out "$dir/run" --resume \
                --minutes "$span" --quiet
        fi
        cp "$dir/run/model.safetensors" "$dir/marks/${m}min.safetensors"
        cp "$dir/run/log.csv" "$dir/marks/${m}min.csv"
        prev="$m"
    done
done

# The official code trained the architecture and config pma trained.
last="${mark_list[${#mark_list[@]}-1]}"
run "$python" "$here/ttq_official.py" same-model "$out/official/official_${last}min.safetensors" \
    "$out/parity/marks/${last}min.safetensors"

# 4. Every model scored alike.
for m in "${mark_list[@]}"; do
    for r in official parity fast; do
        case "$r" in
            official) model="$out/official/official_${m}min.safetensors" ;;
            *) model="$out/$r/marks/${m}min.safetensors" ;;
        esac
        run "$pma" eval --model "$model" --data "$scene/novel_view.npz" --split novel_view \
            --max-images "$eval_images" --pngs 0 --out "$out/eval/${r}_${m}min" > /dev/null
    done
done

"$python" "$here/ttq_table.py" "$out" --marks "$marks" --json "$out/ttq.json" | tee "$out/ttq.md"
