"""Precompiled artifacts (``tracking.precompiled``, :mod:`voxfusion.core.precompiled`): compiled in a real background
process, checked and loaded from a real cache directory, held to the plain function they replace.

The suite runs with ``VOXFUSION_PRECOMPILE=0`` (``tests/conftest.py``); these tests turn it on with a cache of their
own. Compiling costs ~5-40 s of a core per artifact, so two tests compile: one a small function through the
background job, one the tracker's evaluation directly."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from rooms import mapped_room  # tests/core/rooms.py

from voxfusion.core import precompiled
from voxfusion.core.framedata import frame_to_device
from voxfusion.core.lie import se3_exp
from voxfusion.core.precompiled import PrecompiledFunction, PrecompiledVariants, compile_artifact
from voxfusion.core.slam.presets import load_preset
from voxfusion.core.slam.tracking import Tracker, TrackingConfig
from voxfusion.core.slam.tracking_sdf import (
    SdfSolverConfig,
    _huber_weight,
    depth_reference,
    gray_images,
    linearize_signature,
    linearize_terms,
    sample_points,
    with_older_frames,
)

TINY = ["device=cpu", "mapping.rays_per_frame=192", "mapping.iters=8", "mapping.first_frame_iters=40"]


@pytest.fixture
def cache(monkeypatch, tmp_path):
    """Artifacts on, in a cache directory of this test's own."""
    monkeypatch.setenv(precompiled.ENV_SWITCH, "1")
    monkeypatch.setenv(precompiled.ENV_CACHE_DIR, str(tmp_path))
    return tmp_path / "precompiled"


def test_switched_off_nothing_is_loaded_or_compiled(monkeypatch, tmp_path):
    monkeypatch.setenv(precompiled.ENV_SWITCH, "0")
    monkeypatch.setenv(precompiled.ENV_CACHE_DIR, str(tmp_path))
    fn = PrecompiledFunction(_huber_weight, "test")
    view = PrecompiledVariants(fn)
    r = torch.linspace(-0.05, 0.05, 11, dtype=torch.float64)
    assert torch.equal(view(("k", 0.01), r, 0.01), _huber_weight(r, 0.01))
    assert fn.pending() == [] and not (tmp_path / "precompiled").exists()
    assert not view.uses_artifacts and view.served == 0


def test_a_variant_that_failed_to_compile_is_not_tried_again(cache, caplog):
    fn = PrecompiledFunction(_huber_weight, "test")
    key = fn.key(("k", 0.01))
    cache.mkdir(parents=True)
    fn.path(key).with_suffix(".failed").write_text("RuntimeError: no C++ compiler\n")
    r = torch.linspace(-0.05, 0.05, 11, dtype=torch.float64)
    with caplog.at_level(logging.INFO, logger="voxfusion.precompiled"):
        assert torch.equal(PrecompiledVariants(fn)(("k", 0.01), r, 0.01), _huber_weight(r, 0.01))
    assert fn.pending() == [] and not fn.path(key).exists()
    assert "could not be compiled earlier" in caplog.text and "no C++ compiler" in caplog.text


def test_a_background_job_compiles_a_variant_that_later_sessions_load(cache):
    """The first view to meet a variant runs the plain function and starts a real background job; that view keeps
    the plain function even once the artifact exists (a session never switches), a new view loads and serves it,
    and a call its guards reject (another Huber scale: a constant of the graph) runs the plain function."""
    fn = PrecompiledFunction(_huber_weight, "test")
    r = torch.linspace(-0.05, 0.05, 101, dtype=torch.float64)
    first = PrecompiledVariants(fn)
    assert torch.equal(first(("k", 0.01), r, 0.01), _huber_weight(r, 0.01))
    assert len(fn.pending()) == 1
    first(("k", 0.01), r, 0.01)  # met again while compiling: no second job
    assert fn.wait(timeout_s=300), "the compile job did not finish"
    key = fn.key(("k", 0.01))
    log = fn.path(key).with_suffix(".log").read_text()
    assert fn.path(key).exists(), log
    assert not fn.path(key).with_suffix(".failed").exists() and not fn.path(key).with_suffix(".lock").exists()
    first(("k", 0.01), r, 0.01)
    assert first.served == 0 and not first.uses_artifacts

    later = PrecompiledVariants(fn)
    other = torch.randn(57, dtype=torch.float64)  # another size: shapes are dynamic
    for x in (r, other):
        torch.testing.assert_close(later(("k", 0.01), x, 0.01), _huber_weight(x, 0.01), rtol=1e-12, atol=0)
    assert later.served == 2 and later.fallbacks == 0 and later.uses_artifacts
    # the caller's signature missed the constant: the artifact's guard rejects it, the plain function answers
    torch.testing.assert_close(later(("k", 0.01), r, 0.02), _huber_weight(r, 0.02), rtol=0, atol=0)
    assert later.fallbacks == 1 and later.uses_artifacts


