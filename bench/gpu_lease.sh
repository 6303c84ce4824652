#!/usr/bin/env bash
# The GPU benchmark suite at lease sizes (`bench/gpu_suite.py --lease`: every section, no section started after
# 360 s) on a CUDA machine that has Python, PyTorch with CUDA, NumPy, SciPy, OpenCV, scikit-image, PyYAML, Pillow,
# tqdm and typer but no internet and no voxfusion install: the missing wheels and 7-Scenes frames come from .gpu-kit (scripts/gpu_kit.sh, run first
# where pip works). Nothing is installed system-wide: the wheels go to a temporary folder on PYTHONPATH, and the
# voxfusion package is this checkout's folders laid out as pyproject.toml maps them (voxfusion.core = core/, ...).
#
# Usage: [GPU_PYTEST="TEST_PATHS"] [GPU_PROFILE=1] bash bench/gpu_lease.sh OUT_DIR [gpu_suite.py options]
#   GPU_PYTEST: run these tests with pytest first (their CUDA tests; OUT_DIR/gpu-pytest.log); GPU_PROFILE=1: then,
#   after the suite, bench/gpu_profile.py (OUT_DIR/gpu-profile.log); GPU_COMPILE_WARMUP=1: then
#   bench/bench_compile_warmup.py (OUT_DIR/compile-warmup*.json and .log); the suite
#   writes OUT_DIR/gpu-<gpu>-lease.json (rewritten after every section, so a run cut short keeps what it
#   measured) and OUT_DIR/gpu-lease.log. PYTHON=... picks the interpreter (default python3). With --smoke it runs the
#   suite's CPU smoke sizes instead: the same setup, checked on a machine without CUDA.
set -euo pipefail
OUT=${1:?usage: bash bench/gpu_lease.sh OUT_DIR [gpu_suite.py options]}
shift
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)  # before the cd below: a relative OUT_DIR is the caller's
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
KIT=.gpu-kit
log() { printf '[gpu-lease] %s\n' "$*"; }

[ -d "$KIT/wheels" ] || { echo "no $KIT/wheels here: run 'bash scripts/gpu_kit.sh' where pip works" >&2; exit 1; }
# the kit's wheels are built for one Python (cp312 by default): say so plainly rather than through pip's refusal
kit_py=$(cd "$KIT/wheels" && ls ./*-cp3*.whl 2>/dev/null | sed -n 's/.*-cp3\([0-9]*\)-.*/3.\1/p' | head -1)
here_py=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
if [ -n "$kit_py" ] && [ "$kit_py" != "$here_py" ]; then
    echo "the kit's wheels are for Python $kit_py, $PY is $here_py: rebuild it with 'bash scripts/gpu_kit.sh --python $here_py'" >&2
    exit 1
fi
SITE=$(mktemp -d /tmp/voxfusion-site.XXXXXX)
trap 'rm -rf "$SITE"' EXIT
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
if [ -n "${GPU_PYTEST:-}" ]; then  # the CUDA tests first, e.g. GPU_PYTEST="tests/core/test_tracking_graphs.py"
    # -c /dev/null: not pyproject.toml's pythonpath ["."], whose bare voxfusion/ would hide the layout above
    # shellcheck disable=SC2086
    "$PY" -P -m pytest -q -rs -c /dev/null -p no:cacheprovider $GPU_PYTEST 2>&1 | tee "$OUT/gpu-pytest.log" || true
fi
SIZE=(--lease)
case " $* " in *" --smoke "*) SIZE=() ;; esac  # --smoke: the same setup checked on a machine without CUDA
SEVEN=()
[ -d "$KIT/sevenscenes_redkitchen" ] && SEVEN=(--sevenscenes "$KIT/sevenscenes_redkitchen")
log "bench/gpu_suite.py ${SIZE[*]} ${SEVEN[*]} $*"
"$PY" bench/gpu_suite.py "${SIZE[@]}" --out-dir "$OUT" "${SEVEN[@]}" "$@" 2>&1 | tee "$OUT/gpu-lease.log"
if [ -n "${GPU_PROFILE:-}" ]; then  # where a frame's time goes, the tracker's graphs on and off (~1 minute)
    "$PY" -P bench/gpu_profile.py 2>&1 | tee "$OUT/gpu-profile.log" || true
fi
if [ -n "${GPU_COMPILE_WARMUP:-}" ]; then  # mapping.compile's warm-up in fresh processes, cache cold then warm (~1.5 min)
    "$PY" -P bench/bench_compile_warmup.py --out-dir "$OUT" 2>&1 | tee "$OUT/compile-warmup.log" || true
fi
