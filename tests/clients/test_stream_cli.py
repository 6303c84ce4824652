"""``voxfusion stream`` against a real server on loopback, over HTTP and over zenoh, and the pacing."""

from __future__ import annotations

import json
import stat
import time

import pytest
from clientutil import TINY, LiveServer
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.clients.stream import Pacer, StreamOptions
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
from voxfusion.core.errors import ValidationError
from voxfusion.core.trajectory import read_tum_trajectory

SETS = [arg for item in TINY for arg in ("--set", item)]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = LiveServer(tmp_path_factory.mktemp("stream-cli") / "data")
    yield srv
    srv.stop()


def _check_outputs(server, out, n_frames: int, output: str) -> str:
    """Files written, id and mesh location printed, every frame received; the trajectory holds every tracked
    frame (all of them in offline mode; realtime mode may skip frames to keep up)."""
    info = json.loads((out / "session.json").read_text())
    assert stat.S_IMODE((out / "session.json").stat().st_mode) == 0o600
    assert f"session {info['id']}" in output
    assert f"mesh: {info['mesh']}" in output
    assert (out / "mesh.ply").read_bytes()[:3] == b"ply"
    status = server.manager.status(info["id"])
    assert status.frames_received == n_frames and status.state.value == "finished"
    assert 1 <= len(read_tum_trajectory(out / "trajectory.txt")) == status.frames_tracked <= n_frames
    return info["id"]


def test_stream_synthetic_over_http(server, tmp_path):
    out = tmp_path / "http"
    result = CliRunner().invoke(app, ["stream", "--synthetic", "5", "--synthetic-size", "96x72", "--server",
                                      server.url, "--out", str(out), *SETS])
    assert result.exit_code == 0, result.output + repr(result.exception)
    sid = _check_outputs(server, out, 5, result.output)
    assert f"mesh: {server.url}/sessions/{sid}/mesh" in result.output
    assert "ATE rmse" in result.output
    status = server.manager.status(sid)
    assert status.mode.value == "offline" and status.frames_tracked == 5  # as fast as possible: every frame


def test_stream_a_capture_on_disk_over_zenoh_at_its_recorded_rate(server, tmp_path):
    capture = write_capture(SyntheticCapture(SyntheticConfig(n_frames=6, width=96, height=72, seed=1)),
                            tmp_path / "tum_capture", layout="tum")
    config = tmp_path / "client.json5"
    config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": server.zenoh_connect},
                                  "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
    out = tmp_path / "zenoh"
    t0 = time.monotonic()
    result = CliRunner().invoke(app, ["stream", str(capture), "--zenoh", str(config), "--realtime", "--out", str(out),
                                      *SETS])
    assert result.exit_code == 0, result.output + repr(result.exception)
    sid = _check_outputs(server, out, 6, result.output)
    assert f"mesh: voxfusion/@v1/sessions/{sid}/mesh" in result.output
    assert time.monotonic() - t0 >= 5 / 30  # 6 frames at their recorded 30 fps
    assert server.manager.status(sid).mode.value == "realtime"


def test_stream_refuses_ambiguous_arguments(server, tmp_path):
    result = CliRunner().invoke(app, ["stream", "--synthetic", "3", "--server", server.url, "--zenoh", "default"])
    assert result.exit_code != 0 and isinstance(result.exception, ValidationError)
    assert result.exception.field == "server"
    result = CliRunner().invoke(app, ["stream", "--synthetic", "3", "--server", server.url, "--fps", "5",
                                      "--realtime"])
    assert isinstance(result.exception, ValidationError) and result.exception.field == "fps"


class _FakeClock:
    """``time.monotonic`` / ``time.sleep`` of the pacer: sleeping advances the clock exactly."""

    def __init__(self) -> None:
        self.now = 100.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        assert s > 0
        self.now += s


def test_pacer_follows_fps_and_timestamps(monkeypatch):
    frames = list(SyntheticCapture(SyntheticConfig(n_frames=4, width=16, height=12, fps=40.0)).frames())
    for options, expected_s in ((StreamOptions(fps=50.0), 3 / 50), (StreamOptions(realtime=True), 3 / 40),
                                (StreamOptions(), 0.0)):
        clock = _FakeClock()
        monkeypatch.setattr("voxfusion.clients.stream.time", clock)
        pacer = Pacer(options)
        sent_at = []
        for f in frames:
            pacer.wait(f)
            sent_at.append(clock.now - 100.0)
        assert sent_at == pytest.approx([i * expected_s / 3 for i in range(4)])
