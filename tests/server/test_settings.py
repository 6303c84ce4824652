"""ServerSettings: which device the sessions' engines run on when they run as Ray actors."""

from __future__ import annotations

from pathlib import Path

import pytest

from voxfusion.core.errors import ConfigError
from voxfusion.server import ServerSettings


def test_ray_actors_without_a_gpu_share_run_cpu_sessions(tmp_path: Path):
    """Ray empties ``CUDA_VISIBLE_DEVICES`` in an actor that asks for no GPU: ``auto`` must mean CPU there (CPU
    presets), ``cuda`` is refused at start with the flag to give, and a GPU share keeps the server's choice."""
    common = {"data_dir": tmp_path, "zenoh": False, "ray_address": "127.0.0.1:6379"}
    assert ServerSettings(**common).session_device() == "cpu"
    assert ServerSettings(**common, gpus_per_session=0.25).session_device() == "auto"
    assert ServerSettings(**common, device="cuda", gpus_per_session=0.25).session_device() == "cuda"
    with pytest.raises(ConfigError, match="gpus_per_session") as info:
        ServerSettings(**common, device="cuda")
    assert "--gpus-per-session" in str(info.value)
    # worker processes and threads see the host's devices: the server's setting stands
    assert ServerSettings(data_dir=tmp_path, zenoh=False, device="cuda").session_device() == "cuda"
