"""``voxfusion encode`` and the README's upload requests against a real server: the session created with the
README's body, the binary frame and the multipart parts posted with exactly the README's headers and parts."""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
from pathlib import Path

import httpx
import numpy as np
import pytest
from clientutil import LiveServer, wait_until
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.commands.encode import write_parts
from voxfusion.core.datasets import open_capture
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
from voxfusion.core.errors import ValidationError
from voxfusion.proto import decode_frame
from voxfusion.proto.recording import RecordingCapture

README = Path(__file__).resolve().parents[2] / "README.md"


def readme_command(marker: str) -> list[str]:
    """The README command (a ``bash`` block line with its ``\\`` continuations) containing ``marker``, split as
    the shell would (comments dropped; ``$ID`` / ``$TOKEN`` left in place)."""
    lines = README.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if marker in line)
    while start > 0 and lines[start - 1].rstrip().endswith("\\"):
        start -= 1
    text = ""
    for line in lines[start:]:
        text += line.rstrip()[:-1] + " " if line.rstrip().endswith("\\") else line
        if not line.rstrip().endswith("\\"):
            break
    return shlex.split(text, comments=True)


def curl_request(args: list[str], base_url: str, sid: str, token: str) -> dict:
    """What a README ``curl`` line sends: method, path, headers, body file / form parts (``$ID``/``$TOKEN``
    substituted; the README's ``http://127.0.0.1:8000`` becomes ``base_url``)."""
    req: dict = {"method": "GET", "headers": {}, "form": {}, "data_file": None, "json": None}
    it = iter(a.replace("$TOKEN", token).replace("$ID", sid) for a in args[1:])
    for arg in it:
        if arg == "-H":
            key, value = next(it).split(":", 1)
            req["headers"][key.strip()] = value.strip()
        elif arg == "-X":
            req["method"] = next(it)
        elif arg == "--data-binary":
            req["data_file"], req["method"] = next(it).removeprefix("@"), "POST"
        elif arg == "-d":  # the JSON body (the shell's closing ")" may follow it)
            req["json"], req["method"] = json.JSONDecoder().raw_decode(next(it))[0], "POST"
        elif arg == "-F":
            name, value = next(it).split("=", 1)
            req["form"][name] = value.removeprefix("@")
            req["method"] = "POST"
        elif arg.startswith("http"):
            req["url"] = re.sub(r"^http://127\.0\.0\.1:8000", base_url, arg)
    return req


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = LiveServer(tmp_path_factory.mktemp("encode") / "data")
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A small TUM-layout capture (the README uses the shared TUM desk: same reader, same layout)."""
    return write_capture(SyntheticCapture(SyntheticConfig(n_frames=3, width=96, height=72, seed=6)),
                         tmp_path_factory.mktemp("cap") / "tum_capture", layout="tum")


def test_readme_uploads_work_as_written(server, capture, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the README's relative out/... paths land here
    # voxfusion encode, as the README writes it, on another capture of the same format
    for marker in ("--out out/frame.vxfr", "--parts out/frame1"):
        args = readme_command(marker)
        assert args[:2] == ["voxfusion", "encode"]
        result = CliRunner().invoke(app, [args[1], str(capture), *args[3:]])
        assert result.exit_code == 0, result.output + repr(result.exception)
    assert decode_frame(Path("out/frame.vxfr").read_bytes()).seq == 0

    create = curl_request(readme_command("-d '{\"name\": \"desk\""), server.url, "", "")
    with httpx.Client(timeout=60) as http:
        r = http.post(create["url"], json=create["json"], headers=create["headers"])
        assert r.status_code == 201, r.text
        sid, token = r.json()["id"], r.json()["token"]

        binary = curl_request(readme_command("--data-binary @"), server.url, sid, token)
        assert binary["headers"] == {"Authorization": f"Bearer {token}",
                                     "Content-Type": "application/vnd.voxfusion.frame"}
        r = http.post(binary["url"], content=Path(binary["data_file"]).read_bytes(), headers=binary["headers"])
        assert r.status_code == 202, r.text
        assert r.json()["seq"] == 0

        multipart = curl_request(readme_command("-F metadata="), server.url, sid, token)
        assert set(multipart["form"]) == {"metadata", "depth", "color"}
        files = {name: (Path(path).name, Path(path).read_bytes()) for name, path in multipart["form"].items()}
        r = http.post(multipart["url"], files=files, headers=multipart["headers"])
        assert r.status_code == 202, r.text
        assert r.json()["seq"] == 1

        status = curl_request(readme_command("# state and counters"), server.url, sid, token)
        wait_until(lambda: http.get(status["url"], headers=status["headers"]).json()["frames_received"] == 2, 30,
                   "both frames to be recorded")
    # what the server recorded is the capture's frames 0 and 1 (depth in 1 mm steps, same intrinsics)
    recorded = list(RecordingCapture(server.settings.sessions_dir / sid).frames())
    want = list(open_capture(capture).frames())[:2]
    for got, ref in zip(recorded, want, strict=True):
        np.testing.assert_allclose(got.depth_m, ref.depth_m, atol=6e-4)
        np.testing.assert_allclose(got.K, ref.K, rtol=1e-6)
        assert got.timestamp_s == pytest.approx(ref.timestamp_s, abs=1e-6)
        assert got.color is not None and np.abs(got.color.astype(int) - ref.color.astype(int)).mean() < 10  # jpeg


def test_encode_a_synthetic_frame_and_refuse_bad_arguments(tmp_path):
    out = tmp_path / "s.vxfr"
    result = CliRunner().invoke(app, ["encode", "--synthetic", "4", "--synthetic-size", "64x48", "--frame", "3",
                                      "--seq", "7", "--session", "abc", "--color-encoding", "none", "--out", str(out)])
    assert result.exit_code == 0, result.output + repr(result.exception)
    decoded = decode_frame(out.read_bytes())
    assert (decoded.seq, decoded.session, decoded.frame.depth_m.shape) == (7, "abc", (48, 64))
    assert decoded.frame.color is None
    for args, field in ((["--synthetic", "2", "--frame", "2", "--out", str(out)], "frame"),
                        (["--synthetic", "2"], "out"),
                        (["--synthetic", "2", "--out", str(out), "--depth-encoding", "png"], "depth_encoding"),
                        (["--out", str(out)], "capture")):
        result = CliRunner().invoke(app, ["encode", *args])
        assert isinstance(result.exception, ValidationError) and result.exception.field == field, result.output


def test_parts_carry_confidence_and_the_device_pose(server, tmp_path):
    """An iPhone-like frame (confidence, ARKit pose) as multipart parts is recorded as the same frame."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=2, lidar=True, seed=2))
    frame = cap[1]
    frame = dataclasses.replace(frame, T_world_cam_device=frame.T_world_cam)
    files = write_parts(frame, tmp_path / "parts", seq=0)
    assert [p.name for p in files] == ["metadata.json", "depth_mm.png", "color.jpg", "confidence.png"]
    with httpx.Client(base_url=server.url, timeout=60) as http:
        r = http.post("/sessions", json={"name": "parts", "mode": "offline"})
        sid, token = r.json()["id"], r.json()["token"]
        r = http.post(f"/sessions/{sid}/frames", headers={"Authorization": f"Bearer {token}"},
                      files={p.stem.removesuffix("_mm"): (p.name, p.read_bytes()) for p in files})
        assert r.status_code == 202, r.text
    got = next(iter(RecordingCapture(server.settings.sessions_dir / sid).frames()))
    np.testing.assert_array_equal(got.confidence, frame.confidence)
    np.testing.assert_allclose(got.T_world_cam_device, frame.T_world_cam, atol=1e-9)
    np.testing.assert_allclose(got.depth_m, frame.depth_m, atol=6e-4)
