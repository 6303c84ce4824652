"""The ``<mesh>.frame.json`` sidecar reader and mesh transforms."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from voxfusion.core.errors import CaptureError, ValidationError
from voxfusion.core.eval import read_mesh_frame, sidecar_path, to_jsonable, transform_mesh

Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def test_no_sidecar_is_identity_and_unknown(tmp_path):
    mesh_path = tmp_path / "mesh.ply"
    assert sidecar_path(mesh_path) == tmp_path / "mesh.ply.frame.json"
    frame = read_mesh_frame(mesh_path)
    assert frame.world == "unknown" and frame.path is None and frame.is_identity
    np.testing.assert_array_equal(frame.T_world_file, np.eye(4))


def test_sidecar_is_read_tolerantly(tmp_path):
    mesh_path = tmp_path / "scan.glb"
    side = sidecar_path(mesh_path)
    side.write_text(json.dumps({"T_world_file": Y_UP_TO_Z_UP.tolist(), "world": "first_camera", "extra": 1}))
    frame = read_mesh_frame(mesh_path)
    assert frame.world == "first_camera" and frame.path == side and not frame.is_identity
    np.testing.assert_array_equal(frame.T_world_file, Y_UP_TO_Z_UP)
    assert frame.raw["extra"] == 1
    assert to_jsonable(frame)["world"] == "first_camera"
    side.write_text(json.dumps({"world": "somewhere else"}))  # no transform, unknown world
    frame = read_mesh_frame(mesh_path)
    assert frame.is_identity and frame.world == "unknown"
    side.write_text(json.dumps({"world": "reference"}))
    assert read_mesh_frame(mesh_path).world == "reference"


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", json.dumps({"T_world_file": [[1, 0], [0, 1]]}),
                                  json.dumps({"T_world_file": (2 * np.eye(4)).tolist()}),
                                  json.dumps({"T_world_file": [["a"] * 4] * 4})])
def test_broken_sidecar_is_an_error_naming_the_file(tmp_path, text):
    mesh_path = tmp_path / "mesh.ply"
    sidecar_path(mesh_path).write_text(text)
    with pytest.raises(CaptureError, match="mesh.ply.frame.json"):
        read_mesh_frame(mesh_path)


def test_transform_mesh_follows_the_ate_convention():
    m = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T[:3, 3] = [1.0, -2.0, 0.5]
    out = transform_mesh(m, T, scale=2.0)
    expected = 2.0 * m.vertices @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(out.vertices, expected, atol=1e-12)
    np.testing.assert_allclose(m.vertices, trimesh.creation.box(extents=(1.0, 2.0, 3.0)).vertices)  # a copy
    assert out.area == pytest.approx(4.0 * m.area)
    with pytest.raises(ValidationError):
        transform_mesh(m, T, scale=0.0)


def test_alignment_lever_flags_a_straight_path():
    from voxfusion.core.eval import alignment_lever

    room = trimesh.creation.box(extents=(4.0, 4.0, 3.0))
    rng = np.random.default_rng(0)
    line = np.zeros((30, 3))
    line[:, 0] = np.linspace(-0.15, 0.15, 30)  # 30 cm straight along x
    line += rng.normal(scale=0.002, size=line.shape)
    weak = alignment_lever(line, 0.002, room)
    assert weak.spread_m[0] > 10 * weak.spread_m[1]
    assert weak.rotation_deg > 1.0 and weak.mesh_shift_m > 0.02  # metres-wide room: centimetres of swing
    assert weak.reach_m == pytest.approx(np.sqrt(4 + 4 + 2.25), rel=0.05)  # box corners from the centre
    loop = np.stack([np.cos(np.linspace(0, 2 * np.pi, 30)), np.sin(np.linspace(0, 2 * np.pi, 30)),
                     0.3 * np.sin(np.linspace(0, 4 * np.pi, 30))], axis=1)  # a 2 m loop, 30 cm up and down
    strong = alignment_lever(loop, 0.002, room)
    assert strong.rotation_deg < 0.1 and strong.mesh_shift_m < 0.005
    with pytest.raises(ValidationError):
        alignment_lever(np.zeros((1, 3)), 0.01, room)
