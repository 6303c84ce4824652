"""How the process's C heap treats the engine's short-lived CPU tensors.

A CPU mapping iteration allocates and frees tens of megabytes of temporaries (``[samples, hidden]``
activations, gathered corner rows), tens of times per frame. PyTorch's CPU allocator takes them from the C
library's ``malloc``. With glibc's defaults a freed block that leaves more than its (dynamic) trim threshold
free at the top of the heap is handed back to the kernel, so the next iteration's allocation of the same size
faults every page in again (and the kernel zeroes each one). Measured on the 320x240 synthetic room, 100
frames, ``cpu`` preset, 2-core Intel Xeon (``python bench/bench_host_memory.py``, 3 pairs,
``bench/results/host_memory.json``): 283k-493k minor page faults during the frames with glibc's defaults
against 17k-19k with the limits below, 11.57 -> 12.25 frames/s (median; pairwise ratio 1.06), the same peak
resident memory (544 MB).

:func:`retain_freed_memory` sets two fixed limits with ``mallopt`` (glibc only; elsewhere it does nothing):
blocks up to :data:`MMAP_THRESHOLD_BYTES` come from the heap, and up to :data:`TRIM_THRESHOLD_BYTES` of freed
heap stay mapped for reuse. The cost is that much resident memory kept after a peak. It is process-wide and
idempotent; :class:`~.slam.SlamSystem` calls it when its device is the CPU (engine processes: ``voxfusion run``,
the server's workers). Set the environment variable ``VOXFUSION_HEAP_DEFAULTS=1`` to keep the C library's
defaults (a process where resident memory matters more than speed; the benchmark's reference runs).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import os
import sys

__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "retain_freed_memory"]

log = logging.getLogger(__name__)

MMAP_THRESHOLD_BYTES = 32 << 20
"""Allocations below this come from the heap, not from a fresh ``mmap`` (glibc's default starts at 128 KiB and
adapts upwards; setting it fixes it)."""
TRIM_THRESHOLD_BYTES = 64 << 20
"""Freed memory at the top of the heap kept mapped before it is returned to the kernel."""

_M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
_M_MMAP_THRESHOLD = -3


@functools.cache
def retain_freed_memory() -> bool:
    """Apply the heap limits once per process; True when they are in force (glibc), False where this C
    library has no ``mallopt``, refused a value, or ``VOXFUSION_HEAP_DEFAULTS`` is set. Later calls return the
    first call's answer (``mallopt`` is idempotent, so two first calls racing do no harm)."""
    if os.environ.get("VOXFUSION_HEAP_DEFAULTS", "") not in ("", "0"):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    if not ok:
        log.debug("mallopt refused the heap limits; the C library's defaults stay")
    return ok