def test_the_cache_keeps_the_newest_artifacts(tmp_path):
    """Each engine build compiles its own artifacts, so the cache drops the oldest beyond a count (an artifact with
    its log and failure note as one), never one a job is writing."""
    import os

    for i in range(5):
        for suffix in (".pt", ".log"):
            (tmp_path / f"a{i}{suffix}").write_text("x")
            os.utime(tmp_path / f"a{i}{suffix}", (1000 + i, 1000 + i))
    (tmp_path / "a0.lock").write_text("123")  # the oldest is being recompiled
    (tmp_path / "b.failed").write_text("RuntimeError\n")
    os.utime(tmp_path / "b.failed", (999, 999))
    precompiled._prune(tmp_path, keep=2)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["a0.lock", "a0.log", "a0.pt", "a3.log", "a3.pt", "a4.log", "a4.pt"]


def test_the_artifact_check_compares_every_output():
    """What a compile job holds an artifact to before writing it: every tensor within a relative tolerance, flags
    all but a few the same, other values equal."""
    a = (torch.tensor([1.0, 2.0]), None, torch.tensor([True, False]), 3)
    precompiled._check_close(a, (a[0] * (1 + 1e-6), None, a[2], 3))
    for bad in ((a[0] * 1.01, None, a[2], 3), (a[0], a[0], a[2], 3), (a[0], None, ~a[2], 3), (a[0], None, a[2], 4)):
        with pytest.raises(AssertionError):
            precompiled._check_close(a, bad)


@pytest.fixture(scope="module")
def room():
    cap, _, mapper = mapped_room("cpu", TINY)
    return cap, mapper


