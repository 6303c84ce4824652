"""What machine a benchmark ran on, and how much memory a block of code used at its peak.

Every figure in ``bench/results/`` is stored beside :func:`machine_info` (no hostname, no user name):
absolute times only mean something together with the CPU / GPU they were measured on.

Peak memory (:class:`PeakMemory`) is the resident set size (RSS) of this process, read from ``psutil``
when it is installed and from ``/proc/self/statm`` otherwise (Linux), sampled by a background thread
every ``interval_s`` (20 ms) and whenever :meth:`PeakMemory.sample` is called. A sampling thread can
miss a short spike inside a long C++ call that holds the GIL, so the process's lifetime high-water mark
``resource.getrusage(RUSAGE_SELF).ru_maxrss`` is read too: when it grew during the block, the block set
a new process-wide peak and that exact figure is used. On CUDA, ``torch.cuda.max_memory_allocated`` is
reported as well (only when ``torch`` was already imported: measuring never imports it).

Example::

    with PeakMemory() as mem:
        run_something()
    print(mem.result.increase_mb, mem.result.peak_rss_mb)
"""

from __future__ import annotations

import os
import platform
import sys
import threading
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from voxfusion.core.cpu import usable_cpu_count

__all__ = ["MemoryUsage", "PeakMemory", "current_rss_mb", "machine_info"]

_MB = 1024.0 * 1024.0


def _read_text(path: str) -> str | None:
    try:
        return Path(path).read_text()
    except OSError:
        return None


def _cpu_model() -> str:
    text = _read_text("/proc/cpuinfo")
    if text:
        for line in text.splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware", "cpu model"):
                return value.strip()
    return platform.processor() or platform.machine() or "unknown"


def _ram_total_gb() -> float | None:
    text = _read_text("/proc/meminfo")
    if text:
        for line in text.splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / (1024.0 * 1024.0), 2)
    try:
        import psutil
    except ImportError:
        return None
    return round(psutil.virtual_memory().total / (1024.0**3), 2)


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def machine_info() -> dict[str, object]:
    """Describe this machine and the software stack, without hostname or user names.

    Returns:
        A JSON-ready dict: ``cpu_model``, ``cpu_logical_cores``, ``cpu_usable_cores`` (this process's
        affinity), ``ram_total_gb``, ``os``, ``python``, versions of ``numpy``, ``torch``, ``open3d``,
        ``trimesh`` (``None`` when not installed), ``cuda_available`` and ``cuda_device`` (name and
        memory of GPU 0, or ``None``).
    """
    info: dict[str, object] = {
        "cpu_model": _cpu_model(),
        "cpu_logical_cores": os.cpu_count(),
        "cpu_usable_cores": usable_cpu_count(),
        "ram_total_gb": _ram_total_gb(),
        "os": f"{platform.system()} {platform.release()} ({platform.machine()})",
        "python": platform.python_version(),
        "numpy": _version("numpy"),
        "torch": _version("torch"),
        "open3d": _version("open3d") or _version("open3d-cpu"),
        "trimesh": _version("trimesh"),
        "cuda_available": False,
        "cuda_device": None,
    }
    try:
        import torch
    except ImportError:
        return info
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        info["cuda_available"] = True
        info["cuda_device"] = {
            "name": props.name,
            "memory_gb": round(props.total_memory / (1024.0**3), 2),
            "count": torch.cuda.device_count(),
            "cuda_version": torch.version.cuda,
        }
    return info


def current_rss_mb() -> float:
    """Resident set size of this process now, in MiB (psutil, else ``/proc/self/statm``).

    Falls back to the lifetime peak ``ru_maxrss`` where neither is available (not Linux, no psutil).
    """
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        return psutil.Process().memory_info().rss / _MB
    text = _read_text("/proc/self/statm")
    if text:
        return int(text.split()[1]) * os.sysconf("SC_PAGE_SIZE") / _MB
    return _ru_maxrss_mb()


def _ru_maxrss_mb() -> float:
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / _MB if sys.platform == "darwin" else peak / 1024.0  # bytes on macOS, KiB elsewhere


def _torch_cuda():
    torch = sys.modules.get("torch")
    if torch is None:
        return None
    try:
        return torch.cuda if torch.cuda.is_available() else None
    except Exception:  # a broken CUDA setup must not break a CPU benchmark
        return None


@dataclass(frozen=True)
class MemoryUsage:
    """Memory used by a measured block (MiB).

    Attributes:
        start_rss_mb: RSS when the block started.
        peak_rss_mb: highest RSS seen during the block (absolute, includes everything the process
            held before: Python, imported libraries).
        increase_mb: ``peak_rss_mb - start_rss_mb``: what the block itself added at its peak.
        cuda_peak_mb: ``torch.cuda.max_memory_allocated`` during the block, or ``None`` without CUDA.
        n_samples: RSS readings taken.
        method: how RSS was read (``"psutil"``, ``"/proc/self/statm"`` or ``"ru_maxrss"``), with
            ``"+ru_maxrss"`` when the lifetime high-water mark raised the peak.
    """

    start_rss_mb: float
    peak_rss_mb: float
    increase_mb: float
    cuda_peak_mb: float | None
    n_samples: int
    method: str


class PeakMemory:
    """Context manager measuring the peak RSS (and CUDA allocation) of a block; see the module docstring.

    Args:
        interval_s: background sampling period in seconds (default 20 ms); ``0`` disables the thread
            (only :meth:`sample` calls and the start / end readings count).
    """

    def __init__(self, interval_s: float = 0.02) -> None:
        if not interval_s >= 0:
            raise ValueError(f"interval_s must be >= 0 seconds, got {interval_s}")
        self.interval_s = interval_s
        self._peak = 0.0
        self._start = 0.0
        self._n = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._maxrss_start = 0.0
        self._cuda = None
        self.result: MemoryUsage | None = None

    @staticmethod
    def _method() -> str:
        try:
            import psutil  # noqa: F401
        except ImportError:
            return "/proc/self/statm" if Path("/proc/self/statm").exists() else "ru_maxrss"
        return "psutil"

    def sample(self) -> float:
        """Take one RSS reading now (MiB), update the peak and return the reading."""
        rss = current_rss_mb()
        with self._lock:
            self._n += 1
            if rss > self._peak:
                self._peak = rss
        return rss

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    def __enter__(self) -> PeakMemory:
        self.result = None
        self._stop.clear()
        self._n = 0
        self._start = current_rss_mb()
        self._peak = self._start
        self._maxrss_start = _ru_maxrss_mb()
        self._cuda = _torch_cuda()
        if self._cuda is not None:
            self._cuda.synchronize()
            self._cuda.reset_peak_memory_stats()
        if self.interval_s > 0:
            self._thread = threading.Thread(target=self._run, name="PeakMemory", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.sample()
        method = self._method()
        peak = self._peak
        maxrss_end = _ru_maxrss_mb()
        if maxrss_end > self._maxrss_start + 1e-9 and maxrss_end > peak:
            peak = maxrss_end
            method += "+ru_maxrss"
        cuda_peak = None
        if self._cuda is not None:
            self._cuda.synchronize()
            cuda_peak = self._cuda.max_memory_allocated() / _MB
        self.result = MemoryUsage(
            start_rss_mb=self._start,
            peak_rss_mb=peak,
            increase_mb=max(0.0, peak - self._start),
            cuda_peak_mb=cuda_peak,
            n_samples=self._n,
            method=method,
        )
