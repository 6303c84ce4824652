"""The live web viewer: its routes over HTTP, and the page itself in a real headless Chromium while a
synthetic capture streams into a real server."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
from browser import CHROMIUM_MISSING, headless_chromium, screenshot, viewer_value
from srvutil import TINY, make_scene, wait_until

from voxfusion.server.outputs import MESH_DETAILS
from voxfusion.server.viewer_assets import BUILD_INFO, VIEWER_DIST, source_digest

PANEL_PX = 320
"""Width of the viewer's side panel (style.css); the 3D view is the rest of the page."""


def test_built_viewer_matches_its_sources():
    """``server/viewer/dist`` was rebuilt (``make viewer``) after the last change to the viewer's sources."""
    assert (VIEWER_DIST / "index.html").is_file(), "server/viewer/dist is missing: run `make viewer`"
    info = json.loads(BUILD_INFO.read_text())
    assert info["source_sha256"] == source_digest(), "the viewer's sources changed since dist/ was built: " \
                                                      "run `make viewer` and commit server/viewer/dist"


def test_view_page_needs_the_token(server_factory):
    srv = server_factory()
    sid, token = srv.api.create()
    assert srv.api.http.get(f"/sessions/{sid}/view").status_code == 401
    r = srv.api.http.get(f"/sessions/{sid}/view", params={"token": "x" * 43})
    assert r.status_code == 403 and r.json()["field"]
    assert srv.api.http.get(f"/sessions/{'0' * 32}/view", params={"token": token}).status_code == 404
    r = srv.api.http.get(f"/sessions/{sid}/view", params={"token": token})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["cache-control"] == "no-store" and r.headers["referrer-policy"] == "no-referrer"
    assert "http://" not in r.text and "https://" not in r.text, "the page must not load anything from elsewhere"
    for asset in ("/viewer/assets/../../pyproject.toml", "/viewer/assets/%2e%2e%2fbuild-info.json",
                  "/viewer/assets/build-info.json", "/viewer/assets/nope.js"):
        assert srv.api.http.get(asset).status_code == 404, asset
    js = next((VIEWER_DIST / "assets").glob("*.js")).name
    r = srv.api.http.get(f"/viewer/assets/{js}")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript")


def test_latest_frame_routes(server_factory):
    srv = server_factory()
    scene = make_scene(3, seed=1)
    sid, token = srv.api.create(config=TINY, mode="offline")
    auth = srv.api.auth(token)
    assert srv.api.http.get(f"/sessions/{sid}/frames/latest", headers=auth).status_code == 409
    assert srv.api.http.get(f"/sessions/{sid}/frames/latest").status_code == 401
    for message in scene.messages:
        assert srv.api.post_frame(sid, token, message).status_code == 202
    info = srv.api.http.get(f"/sessions/{sid}/frames/latest", headers=auth).json()
    frame = list(scene.capture.frames())[-1]
    assert info["seq"] == 2 and (info["width"], info["height"]) == (frame.width, frame.height)
    np.testing.assert_allclose([info["fx"], info["fy"], info["cx"], info["cy"]],
                               [frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]], rtol=1e-6)
    assert info["has_colour"] and 0.5 < info["valid_depth_fraction"] <= 1.0
    valid = frame.depth_m[frame.depth_m > 0]
    assert info["median_depth_m"] == pytest.approx(float(np.median(valid)), abs=0.01)  # png16_mm: 1 mm steps

    depth = srv.api.http.get(f"/sessions/{sid}/frames/latest/depth.png", headers=auth)
    assert depth.status_code == 200 and depth.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert srv.api.http.get(f"/sessions/{sid}/frames/latest/depth.png",
                            headers={**auth, "If-None-Match": depth.headers["etag"]}).status_code == 304
    colour = srv.api.http.get(f"/sessions/{sid}/frames/latest/colour.jpg", headers=auth)
    assert colour.status_code == 200 and colour.content[:2] == b"\xff\xd8"

    srv.api.http.post(f"/sessions/{sid}/finish", headers=auth).raise_for_status()
    srv.stop()  # a new server reads the finished session's newest frame from its recording
    srv2 = server_factory(data_dir=srv.settings.data_dir)
    again = srv2.api.http.get(f"/sessions/{sid}/frames/latest", headers=auth)
    assert again.status_code == 200 and again.json() == info


