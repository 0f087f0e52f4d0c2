#!/bin/bash
# Make the working tree fit what a GPU session carries, and put it back after.
#
#   scripts/gpu-session.sh leave      before the session's device call
#   scripts/gpu-session.sh restore    after it (also safe to run twice)
#   scripts/gpu-session.sh size       what would travel now, in bytes
#
# A GPU session sends the tracked files and the untracked ones git does not ignore, 64 MiB in
# all with the carried kit (target-cuda/gpu-kit.tar.xz, ~16 MB). The tracked files alone are
# ~66 MB: the golden case (38 MB with the official checkpoint that bench/official reads), its
# dense variant, LPIPS's weights, the vendored candle. `leave` takes what scripts/gpu-check.sh
# does not read out of the index (the files stay on disk, untouched) and ignores them in
# .git/info/exclude, so they stay behind; `restore` puts both back. Commit nothing in between:
# the index then says they were deleted.
set -euo pipefail
cd "$(dirname "$0")/.."
# Not read on the GPU machine: the binaries embed LPIPS's weights and the plot font; the
# doctor reads fixtures/golden without its dense variant; the official harness reads
# fixtures/golden (ckpt.th included) and bench/official.
LEAVE=(assets vendor docs fixtures/lpips fixtures/capture fixtures/convert fixtures/layers fixtures/golden/dense)
EXCLUDE=$(git rev-parse --git-common-dir)/info/exclude
MARK="# scripts/gpu-session.sh leave"

size() {
  {
    git ls-files -z
    git ls-files -z --others --exclude-standard
  } | xargs -0 -r du -cb 2>/dev/null | tail -1 | cut -f1
}

case "${1:-}" in
  leave)
    grep -qxF "$MARK" "$EXCLUDE" 2>/dev/null && { echo "gpu-session: already left (run restore first)" >&2; exit 2; }
    mkdir -p "$(dirname "$EXCLUDE")"
    git rm -r -q --cached --ignore-unmatch -- "${LEAVE[@]}"
    { echo "$MARK"; printf '/%s/\n' "${LEAVE[@]}"; echo "$MARK end"; } >> "$EXCLUDE"
    echo "gpu-session: $(size) bytes travel, plus the carried kit; run restore after the device call"
    ;;
  restore)
    git reset -q -- "${LEAVE[@]}"
    if [ -f "$EXCLUDE" ]; then
      sed -i "\|^$MARK\$|,\|^$MARK end\$|d" "$EXCLUDE"
    fi
    echo "gpu-session: restored; $(size) bytes tracked or untracked"
    ;;
  size)
    size
    ;;
  *)
    echo "usage: scripts/gpu-session.sh leave|restore|size" >&2
    exit 2
    ;;
esac
