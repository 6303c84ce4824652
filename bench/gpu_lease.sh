#!/usr/bin/env bash
# The GPU benchmark suite at lease sizes (`bench/gpu_suite.py --lease`: every section in ~6-7 minutes) on a CUDA
# machine that has Python, PyTorch with CUDA, NumPy, SciPy, OpenCV and scikit-image but no internet and no
# voxfusion install: the missing wheels and 7-Scenes frames come from .gpu-kit (scripts/gpu_kit.sh, run first
# where pip works). Nothing is installed system-wide: the wheels go to a temporary folder on PYTHONPATH, and the
# voxfusion package is this checkout's folders laid out as pyproject.toml maps them (voxfusion.core = core/, ...).
#
# Usage: bash bench/gpu_lease.sh OUT_DIR [gpu_suite.py options]
#   writes OUT_DIR/gpu-<gpu>-lease.json (rewritten after every section, so a run cut short keeps what it
#   measured) and OUT_DIR/gpu-lease.log. PYTHON=... picks the interpreter (default python3). With --smoke it runs the
#   suite's CPU smoke sizes instead: the same setup, checked on a machine without CUDA.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: bash bench/gpu_lease.sh OUT_DIR [gpu_suite.py options]}
shift
PY=${PYTHON:-python3}
KIT=.gpu-kit
log() { printf '[gpu-lease] %s\n' "$*"; }

[ -d "$KIT/wheels" ] || { echo "no $KIT/wheels here: run 'bash scripts/gpu_kit.sh' where pip works" >&2; exit 1; }
mkdir -p "$OUT"
SITE=$(mktemp -d /tmp/voxfusion-site.XXXXXX)
"$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$SITE" "$KIT"/wheels/*.whl
mkdir -p "$SITE/voxfusion"
for entry in voxfusion/*; do
    ln -s "$PWD/$entry" "$SITE/voxfusion/"
done
for pkg in core server proto clients configs; do
    ln -s "$PWD/$pkg" "$SITE/voxfusion/$pkg"
done
export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1

"$PY" -P - <<'EOF'  # -P: not the current folder first, whose bare voxfusion/ would hide the layout above
import sys
import torch
import voxfusion.core  # noqa: F401  (the layout above works)
cuda = torch.cuda.is_available()
name = torch.cuda.get_device_name(0) if cuda else "none"
print(f"[gpu-lease] python {sys.version.split()[0]}, torch {torch.__version__}, CUDA {torch.version.cuda}, GPU: {name}")
EOF
SIZE=(--lease)
case " $* " in *" --smoke "*) SIZE=() ;; esac  # --smoke: the same setup checked on a machine without CUDA
SEVEN=()
[ -d "$KIT/sevenscenes_redkitchen" ] && SEVEN=(--sevenscenes "$KIT/sevenscenes_redkitchen")
log "bench/gpu_suite.py ${SIZE[*]} ${SEVEN[*]} $*"
"$PY" bench/gpu_suite.py "${SIZE[@]}" --out-dir "$OUT" "${SEVEN[@]}" "$@" 2>&1 | tee "$OUT/gpu-lease.log"
