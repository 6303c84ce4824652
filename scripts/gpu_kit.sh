#!/usr/bin/env bash
# Pack what a CUDA machine without internet needs to run the GPU benchmark suite from this checkout
# (`bash bench/gpu_lease.sh OUT_DIR` there), into .gpu-kit/ (git-ignored; copy or carry it with the checkout):
#
#   * .gpu-kit/wheels/: the engine's Python dependencies that a CUDA image with PyTorch, NumPy, SciPy, OpenCV and
#     scikit-image usually lacks (trimesh, rtree, embreex for the synthetic room's ray casting, lzfse), built for
#     that machine's Python (--python, default 3.12) on x86-64 Linux, at the versions this checkout's .venv has;
#   * .gpu-kit/sevenscenes_redkitchen/: the first frames of ../shared/data/sevenscenes_redkitchen (the realtime
#     section's real capture, played back and forth), as many as keep the working tree plus the kit under
#     --max-mib (default 60: such a copy is often capped at 64 MiB).
#
# Usage: bash scripts/gpu_kit.sh [--python 3.12] [--max-mib 60] [--max-frames 150]
# Needs pip's access to PyPI (run it where `make setup` works). Prints the kit's size and what travels.
set -euo pipefail
cd "$(dirname "$0")/.."

PYVER=3.12
MAX_MIB=60
MAX_FRAMES=150
while [ $# -gt 0 ]; do
    case $1 in
        --python) PYVER=$2; shift 2 ;;
        --max-mib) MAX_MIB=$2; shift 2 ;;
        --max-frames) MAX_FRAMES=$2; shift 2 ;;
        *) echo "usage: bash scripts/gpu_kit.sh [--python 3.12] [--max-mib 60] [--max-frames 150]" >&2; exit 2 ;;
    esac
done
KIT=.gpu-kit
PACKAGES=(trimesh rtree embreex lzfse)
VENV_PY=.venv/bin/python
log() { printf '\033[1m[gpu-kit]\033[0m %s\n' "$*"; }

git rev-parse --git-dir >/dev/null 2>&1 || { echo "run it in a git checkout (it measures what travels with git)" >&2; exit 1; }
[ -x "$VENV_PY" ] || { echo "no .venv here: run 'make setup' first (the kit takes the versions it has)" >&2; exit 1; }
NEW=$(mktemp -d "${TMPDIR:-/tmp}/gpu-kit.XXXXXX")  # built aside, replacing the old kit only once complete
trap 'rm -rf "$NEW"' EXIT
mkdir -p "$NEW/wheels"

# the versions this checkout runs with, so the GPU machine runs the same ones
mapfile -t PINS < <("$VENV_PY" - "${PACKAGES[@]}" <<'EOF'
import importlib.metadata as md
import sys
for name in sys.argv[1:]:
    print(f"{name}=={md.version(name)}")
EOF
)
log "wheels for Python $PYVER (x86-64 Linux): ${PINS[*]}"
PLATFORMS=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_24_x86_64 manylinux_2_17_x86_64 \
         manylinux2014_x86_64 manylinux1_x86_64; do
    PLATFORMS+=(--platform "$p")
done
"$VENV_PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
    "${PLATFORMS[@]}" -d "$NEW/wheels" "${PINS[@]}" 2>&1 | grep -v "^WARNING: Location '.*' is ignored" || true
n_wheels=$(find "$NEW/wheels" -name '*.whl' | wc -l)
[ "$n_wheels" -eq "${#PACKAGES[@]}" ] || { echo "expected ${#PACKAGES[@]} wheels, got $n_wheels" >&2; exit 1; }

# what travels besides the kit: the tracked files and the untracked ones git does not ignore
tree_kib=$(git ls-files -z --cached --others --exclude-standard | xargs -0 -r du -k 2>/dev/null \
           | awk '{s += $1} END {print s + 0}' || true)  # files listed but deleted here are left out
wheels_kib=$(du -sk "$NEW/wheels" | cut -f1)
left_kib=$((MAX_MIB * 1024 - tree_kib - wheels_kib))

SRC=../shared/data/sevenscenes_redkitchen
if [ -d "$SRC" ]; then
    DST="$NEW/sevenscenes_redkitchen"
    mkdir -p "$DST"
    cp "$SRC/camera-intrinsics.txt" "$DST/" 2>/dev/null || true
    n=0
    used=$(du -sk "$DST" | cut -f1)
    for color in "$SRC"/frame-*.color.*; do
        [ "$n" -lt "$MAX_FRAMES" ] || break
        stem=${color%.color.*}
        frame_kib=$(du -ck "$stem".* | tail -1 | cut -f1)
        [ $((used + frame_kib)) -le "$left_kib" ] || break
        cp "$stem".* "$DST/"
        used=$((used + frame_kib))
        n=$((n + 1))
    done
    log "7-Scenes redkitchen: the first $n frames ($((used / 1024)) MiB)"
    [ "$n" -ge 30 ] || echo "[gpu-kit] warning: only $n 7-Scenes frames fit in --max-mib $MAX_MIB" >&2
else
    log "no $SRC: the realtime section will run the synthetic room only"
fi
rm -rf "$KIT"
mv "$NEW" "$KIT"
trap - EXIT
kit_kib=$(du -sk "$KIT" | cut -f1)
log "kit $((kit_kib / 1024)) MiB + working tree $((tree_kib / 1024)) MiB = $(((kit_kib + tree_kib) / 1024)) MiB" \
    "(of --max-mib $MAX_MIB)"
log "there: bash bench/gpu_lease.sh OUT_DIR   (with .gpu-kit beside the checkout's files)"
