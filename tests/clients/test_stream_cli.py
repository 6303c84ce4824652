"""``voxfusion stream`` against a real server on loopback, over HTTP and over zenoh, and the pacing."""

from __future__ import annotations

import json
import re
import stat
import time

import httpx
import pytest
from clientutil import TINY, LiveServer, wait_until
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


def test_pacer_follows_irregular_timestamps(monkeypatch):
    """``realtime`` follows each frame's own timestamp (a phone's frames are not evenly spaced), not a rate."""
    import dataclasses

    base = list(SyntheticCapture(SyntheticConfig(n_frames=4, width=16, height=12)).frames())
    stamps = [50.0, 50.231, 50.431, 50.532]
    frames = [dataclasses.replace(f, timestamp_s=t) for f, t in zip(base, stamps, strict=True)]
    clock = _FakeClock()
    monkeypatch.setattr("voxfusion.clients.stream.time", clock)
    pacer = Pacer(StreamOptions(realtime=True))
    sent_at = []
    for f in frames:
        pacer.wait(f)
        sent_at.append(clock.now - 100.0)
    assert sent_at == pytest.approx([t - 50.0 for t in stamps])


def test_realtime_sends_at_the_capture_rate_and_reports_drops(server, tmp_path):
    """A 5 frames/s capture is sent over 1 s (not at 30 frames/s or as fast as possible); the summary
    counts what the server received, tracked, lost and dropped, and the viewer link comes with the id."""
    capture = write_capture(SyntheticCapture(SyntheticConfig(n_frames=6, width=96, height=72, seed=3, fps=5.0)),
                            tmp_path / "slow_capture", layout="tum")
    out = tmp_path / "realtime"
    t0 = time.monotonic()
    result = CliRunner().invoke(app, ["stream", str(capture), "--server", server.url, "--realtime", "--out", str(out),
                                      *SETS])
    elapsed = time.monotonic() - t0
    assert result.exit_code == 0, result.output + repr(result.exception)
    sid = _check_outputs(server, out, 6, result.output)
    assert elapsed >= 1.0
    assert "the capture's own rate: 5.0 frames/s over 1.0 s" in result.output
    status = server.manager.status(sid)
    assert status.mode.value == "realtime"
    assert re.search(rf"session {sid} finished: 6 received, {status.frames_tracked} tracked "
                     rf"\({status.frames_lost} lost, {status.frames_limited} limited\), "
                     rf"{status.frames_dropped} dropped by the server", result.output)
    assert status.frames_tracked + status.frames_dropped == 6
    token = json.loads((out / "session.json").read_text())["token"]
    lines = result.output.splitlines()
    viewer = lines.index(f"viewer: {server.url}/sessions/{sid}/view?token={token}")
    assert lines[viewer - 1] == f"session {sid}"  # printed as soon as the session exists, before streaming
    assert viewer < next(i for i, line in enumerate(lines) if "sent 6 frames" in line)


def test_viewer_url_is_made_in_one_place(server):
    from voxfusion.clients import Client
    from voxfusion.clients.http_client import viewer_url

    assert viewer_url("http://h:8000/", "abc", "t/k+n=") == "http://h:8000/sessions/abc/view?token=t%2Fk%2Bn%3D"
    with Client(server.url) as client:
        h = client.create_session("viewer-link", TINY, mode="offline")
        assert client.viewer_url == f"{server.url}/sessions/{h.id}/view?token={h.token}"
        assert client.server_device() == "cpu"


def test_an_iphone_capture_gets_the_iphone_preset_at_the_servers_sizes(server, shared_data, tmp_path):
    """No --preset: the Stray Scanner capture gets what `voxfusion run` picks on a CPU (iphone+cpu), printed; the
    session is built with exactly that configuration (sent as the iphone preset plus the cpu sizes)."""
    from voxfusion.core.config import config_to_dict
    from voxfusion.core.datasets import open_capture
    from voxfusion.core.slam.presets import load_preset

    capture = shared_data / "stray_iphone_lidar"
    out = tmp_path / "iphone"
    result = CliRunner().invoke(app, ["stream", str(capture), "--max-frames", "2", "--server", server.url,
                                      "--out", str(out), "--no-finish", *SETS])
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "preset iphone+cpu: stray_iphone_lidar is" in result.output
    assert "; the server's device is cpu (/healthz)" in result.output
    sid = json.loads((out / "session.json").read_text())["id"]
    row = server.manager.store.get(sid)
    want = config_to_dict(load_preset("iphone+cpu", TINY, profile=open_capture(capture).profile))  # as `run` would
    for key in ("field", "mapping", "tracking", "render", "loss", "sized_for", "voxel_size_m"):
        assert row.config[key] == want[key], key
    # the iphone kind's own choices reached the server (ARKit prior weight, a mapping round every 2nd frame)
    assert row.config["tracking"]["device_prior_weight"] == 1000.0 and row.config["mapping"]["map_every"] == 2


