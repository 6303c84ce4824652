"""The client SDK, the wire format and the engine's frames, readers and errors import without torch
(``voxfusion.core``'s docstring promises it; a capture client or a robot's uploader should not wait ~1 s for
torch, or need its memory)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from voxfusion.core.geometry import pose_from_tum, pose_to_tum, scale_motion


def test_sdk_wire_format_and_frames_import_without_torch():
    code = ("import sys\n"
            "import voxfusion.clients, voxfusion.proto, voxfusion.core\n"
            "from voxfusion.core import RGBDFrame, ValidationError\n"
            "from voxfusion.core.datasets import open_capture\n"
            "heavy = sorted(m for m in ('torch', 'scipy.spatial') if m in sys.modules)\n"
            "assert not heavy, heavy\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_geometry_helpers_that_load_their_dependencies_on_use_still_work():
    T = pose_from_tum(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, np.sin(0.25), np.cos(0.25)]))
    t, q = pose_to_tum(T)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(q, [0.0, 0.0, np.sin(0.25), np.cos(0.25)], atol=1e-12)
    half = scale_motion(T, 0.5)  # half the screw motion: applied twice it gives the whole
    np.testing.assert_allclose(half @ half, T, atol=1e-9)
