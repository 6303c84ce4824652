"""The NeRFCapture bridge: its fast CDR decoder against cyclonedds' own, the ARKit -> OpenCV conversion,
and a real CycloneDDS publisher (a subprocess with the app's exact IDL type, on loopback) streamed into a
real server session."""

import json
import random
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from clientutil import TINY, LiveServer, tiny_frames
from cyclonedds.idl._support import Endianness
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.clients import Client
from voxfusion.clients.nerfcapture import (
    NeRFCaptureFrame,
    NeRFCaptureReceiver,
    convert_nerfcapture,
    dds_config_xml,
    parse_nerfcapture_cdr,
    run_nerfcapture_bridge,
)
from voxfusion.core.errors import ValidationError
from voxfusion.core.geometry import opencv_to_opengl
from voxfusion.proto.recording import RecordingCapture

HERE = Path(__file__).resolve().parent


def _message(frame, scale: int = 4, msg_id: int = 7) -> NeRFCaptureFrame:
    """A sample as the app writes it for ``frame``: ARKit pose (column-major), K and RGB for scale x depth."""
    h, w = frame.depth_m.shape
    color = np.repeat(np.repeat(frame.color, scale, axis=0), scale, axis=1)
    K = frame.K
    return NeRFCaptureFrame(
        id=msg_id, timestamp=frame.timestamp_s, fl_x=K[0, 0] * scale, fl_y=K[1, 1] * scale, cx=K[0, 2] * scale,
        cy=K[1, 2] * scale, transform_matrix=[float(v) for v in opencv_to_opengl(frame.T_world_cam).T.reshape(-1)],
        width=w * scale, height=h * scale, image=color.tobytes(), has_depth=True, depth_width=w, depth_height=h,
        depth_scale=1.0, depth_image=frame.depth_m.astype("<f4").tobytes())


@pytest.fixture(scope="module")
def frames():
    return tiny_frames(4, seed=2)


@pytest.mark.parametrize("endianness", [Endianness.Little, Endianness.Big])
@pytest.mark.parametrize("xcdr2", [False, True])
def test_fast_decoder_matches_cyclonedds(frames, endianness, xcdr2):
    msg = _message(frames[1], scale=2)
    data = msg.serialize(endianness=endianness, use_version_2=xcdr2)
    ref = NeRFCaptureFrame.__idl__.deserialize(data)  # cyclonedds' generic decoder
    fast = parse_nerfcapture_cdr(data)
    assert NeRFCaptureFrame.deserialize(data).image == fast.image  # the override takes the fast path
    for name in ("id", "timestamp", "fl_x", "fl_y", "cx", "cy", "width", "height", "has_depth", "depth_width",
                 "depth_height", "depth_scale"):
        assert getattr(fast, name) == getattr(ref, name), name
    assert fast.transform_matrix == ref.transform_matrix
    assert fast.image == bytes(ref.image) and fast.depth_image == bytes(ref.depth_image)


def test_fast_decoder_refuses_truncated_samples(frames):
    data = _message(frames[0], scale=1).serialize()
    for cut in (2, 10, 60, len(data) - 5):
        with pytest.raises(ValidationError):
            parse_nerfcapture_cdr(data[:cut])


def test_conversion_to_opencv_row_major_and_depth_intrinsics(frames):
    frame = frames[2]
    conv = convert_nerfcapture(_message(frame, scale=4), color_width=192)
    h, w = frame.depth_m.shape
    np.testing.assert_array_equal(conv.frame.depth_m, frame.depth_m)
    np.testing.assert_allclose(conv.frame.K, frame.K, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(conv.frame.T_world_cam_device, frame.T_world_cam, atol=1e-6)
    assert conv.frame.index == 7 and conv.frame.timestamp_s == pytest.approx(frame.timestamp_s)
    assert (conv.intrinsics.width, conv.intrinsics.height) == (4 * w, 4 * h)
    assert conv.intrinsics.fx == pytest.approx(4 * frame.K[0, 0], rel=1e-6)
    assert conv.color.shape == (h * 2, 192, 3)
    np.testing.assert_allclose(conv.color[::2, ::2].astype(float), frame.color.astype(float), atol=1)
    assert convert_nerfcapture(_message(frame), color_width=0).color is None


def test_conversion_skips_frames_without_depth_and_refuses_bad_sizes(frames):
    msg = _message(frames[0], scale=1)
    msg.has_depth = False
    assert convert_nerfcapture(msg) is None
    msg = _message(frames[0], scale=1)
    msg.depth_image = msg.depth_image[:-4]
    with pytest.raises(ValidationError) as err:
        convert_nerfcapture(msg)
    assert err.value.field == "depth_image"
    msg = _message(frames[0], scale=1)
    msg.width += 1
    with pytest.raises(ValidationError) as err:
        convert_nerfcapture(msg)
    assert err.value.field == "image"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = LiveServer(tmp_path_factory.mktemp("nerfcapture") / "data")
    yield srv
    srv.stop()


def _publisher(domain_id: int, n_frames: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(HERE / "nerfcapture_publisher.py"), str(domain_id), str(n_frames)],
                            stderr=subprocess.PIPE, text=True)


