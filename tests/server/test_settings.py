"""ServerSettings: which device the sessions' engines run on when they run as Ray actors."""

from __future__ import annotations

from pathlib import Path

import pytest

from voxfusion.core.errors import ConfigError
from voxfusion.server import ServerSettings


def test_ray_actors_without_a_gpu_share_run_cpu_sessions(tmp_path: Path):
    """Ray empties ``CUDA_VISIBLE_DEVICES`` in an actor that asks for no GPU: ``auto`` must mean CPU there (CPU
    presets), ``cuda`` is refused at start with the flag to give; with a GPU share the sessions are CUDA ones."""
    common = {"data_dir": tmp_path, "zenoh": False, "ray_address": "127.0.0.1:6379"}
    assert ServerSettings(**common).session_device() == "cpu"
    # a GPU share: the actors run on GPU nodes whatever the API host has
    assert ServerSettings(**common, gpus_per_session=0.25).session_device() == "cuda"
    assert ServerSettings(**common, device="cuda", gpus_per_session=0.25).session_device() == "cuda"
    with pytest.raises(ConfigError, match="gpus_per_session") as info:
        ServerSettings(**common, device="cuda")
    assert "--gpus-per-session" in str(info.value)
    # worker processes and threads see the host's devices: the server's setting stands
    assert ServerSettings(data_dir=tmp_path, zenoh=False, device="cuda").session_device() == "cuda"


def test_a_gpu_less_api_host_picks_gpu_presets_for_ray_sessions_with_a_gpu_share(tmp_path: Path):
    """The API host here has no GPU; sessions on Ray actors with a GPU share run on GPU nodes, so the server's
    default preset is the GPU-sized one and the host itself keeps the CPU (stored maps, health)."""
    from voxfusion.server.manager import SessionManager

    common = {"data_dir": tmp_path, "zenoh": False, "ray_address": "127.0.0.1:6379"}
    with_gpus = SessionManager(ServerSettings(**common, gpus_per_session=0.25))
    assert with_gpus.default_preset == "default" and with_gpus.device.type == "cpu"
    without = SessionManager(ServerSettings(**common))
    assert without.default_preset == "cpu" and without.device.type == "cpu"
    # --device cuda names the sessions' device: a GPU-less API host in front of GPU nodes still starts
    explicit = SessionManager(ServerSettings(**common, device="cuda", gpus_per_session=0.25))
    assert explicit.default_preset == "default" and explicit.device.type == "cpu"


def test_worker_threads_follow_the_cores_this_process_may_use(tmp_path: Path, monkeypatch):
    """The automatic torch thread count of a worker divides the cores the API process may run on (its affinity,
    e.g. a container's cpuset), not every core of the host, among the sessions' tracking and mapping threads."""
    import os

    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    common = {"data_dir": tmp_path, "zenoh": False}
    assert ServerSettings(**common, max_sessions=2).torch_threads_per_worker() == 2
    assert ServerSettings(**common, max_sessions=8).torch_threads_per_worker() == 1  # at least one
    assert ServerSettings(**common, max_sessions=8, worker_threads=3).torch_threads_per_worker() == 3
