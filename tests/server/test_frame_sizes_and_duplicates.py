"""Frames over HTTP, both body kinds: multipart images that do not match the sizes the upload declares are
refused with 422 naming the part (nothing recorded), what the binary format allows (colour and intrinsics at
another resolution of the same aspect ratio) stays allowed, and a resent ``seq`` is answered as a duplicate
and never changes the recording, before and after a restart."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import zstandard
from srvutil import FAST, ServerThread, jpeg, make_scene, png

from voxfusion.proto import read_header
from voxfusion.proto.container import Payloads, pack_message
from voxfusion.proto.recording import RecordingCapture
from voxfusion.server import ServerSettings

W, H = 96, 72


@pytest.fixture(scope="module")
def scene():
    return make_scene(2, seed=11, width=W, height=H)


@pytest.fixture
def session(server_factory):
    srv = server_factory()
    sid, token = srv.api.create("sizes", config=FAST)
    return srv, sid, token


def intrinsics(frame, scale: float = 1.0, width: int = W, height: int = H) -> dict:
    K = frame.K
    return {"fx": K[0, 0] * scale, "fy": K[1, 1] * scale, "cx": K[0, 2] * scale, "cy": K[1, 2] * scale,
            "width": round(width * scale), "height": round(height * scale)}


def post_multipart(srv, sid, token, meta: dict, **files):
    return srv.api.http.post(f"/sessions/{sid}/frames", headers=srv.api.auth(token),
                             data={"metadata": json.dumps(meta)}, files=files)


def recording(srv, sid) -> RecordingCapture:
    return RecordingCapture(srv.settings.sessions_dir / sid)


def check_422(r, field: str, *words: str) -> None:
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == field, body
    for w in words:
        assert w in body["detail"], body


def test_multipart_images_must_match_the_declared_sizes(session, scene):
    srv, sid, token = session
    frame = scene.capture[0]
    depth_mm = np.round(frame.depth_m * 1000).astype(np.uint16)
    depth_png = ("d.png", png(depth_mm), "image/png")
    meta = {"seq": 1, "timestamp_s": 0.5, "intrinsics": intrinsics(frame)}
    wide = np.zeros((50, 50, 3), np.uint8)
    f32 = frame.depth_m.astype("<f4").tobytes()
    zstd_small = zstandard.ZstdCompressor().compress(depth_mm[:36, :48].astype("<u2").tobytes())
    cases = [
        # depth: declared size, aspect ratio of the intrinsics, byte counts of raw and zstd payloads
        ({**meta, "depth_width": 48, "depth_height": 36}, {"depth": depth_png}, "depth", ("96x72", "48x36")),
        ({**meta, "intrinsics": {**meta["intrinsics"], "width": 96, "height": 96, "cy": 47.5}}, {"depth": depth_png},
         "depth", ("96x72", "96x96")),
        ({**meta, "depth_encoding": "raw_f32_m", "depth_width": W, "depth_height": H},
         {"depth": ("d.bin", f32[:-4], "application/octet-stream")}, "depth", ("27644",)),
        ({**meta, "depth_encoding": "zstd_u16_mm", "depth_width": W, "depth_height": H},
         {"depth": ("d.zst", zstd_small, "application/octet-stream")}, "depth", ("3456",)),
        # colour: aspect ratio, declared size
        (meta, {"depth": depth_png, "color": ("c.jpg", jpeg(wide), "image/jpeg")}, "color", ("50x50",)),
        ({**meta, "color_width": W, "color_height": H},
         {"depth": depth_png, "color": ("c.jpg", jpeg(cv2.resize(frame.color, (2 * W, 2 * H))), "image/jpeg")},
         "color", ("192x144", "96x72")),
        # confidence: always the depth's size
        (meta, {"depth": depth_png, "confidence": ("q.png", png(np.ones((36, 48), np.uint8)), "image/png")},
         "confidence", ("48x36",)),
        (meta, {"depth": depth_png, "confidence": ("q.bin", bytes(W * H - 1), "application/octet-stream")},
         "confidence", ("6911",)),
    ]
    for m, files, field, words in cases:
        check_422(post_multipart(srv, sid, token, m, **files), field, *words)
    assert len(recording(srv, sid)) == 0  # nothing refused was recorded

    # declared sizes that match; confidence at the depth's size
    ok = post_multipart(srv, sid, token, {**meta, "depth_width": W, "depth_height": H, "color_width": W,
                                          "color_height": H},
                        depth=depth_png, color=("c.jpg", jpeg(frame.color), "image/jpeg"),
                        confidence=("q.png", png(np.full((H, W), 2, np.uint8)), "image/png"))
    assert ok.status_code == 202, ok.text
    assert ok.json() == {"seq": 1, "session": sid, "duplicate": False, "action": "recorded"}


def test_what_the_binary_format_allows_stays_allowed(session, scene):
    """proto/README.md: colour at another size of the depth's aspect ratio is resized to the depth's size
    (§3.2); intrinsics may be stated for another resolution of that aspect ratio and are scaled (§4)."""
    srv, sid, token = session
    frame = scene.capture[1]
    big = cv2.resize(frame.color, (2 * W, 2 * H), interpolation=cv2.INTER_CUBIC)
    depth_png = png(np.round(frame.depth_m * 1000).astype(np.uint16))
    meta = {"seq": 7, "timestamp_s": 1.0, "intrinsics": intrinsics(frame, scale=4.0), "color_width": 2 * W,
            "color_height": 2 * H}
    r = post_multipart(srv, sid, token, meta, depth=("d.png", depth_png, "image/png"),
                       color=("c.jpg", jpeg(big), "image/jpeg"))
    assert r.status_code == 202, r.text
    # the same frame as a binary message
    hdr = {"session": None, "seq": 8, "timestamp_s": 1.0, "intrinsics": intrinsics(frame, scale=4.0),
           "depth": {"encoding": "png16_mm", "units": "mm", "width": W, "height": H},
           "color": {"encoding": "jpeg", "width": 2 * W, "height": 2 * H}, "confidence": None, "device_pose": None}
    r = srv.api.post_frame(sid, token, pack_message(hdr, Payloads(color=jpeg(big), depth=depth_png, confidence=b"")))
    assert r.status_code == 202, r.text
    cap = recording(srv, sid)
    assert cap.seqs() == [7, 8]
    assert read_header(cap.message(0)).color_width == 2 * W  # recorded as sent, not re-encoded
    for i in range(2):
        got = cap[i]
        assert got.color.shape == (H, W, 3)
        np.testing.assert_allclose(got.K, frame.K, rtol=1e-6)
        np.testing.assert_allclose(got.depth_m, frame.depth_m, atol=6e-4)


def test_a_resent_seq_is_a_duplicate_and_never_changes_the_recording(server_factory, scene, tmp_path):
    data_dir = tmp_path / "data"
    srv = server_factory(data_dir=data_dir)
    sid, token = srv.api.create("dup", config=FAST)
    first, other = scene.messages
    frame = scene.capture[1]  # another frame's images, sent with the same seq over multipart
    multipart_other = {"depth": ("d.png", png(np.round(frame.depth_m * 1000).astype(np.uint16)), "image/png")}
    meta0 = {"seq": 0, "timestamp_s": 9.0, "intrinsics": intrinsics(frame)}

    r = srv.api.post_frame(sid, token, first)
    assert r.json() == {"seq": 0, "session": sid, "duplicate": False, "action": "recorded"}
    assert "X-Duplicate" not in r.headers
    duplicate = {"seq": 0, "session": sid, "duplicate": True, "action": "ignored"}
    again = srv.api.post_frame(sid, token, first)
    assert again.status_code == 202 and again.json() == duplicate and again.headers["X-Duplicate"] == "true"
    changed = post_multipart(srv, sid, token, meta0, **multipart_other)  # same seq, other content, multipart
    assert changed.status_code == 202 and changed.json() == duplicate and changed.headers["X-Duplicate"] == "true"
    r = post_multipart(srv, sid, token, {**meta0, "seq": 1}, **multipart_other)
    assert r.json()["action"] == "recorded"
    assert post_multipart(srv, sid, token, {**meta0, "seq": 1}, **multipart_other).json()["duplicate"] is True
    assert srv.api.post_frame(sid, token, other).json()["duplicate"] is True  # seq 1 again, binary this time
    cap = recording(srv, sid)
    assert cap.seqs() == [0, 1] and cap.message(0) == first
    assert srv.api.status(sid, token)["frames_received"] == 2
    srv.stop()

    # after a restart the session resumes from its recording and still knows both seqs
    again_srv = ServerThread(ServerSettings(data_dir=data_dir, device="cpu", zenoh=False))
    try:
        r = again_srv.api.post_frame(sid, token, first)
        assert r.status_code == 202 and r.json() == duplicate, r.text
        r = again_srv.api.post_frame(sid, token, other)
        assert r.json()["duplicate"] is True
        cap = recording(again_srv, sid)
        assert cap.seqs() == [0, 1] and cap.message(0) == first
    finally:
        again_srv.stop()