def test_bridge_streams_a_dds_publisher_into_a_session(server):
    n_frames = 6
    domain_id = random.randint(100, 150)
    receiver = NeRFCaptureReceiver(domain_id, dds_config_xml(loopback=True))
    publisher = _publisher(domain_id, n_frames)
    try:
        with Client(server.url) as client:
            session = client.create_session("nerfcapture", TINY, mode="offline")
            stats = run_nerfcapture_bridge(client, receiver=receiver, max_frames=n_frames, idle_timeout_s=90)
            assert publisher.wait(timeout=60) == 0, publisher.stderr.read()
            assert (stats.received, stats.sent, stats.invalid, stats.skipped_no_depth) == (n_frames, n_frames, 0, 0)
            status = client.finish(timeout_s=300)
            assert status.state.value == "finished" and status.frames_tracked == n_frames
            assert len(client.trajectory()) == n_frames
        # what the server recorded is the publisher's frame in OpenCV conventions at the depth resolution
        expected = tiny_frames(n_frames, seed=5)
        recorded = list(RecordingCapture(server.settings.sessions_dir / session.id).frames())
        assert len(recorded) == n_frames
        for got, want in zip(recorded, expected, strict=True):
            np.testing.assert_allclose(got.T_world_cam_device, want.T_world_cam, atol=1e-5)
            np.testing.assert_allclose(got.K, want.K, rtol=1e-5)
            np.testing.assert_allclose(got.depth_m, want.depth_m, atol=1e-3)  # zstd_u16_mm: 1 mm steps
            assert got.color is not None and got.color.shape == want.color.shape
    finally:
        if publisher.poll() is None:
            publisher.kill()


def test_bridge_command(server, tmp_path):
    domain_id = random.randint(151, 200)
    publisher = _publisher(domain_id, 3)
    out = tmp_path / "out"
    try:
        result = CliRunner().invoke(app, ["bridge", "nerfcapture", "--server", server.url, "--loopback",
                                          "--domain-id", str(domain_id), "--max-frames", "3", "--idle-timeout", "90",
                                          "--out", str(out), *[a for item in TINY for a in ("--set", item)]])
        assert result.exit_code == 0, result.output + repr(result.exception)
        assert publisher.wait(timeout=60) == 0, publisher.stderr.read()
    finally:
        if publisher.poll() is None:
            publisher.kill()
    info = json.loads((out / "session.json").read_text())
    assert f"session {info['id']}" in result.output
    assert f"viewer: {server.url}/sessions/{info['id']}/view?token={info['token']}" in result.output
    assert f"mesh: {server.url}/sessions/{info['id']}/mesh" in result.output
    assert "received 3, sent 3" in result.output
    assert (out / "mesh.ply").read_bytes()[:3] == b"ply" and (out / "trajectory.txt").is_file()
    assert server.manager.status(info["id"]).frames_received == 3


def test_bridge_without_a_phone_leaves_no_session(server, tmp_path):
    """No frame ever arrives: the session is created lazily, so none is created at all (nothing to delete,
    even had the bridge been killed)."""
    before = {row.id for row in server.manager.store.all()}
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["bridge", "nerfcapture", "--server", server.url, "--loopback", "--domain-id",
                                      str(random.randint(201, 232)), "--idle-timeout", "1", "--out", str(out)])
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "received 0, sent 0" in result.output
    assert "no frame with depth arrived: no session was created" in result.output
    assert not re.search(r"^session [0-9a-f]", result.output, re.MULTILINE) and "viewer:" not in result.output
    assert {row.id for row in server.manager.store.all()} == before
    assert not (out / "session.json").exists()


def test_bridge_creates_its_session_with_the_first_frame(server):
    """The library call: ``open_session`` runs once, just before the first frame is sent."""
    domain_id = random.randint(100, 232)
    receiver = NeRFCaptureReceiver(domain_id, dds_config_xml(loopback=True))
    publisher = _publisher(domain_id, 2)
    calls = []
    try:
        with Client(server.url) as client:
            def open_session():
                calls.append(len(server.manager.store.all()))
                client.create_session("lazy", TINY, mode="offline")

            stats = run_nerfcapture_bridge(client, receiver=receiver, max_frames=2, idle_timeout_s=90,
                                           open_session=open_session)
            assert publisher.wait(timeout=60) == 0, publisher.stderr.read()
            assert stats.sent == 2 and len(calls) == 1
            assert server.manager.status(client.session.id).frames_received == 2
    finally:
        if publisher.poll() is None:
            publisher.kill()
