"""ATE / RPE: analytic cases, association, errors, and a cross-check against evo."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from voxfusion.core.errors import ShapeError, ValidationError
from voxfusion.core.eval import (
    TrajectoryEvalConfig,
    align_umeyama,
    associate,
    compute_ate,
    compute_rpe,
)
from voxfusion.core.trajectory import Trajectory


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """A wandering trajectory: random-walk positions, random rotations, ``[n, 4, 4]``."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.5).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)) * 0.1, axis=0)
    return T


def perturb(T: np.ndarray, sigma_t: float, sigma_r: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    E = T.copy()
    E[:, :3, 3] += rng.normal(size=(len(T), 3)) * sigma_t
    E[:, :3, :3] = E[:, :3, :3] @ Rotation.from_rotvec(rng.normal(size=(len(T), 3)) * sigma_r).as_matrix()
    return E


def rigid(rotvec, t) -> np.ndarray:
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    G[:3, 3] = t
    return G


G_WORLD = rigid([0.3, -0.5, 1.0], [1.0, -2.0, 0.5])


def test_rigid_world_change_is_removed_by_alignment_and_by_anchoring():
    T = random_poses(40)
    E = G_WORLD @ T
    for align in ("se3", "sim3", "none"):
        r = compute_ate(E, T, TrajectoryEvalConfig(align=align))
        assert r.rmse_m < 1e-9 and r.max_m < 1e-9, align
        assert r.n == 40
        np.testing.assert_allclose(r.T_align, np.linalg.inv(G_WORLD), atol=1e-9)
        np.testing.assert_allclose(r.scale, 1.0, atol=1e-9)
    assert compute_ate(E, T, TrajectoryEvalConfig(align="none")).aligned is False
    assert compute_ate(E, T).aligned is True


def test_unaligned_ate_equals_known_offset():
    T = random_poses(21)
    E = G_WORLD @ T
    offset = np.array([0.03, -0.04, 0.0])  # 5 cm, applied in the reference world after the first frame
    E[1:, :3, 3] += (G_WORLD[:3, :3] @ offset)
    r = compute_ate(E, T, TrajectoryEvalConfig(align="none"))
    np.testing.assert_allclose(r.errors_m[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(r.errors_m[1:], 0.05, atol=1e-12)
    np.testing.assert_allclose(r.max_m, 0.05, atol=1e-12)
    np.testing.assert_allclose(r.median_m, 0.05, atol=1e-12)
    np.testing.assert_allclose(r.rmse_m, 0.05 * np.sqrt(20 / 21), atol=1e-12)
    # A least-squares fit spreads the jump over all poses: smaller than the anchored error.
    assert compute_ate(E, T).rmse_m < r.rmse_m


def test_sim3_recovers_scale_and_se3_does_not():
    T = random_poses(30)
    E = G_WORLD @ T
    E[:, :3, 3] *= 0.5  # the estimate is at half scale (p_est = 0.5 * (R p + t))
    sim = compute_ate(E, T, TrajectoryEvalConfig(align="sim3"))
    assert sim.rmse_m < 1e-9
    np.testing.assert_allclose(sim.scale, 2.0, rtol=1e-9)
    assert compute_ate(E, T, TrajectoryEvalConfig(align="se3")).rmse_m > 0.01


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(100, 3))
    G = rigid([0.1, 0.2, -0.3], [3.0, 0.0, -1.0])
    dst = 1.7 * src @ G[:3, :3].T + G[:3, 3]
    T, s = align_umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(T, G, atol=1e-10)
    np.testing.assert_allclose(s, 1.7, rtol=1e-10)
    with pytest.raises(ShapeError):
        align_umeyama(src, dst[:10])
    with pytest.raises(ValidationError):
        align_umeyama(np.zeros((5, 3)), dst[:5], with_scale=True)


def test_straight_line_and_static_trajectories_align():
    # Rank-deficient position sets (evo refuses them): the rotation about the line is free, the error is 0.
    T = np.tile(np.eye(4), (10, 1, 1))
    T[:, 0, 3] = 0.2 * np.arange(10)
    assert compute_ate(G_WORLD @ T, T).rmse_m < 1e-9
    static = np.tile(np.eye(4), (10, 1, 1))
    assert compute_ate(G_WORLD @ static, static).rmse_m < 1e-9


def test_ate_statistics_match_definition():
    T = random_poses(25)
    E = perturb(T, 0.02, 0.0)
    r = compute_ate(E, T, TrajectoryEvalConfig(align="none"))
    e = r.errors_m
    assert r.rmse_m == pytest.approx(np.sqrt(np.mean(e**2)))
    assert r.mean_m == pytest.approx(e.mean())
    assert r.median_m == pytest.approx(np.median(e))
    assert r.max_m == pytest.approx(e.max())
    assert r.mean_m <= r.rmse_m <= r.max_m


def test_association_by_timestamp():
    T = random_poses(50)
    ts = np.arange(50) * 0.1
    # The estimate: every other pose, 5 ms late, plus two poses that match nothing.
    keep = np.arange(0, 50, 2)
    est_ts = np.concatenate([ts[keep] + 0.005, [100.0, -50.0]])
    est_T = np.concatenate([G_WORLD @ T[keep], np.tile(np.eye(4), (2, 1, 1))])
    r = compute_ate(Trajectory(est_ts, est_T), Trajectory(ts, T))
    assert r.n == 25
    assert r.rmse_m < 1e-9
    # A clock offset beyond max_diff breaks association unless it is given.
    with pytest.raises(ValidationError, match="associate"):
        compute_ate(Trajectory(ts + 0.05, T), Trajectory(ts, T))
    r = compute_ate(Trajectory(ts + 0.05, T), Trajectory(ts, T), TrajectoryEvalConfig(offset_s=-0.05))
    assert r.n == 50


def test_associate_is_one_to_one_nearest_first():
    t_ref = np.array([0.0, 1.0, 2.0, 3.0])
    t_est = np.array([0.011, 0.001, 2.05, 2.99, 3.0])
    i_est, i_ref = associate(t_est, t_ref, max_diff_s=0.02)
    # ref 0 takes est 1 (closer than est 0); ref 3 takes est 4 (exact); est 2 is 50 ms off; ref 1 alone.
    assert i_est.tolist() == [1, 4]
    assert i_ref.tolist() == [0, 3]
    i_est, i_ref = associate(t_est, t_ref, max_diff_s=0.1)
    assert list(zip(i_est.tolist(), i_ref.tolist(), strict=True)) == [(1, 0), (2, 2), (4, 3)]
    e, r = associate(np.array([5.0]), t_ref)
    assert e.size == 0 and r.size == 0


def test_too_few_poses_and_bad_inputs_raise():
    T = random_poses(10)
    ts = np.arange(10.0)
    with pytest.raises(ValidationError) as exc:
        compute_ate(Trajectory(ts[:2], T[:2]), Trajectory(ts, T))
    assert exc.value.field == "estimate trajectory"
    assert "only 2 poses" in str(exc.value)
    with pytest.raises(ValidationError):
        compute_ate(T[:2], T[:2])
    with pytest.raises(ShapeError):
        compute_ate(T[:5], T)
    with pytest.raises(ShapeError):
        compute_ate(T[:, :3], T[:, :3])
    with pytest.raises(ValidationError):
        compute_ate(Trajectory(ts, T), T)
    bad = T.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(ValidationError):
        compute_ate(bad, T)
    with pytest.raises(ValidationError):
        TrajectoryEvalConfig(align="affine")
    with pytest.raises(ValidationError):
        TrajectoryEvalConfig(rpe_delta=0)
    with pytest.raises(ValidationError):
        compute_rpe(T[:3], T[:3], TrajectoryEvalConfig(rpe_delta=3))


def constant_velocity(n: int) -> np.ndarray:
    """Moves 0.1 m/frame along x and yaws 2 degrees per frame."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", 2.0 * np.arange(n)[:, None], degrees=True).as_matrix()
    T[:, 0, 3] = 0.1 * np.arange(n)
    return T


def test_rpe_of_identical_and_world_shifted_trajectories_is_zero():
    T = constant_velocity(20)
    r = compute_rpe(G_WORLD @ T, T)
    assert r.n == 19 and r.delta == 1
    assert r.trans_max_m < 1e-12 and r.rot_max_deg < 1e-9


def test_rpe_of_one_perturbed_pose():
    n, k = 20, 7
    T = constant_velocity(n)
    E = T.copy()
    E[k, :3, 3] += [0.0, 0.03, 0.04]  # 5 cm displacement of one pose
    r = compute_rpe(E, T)
    # Exactly the two pairs touching pose k see the displacement, in full.
    np.testing.assert_allclose(np.sort(r.trans_errors_m)[-2:], 0.05, atol=1e-12)
    assert np.count_nonzero(r.trans_errors_m > 1e-12) == 2
    np.testing.assert_allclose(r.trans_rmse_m, 0.05 * np.sqrt(2 / (n - 1)), atol=1e-12)
    assert r.rot_max_deg < 1e-9

    E = T.copy()
    E[k, :3, :3] = E[k, :3, :3] @ Rotation.from_euler("x", 3.0, degrees=True).as_matrix()
    r = compute_rpe(E, T)
    np.testing.assert_allclose(np.sort(r.rot_errors_deg)[-2:], 3.0, atol=1e-9)
    assert np.count_nonzero(r.rot_errors_deg > 1e-9) == 2

    # delta = 5: only pairs (k-5, k) and (k, k+5) touch pose k.
    r = compute_rpe(E, T, TrajectoryEvalConfig(rpe_delta=5))
    assert r.n == n - 5 and r.delta == 5
    assert np.count_nonzero(r.rot_errors_deg > 1e-9) == 2


def test_rpe_of_scale_drift_and_sim3_scale():
    T = constant_velocity(15)
    E = T.copy()
    E[:, :3, 3] *= 1.1  # 10% too fast: 1 cm error per 10 cm step
    r = compute_rpe(E, T)
    np.testing.assert_allclose(r.trans_errors_m, 0.01, atol=1e-12)
    assert compute_rpe(E, T, scale=1 / 1.1).trans_max_m < 1e-12


# ---------------------------------------------------------------------------------------------------
# Cross-check against evo (the reference implementation the community uses).

evo_metrics = pytest.importorskip("evo.core.metrics")
evo_sync = pytest.importorskip("evo.core.sync")
evo_traj = pytest.importorskip("evo.core.trajectory")


def _evo_pair(E: np.ndarray, T: np.ndarray, ts: np.ndarray):
    ref = evo_traj.PoseTrajectory3D(poses_se3=list(T), timestamps=ts)
    est = evo_traj.PoseTrajectory3D(poses_se3=list(E), timestamps=ts + 0.003)
    return evo_sync.associate_trajectories(ref, est, max_diff=0.01)


@pytest.mark.parametrize("align", ["se3", "sim3", "none"])
def test_ate_matches_evo_ape(align):
    T = random_poses(60, seed=4)
    E = G_WORLD @ perturb(T, 0.02, 0.02, seed=5)
    E[:, :3, 3] *= 1.05
    ts = np.arange(60) * 0.05
    ref, est = _evo_pair(E, T, ts)
    est = copy.deepcopy(est)
    if align == "none":
        est.align_origin(ref)
    else:
        est.align(ref, correct_scale=align == "sim3")
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = ape.get_all_statistics()
    r = compute_ate(Trajectory(ts + 0.003, E), Trajectory(ts, T), TrajectoryEvalConfig(align=align))
    assert r.n == 60
    for ours, theirs in ((r.rmse_m, "rmse"), (r.mean_m, "mean"), (r.median_m, "median"), (r.max_m, "max")):
        assert ours == pytest.approx(stats[theirs], abs=1e-6), theirs


@pytest.mark.parametrize("delta", [1, 4])
def test_rpe_matches_evo_rpe(delta):
    T = random_poses(60, seed=6)
    E = G_WORLD @ perturb(T, 0.02, 0.03, seed=7)
    ts = np.arange(60) * 0.05
    ref, est = _evo_pair(E, T, ts)
    r = compute_rpe(Trajectory(ts + 0.003, E), Trajectory(ts, T), TrajectoryEvalConfig(rpe_delta=delta))
    for relation, prefix, unit in (
        (evo_metrics.PoseRelation.translation_part, "trans", "m"),
        (evo_metrics.PoseRelation.rotation_angle_deg, "rot", "deg"),
    ):
        rpe = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
        rpe.process_data((ref, est))
        stats = rpe.get_all_statistics()
        assert r.n == len(rpe.error)
        for stat in ("rmse", "mean", "median", "max"):
            ours = getattr(r, f"{prefix}_{stat}_{unit}")
            assert ours == pytest.approx(stats[stat], abs=1e-6), (prefix, stat)