def test_an_explicit_preset_wins(server, tmp_path):
    out = tmp_path / "explicit"
    result = CliRunner().invoke(app, ["stream", "--synthetic", "2", "--synthetic-size", "96x72", "--server",
                                      server.url, "--preset", "cpu", "--out", str(out), "--no-finish", *SETS])
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "preset cpu (--preset)" in result.output and "preset synthetic+cpu" not in result.output
    sid = json.loads((out / "session.json").read_text())["id"]
    assert server.manager.store.get(sid).preset == "cpu"


def test_composed_presets_travel_as_kind_plus_sizes():
    """A session request names one preset: ``kind+size`` goes as the kind plus the numbers the size changes,
    which the server turns back into exactly the composed configuration (device and mode left to it)."""
    from voxfusion.commands.stream import wire_preset
    from voxfusion.core.config import apply_overrides, config_to_dict
    from voxfusion.core.slam.presets import load_preset

    for name in ("tum+cpu", "iphone+cpu", "replica+paper", "sevenscenes+cpu"):
        kind, settings = wire_preset(name)
        assert kind == name.split("+")[0] and "device" not in settings and "mode" not in settings
        server_side = config_to_dict(apply_overrides(load_preset(kind), settings))
        want = config_to_dict(load_preset(name))
        assert {k: v for k, v in server_side.items() if k != "device"} == \
            {k: v for k, v in want.items() if k != "device"}, name
    assert wire_preset("iphone") == ("iphone", {})


def test_a_cuda_servers_preset_is_the_kind_alone(monkeypatch):
    import torch

    from voxfusion.commands.stream import session_preset

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # this machine has no GPU; the server has
    cap = SyntheticCapture(SyntheticConfig(n_frames=2, width=32, height=24))
    choice = session_preset(cap, "cuda", None)
    assert choice.name == "synthetic" and choice.reason.endswith("the server has a CUDA device: GPU sizes")
    on_cpu = session_preset(cap, "cpu", None)
    assert on_cpu.name == "synthetic+cpu" and "the server has no CUDA device: CPU sizes" in on_cpu.reason
    assert "requested" not in on_cpu.reason  # nobody asked for the CPU: the server has no GPU


def test_a_frame_beyond_the_trackers_reach_is_limited_on_the_wire(server, shared_data, tmp_path):
    """Real 7-Scenes frames at every 16th (1.9 Hz) through a real server and its worker, with the preset `voxfusion
    run` picks (no tiny sizes: the case measured in tests/core/test_tracking_state.py): frame 4 ends ~14 cm off
    without being lost, and the poses over HTTP, the session status and `/metrics` (open sessions: the session is
    left open) say ``limited``."""
    out = tmp_path / "limited"
    result = CliRunner().invoke(app, ["stream", str(shared_data / "sevenscenes_redkitchen"), "--stride", "16",
                                      "--max-frames", "6", "--server", server.url, "--out", str(out), "--no-finish"])
    assert result.exit_code == 0, result.output + repr(result.exception)
    info = json.loads((out / "session.json").read_text())
    wait_until(lambda: server.manager.status(info["id"]).frames_tracked >= 6, 180, "six frames tracked")
    status = server.manager.status(info["id"])
    assert status.frames_tracked == 6 and status.frames_limited >= 1 and status.frames_lost == 0, status
    auth = {"Authorization": f"Bearer {info['token']}"}
    with httpx.Client(base_url=server.url, timeout=30) as http:
        poses = http.get(f"/sessions/{info['id']}/poses", headers=auth).raise_for_status().json()["poses"]
        metrics = http.get("/metrics").raise_for_status().text
        http.post(f"/sessions/{info['id']}/finish", headers=auth).raise_for_status()
    states = [p["tracking_state"] for p in poses]
    assert states[4] == "limited" and states[:4] == ["normal"] * 4 and poses[4]["cost_ratio"] > 3, poses
    line = next(x for x in metrics.splitlines()
                if x.startswith("voxfusion_session_frames_limited_total{") and info["id"] in x)
    assert float(line.rsplit(" ", 1)[1]) == status.frames_limited
