#!/usr/bin/env bash
# Set up everything voxfusion needs on a fresh machine: system libraries, a virtual environment in .venv,
# PyTorch (pinned CPU build 2.13.0 where there is no NVIDIA GPU, the regular CUDA build where there is),
# and the project with its extras. Idempotent: re-running only fills in what is missing.
#
# It prints one [bootstrap] line per step; what apt-get and pip print goes to .venv/bootstrap.log (rewritten
# by every run). When a step fails it prints the end of that log and its path.
#
# Environment overrides:
#   PYTHON=python3.11        interpreter used to create .venv (>= 3.11)
#   VOXFUSION_TORCH="torch==2.13.0"   the torch requirement to install (e.g. a CUDA build pin)
#   VOXFUSION_EXTRAS="baseline,test,server,iphone,cluster"   extras of the voxfusion distribution to install
#   VOXFUSION_SKIP_APT=1     do not install system packages (you manage them yourself)
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
EXTRAS=${VOXFUSION_EXTRAS:-baseline,test,server,iphone,cluster}
# gcc and libc6-dev build the engine's CPU kernels (core/native/*.c) on first use; without them the engine runs the
# PyTorch operators those kernels replace (slower on a CPU)
SYSTEM_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libglx0 libgomp1 libx11-6 curl gcc libc6-dev)
# The headless browser of the viewer's tests (tests/server/browser.py, scripts/viewer_screenshot.py), Debian's
# names. Optional: when it cannot be installed, setup goes on with a warning and those tests are skipped.
BROWSER_PACKAGES=(chromium chromium-driver)
LOG=.venv/bootstrap.log

log() { printf '\033[1m[bootstrap]\033[0m %s\n' "$*"; }
warn() { printf '\033[1;33m[bootstrap] warning:\033[0m %s\n' "$*" >&2; }

mkdir -p .venv
: >"$LOG"
START=$SECONDS

# The end of the log, then its path, and stop. pip's "WARNING: Location 'file:///...' is ignored" lines (a
# local file:// index in the machine's pip configuration that lacks a package; harmless) are left out.
fail() {
    log "failed: $1"
    {
        echo "---- last lines of $LOG ----"
        grep -v "^WARNING: Location '.*' is ignored" "$LOG" | tail -n 30
        echo "---- the whole log: $LOG ----"
    } >&2
    exit 1
}

# logged CMD...: run a command with its output in the log; its exit status is the command's.
logged() {
    printf '\n$ %s\n' "$*" >>"$LOG"
    "$@" >>"$LOG" 2>&1
}

# step WHAT CMD...: a step that must succeed.
step() {
    local what=$1
    shift
    logged "$@" || fail "$what"
}

missing_packages() {
    local p
    for p in "$@"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || echo "$p"
    done
}

install_system_packages() {
    if [ "${VOXFUSION_SKIP_APT:-0}" = 1 ]; then return; fi
    if ! command -v dpkg-query >/dev/null 2>&1; then
        log "not a Debian/Ubuntu system: make sure these libraries are installed: ${SYSTEM_PACKAGES[*]}" \
            "(and a Chromium with its chromedriver for the viewer's browser tests)"
        return
    fi
    local missing browser
    mapfile -t missing < <(missing_packages "${SYSTEM_PACKAGES[@]}")
    mapfile -t browser < <(missing_packages "${BROWSER_PACKAGES[@]}")
    if [ ${#missing[@]} -eq 0 ] && [ ${#browser[@]} -eq 0 ]; then return; fi
    local sudo=() sudo_n=()
    if [ "$(id -u)" != 0 ]; then
        if command -v sudo >/dev/null 2>&1; then
            sudo=(sudo)
            sudo_n=(sudo -n)  # never ask a password for the optional browser
        elif [ ${#missing[@]} -gt 0 ]; then
            log "missing system packages ${missing[*]} and no root/sudo: install them and re-run"; exit 1
        else
            warn "no root/sudo to install ${browser[*]}: the viewer's browser tests will be skipped"
            return
        fi
    fi
    local updated=0
    if [ ${#missing[@]} -gt 0 ]; then
        log "installing system packages: ${missing[*]}"
        step "apt-get update" "${sudo[@]}" apt-get update -q
        updated=1
        step "installing ${missing[*]}" "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive \
            apt-get install -y -q --no-install-recommends "${missing[@]}"
    fi
    if [ ${#browser[@]} -gt 0 ]; then
        log "installing the viewer tests' browser: ${browser[*]}"
        if ! { [ $updated = 1 ] || logged "${sudo_n[@]}" apt-get update -q; } \
            || ! logged "${sudo_n[@]}" env DEBIAN_FRONTEND=noninteractive \
                apt-get install -y -q --no-install-recommends "${browser[@]}"; then
            warn "could not install ${browser[*]} (details in $LOG): the viewer's browser tests will be skipped"
        fi
    fi
}

has_nvidia_gpu() { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }

PIP=(.venv/bin/python -m pip --disable-pip-version-check)

install_system_packages

if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' || {
        log "Python >= 3.11 is required (found $("$PYTHON" --version 2>&1)); set PYTHON=..."; exit 1; }
    log "creating .venv with $("$PYTHON" --version)"
    step "creating .venv" "$PYTHON" -m venv .venv
    step "upgrading pip" "${PIP[@]}" install --progress-bar off --upgrade pip setuptools
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
    step "installing $torch_req" "${PIP[@]}" install --progress-bar off "$torch_req"
fi

log "installing voxfusion[$EXTRAS] (editable)"
step "installing voxfusion[$EXTRAS]" "${PIP[@]}" install --progress-bar off -e ".[$EXTRAS]"
versions=$(.venv/bin/python -c 'import torch, voxfusion; print(f"torch {torch.__version__}, cuda={torch.cuda.is_available()}")' \
    2>>"$LOG") || fail "importing torch and voxfusion"
log "ready in $((SECONDS - START)) s: $versions (log: $LOG)"
