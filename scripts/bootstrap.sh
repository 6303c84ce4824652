#!/usr/bin/env bash
# Set up everything voxfusion needs on a fresh machine: system libraries, a virtual environment in .venv,
# PyTorch (pinned CPU build 2.13.0 where there is no NVIDIA GPU, the regular CUDA build where there is),
# and the project with its extras. Idempotent: re-running only fills in what is missing.
#
# Environment overrides:
#   PYTHON=python3.11        interpreter used to create .venv (>= 3.11)
#   VOXFUSION_TORCH="torch==2.13.0"   the torch requirement to install (e.g. a CUDA build pin)
#   VOXFUSION_EXTRAS="baseline,test,server,iphone"   extras of the voxfusion distribution to install
#   VOXFUSION_SKIP_APT=1     do not install system packages (you manage them yourself)
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
EXTRAS=${VOXFUSION_EXTRAS:-baseline,test,server,iphone}
SYSTEM_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libglx0 libgomp1 libx11-6 curl)

log() { printf '\033[1m[bootstrap]\033[0m %s\n' "$*"; }

install_system_packages() {
    if [ "${VOXFUSION_SKIP_APT:-0}" = 1 ]; then return; fi
    if ! command -v dpkg-query >/dev/null 2>&1; then
        log "not a Debian/Ubuntu system: make sure these libraries are installed: ${SYSTEM_PACKAGES[*]}"
        return
    fi
    local missing=()
    for p in "${SYSTEM_PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
    done
    [ ${#missing[@]} -eq 0 ] && return
    local sudo=""
    if [ "$(id -u)" != 0 ]; then
        if command -v sudo >/dev/null 2>&1; then sudo="sudo"; else
            log "missing system packages ${missing[*]} and no root/sudo: install them and re-run"; exit 1
        fi
    fi
    log "installing system packages: ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

has_nvidia_gpu() { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }

install_system_packages

if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' || {
        log "Python >= 3.11 is required (found $("$PYTHON" --version 2>&1)); set PYTHON=..."; exit 1; }
    log "creating .venv with $("$PYTHON" --version)"
    "$PYTHON" -m venv .venv
    .venv/bin/python -m pip install -q --upgrade pip setuptools wheel
fi

if ! .venv/bin/python -c 'import torch' >/dev/null 2>&1; then
    if [ -n "${VOXFUSION_TORCH:-}" ]; then
        torch_req=$VOXFUSION_TORCH
    elif has_nvidia_gpu; then
        torch_req="torch"          # the regular PyPI build ships CUDA
    else
        torch_req="torch==2.13.0"  # pinned CPU build; an unpinned torch pulls gigabytes of CUDA packages
    fi
    log "installing $torch_req"
    .venv/bin/python -m pip install -q "$torch_req"
fi

log "installing voxfusion[$EXTRAS] (editable)"
.venv/bin/python -m pip install -q -e ".[$EXTRAS]"
.venv/bin/python -c 'import torch, voxfusion; print(f"[bootstrap] ready: torch {torch.__version__}, cuda={torch.cuda.is_available()}")'
