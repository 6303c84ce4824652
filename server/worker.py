"""Session workers: where a session's :class:`~.engine_host.EngineHost` runs.

* :class:`ProcessWorker` (the default, ``voxfusion serve --session-workers process``): the host runs in a
  process of its own, so sessions do not share a GIL (the OS shares the cores between them fairly) and a
  crash, a CUDA error or an out-of-memory kill takes down only that session's worker. Workers are forked
  from a ``forkserver`` that has imported the engine once (a new worker starts in ~10 ms, not the ~2 s of
  importing torch). The API process talks to it over a pipe: calls (``stats``, ``render``, ``mesh_bytes``,
  ...) with replies, notices (``available``) and events (poses, failures). Frames never travel on the pipe:
  the worker maps the session's recording (:class:`~voxfusion.proto.recording.RecordingReader`).
* :class:`ThreadWorker` (``--session-workers thread``): the same host on threads of the API process; the
  plain reference, and what tests that patch the engine use.

Both have the same methods: :meth:`call`, :meth:`available`, :meth:`close`, :attr:`pid`; ``on_event``
receives the host's events and ``on_exit(exitcode)`` is called (on a thread of the worker's) when a worker
process ends without having been closed.

Pipe messages (pickled tuples)::

    API -> worker:  ("available", n) | ("call", id, verb, args)
    worker -> API:  ("event", event) | ("reply", id, ok, value_or_error)
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import socket
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, Protocol

from voxfusion.core.errors import VoxFusionError

from .engine_host import HOST_VERBS, EngineHost, HostSpec

__all__ = ["SessionWorker", "ProcessWorker", "ThreadWorker", "WorkerLostError", "start_worker", "warm_up",
           "WORKER_KINDS"]

log = logging.getLogger("voxfusion.server")

WORKER_KINDS = ("process", "thread", "ray")
"""``voxfusion serve --session-workers`` choices."""

OnEvent = Callable[[tuple], None]
OnExit = Callable[[int | None], None]


class WorkerLostError(VoxFusionError):
    """The session's worker process ended (killed, crashed) before it answered."""


class SessionWorker(Protocol):
    """What a session needs of its worker (see the module docstring)."""

    pid: int | None
    node_id: str | None
    """Where it runs: a Ray node id, or this machine's host name."""

    def call(self, verb: str, *args: Any, timeout_s: float | None = None) -> Any: ...

    def available(self, count: int) -> None: ...

    def close(self, checkpoint: bool, timeout_s: float = 60.0) -> None: ...

    def kill(self) -> None: ...


# ---------------------------------------------------------------------- inside the worker process
def _worker_main(conn: multiprocessing.connection.Connection, spec: HostSpec) -> None:
    """The worker process: host the engine, answer calls until ``close`` (or the API process is gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the API process decides
    logging.basicConfig(level=logging.WARNING,
                        format=f"%(asctime)s voxfusion-worker[{spec.session_id[:8]}] %(levelname)s %(message)s")
    if spec.torch_threads > 0:
        import torch

        torch.set_num_threads(spec.torch_threads)
    send_lock = threading.Lock()

    def send(message: tuple) -> None:
        try:
            data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
            if message[0] == "reply" and not message[2]:
                pickle.loads(data)  # an error that pickles but cannot be rebuilt would break the API's reader
        except Exception as e:  # noqa: BLE001 - an unpicklable value or error: say what it was
            if message[0] != "reply":
                raise
            detail = message[3] if not message[2] else e
            data = pickle.dumps(("reply", message[1], False,
                                 VoxFusionError(f"{type(detail).__name__}: {detail}")))
        with send_lock:
            conn.send_bytes(data)

    host = EngineHost(spec, emit=lambda event: send(("event", event)))
    pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="voxfusion-call")
    closed = threading.Event()

    def answer(call_id: int, verb: str, args: tuple) -> None:
        try:
            value = getattr(host, verb)(*args)
            send(("reply", call_id, True, value))
        except BaseException as e:  # noqa: BLE001 - every error goes back to the caller
            send(("reply", call_id, False, e))
        if verb == "close":
            closed.set()

    try:
        while not closed.is_set():
            if not conn.poll(0.2):
                continue
            message = conn.recv()
            if message[0] == "available":
                host.available(message[1])
            elif message[0] == "call":
                _, call_id, verb, args = message
                if verb not in HOST_VERBS:
                    send(("reply", call_id, False, VoxFusionError(f"unknown verb {verb!r}")))
                elif verb in ("finish", "close"):  # never queued behind slow queries (meshes)
                    threading.Thread(target=answer, args=(call_id, verb, args), daemon=True).start()
                else:
                    pool.submit(answer, call_id, verb, args)
    except (EOFError, OSError):  # the API process is gone: keep the map, leave
        host.close(checkpoint=True)
    pool.shutdown(wait=True)
    conn.close()


# ---------------------------------------------------------------------- in the API process
_CONTEXT: multiprocessing.context.BaseContext | None = None
_CONTEXT_LOCK = threading.Lock()


def _context() -> multiprocessing.context.BaseContext:
    """The ``forkserver`` context (its server imports the engine once), or ``spawn`` where there is none."""
    global _CONTEXT
    with _CONTEXT_LOCK:
        if _CONTEXT is None:
            if "forkserver" in multiprocessing.get_all_start_methods():
                ctx = multiprocessing.get_context("forkserver")
                ctx.set_forkserver_preload([__name__])
            else:
                ctx = multiprocessing.get_context("spawn")
            _CONTEXT = ctx
        return _CONTEXT


def _noop() -> None:
    """What :func:`warm_up`'s process runs."""