def test_the_tracker_evaluation_artifact_is_the_plain_function_as_the_map_grows(room, tmp_path):
    """``tracking.precompiled``'s function with every term (SDF, frame-to-frame with two older frames and an empty
    slot, photometric), compiled ahead of time on one map and loaded: the same residuals and normal equations as
    :func:`linearize_terms` on that map, at another pose, and on a grown map (its tables change size every frame),
    whose signature is the same."""
    cap, mapper = room
    f, f_ref = cap[7], cap[6]
    ref_data = frame_to_device(f_ref, "cpu")
    newest = depth_reference(ref_data, f_ref.T_world_cam, images=gray_images(ref_data.color))
    older = None
    for k in (4, 5):
        older = with_older_frames(depth_reference(frame_to_device(cap[k], "cpu"), cap[k].T_world_cam), older, 3, 1.0)
    ref = with_older_frames(newest, older, 3, 0.5)
    pts = sample_points(frame_to_device(f, "cpu"), 512, torch.Generator().manual_seed(0), with_gray=True)
    scfg = SdfSolverConfig(w_frame=1.0, w_photo=0.1)
    xi = torch.tensor([0.003, -0.002, 0.0025, 0.003, -0.002, 0.001], dtype=torch.float64)
    T = torch.as_tensor(f.T_world_cam @ se3_exp(xi).numpy())
    voxels, decoder = mapper.voxels.snapshot(), mapper.decoder.frozen_copy()  # what a tracker is given
    path = tmp_path / "linearize.pt"
    compile_artifact(linearize_terms, (voxels, decoder, pts, T, scfg, ref), path)
    with open(path, "rb") as fh:
        compiled = torch.compiler.load_compiled_function(fh)

    grown = mapper.voxels.snapshot()
    grown.allocate(torch.rand(200, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float32) * 4 - 2)
    grown = grown.snapshot()  # frozen, as the tracker's maps are
    assert grown.n_voxels > voxels.n_voxels
    signature = linearize_signature(voxels, decoder, pts, scfg, ref)
    assert linearize_signature(grown, decoder, pts, scfg, ref) == signature
    T_other = torch.as_tensor(f.T_world_cam @ se3_exp(-2 * xi).numpy())
    for vox, pose in ((voxels, T), (voxels, T_other), (grown, T)):
        cost, H, b, terms = linearize_terms(vox, decoder, pts, pose, scfg, ref)
        got = compiled(vox, decoder, pts, pose, scfg, ref)
        assert int(terms.ok.sum()) > 100 and float(H.abs().max()) > 0
        torch.testing.assert_close(got[0], cost, rtol=1e-5, atol=1e-9)
        torch.testing.assert_close(got[1], H, rtol=1e-4, atol=1e-6 * float(H.abs().max()))
        torch.testing.assert_close(got[2], b, rtol=1e-4, atol=1e-6 * float(b.abs().max()))
        torch.testing.assert_close(got[3].r, terms.r, rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(got[3].grads, terms.grads, rtol=1e-4, atol=1e-5)
        assert torch.equal(got[3].ok, terms.ok)
        torch.testing.assert_close(got[3].rf, terms.rf, rtol=1e-4, atol=1e-6)
        assert torch.equal(got[3].okf, terms.okf)
        assert int(terms.okf[512 : 3 * 512].sum()) > 0 and int(terms.okf[3 * 512 :].sum()) == 0  # two older, one empty
    # another option is another variant: a different artifact name
    other = SdfSolverConfig(w_frame=1.0, w_photo=0.2)
    assert linearize_signature(voxels, decoder, pts, other, ref) != signature
    assert linearize_signature(voxels, decoder, pts, scfg, newest) != signature  # no older frames: another too
    assert np.isfinite(float(cost))


def test_a_tracker_runs_its_stages_from_artifacts_once_they_exist(room, cache):
    """``tracking.precompiled`` end to end: the first tracker meets its stage, starts the compile job and tracks
    exactly as the eager tracker does; once the job has written the artifact, a new tracker (a new session) loads it,
    serves every evaluation of that stage from it and lands where the eager tracker does (compiled code rounds
    differently: within a micrometre and a microradian here)."""
    cap, mapper = room
    f, f_ref = cap[7], cap[6]
    options = {"method": "sdf", "sdf_levels": 1, "sdf_w_photo_blur": 0.0}  # one stage: one artifact to compile
    prior = f.T_world_cam @ se3_exp(torch.tensor([0.02, -0.01, 0.015, 0.02, -0.01, 0.01],
                                                 dtype=torch.float64)).numpy()

    def track(precompiled: bool) -> tuple[np.ndarray, Tracker]:
        tr = Tracker(TrackingConfig(precompiled=precompiled, **options), load_preset("cpu", TINY).render,
                     use_color=True)
        tr.set_map(mapper.voxels.snapshot(), mapper.decoder.frozen_copy())
        tr.remember(frame_to_device(f_ref, "cpu"), f_ref.T_world_cam)
        res = tr.track(frame_to_device(f, "cpu"), prior)
        assert not res.lost, res.reason
        return res.T_world_cam, tr

    eager, _ = track(False)
    first, tr = track(True)
    assert np.array_equal(first, eager) and tr.precompiled is not None and tr.precompiled.served == 0
    from voxfusion.core.slam.tracking_sdf import PRECOMPILED_LINEARIZE

    assert len(PRECOMPILED_LINEARIZE.pending()) == 1
    assert PRECOMPILED_LINEARIZE.wait(timeout_s=600), "the compile job did not finish"
    assert len(list(cache.glob("*.pt"))) == 1, [p.read_text() for p in cache.glob("*.log")]
    later, tr = track(True)
    assert tr.precompiled.fallbacks == 0
    assert tr.precompiled.served > 0
    assert np.abs(later[:3, 3] - eager[:3, 3]).max() < 1e-6
    assert np.abs(later[:3, :3] - eager[:3, :3]).max() < 1e-6
