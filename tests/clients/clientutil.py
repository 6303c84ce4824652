"""Helpers of the client tests: a real server (uvicorn thread on 127.0.0.1, zenoh bridge on a free
loopback port), tiny engine settings and tiny synthetic frames.

(A plain module beside the tests: pytest puts this folder on ``sys.path``; conftest is not importable.)
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import uvicorn

from tests.server.srvutil import free_port, wait_until  # noqa: F401 - shared test helpers, re-exported
from voxfusion.core.datasets.frame import RGBDFrame
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.trajectory import Trajectory
from voxfusion.server import ServerSettings, create_app

TINY = ["mapping.rays_per_frame=128", "tracking.rays=128", "tracking.iters=10", "mapping.first_frame_iters=30",
        "field.sdf_hidden=32", "field.color_hidden=32", "mesh_res=4"]
"""Engine overrides small enough for a 2-core CPU (same method, fewer rays and iterations)."""


def tiny_frames(n: int, seed: int = 0, width: int = 96, height: int = 72) -> list[RGBDFrame]:
    """``n`` frames of the synthetic room at ``width`` x ``height`` (with reference poses)."""
    return list(SyntheticCapture(SyntheticConfig(n_frames=n, width=width, height=height, seed=seed)).frames())


def reference(frames: list[RGBDFrame]) -> Trajectory:
    return Trajectory(np.array([f.timestamp_s for f in frames]), np.stack([f.T_world_cam for f in frames]))


def write_zenoh_server_config(path: Path, port: int) -> Path:
    """The shipped server config with the listen port replaced (loopback only, scouting off)."""
    text = (Path(__file__).resolve().parents[2] / "configs" / "zenoh" / "server.json5").read_text()
    path.write_text(text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}"))
    return path


class LiveServer:
    """``create_app`` served by uvicorn in a thread, with the zenoh bridge listening on a free port."""

    def __init__(self, data_dir: Path, **settings) -> None:
        self.zenoh_port = free_port()
        zenoh_config = write_zenoh_server_config(data_dir.parent / f"zenoh-{self.zenoh_port}.json5", self.zenoh_port)
        self.settings = ServerSettings(data_dir=data_dir, device="cpu", zenoh=True, zenoh_config=zenoh_config,
                                       **settings)
        self.port = free_port()
        self.app = create_app(self.settings)
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning",
                                                    lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-client-tests", daemon=True)
        self.thread.start()
        wait_until(lambda: self.server.started, 60, "the server to start")
        self.url = f"http://127.0.0.1:{self.port}"
        self.zenoh_connect = [f"tcp/127.0.0.1:{self.zenoh_port}"]

    @property
    def manager(self):
        return self.app.state.manager

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)
