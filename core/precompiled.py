"""Ahead-of-time compiled versions of a plain function, cached on disk and compiled in the background.

``torch.compile`` makes the CPU tracker's iteration about twice as fast, but compiles for 7-50 s in every process
(:mod:`.compiled`), more than a run of a few hundred frames saves. ``torch.compile(...).aot_compile`` instead
produces an artifact that a later process loads in ~0.1 s. This module keeps such artifacts in a cache directory,
one per *variant*: the plain function's arguments differ from call to call in tensor sizes (dynamic: the map
grows) but also in what the compiled graph is specialised to (Python floats of the solver's options, which terms
exist, the map's voxel size), and the caller names those in a ``signature``.

How a variant comes to be used:

* the first time a process meets a variant that the cache lacks, it starts one compile job for it: a child process
  (``python -m voxfusion.core.precompiled JOB``) at the lowest CPU priority (``nice 19``, so it runs on time the
  engine leaves idle), handed the call's own arguments as the example; the job compiles, checks the artifact
  against the plain function on those arguments, and writes it (or a ``.failed`` note with the reason, never
  retried). It outlives its parent, so a short first run still leaves the artifact for the next;
* a :class:`PrecompiledVariants` (one per user: a tracker, so a session) decides per variant, the first time it
  meets it, between the artifact on disk and the plain function, and keeps that choice for its lifetime: a
  session's arithmetic never changes mid-run (compiled code rounds differently from eager), and an artifact that
  appears meanwhile serves the next session;
* a call whose artifact rejects its arguments (a guard: something the graph was specialised to differs) runs the
  plain function; any other failure of an artifact logs one warning and that view stops using it.

The plain function stays the reference (the tests hold artifacts to it). ``VOXFUSION_PRECOMPILE=0`` turns all
of it off (nothing loaded, nothing compiled); ``VOXFUSION_CACHE_DIR`` moves the cache (default
``$XDG_CACHE_HOME/voxfusion``, else ``~/.cache/voxfusion``). An artifact's name is a digest of the variant, the
function's name, torch's and Python's versions, the CPU's vector instruction set, torch's intra-op thread count
and the source of the whole engine (``voxfusion/core``), so any change to any of them compiles afresh.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .errors import VoxFusionError

__all__ = ["PrecompiledFunction", "PrecompiledVariants", "cache_root", "cache_dir", "enabled", "preload",
           "compile_artifact", "ENV_SWITCH", "ENV_CACHE_DIR"]

log = logging.getLogger("voxfusion.precompiled")

ENV_SWITCH = "VOXFUSION_PRECOMPILE"
"""Environment variable: ``0`` (or ``false``, ``no``, ``off``) turns precompiled artifacts off in this process."""
ENV_CACHE_DIR = "VOXFUSION_CACHE_DIR"
"""Environment variable: the cache directory (artifacts under its ``precompiled/``)."""

_DYNAMO_OPTIONS = {"force_parameter_static_shapes": False, "specialize_float": True}
"""What the compile jobs trace with (:mod:`.compiled`'s options: shapes dynamic, Python floats constants)."""
_STALE_LOCK_S = 1800.0
"""A job's lock older than this is taken for a job that died; a new one may start."""
_CHECK_RTOL = 1e-4
"""Relative tolerance (of each output tensor's largest magnitude) of a job's check against the plain function."""


def enabled() -> bool:
    """Whether precompiled artifacts may be loaded and compiled in this process (:data:`ENV_SWITCH`)."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "false", "no", "off")


def cache_root() -> Path:
    """The engine's per-machine cache: ``$VOXFUSION_CACHE_DIR``, else ``$XDG_CACHE_HOME/voxfusion`` or
    ``~/.cache/voxfusion`` (precompiled artifacts in ``precompiled/``, the C kernels of :mod:`.native` in
    ``native/``)."""
    root = os.environ.get(ENV_CACHE_DIR)
    if not root:
        root = str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "voxfusion")
    return Path(root)


def cache_dir() -> Path:
    """Where artifacts live: ``precompiled/`` of :func:`cache_root`."""
    return cache_root() / "precompiled"


@functools.cache
def _build_digest() -> str:
    """What every artifact is specific to besides its variant: torch's and Python's versions, the machine, the CPU
    vector instruction set Inductor compiles for and the engine's source (``voxfusion/core``, every ``.py``)."""
    h = hashlib.sha256()
    try:
        from torch._inductor.cpu_vec_isa import pick_vec_isa
        isa = str(pick_vec_isa())
    except Exception:  # noqa: BLE001 - an older or newer torch: the machine's name stands in
        isa = "?"
    for part in (torch.__version__, sys.version, platform.machine(), isa):
        h.update(part.encode())
    core = Path(__file__).resolve().parent
    for path in sorted(core.rglob("*.py")):
        h.update(str(path.relative_to(core)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def preload() -> None:
    """Do before the first frame what a process's first artifact load does (~2 s on a 2-core CPU): import Inductor's
    loading machinery and pick the CPU's vector instruction set (Inductor runs the C++ compiler and a probe
    process for it). Nothing when :func:`enabled` is false; never raises (loading then fails as it would)."""
    if not enabled():
        return
    try:
        import torch._functorch._aot_autograd.aot_autograd_result  # noqa: F401
        import torch._inductor.compile_fx  # noqa: F401
        _build_digest()
    except Exception as e:  # noqa: BLE001 - the artifacts' own loading reports what is wrong
        log.debug("precompiled preload failed: %s: %s", type(e).__name__, e)


@dataclass(frozen=True)
class _Job:
    """What a compile job is handed (saved with ``torch.save``): the function by module and name, the example
    arguments, the thread count and grad mode to compile for and the artifact's path."""

    module: str
    name: str
    args: tuple
    threads: int
    grad_enabled: bool
    path: str


class PrecompiledFunction:
    """The artifacts of one plain function ``fn`` (module-level, importable by ``fn.__module__`` and ``__name__``).

    Args:
        fn: the plain function: the reference and the fall-back.
        option: the configuration name that asks for it (``"tracking.precompiled"``), for log lines.
        logger: where its lines go.
    """

    def __init__(self, fn: Callable, option: str, logger: logging.Logger | None = None) -> None:
        self.fn = fn
        self.option = option
        self._log = logger or log
        self._lock = threading.Lock()
        self._jobs: dict[str, subprocess.Popen] = {}
        """Compile jobs this process started, by artifact name."""
        self._noted: set[str] = set()
        self._preloaded: dict[str, Callable] = {}
        """Artifacts loaded ahead of use (:meth:`preload_artifacts`), by name, until a view takes them."""

    # ------------------------------------------------------------------ names and files
    def key(self, signature: tuple) -> str:
        """The artifact's name for ``signature`` (in this process, at torch's current thread count and grad mode: an
        artifact's guards hold both)."""
        h = hashlib.sha256()
        for part in (_build_digest(), self.fn.__module__, self.fn.__name__, str(torch.get_num_threads()),
                     str(torch.is_grad_enabled()), repr(signature)):
            h.update(part.encode())
            h.update(b"\0")
        return f"{self._prefix()}{h.hexdigest()[:24]}"

    def _prefix(self) -> str:
        """What every artifact name of this function and engine build starts with (:meth:`preload_artifacts`)."""
        return f"{self.fn.__name__}-{_build_digest()[:12]}-"

    def path(self, key: str) -> Path:
        """The artifact file of ``key`` (it exists once compiled and checked)."""
        return cache_dir() / f"{key}.pt"

    # ------------------------------------------------------------------ loading
    def resolve(self, signature: tuple, args: tuple) -> Callable | None:
        """The artifact of ``signature`` loaded (a fresh load: each caller its own copy), or None when there is
        none yet, in which case a compile job for it starts (once per process and variant, unless one is running
        or has failed) with ``args`` as its example. None, and nothing started, when :func:`enabled` is false."""
        if not enabled():
            return None
        key = self.key(signature)
        with self._lock:
            preloaded = self._preloaded.pop(key, None)
        if preloaded is not None:
            return preloaded
        path = self.path(key)
        if path.exists():
            return self._load(key, path)
        failed = path.with_suffix(".failed")
        if failed.exists():
            self._note(key, logging.INFO, "%s: %s could not be compiled earlier (%s); running the plain function",
                       self.option, key, failed.read_text(errors="replace").strip().splitlines()[-1:])
            return None
        self._start_job(key, args)
        return None

    def _load(self, key: str, path: Path) -> Callable | None:
        """The artifact at ``path`` loaded, or None (with one warning) when it cannot be."""
        try:
            t0 = time.perf_counter()
            with open(path, "rb") as fh:
                fn = torch.compiler.load_compiled_function(fh)
            self._note(key, logging.INFO, "%s: loaded %s in %.2f s", self.option, path.name, time.perf_counter() - t0)
            return fn
        except Exception as e:  # noqa: BLE001 - an unreadable artifact: plain function, say so once
            self._note(key, logging.WARNING, "%s: cannot load %s (%s: %s); running the plain function",
                       self.option, path, type(e).__name__, e)
            return None

    def preload_artifacts(self, limit: int = 16) -> int:
        """Load up to ``limit`` of this engine build's artifacts of the function now (the newest first), so that the
        first :meth:`resolve` of each variant takes it instead of loading it then (~0.1-0.5 s each on a 2-core CPU,
        the first the dearest): what an engine does before its first frame. Each is handed out once (a loaded
        artifact serves one view); later views load their own. Returns how many were loaded; nothing when
        :func:`enabled` is false."""
        if not enabled():
            return 0
        try:
            paths = sorted(cache_dir().glob(f"{self._prefix()}*.pt"), key=lambda p: p.stat().st_mtime, reverse=True)
        except OSError:
            return 0
        n = 0
        for path in paths[:limit]:
            key = path.stem
            with self._lock:
                if key in self._preloaded:
                    continue
            fn = self._load(key, path)
            if fn is not None:
                with self._lock:
                    self._preloaded[key] = fn
                n += 1
        return n

    def _note(self, key: str, level: int, msg: str, *args: Any) -> None:
        """Log ``msg`` once per process and artifact."""
        with self._lock:
            if key in self._noted:
                return
            self._noted.add(key)
        self._log.log(level, msg, *args)

    # ------------------------------------------------------------------ compiling
    def _start_job(self, key: str, args: tuple) -> None:
        with self._lock:
            if key in self._jobs:
                return
            directory = cache_dir()
            try:
                directory.mkdir(parents=True, exist_ok=True)
                _prune(directory)
                lock = directory / f"{key}.lock"
                if lock.exists() and time.time() - lock.stat().st_mtime < _STALE_LOCK_S:
                    return  # another process is compiling it
                lock.write_text(str(os.getpid()))
                job_path = directory / f"{key}.job"
                torch.save(_Job(self.fn.__module__, self.fn.__name__, tuple(args), torch.get_num_threads(),
                                torch.is_grad_enabled(), str(self.path(key))), job_path)
                with open(directory / f"{key}.log", "wb") as out:
                    proc = subprocess.Popen([sys.executable, "-c", _JOB_BOOTSTRAP, str(job_path)],
                                            stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                            start_new_session=True)
            except Exception as e:  # noqa: BLE001 - no cache directory, no child: stay with the plain function
                self._log.warning("%s: cannot start compiling %s (%s: %s)", self.option, key, type(e).__name__, e)
                self._jobs[key] = None  # type: ignore[assignment]
                for leftover in (f"{key}.lock", f"{key}.job"):
                    (directory / leftover).unlink(missing_ok=True)
                return
            self._jobs[key] = proc
        self._log.info("%s: compiling %s in the background (pid %d, lowest priority; later sessions load it)",
                       self.option, key, proc.pid)

    def pending(self) -> list[str]:
        """Artifacts whose compile job (started by this process) is still running."""
        with self._lock:
            return [k for k, p in self._jobs.items() if p is not None and p.poll() is None]

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for this process's compile jobs; True when all ended within ``timeout_s`` (None: no limit)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._lock:
            procs = [p for p in self._jobs.values() if p is not None]
        for p in procs:
            try:
                p.wait(None if deadline is None else max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                return False
        return True


_KEEP_ARTIFACTS = 64
"""Artifacts (with their logs and failure notes) a cache keeps; the oldest go first (:func:`_prune`). An engine build
needs a handful, and every change to the engine's source makes a new build."""


def _prune(directory: Path, keep: int = _KEEP_ARTIFACTS) -> None:
    """Delete all but the ``keep`` newest artifacts in ``directory`` (by name: ``.pt``, ``.log`` and ``.failed``
    together); what is running (a ``.lock`` or ``.job``) is left alone."""
    stems: dict[str, float] = {}
    for path in directory.iterdir():
        if path.suffix in (".pt", ".log", ".failed"):
            stems[path.stem] = max(stems.get(path.stem, 0.0), path.stat().st_mtime)
    for stem in sorted(stems, key=stems.__getitem__, reverse=True)[keep:]:
        if (directory / f"{stem}.lock").exists():
            continue
        for suffix in (".pt", ".log", ".failed"):
            (directory / f"{stem}{suffix}").unlink(missing_ok=True)


def compile_artifact(fn: Callable, args: tuple, path: Path) -> None:
    """Compile ``fn`` ahead of time on example ``args`` (``torch.compile(fullgraph=True, dynamic=True)``), check the
    artifact against ``fn`` on them (every tensor output within :data:`_CHECK_RTOL` of its largest magnitude; boolean
    ones may differ on under 1 % of entries: values at a threshold) and write it to ``path`` (atomically). Raises
    on any failure. What a compile job runs; tests call it directly."""
    from torch.fx.experimental import _config as fx_config

    # no duck sizing: two sizes that happen to be equal in the example (a map of 601 voxels and 601 of something
    # else) would otherwise be assumed equal for good, and the artifact's guards reject every call where they differ
    with torch._dynamo.config.patch(**_DYNAMO_OPTIONS), fx_config.patch(use_duck_shape=False):
        compiled = torch.compile(fn, fullgraph=True, dynamic=True).aot_compile((tuple(args), {}))
        got = compiled(*args)
    _check_close(got, fn(*args))
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    compiled.save_compiled_function(str(tmp))
    os.replace(tmp, path)


def _tensors(out: Any) -> Iterator[Any]:
    """The leaves of nested tuples (NamedTuples included): tensors, None and any other value, in order."""
    if isinstance(out, tuple):
        for item in out:
            yield from _tensors(item)
    else:
        yield out


def _check_close(got: Any, want: Any) -> None:
    pairs = list(zip(_tensors(got), _tensors(want), strict=True))
    for i, (a, b) in enumerate(pairs):
        if not isinstance(a, torch.Tensor) or not isinstance(b, torch.Tensor):
            if type(a) is not type(b) or (not isinstance(a, torch.Tensor) and a != b):
                raise AssertionError(f"output {i}: {a!r} against {b!r}")
            continue
        if b.dtype == torch.bool:
            if (a != b).float().mean() > 0.01:
                raise AssertionError(f"output {i}: {(a != b).float().mean() * 100:.2f} % of the flags differ")
            continue
        scale = float(b.abs().max()) if b.numel() else 0.0
        torch.testing.assert_close(a, b, rtol=_CHECK_RTOL, atol=_CHECK_RTOL * max(scale, 1e-12), equal_nan=True,
                                   msg=lambda m, i=i: f"output {i}: {m}")


_JOB_BOOTSTRAP = """\
import os, sys
try:
    os.nice(19)
except OSError:
    pass
try:
    with open("/proc/self/autogroup", "w") as fh:
        fh.write("19")
except OSError:
    pass
from voxfusion.core.precompiled import _run_job
sys.exit(_run_job(sys.argv[1]))
"""
"""A compile job's command (``python -c``): the lowest CPU priority before anything heavy is imported (torch alone
is seconds of CPU; at normal priority three jobs' imports slowed the engine's next frame from 0.15 to 5 s on 2
cores), for the process and for its scheduling autogroup (a job runs in a session of its own, and where the kernel
groups sessions, ``sched_autogroup``, a group's nice value is what weighs against the engine's group: with only the
process niced, three jobs slowed a 2-core run 15-fold); then :func:`_run_job`."""


def _run_job(job_path: Path | str) -> int:
    """A compile job's body (run by :data:`_JOB_BOOTSTRAP`): one job at a time per cache (a lock file), compile the
    saved job's function and write the artifact, or a ``.failed`` note with the reason; the job file and lock are
    removed either way."""
    job_path = Path(job_path)
    job: _Job = torch.load(job_path, weights_only=False)
    out = Path(job.path)
    serial = open(out.parent / "compiling.lock", "a")  # noqa: SIM115 - held for the job's life
    try:
        import fcntl
        fcntl.flock(serial, fcntl.LOCK_EX)
    except (ImportError, OSError):
        pass
    try:
        torch.set_num_threads(job.threads)
        module = __import__(job.module, fromlist=[job.name])
        t0 = time.perf_counter()
        with torch.set_grad_enabled(job.grad_enabled):
            compile_artifact(getattr(module, job.name), job.args, out)
        print(f"compiled {out.name} in {time.perf_counter() - t0:.1f} s", flush=True)
        return 0
    except Exception as e:  # noqa: BLE001 - recorded for the parent, never retried
        traceback.print_exc()
        out.with_suffix(".failed").write_text(f"{type(e).__name__}: {e}\n")
        return 1
    finally:
        job_path.unlink(missing_ok=True)
        out.with_suffix(".lock").unlink(missing_ok=True)
        serial.close()


class PrecompiledVariants:
    """One user's view of a :class:`PrecompiledFunction`: per variant, the artifact or the plain function, chosen
    the first time the variant is met and kept (see the module docstring). Not shared between threads (a loaded
    artifact is not thread-safe), so make one per tracker.

    ``served`` and ``fallbacks`` count the calls an artifact ran and the calls that had one but ran the plain
    function (its guards rejected the arguments); benchmarks report them."""

    def __init__(self, function: PrecompiledFunction) -> None:
        self.function = function
        self._chosen: dict[tuple, Callable | None] = {}
        self.served = 0
        self.fallbacks = 0

    def __call__(self, signature: tuple, *args: Any) -> Any:
        if signature not in self._chosen:
            self._chosen[signature] = self.function.resolve(signature, args)
        compiled = self._chosen[signature]
        if compiled is not None:
            try:
                out = compiled(*args)
                self.served += 1
                return out
            except VoxFusionError:
                raise
            except Exception as e:  # noqa: BLE001 - a guard rejected the call, or the artifact failed
                self.fallbacks += 1
                if "guard" in str(e).lower():
                    log.debug("%s: a guard rejected the call: %s", self.function.option, str(e)[:300])
                else:
                    log.warning("%s: a precompiled artifact failed (%s: %s); running the plain function from now on",
                                self.function.option, type(e).__name__, str(e).splitlines()[0] if str(e) else "")
                    self._chosen[signature] = None
        return self.function.fn(*args)

    @property
    def uses_artifacts(self) -> bool:
        """Whether any variant met so far runs from an artifact."""
        return any(f is not None for f in self._chosen.values())