def warm_up() -> None:
    """Start the forkserver now (it imports the engine: about 2 s on a small CPU), so that the first session
    does not wait for it. Blocks until a first worker-sized process has started and ended."""
    proc = _context().Process(target=_noop, daemon=True, name="voxfusion-worker-warm-up")
    proc.start()
    proc.join(timeout=120)


class ProcessWorker:
    """A session's engine in a worker process (see the module docstring).

    Args:
        spec: the host to run.
        on_event: receives each event of the host (on this worker's reader thread; keep it fast).
        on_exit: called with the exit code when the process ends without :meth:`close` (killed, crashed).
    """

    def __init__(self, spec: HostSpec, on_event: OnEvent, on_exit: OnExit) -> None:
        self.spec = spec
        self._on_event = on_event
        self._on_exit = on_exit
        ctx = _context()
        self._conn, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=_worker_main, args=(child, spec), daemon=True,
                                 name=f"voxfusion-worker-{spec.session_id[:8]}")
        self._proc.start()
        child.close()
        self.pid: int | None = self._proc.pid
        self.node_id: str | None = socket.gethostname()
        self._send_lock = threading.Lock()
        self._lock = threading.Lock()
        self._calls: dict[int, Future] = {}
        self._next_id = 0
        self._closing = False
        self._lost = False
        self._reader = threading.Thread(target=self._read, name=f"voxfusion-worker-io-{spec.session_id[:8]}",
                                        daemon=True)
        self._reader.start()

    def _send(self, message: tuple) -> None:
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        with self._send_lock:
            self._conn.send_bytes(data)

    def _read(self) -> None:
        try:
            while True:
                data = self._conn.recv_bytes()
                try:
                    message = pickle.loads(data)
                except Exception:  # noqa: BLE001 - one bad message must not stop the replies and events
                    log.exception("session %s: unreadable message from the worker", self.spec.session_id)
                    continue
                if message[0] == "event":
                    try:
                        self._on_event(message[1])
                    except Exception:  # noqa: BLE001 - a bad handler must not stop the worker's replies
                        log.exception("session %s: worker event handler failed", self.spec.session_id)
                else:
                    _, call_id, ok, value = message
                    with self._lock:
                        future = self._calls.pop(call_id, None)
                    if future is not None:
                        if ok:
                            future.set_result(value)
                        else:
                            future.set_exception(value)
        except (EOFError, OSError):
            pass
        self._proc.join(timeout=10)
        with self._lock:
            self._lost = True
            pending = list(self._calls.values())
            self._calls.clear()
            closing = self._closing
        code = self._proc.exitcode
        for future in pending:
            future.set_exception(WorkerLostError(f"the worker process of session {self.spec.session_id} ended "
                                                 f"(exit code {code})"))
        if not closing:
            self._on_exit(code)

    def call(self, verb: str, *args: Any, timeout_s: float | None = None) -> Any:
        """Run ``verb(*args)`` on the host and return its value (or raise its error).

        Raises:
            WorkerLostError: the worker process ended before answering.
            TimeoutError: no answer within ``timeout_s``.
        """
        future: Future = Future()
        with self._lock:
            if self._lost:
                raise WorkerLostError(f"the worker process of session {self.spec.session_id} has ended")
            call_id = self._next_id
            self._next_id += 1
            self._calls[call_id] = future
        try:
            self._send(("call", call_id, verb, args))
        except (OSError, ValueError) as e:
            with self._lock:
                self._calls.pop(call_id, None)
            raise WorkerLostError(f"the worker process of session {self.spec.session_id} has ended: {e}") from e
        try:
            return future.result(timeout_s)
        except FutureTimeout as e:
            with self._lock:
                self._calls.pop(call_id, None)
            raise TimeoutError(f"session {self.spec.session_id}: the worker did not answer {verb!r} within "
                               f"{timeout_s:g} s") from e

    def available(self, count: int) -> None:
        """Tell the worker the recording holds ``count`` records (ignored once the worker has ended)."""
        try:
            self._send(("available", count))
        except (OSError, ValueError):
            pass  # the reader thread reports the exit

    def close(self, checkpoint: bool, timeout_s: float = 60.0) -> None:
        """Stop the host (``checkpoint``: save the map first) and let the process exit; kill it after
        ``timeout_s``."""
        with self._lock:
            self._closing = True
        try:
            self.call("close", checkpoint, timeout_s=timeout_s)
        except (WorkerLostError, TimeoutError) as e:
            log.warning("session %s: worker did not close cleanly (%s)", self.spec.session_id, e)
        except VoxFusionError as e:
            log.warning("session %s: closing the engine failed: %s", self.spec.session_id, e)
        self._proc.join(timeout=10)
        if self._proc.is_alive():
            self.kill()
        self._conn.close()

    def kill(self) -> None:
        """SIGKILL the worker process (what a crash looks like)."""
        if self.pid is not None and self._proc.is_alive():
            os.kill(self.pid, signal.SIGKILL)
            self._proc.join(timeout=10)


