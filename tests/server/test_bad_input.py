"""Bad input over HTTP: each refusal is a clear 4xx with the offending field, and the session keeps working."""

from __future__ import annotations

import json
import struct
import zlib

import cv2
import numpy as np
import pytest
from srvutil import FAST, jpeg, make_scene, png, wait_until

from voxfusion.proto import encode_frame, read_header
from voxfusion.proto.container import Payloads, pack_message
from voxfusion.proto.recording import RecordingCapture

MAX_BODY = 1 << 20


def raw_message(header_text: str, color: bytes = b"", depth: bytes = b"", confidence: bytes = b"") -> bytes:
    """A frame message with a literal JSON header (to send what the encoder refuses to write, e.g. 1e999)."""
    hb = header_text.encode()
    body = struct.pack("<4sHHIIII", b"VXFR", 1, 0, len(hb), len(color), len(depth), len(confidence))
    body += hb + color + depth + confidence
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.fixture(scope="module")
def scene():
    return make_scene(3, seed=7)


@pytest.fixture
def session(server_factory, scene):
    srv = server_factory(max_frame_bytes=MAX_BODY, max_image_width=256, max_image_height=256)
    sid, token = srv.api.create("bad-input", config=FAST)
    sent = iter(range(100, 1000))

    def good_frame_accepted() -> None:
        """A valid frame is still accepted (and recorded) after the refusal."""
        frame = scene.capture[0]
        seq = next(sent)
        r = srv.api.post_frame(sid, token, encode_frame(frame, seq=seq))
        assert r.status_code == 202, r.text
        assert r.json()["seq"] == seq

    return srv, sid, token, good_frame_accepted


def parts(scene, **changes):
    """Header dict and payloads of a valid frame message, with header keys replaced."""
    msg = scene.messages[0]
    hdr = dict(read_header(msg).raw)
    hdr.update(changes)
    frame = scene.capture[0]
    return hdr, Payloads(color=jpeg(frame.color), depth=png((frame.depth_m * 1000).astype(np.uint16)), confidence=b"")


def check(r, status: int, field: str | None, words: str = "") -> None:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"detail", "field"} and body["field"] == field, body
    assert words.lower() in body["detail"].lower(), body


def test_malformed_messages_are_400_with_the_field(session, scene):
    srv, sid, token, good = session
    api = srv.api
    hdr, pl = parts(scene)
    cases = [
        (scene.messages[0][:-10], "length", "add up"),
        (scene.messages[0][:-4] + b"\0\0\0\0", "crc", "crc"),
        (pack_message(hdr, pl._replace(color=b"\xff\xd8\xff" + bytes(600))), "color", ""),
        (pack_message(hdr, pl._replace(depth=b"\x89PNG\r\n\x1a\n" + bytes(100))), "depth", ""),
        # colour payload of another size than its header states
        (pack_message(hdr, pl._replace(color=jpeg(np.zeros((48, 64, 3), np.uint8)))), "color", "64x48"),
        # depth and colour of different aspect ratios
        (pack_message({**hdr, "color": {"encoding": "jpeg", "width": 50, "height": 50}},
                      pl._replace(color=jpeg(np.zeros((50, 50, 3), np.uint8)))), "color", "aspect"),
        (pack_message({**hdr, "intrinsics": {**hdr["intrinsics"], "fx": 0.0}}, pl), "intrinsics", "> 0"),
        (raw_message(json.dumps(hdr).replace('"fx": ', '"fx": 1e999, "_": '), pl.color, pl.depth), "intrinsics",
         "finite"),
        (pack_message({**hdr, "device_pose": {"convention": "opencv", "layout": "row-major-c2w",
                                              "matrix": np.diag([2.0, 2.0, 2.0, 1.0]).ravel().tolist()}}, pl),
         "device_pose", "not a rigid pose"),
        (raw_message(json.dumps({**hdr, "device_pose": {"convention": "opencv", "layout": "row-major-c2w",
                                                        "matrix": [7777.5] + [0] * 15}}).replace("7777.5", "1e999"),
                     pl.color, pl.depth),
         "device_pose", "finite"),
        (pack_message({**hdr, "session": "0" * 32}, pl), "header", "session"),
        (b"GIF89a" + bytes(100), "magic", "not a voxfusion frame"),
    ]
    for data, field, words in cases:
        check(api.post_frame(sid, token, data), 400, field, words)
        good()
    assert api.status(sid, token)["state"] == "running"


