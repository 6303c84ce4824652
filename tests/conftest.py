"""Shared test helpers: where the real captures live, and a depth-reprojection check for pose conventions.

Real captures (``../shared/data`` beside the repository; see its README) are optional: tests that need
them take the ``shared_data`` fixture, which skips when the folder is absent (a user's fresh clone).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# No precompiled artifacts in tests (loaded or compiled in the background: a run's arithmetic would depend on what
# an earlier run left in the cache); tests/core/test_precompiled.py turns them on with a cache of its own.
os.environ["VOXFUSION_PRECOMPILE"] = "0"


def pytest_configure(config: pytest.Config) -> None:
    """Under ``pytest -n N`` (``make test``), each worker's torch gets its share of the cores (at least 1): two
    workers with two intra-op threads each on 2 cores left OpenMP threads spinning for cores the other worker held,
    and a test that takes 1 s alone took 62 s in the suite (2026-11-28)."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        import torch

        from voxfusion.core.cpu import usable_cpu_count

        torch.set_num_threads(max(1, usable_cpu_count() // int(workers)))


@pytest.fixture(params=["kernel", "operators"])
def native_path(request, monkeypatch) -> str:
    """Runs a test with the engine's compiled CPU kernels (``core/native/*.c``) and with the PyTorch operators they
    replace (``VOXFUSION_NATIVE=0``; what CUDA runs), so both are held to the plain references. The kernel run
    fails where a C compiler is present but a kernel does not build, and is skipped without a compiler."""
    from voxfusion.core import native

    if request.param == "kernel":
        if native._compiler() is None:
            pytest.skip("no C compiler: the engine's CPU kernels cannot be built here")
        monkeypatch.setenv(native.ENV_SWITCH, "1")
        for name in native._SIGNATURES:
            assert native._kernels(name) is not None, f"the C compiler could not build core/native/{name}.c"
    else:
        monkeypatch.setenv(native.ENV_SWITCH, "0")
    return request.param


def shared_data_dir() -> Path:
    """``<repo>/../shared/data``: the real RGB-D captures (may not exist)."""
    return (REPO_ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared real-data folder; skips the test when it is absent."""
    root = shared_data_dir()
    if not root.is_dir():
        pytest.skip(f"real captures not available ({root} is absent)")
    return root


def depth_reprojection_error_m(depth_a: np.ndarray, K_a: np.ndarray, T_world_a: np.ndarray,
                               depth_b: np.ndarray, K_b: np.ndarray, T_world_b: np.ndarray,
                               stride: int = 4, min_points: int = 500) -> float:
    """Median |z| disagreement (metres) when frame A's depth is moved into frame B with the given poses.

    Pixels of ``depth_a`` (every ``stride``-th in both directions) are back-projected with ``K_a``,
    mapped to B's camera with ``inv(T_world_b) @ T_world_a`` (camera-to-world, OpenCV axes), projected
    with ``K_b`` and compared with ``depth_b`` at the nearest pixel where both are valid. Correct poses
    give the sensor noise (a few cm); wrong axis conventions or identity poses give tens of cm.
    """
    d = depth_a[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    u = u * stride
    v = v * stride
    pts_a = np.stack([(u - K_a[0, 2]) / K_a[0, 0] * z, (v - K_a[1, 2]) / K_a[1, 1] * z, z], axis=-1)
    T_b_a = np.linalg.inv(T_world_b) @ T_world_a
    pts_b = pts_a @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    pts_b = pts_b[pts_b[:, 2] > 1e-3]
    ub = np.round(K_b[0, 0] * pts_b[:, 0] / pts_b[:, 2] + K_b[0, 2]).astype(np.int64)
    vb = np.round(K_b[1, 1] * pts_b[:, 1] / pts_b[:, 2] + K_b[1, 2]).astype(np.int64)
    h, w = depth_b.shape
    inside = (ub >= 0) & (ub < w) & (vb >= 0) & (vb < h)
    pts_b, ub, vb = pts_b[inside], ub[inside], vb[inside]
    observed = depth_b[vb, ub]
    valid = observed > 0
    if valid.sum() < min_points:
        return float("inf")  # the views do not overlap: as bad as it gets
    return float(np.median(np.abs(pts_b[valid, 2] - observed[valid])))


@pytest.fixture(scope="session")
def reprojection_error():
    """The :func:`depth_reprojection_error_m` function, for test modules (conftest is not importable)."""
    return depth_reprojection_error_m
