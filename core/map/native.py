"""The map's compiled CPU kernel: trilinear interpolation of corner embeddings, forward and backward in one pass
over the points (``interpolation.c``), loaded with :mod:`ctypes`.

Why: a CPU mapping iteration evaluates the field at ~5000 samples, and PyTorch's version of the interpolation
(:func:`~.field.local_coords`, :func:`~.field.trilinear_weights`, the corner sum and their backward passes) is ~50
operators, each with its fixed overhead, and two serial ``index_add_`` passes: ~3 ms of a ~14 ms iteration on the
2-core AMD EPYC. The kernel does the same arithmetic in one loop per direction.

How: built on first use with the system's C compiler (``$CC``, else ``cc``; about a second) into the cache
(``$VOXFUSION_CACHE/native``, default ``~/.cache/voxfusion/native``), one file per source, compiler flags and CPU,
written under a temporary name and renamed, so concurrent processes never load a half-written library. Where no
compiler works, or ``VOXFUSION_NATIVE=0``, :func:`interpolation_kernels` returns None after one log line and
callers use the PyTorch operators (the reference the tests hold the kernel to, and what CUDA runs).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

log = logging.getLogger("voxfusion.map.native")

__all__ = ["SOURCE", "FLAGS", "InterpolationKernels", "interpolation_kernels", "cache_dir", "enabled"]

SOURCE = Path(__file__).with_name("interpolation.c")
"""The kernel's C source (installed with the package)."""

FLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-std=c99", "-shared", "-fPIC")
"""Compiler flags: optimised for the CPU it runs on (the library's name includes the CPU), no fused multiply-adds."""

ENV_SWITCH = "VOXFUSION_NATIVE"
"""Environment variable: ``0`` keeps every call on the PyTorch operators."""

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_F32 = ctypes.c_float


class InterpolationKernels:
    """The two entry points of ``interpolation.c`` with their argument types (pointers are ``tensor.data_ptr()``
    of contiguous CPU tensors; see the C file for shapes)."""

    def __init__(self, lib: ctypes.CDLL, path: Path) -> None:
        self.path = path
        self.forward = lib.vf_interpolate_forward
        self.forward.argtypes = [_P, _I64, _P, _P, _P, _P, _I64, _F32, _P, _P, _P]
        self.forward.restype = None
        self.backward = lib.vf_interpolate_backward
        self.backward.argtypes = [_P, _I64, _P, _P, _I64, _F32, _P, _P, _P, _P, _P]
        self.backward.restype = None


_lock = threading.Lock()
_loaded: dict[str, InterpolationKernels | None] = {}


def enabled() -> bool:
    """False when ``VOXFUSION_NATIVE=0``."""
    return os.environ.get(ENV_SWITCH, "1").strip() != "0"


def cache_dir() -> Path:
    """Where built libraries are kept: ``$VOXFUSION_CACHE/native``, default ``~/.cache/voxfusion/native``."""
    root = os.environ.get("VOXFUSION_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "voxfusion") / "native"


def _cpu_signature() -> str:
    """The CPU's model and instruction-set flags (``-march=native`` builds for them)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        keep = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(keep) or platform.processor()
    except OSError:
        return platform.processor() or platform.machine()


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def _build(cc: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.stem + ".", suffix=".tmp.so", dir=target.parent)
    os.close(fd)
    try:
        subprocess.run([cc, *FLAGS, str(SOURCE), "-o", tmp], check=True, capture_output=True, text=True, timeout=120)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def interpolation_kernels() -> InterpolationKernels | None:
    """The loaded kernels, built on first use; None where they are switched off or cannot be built (one log line
    says why, once per process)."""
    if not enabled():
        return None
    key = "interpolation"
    if key in _loaded:
        return _loaded[key]
    with _lock:
        if key in _loaded:
            return _loaded[key]
        kernels = None
        cc = _compiler()
        if cc is None:
            log.warning("no C compiler found ($CC, cc, gcc, clang): the map's interpolation runs as PyTorch "
                        "operators (slower on a CPU)")
        else:
            digest = hashlib.sha256("\n".join([SOURCE.read_text(), cc, *FLAGS, _cpu_signature()]).encode())
            target = cache_dir() / f"interpolation-{platform.machine()}-{digest.hexdigest()[:16]}.so"
            try:
                if not target.exists():
                    _build(cc, target)
                kernels = InterpolationKernels(ctypes.CDLL(str(target)), target)
            except (OSError, subprocess.SubprocessError) as exc:
                detail = getattr(exc, "stderr", "") or str(exc)
                log.warning("could not build the map's interpolation kernel with %s (%s): it runs as PyTorch "
                            "operators (slower on a CPU)", cc, detail.strip().splitlines()[-1] if detail else exc)
        _loaded[key] = kernels
        return kernels