def test_unknown_encodings_and_content_types_are_415(session, scene):
    srv, sid, token, good = session
    api = srv.api
    hdr, pl = parts(scene)
    weird_depth = {**hdr, "depth": {**hdr["depth"], "encoding": "webp16"}}
    check(api.post_frame(sid, token, pack_message(weird_depth, pl)), 415, "depth", "unknown encoding")
    good()
    weird_color = {**hdr, "color": {**hdr["color"], "encoding": "heic"}}
    check(api.post_frame(sid, token, pack_message(weird_color, pl)), 415, "color", "unknown encoding")
    good()
    check(api.post_frame(sid, token, scene.messages[0], content_type="image/png"), 415, "Content-Type")
    good()
    r = api.http.post(f"/sessions/{sid}/frames", headers=api.auth(token),
                      files={"depth": ("d.exr", b"x" * 64, "image/x-exr")},
                      data={"metadata": json.dumps({"seq": 5, "timestamp_s": 0.0, "depth_encoding": "exr",
                                                    "intrinsics": hdr["intrinsics"]})})
    check(r, 415, "depth", "unknown encoding")
    good()


def test_multipart_frames_are_accepted_and_checked(session, scene):
    srv, sid, token, good = session
    api = srv.api
    frame = scene.capture[1]
    h, w = frame.depth_m.shape
    K = frame.K
    meta = {"seq": 50, "timestamp_s": 1.5, "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2],
                                                          "cy": K[1, 2], "width": w, "height": h}}
    depth_png = png(np.round(frame.depth_m * 1000).astype(np.uint16))
    color_big = cv2.resize(frame.color, (2 * w, 2 * h))  # colour may be larger, with the same aspect ratio
    r = api.http.post(f"/sessions/{sid}/frames", headers=api.auth(token), data={"metadata": json.dumps(meta)},
                      files={"depth": ("d.png", depth_png, "image/png"), "color": ("c.jpg", jpeg(color_big),
                                                                                    "image/jpeg")})
    assert r.status_code == 202, r.text
    assert r.json()["seq"] == 50
    # raw float16 metres, with an ARKit device pose (4x4 nested)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 0.3]
    meta2 = {**meta, "seq": 51, "depth_encoding": "raw_f16_m", "depth_width": w, "depth_height": h,
             "device_pose": {"convention": "arkit", "matrix": pose.tolist()}}
    r = api.http.post(f"/sessions/{sid}/frames", headers=api.auth(token), data={"metadata": json.dumps(meta2)},
                      files={"depth": ("d.bin", frame.depth_m.astype("<f2").tobytes(), "application/octet-stream")})
    assert r.status_code == 202, r.text
    cap = RecordingCapture(srv.settings.sessions_dir / sid)
    by_seq = {f.meta["seq"]: f for f in cap.frames()}
    np.testing.assert_allclose(by_seq[50].depth_m, frame.depth_m, atol=6e-4)
    np.testing.assert_allclose(by_seq[51].depth_m, frame.depth_m, rtol=1e-3)
    assert by_seq[50].color.shape == (h, w, 3)
    np.testing.assert_allclose(by_seq[51].T_world_cam_device[:3, 3], [0.1, 0.2, 0.3])
    # refusals: corrupt PNG (400), colour of another aspect ratio and raw depth of the wrong size (422: they do
    # not match the declared sizes, see test_multipart_sizes.py), NaN metadata (400)
    bad = [
        ({"depth": ("d.png", depth_png[:40], "image/png")}, meta, 400, "depth"),
        ({"depth": ("d.png", depth_png, "image/png"),
          "color": ("c.jpg", jpeg(np.zeros((50, 50, 3), np.uint8)), "image/jpeg")}, meta, 422, "color"),
        ({"depth": ("d.bin", b"\0" * 10, "application/octet-stream")}, meta2, 422, "depth"),
        ({"depth": ("d.png", depth_png, "image/png")}, None, 400, "header"),
    ]
    for files, m, status, field in bad:
        text = json.dumps(m) if m is not None else '{"seq": 60, "timestamp_s": NaN}'
        r = api.http.post(f"/sessions/{sid}/frames", headers=api.auth(token), data={"metadata": text}, files=files)
        check(r, status, field)
        good()


def test_oversize_bodies_and_images_are_413(session, scene):
    srv, sid, token, good = session
    api = srv.api
    check(api.post_frame(sid, token, b"\0" * (MAX_BODY + 1)), 413, "body", "limit")
    good()

    def chunks():
        for _ in range(20):
            yield b"\0" * 100_000

    r = api.http.post(f"/sessions/{sid}/frames", content=chunks(),
                      headers={**api.auth(token), "Content-Type": "application/octet-stream"})
    check(r, 413, "body", "limit")
    good()
    big = make_scene(1, seed=7, width=320, height=240).messages[0]
    check(api.post_frame(sid, token, big), 413, "depth", "320x240")
    good()