class ThreadWorker:
    """The host on threads of the API process (the reference path; see the module docstring)."""

    pid = None

    def __init__(self, spec: HostSpec, on_event: OnEvent, on_exit: OnExit) -> None:
        self.spec = spec
        self.node_id = socket.gethostname()
        self.host = EngineHost(dataclasses.replace(spec, shared_process=True), emit=on_event)

    def call(self, verb: str, *args: Any, timeout_s: float | None = None) -> Any:
        if verb not in HOST_VERBS:
            raise VoxFusionError(f"unknown verb {verb!r}")
        return getattr(self.host, verb)(*args)

    def available(self, count: int) -> None:
        self.host.available(count)

    def close(self, checkpoint: bool, timeout_s: float = 60.0) -> None:
        self.host.close(checkpoint)

    def kill(self) -> None:
        raise VoxFusionError("a thread worker cannot be killed; use --session-workers process")


def start_worker(kind: str, spec: HostSpec, on_event: OnEvent, on_exit: OnExit,
                 ray: Any = None) -> SessionWorker:  # noqa: ANN401 - RayOptions, imported only when used
    """A new worker of ``kind`` (:data:`WORKER_KINDS`) running ``spec`` (``ray``: the
    :class:`~.ray_worker.RayOptions` of kind ``ray``)."""
    if kind == "process":
        return ProcessWorker(spec, on_event, on_exit)
    if kind == "thread":
        return ThreadWorker(spec, on_event, on_exit)
    if kind == "ray":
        from .ray_worker import RayWorker

        return RayWorker(spec, on_event, on_exit, ray)
    raise VoxFusionError(f"unknown session worker kind {kind!r}; one of {WORKER_KINDS}")
