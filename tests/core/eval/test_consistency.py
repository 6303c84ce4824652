"""Multi-view depth consistency: exact poses agree, perturbed poses disagree, bad input is named."""

import numpy as np
import pytest
import torch

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.errors import ValidationError
from voxfusion.core.eval.consistency import depth_consistency, pair_disagreement
from voxfusion.core.lie import se3_exp


@pytest.fixture(scope="module")
def capture():
    return SyntheticCapture(SyntheticConfig(n_frames=10, width=96, height=72, seed=2))


def load(capture):
    def frame(i):
        f = capture[i]
        return f.depth_m, f.K
    return frame


def test_exact_poses_agree_and_perturbed_poses_do_not(capture):
    gt = np.stack([f.T_world_cam for f in capture.frames()])
    exact = depth_consistency(load(capture), gt, gaps=(1, 4), every=1)
    assert all(p > 0 for p in exact.pairs)
    assert max(exact.disagreement_m) < 0.01, exact  # only nearest-pixel rounding at 96x72

    rng = np.random.default_rng(0)
    noisy = gt.copy()
    for i in range(len(noisy)):
        xi = np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, np.deg2rad(1.0), 3)])
        noisy[i] = noisy[i] @ se3_exp(torch.from_numpy(xi)).numpy()
    worse = depth_consistency(load(capture), noisy, gaps=(1, 4), every=1)
    for a, b in zip(exact.disagreement_m, worse.disagreement_m, strict=True):
        assert b > 2 * a, (exact, worse)
    assert set(worse.as_dict()) == {"gap_1_cm", "gap_4_cm"}


def test_no_overlap_is_nan(capture):
    f = capture[0]
    away = f.T_world_cam.copy()
    away[:3, 3] += [100.0, 0, 0]  # the second camera looks at nothing frame 0 saw
    assert np.isnan(pair_disagreement(f.depth_m, f.K, f.T_world_cam, f.depth_m, f.K, away))


def test_bad_poses_are_named():
    with pytest.raises(ValidationError) as e:
        depth_consistency(lambda i: (np.zeros((2, 2)), np.eye(3)), np.eye(4))
    assert e.value.field == "poses"
