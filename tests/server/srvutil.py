"""Helpers of the server tests: a real uvicorn server on 127.0.0.1 (a thread of this process, or a
subprocess that can be killed), tiny engine settings, and synthetic frames encoded for the wire.

(A plain module beside the tests: pytest puts this folder on ``sys.path``; conftest is not importable.)
"""

from __future__ import annotations

import io
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import uvicorn
from PIL import Image

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.trajectory import Trajectory
from voxfusion.proto import MEDIA_TYPE, encode_frame
from voxfusion.server import ServerSettings, create_app
from voxfusion.server.child import ServeProcess, ServerStartError, free_port

TINY = {"mapping": {"rays_per_frame": 128, "first_frame_iters": 30}, "tracking": {"rays": 128, "iters": 10},
        "field": {"sdf_hidden": 32, "color_hidden": 32}, "mesh_res": 4}
"""Engine overrides small enough for a 2-core CPU (same method, fewer rays and iterations)."""
FAST = {"mapping": {"rays_per_frame": 64, "first_frame_iters": 2, "iters": 1},
        "tracking": {"rays": 64, "iters": 2}, "field": {"sdf_hidden": 16, "color_hidden": 16}, "mesh_res": 2}
"""For tests of the server's behaviour, not of the map's quality: as little engine work as possible."""


def png(img: np.ndarray) -> bytes:
    """``img`` (uint8 / uint16, grey or BGR) encoded as PNG."""
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def jpeg(rgb: np.ndarray) -> bytes:
    """``rgb`` (``[H, W, 3]`` uint8) encoded as JPEG (quality 90)."""
    out = io.BytesIO()
    Image.fromarray(rgb).save(out, format="JPEG", quality=90)
    return out.getvalue()


def wait_until(predicate, timeout_s: float, what: str, poll_s: float = 0.1):
    """Poll ``predicate`` until it returns a truthy value (returned) or fail the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    event = threading.Event()
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        event.wait(poll_s)


@dataclass
class Scene:
    """A synthetic capture, its frames encoded as wire messages, and its ground-truth trajectory."""

    capture: SyntheticCapture
    messages: list[bytes]
    gt: Trajectory


def make_scene(n_frames: int, seed: int, width: int = 96, height: int = 72) -> Scene:
    cap = SyntheticCapture(SyntheticConfig(n_frames=n_frames, width=width, height=height, seed=seed))
    frames = list(cap.frames())
    messages = [encode_frame(f, seq=i, depth_encoding="png16_mm", color_encoding="jpeg") for i, f in enumerate(frames)]
    gt = Trajectory(np.array([f.timestamp_s for f in frames]), np.stack([f.T_world_cam for f in frames]))
    return Scene(cap, messages, gt)


class Api:
    """A small httpx client of one server, with the session token helpers the tests need."""

    def __init__(self, base_url: str) -> None:
        self.base_url = base_url
        self.http = httpx.Client(base_url=base_url, timeout=120.0)

    def create(self, name: str = "test", config: dict | None = None, mode: str = "realtime",
               **extra) -> tuple[str, str]:
        r = self.http.post("/sessions", json={"name": name, "config": config or TINY, "mode": mode, **extra})
        assert r.status_code == 201, r.text
        body = r.json()
        return body["id"], body["token"]

    @staticmethod
    def auth(token: str) -> dict[str, str]:
        return {"Authorization": f"Bearer {token}"}

    def post_frame(self, sid: str, token: str, data: bytes, content_type: str = MEDIA_TYPE) -> httpx.Response:
        return self.http.post(f"/sessions/{sid}/frames", content=data,
                              headers={**self.auth(token), "Content-Type": content_type})

    def status(self, sid: str, token: str) -> dict:
        r = self.http.get(f"/sessions/{sid}", headers=self.auth(token))
        assert r.status_code == 200, r.text
        return r.json()

    def close(self) -> None:
        self.http.close()


class ServerThread:
    """uvicorn serving ``create_app(settings)`` in a thread of the test process (so tests can patch the
    engine); ``stop()`` shuts it down through the app's lifespan."""

    def __init__(self, settings: ServerSettings) -> None:
        self.settings = settings
        self.port = free_port()
        self.app = create_app(settings)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="on",
                                ws_ping_interval=None)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-test", daemon=True)
        self.thread.start()
        wait_until(lambda: self.server.started, 60, "the server to start")
        self.url = f"http://127.0.0.1:{self.port}"
        self.api = Api(self.url)

    @property
    def manager(self):
        return self.app.state.manager

    def stop(self) -> None:
        self.api.close()
        self.server.should_exit = True
        self.thread.join(timeout=120)


class ServerProcess(ServeProcess):
    """``voxfusion serve`` in a subprocess on a data folder (checkpoints every second), with an :class:`Api`;
    ``kill()`` sends SIGKILL. A child that does not start fails the test with its log."""

    def __init__(self, data_dir: Path, *extra: str) -> None:
        try:
            super().__init__(data_dir, "--checkpoint-interval-s", "1", *extra, start_timeout_s=90)
        except ServerStartError as e:
            pytest.fail(str(e))
        self.api = Api(self.url)

    def read_log(self) -> str:
        return self.log_tail()

    def _close(self) -> None:
        if hasattr(self, "api"):  # not yet there when the child failed to start
            self.api.close()
        super()._close()
