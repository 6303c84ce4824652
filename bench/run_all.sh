#!/usr/bin/env bash
# The issue benchmarks, one after another (CPU presets); each writes bench/results/<name>.json.
# Usage: bash bench/run_all.sh [preset]   (default cpu-small; use `paper` on a GPU)
set -u
cd "$(dirname "$0")/.."
P=${1:-cpu-small}
PY=.venv/bin/python
mkdir -p bench/logs
$PY bench/run.py --synthetic --frames 100 --width 320 --height 240 --method baseline voxfusion-map voxfusion \
    --vf-config "$P" --name "synthetic_320x240_100f_$P" --no-progress > bench/logs/synthetic.log 2>&1
$PY bench/run.py --capture ../shared/data/tum_fr1_desk_9frames --method baseline voxfusion \
    --vf-config "$P" --vf-set mapping.max_depth_m=4.0 --name "tum_fr1_desk_9f_$P" --no-progress > bench/logs/tum.log 2>&1
$PY bench/run.py --capture ../shared/data/sevenscenes_redkitchen --max-frames 300 --method baseline voxfusion \
    --vf-config "$P" --vf-set mapping.max_depth_m=4.0 loss.w_color=0.1 tracking.rays=512 --name "sevenscenes_300f_$P" --no-progress \
    > bench/logs/sevenscenes.log 2>&1
# the real iPhone capture, all 942 frames, with and without the ARKit prior (iphone-small on CPU, iphone on a GPU)
if [ "$P" = "cpu-small" ]; then IP=iphone-small; else IP=iphone; fi
$PY bench/bench_stray.py --preset "$IP" > bench/logs/stray.log 2>&1
