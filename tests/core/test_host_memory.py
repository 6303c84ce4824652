"""The engine's C-heap limits (core/host_memory.py): applied once per process by a CPU engine, skipped on
request. Each case runs in a fresh interpreter: the limits are process-wide."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

GLIBC = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"


def _run(code: str, **env: str) -> subprocess.CompletedProcess:
    full_env = {k: v for k, v in os.environ.items() if k != "VOXFUSION_HEAP_DEFAULTS"} | env
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=full_env)


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_a_cpu_engine_applies_the_heap_limits_once():
    code = ("from voxfusion.core import host_memory\n"
            "assert host_memory.retain_freed_memory.cache_info().misses == 0, 'applied at import'\n"
            "from voxfusion.core.slam import SlamSystem\n"
            "from voxfusion.core.slam.presets import load_preset\n"
            "SlamSystem(load_preset('cpu'))\n"
            "assert host_memory.retain_freed_memory.cache_info().misses == 1\n"
            "assert host_memory.retain_freed_memory() is True\n")
    done = _run(code)
    assert done.returncode == 0, done.stderr


def test_the_environment_keeps_the_c_librarys_defaults():
    code = ("from voxfusion.core import host_memory\n"
            "from voxfusion.core.slam import SlamSystem\n"
            "from voxfusion.core.slam.presets import load_preset\n"
            "SlamSystem(load_preset('cpu'))\n"
            "assert host_memory.retain_freed_memory.cache_info().misses == 1\n"
            "assert host_memory.retain_freed_memory() is False\n")
    done = _run(code, VOXFUSION_HEAP_DEFAULTS="1")
    assert done.returncode == 0, done.stderr