def test_sessions_tokens_and_states(session, scene, server_factory):
    srv, sid, token, good = session
    api = srv.api
    msg = scene.messages[0]
    check(api.post_frame("0123456789abcdef0123456789abcdef", token, msg), 404, "session_id", "no session")
    check(api.post_frame("not-a-session", token, msg), 404, "session_id")
    check(api.http.post(f"/sessions/{sid}/frames", content=msg), 401, "Authorization")
    check(api.post_frame(sid, "wrong-token", msg), 403, "Authorization", "wrong token")
    other_sid, other_token = api.create("other", config=FAST)
    check(api.post_frame(sid, other_token, msg), 403, "Authorization")  # another session's token
    good()
    r = api.http.post(f"/sessions/{other_sid}/finish", params={"wait": "false"}, headers=api.auth(other_token))
    assert r.status_code in (200, 202) and r.json()["state"] in ("finishing", "finished")
    wait_until(lambda: api.status(other_sid, other_token)["state"] == "finished", 60, "the background finish")
    check(api.post_frame(other_sid, other_token, msg), 409, "session_id", "finished")
    check(api.http.get(f"/sessions/{other_sid}/mesh", headers=api.auth(other_token)), 409, None, "no saved map")
    good()


def test_bad_json_requests_are_422(session, scene):
    srv, sid, token, good = session
    api = srv.api
    check(api.http.post("/sessions", json={"config": {"mapping": {"bogus": 1}}}), 422, "config.mapping.bogus",
          "unknown key")
    check(api.http.post("/sessions", json={"config": {"mapping": {"iter": 1}}}), 422, "config.mapping.iter",
          "did you mean 'iters'?")
    check(api.http.post("/sessions", json={"config": {"mapping.iters": 1}}), 422, "config.mapping.iters",
          'nest them, e.g. {"mapping": {"iters": 1}}')
    check(api.http.post("/sessions", json={"config": {"device": "cuda"}}), 422, "config.device")
    check(api.http.post("/sessions", json={"preset": "nope"}), 422, "preset", "unknown preset")
    check(api.http.post("/sessions", json={"preset": "../etc"}), 422, "preset")
    check(api.http.post("/sessions", json={"preset": "tum+"}), 422, "preset")
    check(api.http.post("/sessions", json={"preset": "tum+nope"}), 422, "preset", "unknown preset")
    composed, _ = api.create("composed", config=FAST, preset="synthetic+cpu")  # names composed as on the CLI
    row = srv.manager.get(composed)
    assert row.preset == "synthetic+cpu" and row.config["sized_for"] == "cpu"
    check(api.http.post("/sessions", json={"name": "x", "colour": 1}), 422, "colour")
    K = scene.capture[0].K
    render = {"T_world_cam": (2 * np.eye(4)).tolist(), "width": 32, "height": 24,
              "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": 10, "cy": 10}}
    check(api.http.post(f"/sessions/{sid}/render", json=render, headers=api.auth(token)), 422, "T_world_cam")
    nan_pose = np.eye(4).tolist()
    nan_pose[0][3] = float("nan")
    r = api.http.post(f"/sessions/{sid}/render", content=json.dumps({**render, "T_world_cam": nan_pose}),
                      headers={**api.auth(token), "Content-Type": "application/json"})
    check(r, 422, "T_world_cam", "T_world_cam: contains non-finite")
    assert r.json()["detail"].count("T_world_cam") == 1 and "Value error" not in r.json()["detail"]
    check(api.http.post("/sessions", content=b'{"name": "x",', headers={"Content-Type": "application/json"}),
          422, None, "the request body is not valid JSON at character")
    render["T_world_cam"] = np.eye(4).tolist()
    render["intrinsics"]["cx"] = 100.0
    check(api.http.post(f"/sessions/{sid}/render", json=render, headers=api.auth(token)), 422, "intrinsics")
    check(api.http.get(f"/sessions/{sid}/poses", params={"format": "csv"}, headers=api.auth(token)), 422, "format")
    good()


def test_queue_bound_answers_429_with_retry_after(server_factory, scene):
    srv = server_factory(max_pending_frames=1)
    sid, token = srv.api.create("queue", mode="offline", config=FAST)
    many = make_scene(8, seed=7).messages
    answers = [srv.api.post_frame(sid, token, m) for m in many]
    codes = [a.status_code for a in answers]
    assert set(codes) <= {202, 429} and 429 in codes and codes[0] == 202, codes
    for a in answers:
        if a.status_code == 429:
            assert int(a.headers["Retry-After"]) >= 1 and "retry" in a.json()["detail"]
    accepted = [i for i, c in enumerate(codes) if c == 202]
    assert RecordingCapture(srv.settings.sessions_dir / sid).seqs() == accepted  # refused frames are not recorded


def test_session_limit_is_503(server_factory):
    srv = server_factory(max_sessions=1)
    sid, token = srv.api.create("one", config=FAST)
    r = srv.api.http.post("/sessions", json={"config": FAST})
    check(r, 503, None, "maximum of 1")
    assert int(r.headers["Retry-After"]) > 0
    assert srv.api.http.delete(f"/sessions/{sid}", headers=srv.api.auth(token)).status_code == 204
    assert not (srv.settings.sessions_dir / sid).exists()
    check(srv.api.http.get(f"/sessions/{sid}", headers=srv.api.auth(token)), 404, "session_id")
    srv.api.create("two", config=FAST)
