#!/usr/bin/env bash
# Rebuild vendor/candle-core from the published candle-core release plus pma's changes
# (candle-core.patch here; PATCH.md lists every hunk).
#
#   vendor/candle-core/update.sh            rebuild the vendored copy from the release
#                                           named in its Cargo.toml
#   vendor/candle-core/update.sh 0.11.2     the same from another release (then update the
#                                           workspace's candle-core/candle-nn versions)
#   vendor/candle-core/update.sh --check    rebuild into a temporary directory and compare
#                                           it with the vendored copy (diff -r; exit 1 if
#                                           they differ), changing nothing
#
# The release comes from cargo's registry cache; when it is not there, a scratch crate
# outside the workspace that depends on exactly that version is fetched with `cargo fetch`
# (the workspace's [patch] would otherwise replace it). Of the release, `Cargo.toml`,
# `LICENSE` and `src/` are kept; the manifest's example, test and bench targets, its
# dev-dependencies and its readme are dropped (their files are not vendored) and its
# generated header is replaced by ours. Then the patch is applied with `patch -p1`: a hunk that does not apply
# stops the script with patch's report and leaves the vendored copy as it was.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
check=0
version=""
for arg in "$@"; do
    case "$arg" in
        --check) check=1 ;;
        -h | --help)
            sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
            exit 0
            ;;
        -*) echo "update.sh: unknown option $arg" >&2; exit 2 ;;
        *) version="$arg" ;;
    esac
done
if [ -z "$version" ]; then
    version=$(sed -n '/^\[package\]/,/^\[/ s/^version = "\(.*\)"$/\1/p' "$here/Cargo.toml")
fi

cargo_home=${CARGO_HOME:-$HOME/.cargo}
find_release() {
    [ -d "$cargo_home/registry/src" ] || return 0
    find "$cargo_home/registry/src" -maxdepth 2 -type d -name "candle-core-$version" -print -quit
}
upstream=$(find_release)
if [ -z "$upstream" ]; then
    scratch=$(mktemp -d)
    trap 'rm -rf "$scratch"' EXIT
    mkdir -p "$scratch/src"
    : >"$scratch/src/lib.rs"
    cat >"$scratch/Cargo.toml" <<EOF
[package]
name = "candle-core-fetch"
version = "0.0.0"
edition = "2021"

[dependencies]
candle-core = { version = "=$version", default-features = false }
EOF
    echo "fetching candle-core $version" >&2
    (cd "$scratch" && cargo fetch --quiet)
    upstream=$(find_release)
    if [ -z "$upstream" ]; then
        echo "update.sh: candle-core $version is not in $cargo_home/registry/src after cargo fetch" >&2
        exit 1
    fi
fi

work=$(mktemp -d)
trap 'rm -rf "$work" ${scratch:+"$scratch"}' EXIT
out="$work/candle-core"
mkdir -p "$out"
cp -R "$upstream/src" "$upstream/LICENSE" "$out/"
{
    echo "# candle-core as published (the version below), with pma's five changes (see PATCH.md)."
    echo
    # Everything from [package] on, without the targets whose files are not vendored, the
    # dev-dependencies and the readme (not vendored either).
    awk '
        /^\[/ { skip = ($0 ~ /^\[\[(example|test|bench)\]\]/ || $0 ~ /^\[dev-dependencies/) }
        /^\[package\]/ { started = 1 }
        !started || skip { next }
        /^readme = / { next }
        { print }
    ' "$upstream/Cargo.toml"
} >"$out/Cargo.toml"
patch --quiet --no-backup-if-mismatch -p1 -d "$out" <"$here/candle-core.patch"
cp "$here/PATCH.md" "$here/candle-core.patch" "$here/update.sh" "$out/"

if [ "$check" = 1 ]; then
    if diff -r "$out" "$here"; then
        echo "vendor/candle-core is candle-core $version with candle-core.patch applied"
    else
        exit 1
    fi
else
    rm -rf "$here/src"
    cp -R "$out/src" "$here/"
    cp "$out/Cargo.toml" "$out/LICENSE" "$here/"
    echo "vendor/candle-core rebuilt from candle-core $version with candle-core.patch"
fi
