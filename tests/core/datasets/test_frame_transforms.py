"""Frame transforms (resize, confidence filter, depth clip) and the capture wrappers."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pytest

from voxfusion.core.datasets import (
    BaseCapture,
    RevisitCapture,
    RGBDFrame,
    SlicedCapture,
    TransformedCapture,
    clip_depth,
    drop_depth,
    filter_depth_by_confidence,
    resize_frame,
)
from voxfusion.core.errors import ValidationError
from voxfusion.core.geometry import make_intrinsics


def _frame(index: int = 0, w: int = 64, h: int = 48) -> RGBDFrame:
    rng = np.random.default_rng(index)
    depth = rng.uniform(0.2, 5.0, (h, w)).astype(np.float32)
    depth[::7, ::5] = 0.0
    return RGBDFrame(
        depth_m=depth, K=make_intrinsics(50.0, 51.0, w / 2 - 0.5, h / 2 - 0.5), timestamp_s=float(index),
        color=rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
        confidence=rng.integers(0, 3, (h, w), dtype=np.uint8), T_world_cam=np.eye(4), index=index,
    )


class _ListCapture(BaseCapture):
    def __init__(self, n: int) -> None:
        self.name, self.path, self.n, self.loaded = "list", Path("."), n, []

    def __len__(self) -> int:
        return self.n

    def _load(self, i: int) -> RGBDFrame:
        self.loaded.append(i)
        return _frame(i)


def test_resize_frame_nearest_depth_area_colour_scaled_K():
    f = _frame()
    g = resize_frame(f, 32, 24)
    assert g.depth_m.shape == (24, 32) and g.color.shape == (24, 32, 3) and g.confidence.shape == (24, 32)
    assert set(np.unique(g.depth_m)) <= set(np.unique(f.depth_m))  # nearest: no invented depths
    assert set(np.unique(g.confidence)) <= {0, 1, 2}
    np.testing.assert_array_equal(g.color, cv2.resize(f.color, (32, 24), interpolation=cv2.INTER_AREA))
    np.testing.assert_allclose(g.K[0], f.K[0] / 2)
    np.testing.assert_allclose(g.K[1], f.K[1] / 2)
    assert resize_frame(f, 64, 48) is f
    depth_only = resize_frame(f.with_(color=None, confidence=None), 16, 12)
    assert depth_only.color is None and depth_only.confidence is None and depth_only.K[0, 0] == 12.5
    with pytest.raises(ValidationError):
        resize_frame(f, 0, 10)


def test_confidence_filter_and_clip():
    f = _frame()
    g = filter_depth_by_confidence(f, 2)
    assert np.all(g.depth_m[f.confidence < 2] == 0)
    np.testing.assert_array_equal(g.depth_m[f.confidence == 2], f.depth_m[f.confidence == 2])
    assert filter_depth_by_confidence(f, 0) is f
    no_conf = f.with_(confidence=None)
    assert filter_depth_by_confidence(no_conf, 2) is no_conf
    with pytest.raises(ValidationError, match="min_confidence"):
        filter_depth_by_confidence(f, 3)
    c = clip_depth(f, 1.0, 3.0)
    kept = c.depth_m > 0
    assert c.depth_m.dtype == np.float32
    assert np.all((c.depth_m[kept] >= 1.0) & (c.depth_m[kept] <= 3.0))
    assert kept.sum() == ((f.depth_m >= 1.0) & (f.depth_m <= 3.0)).sum()
    with pytest.raises(ValidationError):
        clip_depth(f, 3.0, 1.0)


def test_drop_depth_blanks_the_frames_of_the_gap_only():
    cap = TransformedCapture(_ListCapture(6), partial(drop_depth, start=2, stop=4))
    valid = [int((cap[i].depth_m > 0).sum()) for i in range(6)]
    assert valid[2] == valid[3] == 0 and all(v > 0 for k, v in enumerate(valid) if k not in (2, 3))
    assert cap[2].color is not None and cap[2].index == 2  # only the depth goes
    with pytest.raises(ValidationError):
        drop_depth(_frame(), 3, 1)


def test_revisit_capture_comes_back_with_the_clock_running_on():
    cap = RevisitCapture(_ListCapture(8), at=6, back_to=1, frames=2, pause_s=0.5)
    assert len(cap) == 8
    assert [cap[i].meta["source_index"] for i in range(8)] == [0, 1, 2, 3, 4, 5, 1, 2]
    assert [cap[i].index for i in range(8)] == list(range(8))
    # the source frames are 1 s apart: after frame 5 (t = 5) a 0.5 s pause, then the revisit keeps its spacing
    assert [cap[i].timestamp_s for i in range(8)] == [0, 1, 2, 3, 4, 5, 5.5, 6.5]
    np.testing.assert_array_equal(cap[6].depth_m, _ListCapture(8)[1].depth_m)
    for bad in ({"at": 0, "back_to": 0, "frames": 1}, {"at": 9, "back_to": 0, "frames": 1},
                {"at": 6, "back_to": 6, "frames": 2}, {"at": 6, "back_to": 0, "frames": 0},
                {"at": 6, "back_to": 5, "frames": 4}):
        with pytest.raises(ValidationError):
            RevisitCapture(_ListCapture(8), **bad)
    for pause in (0.0, -1.0):
        with pytest.raises(ValidationError):
            RevisitCapture(_ListCapture(8), 6, 1, 2, pause_s=pause)


def test_transformed_and_sliced_captures_are_lazy():
    base = _ListCapture(10)
    view = SlicedCapture(TransformedCapture(base, partial(resize_frame, width=32, height=24),
                                            partial(clip_depth, max_m=2.0)), start=1, step=3)
    assert len(view) == 3 and base.loaded == []
    frames = list(view)
    assert base.loaded == [1, 4, 7]
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.meta["source_index"] for f in frames] == [1, 4, 7]
    assert all(f.width == 32 and f.depth_m.max() <= 2.0 for f in frames)
    assert view[-1].meta["source_index"] == 7
    with pytest.raises(IndexError):
        view[3]
    with pytest.raises(ValidationError):
        TransformedCapture(base, "not callable")
    with pytest.raises(ValidationError):
        SlicedCapture(base, step=0)


def test_timed_frames_counts_only_the_wait_for_each_frame(monkeypatch):
    """A run's processing time leaves frame loading out: TimedFrames adds up the time spent inside the
    capture's iterator (here 3 x 20 ms of 'decoding'), not the consumer's (3 x 30 ms of 'engine'). The clock
    is a counter the test advances, so the sums are exact."""
    from voxfusion.core.datasets import frame as frame_module
    from voxfusion.core.datasets.frame import TimedFrames

    clock = [100.0]
    monkeypatch.setattr(frame_module.time, "perf_counter", lambda: clock[0])

    def slow_frames():
        for i in range(3):
            clock[0] += 0.02
            yield i

    frames = TimedFrames(slow_frames())
    got = []
    for f in frames:
        got.append(f)
        clock[0] += 0.03
    assert got == [0, 1, 2]
    assert frames.load_s == pytest.approx(0.06, abs=1e-9)
