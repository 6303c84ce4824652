"""The engine's compiled CPU kernels, loaded with :mod:`ctypes`: plain C files beside this module, each the fast path
of PyTorch operators that stay the reference (the tests hold each kernel to them, and CUDA runs them).

* ``interpolation.c``: trilinear interpolation of a voxel map's corner embeddings, forward and backward
  (:func:`interpolation_kernels`, used by :mod:`..map.field`);
* ``band_losses.c``: a mapping iteration's compositing and loss terms, forward and backward
  (:func:`band_loss_kernels`, used by :func:`..losses.band_losses`);
* ``depth_support.c``: the depth filter's neighbourhood support (:func:`depth_support_kernels`, used by
  :func:`..depth_filter.depth_support`), every frame's first step.

Why: on a CPU, a mapping iteration (~5000 samples) through PyTorch is ~400 small operators, each with a fixed
overhead of several microseconds, and a few serial ``index_add_`` passes; a loop in C does the same arithmetic
without them (numbers in the users' docstrings and ``docs/engine-history.md``).

How: each source is built on first use with the system's C compiler (``$CC``, else ``cc``, ``gcc`` or ``clang``;
about a second) into ``native/`` of the engine's cache (:func:`~..precompiled.cache_root`: ``$VOXFUSION_CACHE_DIR``,
default ``~/.cache/voxfusion``), one file per source, compiler, flags and CPU, written under a temporary name and
renamed, so concurrent processes never load a half-written library. Each build also deletes that kernel's older
libraries beyond the newest :data:`KEEP_LIBRARIES` (every change to a source, the compiler or the CPU makes a new
one) and build files a crashed build left behind (:func:`prune`). Where no compiler works, or with
``VOXFUSION_NATIVE=0``, the accessors return None (after one log line per source and process) and callers run the
PyTorch operators.
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
import time
from pathlib import Path

from ..precompiled import cache_root

log = logging.getLogger("voxfusion.native")

__all__ = ["FLAGS", "ENV_SWITCH", "KEEP_LIBRARIES", "Kernels", "interpolation_kernels", "band_loss_kernels",
           "depth_support_kernels", "cache_dir", "enabled", "prune"]

SOURCE_DIR = Path(__file__).resolve().parent
"""Where the C sources are (installed with the package)."""

FLAGS = ("-O3", "-march=native", "-ffp-contract=off", "-std=c99", "-shared", "-fPIC")
"""Compiler flags: optimised for the CPU it runs on (the library's name includes the CPU), and no fused
multiply-adds, which PyTorch's CPU kernels do not make either."""

ENV_SWITCH = "VOXFUSION_NATIVE"
"""Environment variable: ``0`` keeps every call on the PyTorch operators (read at every call; the tests switch it)."""

KEEP_LIBRARIES = 4
"""Libraries of one kernel (per machine architecture) a cache keeps, the newest builds; older ones are deleted when
a new one is built (:func:`prune`). A process that has one loaded keeps using it (the file's data stays until it
closes it); a checkout that needs a deleted one rebuilds it in about a second."""

_STALE_BUILD_S = 600.0
"""A temporary build file older than this belongs to a build that died (a build takes about a second)."""

_P, _I64, _F32, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_int

_SIGNATURES: dict[str, dict[str, tuple[list, object]]] = {
    "interpolation": {
        "vf_interpolate_forward": ([_P, _I64, _P, _P, _I64, _P, _P, _I64, _F32, _P, _P, _P], _INT),
        "vf_interpolate_backward": ([_P, _I64, _P, _P, _I64, _F32, _P, _P, _P, _P, _P], None),
    },
    "band_losses": {
        "vf_band_losses_forward": ([_P, _P, _P, _P, _P, _P, _P, _P, _I64, _I64, _F32, _F32, _P, _P, _P], _INT),
        "vf_band_losses_backward": ([_P, _P, _P, _P, _P, _P, _P, _P, _I64, _I64, _F32, _F32, _P, _P, _P, _P], _INT),
    },
    "depth_support": {
        "vf_depth_support": ([_P, _I64, _I64, _I64, _F32, _P], None),
    },
}
"""Each source's entry points: argument types (pointers are ``tensor.data_ptr()`` of contiguous CPU tensors) and
return type; shapes are documented in the C files."""


class Kernels:
    """A loaded library's entry points as attributes without their ``vf_`` prefix (``kernels.interpolate_forward``)."""

    def __init__(self, name: str, lib: ctypes.CDLL, path: Path) -> None:
        self.name, self.path = name, path
        for symbol, (argtypes, restype) in _SIGNATURES[name].items():
            fn = getattr(lib, symbol)
            fn.argtypes, fn.restype = argtypes, restype
            setattr(self, symbol.removeprefix("vf_"), fn)


_lock = threading.Lock()
_loaded: dict[str, Kernels | None] = {}


def enabled() -> bool:
    """False when ``VOXFUSION_NATIVE`` is ``0`` (or ``false``, ``no``, ``off``), as ``VOXFUSION_PRECOMPILE``."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir() -> Path:
    """Where built libraries are kept: ``native/`` of the engine's cache (:func:`~..precompiled.cache_root`)."""
    return cache_root() / "native"


def _cpu_signature() -> str:
    """The CPU's model and instruction-set flags (``-march=native`` builds for them)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        keep = [ln for ln in lines if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(keep) or platform.processor()
    except OSError:
        return platform.processor() or platform.machine()


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def _build(cc: str, source: Path, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.stem + ".", suffix=".tmp.so", dir=target.parent)
    os.close(fd)
    try:
        subprocess.run([cc, *FLAGS, str(source), "-o", tmp, "-lm"], check=True, capture_output=True, text=True,
                       timeout=120)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def prune(directory: Path, name: str, keep: int = KEEP_LIBRARIES) -> None:
    """Delete ``name``'s libraries in ``directory`` (``<name>-<machine>-<digest>.so``, this machine's architecture)
    beyond the ``keep`` newest by modification time, and its temporary build files older than
    :data:`_STALE_BUILD_S` (a build running now keeps its own). Other kernels' files and anything else are left
    alone; a file that cannot be deleted (or vanished meanwhile) is skipped."""
    prefix = f"{name}-{platform.machine()}-"
    built, stale = [], []
    now = time.time()
    for path in directory.glob(f"{prefix}*.so"):
        try:
            mtime = path.stat().st_mtime
        except OSError:
            continue
        if path.name.endswith(".tmp.so"):
            if now - mtime > _STALE_BUILD_S:
                stale.append(path)
        else:
            built.append((mtime, path))
    for _, path in sorted(built, reverse=True)[keep:]:
        stale.append(path)
    for path in stale:
        try:
            path.unlink()
        except OSError:
            pass


def _kernels(name: str) -> Kernels | None:
    """The library built from ``<name>.c``, built on first use; None where switched off or it cannot be built."""
    if not enabled():
        return None
    if name in _loaded:
        return _loaded[name]
    with _lock:
        if name in _loaded:
            return _loaded[name]
        kernels = None
        source = SOURCE_DIR / f"{name}.c"
        cc = _compiler()
        if cc is None:
            log.warning("no C compiler found ($CC, cc, gcc, clang): the %s kernel is not built, PyTorch operators "
                        "run instead (slower on a CPU)", name)
        else:
            digest = hashlib.sha256("\n".join([source.read_text(), cc, *FLAGS, _cpu_signature()]).encode())
            target = cache_dir() / f"{name}-{platform.machine()}-{digest.hexdigest()[:16]}.so"
            try:
                built = not target.exists()
                if built:
                    _build(cc, source, target)
                kernels = Kernels(name, ctypes.CDLL(str(target)), target)
                if built:  # once loaded, so that no other process's prune can take it away first
                    prune(target.parent, name)
            except (OSError, subprocess.SubprocessError, AttributeError) as exc:
                detail = (getattr(exc, "stderr", None) or str(exc)).strip().splitlines()
                log.warning("could not build the %s kernel with %s (%s): PyTorch operators run instead (slower on "
                            "a CPU)", name, cc, detail[-1] if detail else type(exc).__name__)
        _loaded[name] = kernels
        return kernels


def interpolation_kernels() -> Kernels | None:
    """``interpolation.c``: ``interpolate_forward`` and ``interpolate_backward``, or None (:func:`_kernels`)."""
    return _kernels("interpolation")


def band_loss_kernels() -> Kernels | None:
    """``band_losses.c``: ``band_losses_forward`` and ``band_losses_backward``, or None (:func:`_kernels`)."""
    return _kernels("band_losses")


def depth_support_kernels() -> Kernels | None:
    """``depth_support.c``: ``depth_support``, or None (:func:`_kernels`)."""
    return _kernels("depth_support")
