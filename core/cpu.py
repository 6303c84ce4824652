"""The CPU this process may use: one answer for the engine (realtime thread counts) and the benchmarks
(machine descriptions). Light: no torch import."""

from __future__ import annotations

import os

__all__ = ["usable_cpu_count"]


def usable_cpu_count() -> int:
    """CPU cores this process may run on: its affinity where the platform reports one, else
    ``os.cpu_count()`` (at least 1)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