def test_preview_mesh_is_coarser_and_labelled(server_factory):
    srv = server_factory()
    scene = make_scene(4, seed=2)
    sid, token = srv.api.create(config={**TINY, "mesh_res": 8, "voxel_size_m": 0.1}, mode="offline")
    auth = srv.api.auth(token)
    for message in scene.messages:
        assert srv.api.post_frame(sid, token, message).status_code == 202
    wait_until(lambda: srv.api.status(sid, token)["frames_tracked"] == 4, 120, "every frame to be tracked")

    def both():  # the same map version for both (mapping may publish between the two requests)
        full = srv.api.http.get(f"/sessions/{sid}/mesh", headers=auth)
        preview = srv.api.http.get(f"/sessions/{sid}/mesh", params={"detail": "preview"}, headers=auth)
        same = full.headers.get("x-map-version") == preview.headers.get("x-map-version")
        return (full, preview) if same else None

    full, preview = wait_until(both, 60, "full and preview meshes of one map version")
    assert full.status_code == preview.status_code == 200
    assert preview.headers["etag"] != full.headers["etag"]
    faces = [trimesh.load(io.BytesIO(r.content), file_type="ply").faces.shape[0] for r in (full, preview)]
    assert 0 < faces[1] < faces[0] / 2, faces  # 4 samples per 10 cm voxel edge against 8
    bad = srv.api.http.get(f"/sessions/{sid}/mesh", params={"detail": "max"}, headers=auth)
    assert bad.status_code == 422 and bad.json()["field"] == "detail"

    # A finished session serves its final mesh (made at finish, coloured from the images) for both.
    srv.api.http.post(f"/sessions/{sid}/finish", headers=auth).raise_for_status()
    srv.stop()
    srv2 = server_factory(data_dir=srv.settings.data_dir)
    stored = [srv2.api.http.get(f"/sessions/{sid}/mesh", params={"detail": d}, headers=auth) for d in MESH_DETAILS]
    assert all(r.status_code == 200 for r in stored) and stored[0].content == stored[1].content


def _scene_region(image: np.ndarray) -> np.ndarray:
    return image[:, : image.shape[1] - PANEL_PX].astype(np.float32)


def _keep_screenshot(driver, name: str) -> None:
    """Save the page to ``$VOXFUSION_SCREENSHOTS/viewer-<name>.png`` when that is set (to look at)."""
    folder = os.environ.get("VOXFUSION_SCREENSHOTS")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / f"viewer-{name}.png").write_bytes(driver.get_screenshot_as_png())


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM_MISSING is not None, reason=CHROMIUM_MISSING or "")
def test_viewer_shows_the_scan_growing_in_chromium(server_factory):
    srv = server_factory()
    scene = make_scene(24, seed=3, width=160, height=120)
    sid, token = srv.api.create(config=TINY, mode="offline")
    for message in scene.messages[:6]:
        assert srv.api.post_frame(sid, token, message).status_code == 202
    wait_until(lambda: srv.api.status(sid, token)["frames_tracked"] >= 6, 180, "the first frames to be tracked")

    driver = headless_chromium()
    try:
        driver.get(f"{srv.url}/sessions/{sid}/view?token={token}")
        wait_until(lambda: int(viewer_value(driver, "meshVertices") or 0) > 0, 180, "the viewer to show a mesh", 0.5)
        assert token not in driver.current_url, "the page must take the token out of the address bar"
        wait_until(lambda: int(viewer_value(driver, "poses") or 0) >= 6, 30, "the viewer to show the trajectory", 0.5)
        first_version = int(viewer_value(driver, "meshVersion"))
        first = screenshot(driver)
        _keep_screenshot(driver, "first")
        region = _scene_region(first)
        assert region.std() > 8, "the 3D view is blank"
        assert len(np.unique((region // 16).reshape(-1, 3), axis=0)) > 20, "the 3D view is nearly one colour"

        for message in scene.messages[6:]:
            assert srv.api.post_frame(sid, token, message).status_code == 202
        wait_until(lambda: int(viewer_value(driver, "frameSeq") or 0) == len(scene.messages) - 1, 60,
                   "the viewer to show the newest frame", 0.5)
        wait_until(lambda: int(viewer_value(driver, "meshVersion") or 0) > first_version, 240,
                   "the viewer to load a newer mesh", 0.5)
        wait_until(lambda: int(viewer_value(driver, "poses") or 0) >= 12, 120, "more poses in the viewer", 0.5)
        assert int(viewer_value(driver, "livePoses") or 0) > 0, "no pose came over the WebSocket (CSP?)"
        later = screenshot(driver)
        _keep_screenshot(driver, "later")
        diff = np.abs(_scene_region(later) - _scene_region(first)).mean()
        assert diff > 1.0, f"the 3D view did not change as frames arrived (mean abs difference {diff:.2f})"
        panel_text = driver.find_element("id", "counters").text
        assert "tracked" in panel_text and "dropped" in panel_text and "lost" in panel_text and "limited" in panel_text
        severe = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert not severe, severe

        # A finished session is served from its checkpoint and recording.
        srv.api.http.post(f"/sessions/{sid}/finish", headers=srv.api.auth(token)).raise_for_status()
        driver.get(f"{srv.url}/sessions/{sid}/view?token={token}")
        wait_until(lambda: viewer_value(driver, "state") == "finished"
                   and int(viewer_value(driver, "meshVertices") or 0), 120,
                   "the finished session's mesh in the viewer", 0.5)
        assert _scene_region(screenshot(driver)).std() > 8
        _keep_screenshot(driver, "finished")
    finally:
        driver.quit()
