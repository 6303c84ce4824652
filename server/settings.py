"""Server settings: one frozen dataclass, filled by ``voxfusion serve`` (flags) or by tests.

Example::

    settings = ServerSettings(data_dir=Path("voxfusion-data"), device="cpu", api_key=None)
    app = create_app(settings)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from voxfusion.core.cpu import usable_cpu_count
from voxfusion.core.errors import ConfigError

__all__ = ["ServerSettings", "API_KEY_ENV"]

API_KEY_ENV = "VOXFUSION_API_KEY"
"""Environment variable holding the optional server API key (required to create and list sessions)."""


@dataclass(frozen=True)
class ServerSettings:
    """Everything the server needs; nothing heavy is built from it before the app's lifespan starts."""

    data_dir: Path = Path("voxfusion-data")
    """Root of the server's state: ``sessions.sqlite3`` and ``sessions/<id>/`` (recording, checkpoints)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Torch device of every session's engine (``auto``: CUDA when available)."""
    default_preset: str | None = None
    """Preset of new sessions that name none; ``None``: ``cpu`` on CPU, ``default`` on CUDA."""
    api_key: str | None = None
    """When set, ``POST /sessions``, ``GET /sessions`` and ``GET /metrics`` require it (``X-API-Key`` or
    ``Authorization: Bearer``). :meth:`from_env` reads it from ``VOXFUSION_API_KEY``."""
    zenoh: bool | None = False
    """Start the zenoh bridge: ``True`` (warn if it cannot start), ``False``, ``None`` = when importable."""
    zenoh_config: Path | None = None
    """A zenoh JSON5 config file for the bridge (default: a peer on loopback)."""
    zenoh_listen: tuple[str, ...] | None = None
    """Replaces the config's ``listen/endpoints`` (e.g. ``("tcp/0.0.0.0:7447",)`` for every interface)."""
    zenoh_secrets: Path | None = None
    """The LAN setup: a folder where the bridge keeps generated credentials and renders its config from
    ``configs/zenoh/server-lan.json5`` (authentication + access control) and ``client.json5`` for clients.
    Excludes ``zenoh_config``."""
    zenoh_insecure: bool = False
    """Let zenoh listen beyond loopback without authentication (refused otherwise)."""
    max_sessions: int = 8
    """Open sessions (created, running or finishing) held at once; more are refused with 503."""
    max_sessions_per_client: int = 2
    """Open sessions one client address may hold when it creates them without an API key (i.e. the server
    has none) and is not on loopback; more are refused with 429. ``0``: no per-client limit. The address is
    the TCP peer's, or ``X-Forwarded-For`` from a proxy uvicorn trusts (environment ``FORWARDED_ALLOW_IPS``,
    default 127.0.0.1); IPv6 clients are counted by their /64."""
    session_idle_timeout_s: float = 600.0
    """A session that has received no frame (or was created or resumed and got none) for this many seconds
    is closed as at a server restart: its map checkpointed, its recording kept, its slot freed; it resumes
    on its next frame or ``POST /resume``. ``0``: never."""
    max_frame_bytes: int = 32 * 1024 * 1024
    """Largest request body (a frame message or multipart upload); larger ones get 413."""
    max_image_width: int = 4096
    """Largest depth / colour image width in pixels; larger frames get 413."""
    max_image_height: int = 4096
    """Largest depth / colour image height in pixels."""
    max_pending_frames: int = 32
    """Frames of one session accepted but not yet handed to tracking (being recorded, or queued behind a
    replay or an ``offline`` session's tracker); more get 429 with ``Retry-After``."""
    checkpoint_interval_s: float = 30.0
    """A running session's map is checkpointed when this many seconds have passed since the last
    checkpoint and the map changed, ..."""
    checkpoint_keyframes: int = 10
    """... or when this many keyframes were added since the last one (and at finish, always)."""
    finish_timeout_s: float = 600.0
    """Longest ``POST /finish`` waits for the queue to drain and the final mapping to run."""
    session_workers: Literal["process", "thread", "ray"] = "process"
    """Where each session's engine runs: ``process``, a worker process of its own (sessions share the cores
    fairly, and a crashed worker takes down only its session, which restarts from its recording);
    ``thread``: threads of the API process (one GIL for all sessions; the reference path); ``ray``: actors on
    the Ray cluster at ``ray_address`` (set automatically when ``ray_address`` is given)."""
    ray_address: str | None = None
    """A Ray cluster (``host:6379``, ``ray://host:10001``, ``auto``) whose nodes run the session workers; the
    data folder must be a path every node shares."""
    cpus_per_session: float = 1.0
    """Logical CPUs each session's Ray actor asks for."""
    gpus_per_session: float = 0.0
    """GPUs each session's Ray actor asks for (a fraction shares a GPU, e.g. 0.25: four sessions per GPU)."""
    worker_threads: int = 0
    """Torch intra-op threads of each worker process; ``0``: the cores this process may use (its CPU affinity, e.g.
    a container's cpuset) divided by ``2 * max_sessions`` (each session runs a tracking and a mapping thread), at
    least 1."""
    worker_restarts: int = 3
    """How often one session's worker process may die (killed, crashed) and be restarted (replaying the
    recording) before the session is marked ``failed``."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "data_dir", Path(self.data_dir))
        if self.zenoh_secrets is not None:
            object.__setattr__(self, "zenoh_secrets", Path(self.zenoh_secrets))
            if self.zenoh_config is not None:
                raise ConfigError("zenoh_secrets", "give zenoh_config or zenoh_secrets, not both")
        if self.zenoh_listen is not None:
            object.__setattr__(self, "zenoh_listen", tuple(self.zenoh_listen))
            bad = [e for e in self.zenoh_listen if "/" not in e]
            if not self.zenoh_listen or bad:
                raise ConfigError("zenoh_listen", f"endpoints look like 'tcp/0.0.0.0:7447', got {bad or '[]'}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError("device", f"must be auto, cpu or cuda, got {self.device!r}")
        for name in ("max_sessions", "max_frame_bytes", "max_image_width", "max_image_height",
                     "max_pending_frames", "checkpoint_keyframes"):
            if getattr(self, name) < 1:
                raise ConfigError(name, f"must be >= 1, got {getattr(self, name)}")
        for name in ("checkpoint_interval_s", "finish_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be > 0 seconds, got {getattr(self, name)}")
        if self.ray_address and self.session_workers == "process":
            object.__setattr__(self, "session_workers", "ray")
        if self.session_workers not in ("process", "thread", "ray"):
            raise ConfigError("session_workers", f"must be process, thread or ray, got {self.session_workers!r}")
        if self.session_workers == "ray" and not self.ray_address:
            raise ConfigError("ray_address", "session workers on Ray need the cluster's address (--ray-address)")
        if self.cpus_per_session <= 0 or self.gpus_per_session < 0:
            raise ConfigError("cpus_per_session", "need cpus_per_session > 0 and gpus_per_session >= 0")
        if self.session_workers == "ray" and self.device == "cuda" and self.gpus_per_session == 0:
            raise ConfigError("gpus_per_session", "Ray hides every GPU from an actor that asks for none, so the "
                                                  "sessions could not run on CUDA: give --gpus-per-session > 0 "
                                                  "(e.g. 0.25 for four sessions per GPU) or --device cpu")
        for name in ("worker_threads", "worker_restarts"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        if self.max_sessions_per_client < 0:
            raise ConfigError("max_sessions_per_client",
                              f"must be >= 0 (0: no limit), got {self.max_sessions_per_client}")
        if not 0 <= self.session_idle_timeout_s < float("inf"):
            raise ConfigError("session_idle_timeout_s", "must be >= 0 seconds (0: never), got "
                                                        f"{self.session_idle_timeout_s}")
        if self.api_key is not None and len(self.api_key) < 8:
            raise ConfigError("api_key", "must be at least 8 characters")

    @classmethod
    def from_env(cls, **kwargs: object) -> ServerSettings:
        """Settings with ``api_key`` from ``VOXFUSION_API_KEY`` (if set and not given explicitly)."""
        if "api_key" not in kwargs:
            kwargs["api_key"] = os.environ.get(API_KEY_ENV) or None
        return cls(**kwargs)  # type: ignore[arg-type]

    def session_device(self) -> str:
        """The device sessions' engines run on (``auto``, ``cpu`` or ``cuda``): ``device`` for worker processes
        and threads (they see this host's devices). Ray actors run elsewhere: one asking for no GPU
        (``gpus_per_session`` 0) sees none (Ray empties its ``CUDA_VISIBLE_DEVICES``), so ``cpu``; one asking for
        a GPU share runs on a GPU node, so ``cuda`` even where the API host itself has no GPU."""
        if self.session_workers == "ray" and self.device == "auto":  # (cuda without a GPU share is refused)
            return "cuda" if self.gpus_per_session > 0 else "cpu"
        return self.device

    def ray_options(self) -> object | None:
        """The :class:`~voxfusion.server.ray_worker.RayOptions` of ``ray`` session workers (else ``None``)."""
        if self.session_workers != "ray":
            return None
        from .ray_worker import RayOptions

        return RayOptions(self.ray_address or "auto", self.cpus_per_session, self.gpus_per_session)

    def torch_threads_per_worker(self) -> int:
        """:attr:`worker_threads`, or its automatic value (see there)."""
        if self.worker_threads:
            return self.worker_threads
        return max(1, usable_cpu_count() // (2 * self.max_sessions))

    @property
    def sessions_dir(self) -> Path:
        return self.data_dir / "sessions"

    @property
    def database_path(self) -> Path:
        return self.data_dir / "sessions.sqlite3"
