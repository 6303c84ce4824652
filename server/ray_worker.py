"""Session workers as Ray actors: sessions spread over the machines of a Ray cluster
(``voxfusion serve --ray-address ADDRESS``).

Each session's :class:`~.engine_host.EngineHost` runs inside an actor (:func:`engine_actor_class`) that Ray
places on whichever node has room (``SPREAD``; ``--cpus-per-session`` and ``--gpus-per-session``, a
fraction of a GPU, are its resource demand). The API server keeps the HTTP / zenoh side, records every
frame durably and tells the actor how many records exist, exactly as with a local worker process
(:class:`~.worker.ProcessWorker`); the actor reads the session's recording from the data folder, which
must therefore be a path every node shares (NFS or the like; on one machine it trivially is).

The actor's events (poses, handed records, failures) come back by long polling (:meth:`events`, up to half a
second per call) on a thread of the API server. An actor whose node disappears, or that is killed, makes that
thread end with Ray's actor error: the session restarts its worker on another node, replaying the recording
(:meth:`~.session.Session._on_worker_exit`), so nothing acknowledged is lost.

The Ray connection is made once per process (:func:`connect`, namespace ``voxfusion``); ``ray`` is an
optional dependency (``pip install 'voxfusion[cluster]'``).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from typing import Any

from voxfusion.core.errors import ConfigError, VoxFusionError

from .engine_host import HOST_VERBS, EngineHost, HostSpec
from .worker import OnEvent, OnExit, WorkerLostError

__all__ = ["RayOptions", "RayWorker", "connect", "engine_actor_class"]

log = logging.getLogger("voxfusion.server")

_EVENT_POLL_S = 0.5
_ACTOR_START_TIMEOUT_S = 180.0


class RayOptions:
    """Where and how big session actors are.

    Args:
        address: the cluster (``ray://host:10001``, ``host:6379`` or ``auto``).
        cpus_per_session: logical CPUs each session actor asks for.
        gpus_per_session: GPUs (a fraction shares one) each session actor asks for.
    """

    def __init__(self, address: str, cpus_per_session: float = 1.0, gpus_per_session: float = 0.0) -> None:
        self.address = address
        self.cpus_per_session = cpus_per_session
        self.gpus_per_session = gpus_per_session


def _ray() -> Any:  # noqa: ANN401 - optional module
    try:
        import ray
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ConfigError("ray_address", "session workers on a Ray cluster need the 'ray' package: "
                                         "pip install 'voxfusion[cluster]'") from e
    return ray


_CONNECT_LOCK = threading.Lock()


def connect(address: str) -> None:
    """Connect this process to the Ray cluster at ``address`` (once; later calls check it is the same)."""
    ray = _ray()
    with _CONNECT_LOCK:
        if ray.is_initialized():
            return
        try:
            ray.init(address=address, namespace="voxfusion", log_to_driver=False, logging_level=logging.WARNING)
        except Exception as e:  # noqa: BLE001 - ConnectionError, RuntimeError, ...: say where and why
            raise ConfigError("ray_address", f"cannot connect to the Ray cluster at {address}: {e}") from e


def disconnect() -> None:
    """Leave the Ray cluster (the cluster and other drivers are not affected)."""
    ray = _ray()
    with _CONNECT_LOCK:
        if ray.is_initialized():
            ray.shutdown()


class _EngineActor:
    """The body of the Ray actor: an :class:`EngineHost` and a queue of its events."""

    def __init__(self, spec: HostSpec) -> None:
        if spec.torch_threads > 0:
            import torch

            torch.set_num_threads(spec.torch_threads)
        self._events: queue.Queue[tuple] = queue.Queue()
        self.host = EngineHost(spec, emit=self._events.put)

    def where(self) -> tuple[int, str]:
        """``(pid, node id)`` of this actor."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()

    def available(self, count: int) -> None:
        self.host.available(count)

    def call(self, verb: str, args: tuple) -> Any:  # noqa: ANN401 - whatever the verb returns
        if verb not in HOST_VERBS:
            raise VoxFusionError(f"unknown verb {verb!r}")
        return getattr(self.host, verb)(*args)

    def events(self, timeout_s: float) -> list[tuple]:
        """The events since the last call (waits up to ``timeout_s`` for the first)."""
        try:
            out = [self._events.get(timeout=timeout_s)]
        except queue.Empty:
            return []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out


_ACTOR_CLASS: Any = None


def engine_actor_class() -> Any:  # noqa: ANN401 - a Ray actor class
    """The Ray actor class of session engines (threaded: calls, notices and event polls run at once)."""
    global _ACTOR_CLASS
    if _ACTOR_CLASS is None:
        _ACTOR_CLASS = _ray().remote(max_restarts=0, max_concurrency=8)(_EngineActor)
    return _ACTOR_CLASS


class RayWorker:
    """A session's engine in a Ray actor (see the module docstring); the :class:`~.worker.SessionWorker`
    interface.

    Raises:
        ConfigError: the actor could not be started (no node has the resources, or it failed to build).
    """

    def __init__(self, spec: HostSpec, on_event: OnEvent, on_exit: OnExit, options: RayOptions) -> None:
        ray = _ray()
        self.spec = spec
        self._on_event = on_event
        self._on_exit = on_exit
        self._closing = False
        self._lock = threading.Lock()
        actor_class = engine_actor_class()
        self._actor = actor_class.options(num_cpus=options.cpus_per_session, num_gpus=options.gpus_per_session,
                                          scheduling_strategy="SPREAD").remote(spec)
        try:
            self.pid, self.node_id = ray.get(self._actor.where.remote(), timeout=_ACTOR_START_TIMEOUT_S)
        except Exception as e:
            ray.kill(self._actor, no_restart=True)
            raise ConfigError("ray_address", f"session {spec.session_id}: its Ray actor did not start: {e}") from e
        self._reader = threading.Thread(target=self._read, name=f"voxfusion-ray-io-{spec.session_id[:8]}",
                                        daemon=True)
        self._reader.start()

    def _read(self) -> None:
        ray = _ray()
        while True:
            try:
                events = ray.get(self._actor.events.remote(_EVENT_POLL_S))
            except Exception as e:  # noqa: BLE001 - RayActorError and friends: the actor is gone or unreachable
                with self._lock:
                    closing = self._closing
                if not closing:
                    log.warning("session %s: its Ray actor on node %s is gone (%s: %s)", self.spec.session_id,
                                self.node_id, type(e).__name__, e)
                    self.kill()  # never two engines for one session: make sure this one is gone before a new one
                    self._on_exit(None)
                return
            for event in events:
                try:
                    self._on_event(event)
                except Exception:  # noqa: BLE001 - a bad handler must not stop the polling
                    log.exception("session %s: worker event handler failed", self.spec.session_id)

    def call(self, verb: str, *args: Any, timeout_s: float | None = None) -> Any:  # noqa: ANN401
        """Run ``verb(*args)`` in the actor; its errors are raised here as they were raised there."""
        ray = _ray()
        try:
            return ray.get(self._actor.call.remote(verb, args), timeout=timeout_s)
        except ray.exceptions.GetTimeoutError as e:
            raise TimeoutError(f"session {self.spec.session_id}: the worker did not answer {verb!r} within "
                               f"{timeout_s:g} s") from e
        except ray.exceptions.RayTaskError as e:
            cause = e.cause if isinstance(e.cause, BaseException) else e
            raise cause from None
        except ray.exceptions.RayActorError as e:
            raise WorkerLostError(f"the Ray actor of session {self.spec.session_id} is gone: {e}") from e

    def available(self, count: int) -> None:
        try:
            self._actor.available.remote(count)
        except Exception:  # noqa: BLE001 - the reader thread reports a dead actor
            pass

    def close(self, checkpoint: bool, timeout_s: float = 60.0) -> None:
        with self._lock:
            self._closing = True
        try:
            self.call("close", checkpoint, timeout_s=timeout_s)
        except (WorkerLostError, TimeoutError, VoxFusionError) as e:
            log.warning("session %s: closing its Ray actor: %s", self.spec.session_id, e)
        self.kill()

    def kill(self) -> None:
        """End the actor now (what a crash looks like, when not closing)."""
        try:
            _ray().kill(self._actor, no_restart=True)
        except Exception:  # noqa: BLE001 - already gone
            pass
