"""The HTTP client against a real server on loopback: every verb, error mapping, ordering of async sends."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
import trimesh
from clientutil import TINY, LiveServer, free_port, tiny_frames

from voxfusion.clients import Client, ClientError, ServerError, TransportError
from voxfusion.clients.base import decode_render
from voxfusion.clients.errors import server_error_from_body
from voxfusion.proto import encode_frame

N_FRAMES = 6


def test_server_error_from_body_keeps_status_detail_and_field():
    err = server_error_from_body(400, b'{"detail": "crc: mismatch", "field": "crc"}')
    assert (err.status, err.detail, err.field) == (400, "crc: mismatch", "crc")
    err = server_error_from_body(500, '{"status": 403, "detail": "wrong token", "field": "Authorization"}')
    assert err.status == 403  # zenoh error replies carry the HTTP-equivalent status in the body
    err = server_error_from_body(422, {"detail": [{"loc": ["body", "width"], "msg": "too big"}]})
    assert err.status == 422 and "too big" in err.detail and err.field is None
    err = server_error_from_body(502, b"<html>bad gateway</html>")
    assert err.status == 502 and "bad gateway" in err.detail
    assert "502" in str(err)


def test_decode_render_reads_the_depth_part_of_both_formats():
    depth = np.array([[0.0, 1.25], [2.5, 0.0]], dtype=np.float32)
    mask = (depth > 0).astype(np.uint8).tobytes()
    body = depth.astype("<f2").tobytes() + mask
    out = decode_render(body, {"X-Depth-Bytes": "8", "X-Mask-Bytes": "4"}, "f16", 2, 2)
    np.testing.assert_array_equal(out, depth)
    png = cv2.imencode(".png", np.round(depth * 1000).astype(np.uint16))[1].tobytes()
    out = decode_render(png + b"mask", {"x-depth-bytes": str(len(png))}, "png16", 2, 2)
    np.testing.assert_array_equal(out, depth)
    with pytest.raises(ClientError):
        decode_render(body, {"X-Depth-Bytes": "8"}, "f16", 3, 2)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = LiveServer(tmp_path_factory.mktemp("http-client") / "data")
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def frames():
    return tiny_frames(N_FRAMES, seed=4)


def test_every_verb_over_http(server, frames, tmp_path):
    with Client(server.url) as client:
        h = client.create_session("http-verbs", TINY, mode="offline")
        assert client.mesh_url == f"{server.url}/sessions/{h.id}/mesh"
        assert client.latest_pose() is None
        with pytest.raises(ServerError) as err:  # a frame naming another session
            client.send_bytes(encode_frame(frames[0], seq=0, session="0" * 32))
        assert err.value.status == 400 and err.value.field == "header"
        futures = [client.send_frame_async(f) for f in frames]
        # the refused frame used seq 0: the client numbers frames on, in order
        assert [f.result(timeout=120) for f in futures] == list(range(1, N_FRAMES + 1))
        status = client.finish(timeout_s=300)
        assert status.state.value == "finished" and status.frames_tracked == N_FRAMES
        poses = client.trajectory()
        assert [p.seq for p in poses] == list(range(1, N_FRAMES + 1))
        assert client.latest_pose().seq == N_FRAMES
        tum = [line for line in client.trajectory_tum().splitlines() if line and not line.startswith("#")]
        assert len(tum) == N_FRAMES
        depth = client.render_depth(np.array(poses[2].T_world_cam), frames[2].K, 96, 72)
        both = (depth > 0) & (frames[2].depth_m > 0)
        assert both.mean() > 0.5 and np.median(np.abs(depth - frames[2].depth_m)[both]) < 0.1
        obj = client.download_mesh(tmp_path / "mesh.obj")  # format from the suffix
        assert (tmp_path / "mesh.obj").read_bytes() == obj
        assert len(trimesh.load(io.BytesIO(obj), file_type="obj").vertices) > 100
        assert client.download_mesh(format="glb")[:4] == b"glTF"
        voxels = np.load(io.BytesIO(client.download_voxels(tmp_path / "voxels.npz")))
        assert len(voxels.files) > 0
        with pytest.raises(ServerError) as err:
            client.send_frame(frames[0])
        assert err.value.status == 409


def test_errors_name_status_and_field(server):
    with Client(server.url) as client:
        h = client.create_session("errors", TINY)
    with Client(server.url, session_id=h.id, token="not-the-token") as wrong:
        with pytest.raises(ServerError) as err:
            wrong.status()
        assert err.value.status == 403 and err.value.field == "Authorization"
        wrong.attach("f" * 32, h.token)
        with pytest.raises(ServerError) as err:
            wrong.status()
        assert err.value.status == 404
    with Client(server.url) as client, pytest.raises(ServerError) as err:
        client.create_session("bad", ["tracking.no_such_option=3"])
    assert err.value.status == 422 and err.value.field.startswith("config.")
    with Client(f"http://127.0.0.1:{free_port()}", timeout_s=5) as nowhere, pytest.raises(TransportError):
        nowhere.create_session("x")
    with Client(server.url) as client, pytest.raises(ClientError):
        client.status()  # no session yet
