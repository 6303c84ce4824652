"""Trajectory error: absolute trajectory error (ATE) and relative pose error (RPE).

Definitions follow the TUM RGB-D benchmark (Sturm et al., IROS 2012) and ``evo``:

* **Association.** Estimated and reference poses are paired by timestamp like TUM's ``associate.py``:
  every (estimate, reference) pair whose timestamps differ by less than ``max_diff_s`` is a candidate;
  candidates are taken greedily in order of increasing difference, each pose used at most once; the
  pairs are returned in reference-time order.
* **ATE.** Estimated camera centres are mapped onto the reference by ``T_align`` and the error of pose
  ``i`` is ``||t_ref_i - (s R t_est_i + t)||`` in metres. ``align="se3"`` fits ``T_align`` (rotation +
  translation) to all positions by Umeyama's least squares (Horn's method; scale fixed to 1, identical to
  ``evo``'s ``align(correct_scale=False)``); ``"sim3"`` also fits a scale; ``"none"`` anchors the first
  associated pose instead: ``T_align = T_ref_0 @ inv(T_est_0)`` maps the estimate's first pose exactly
  onto the reference's first pose (an odometry system's natural frame), so drift shows up in full.
* **RPE.** For each pair ``(i, i + delta)`` (all overlapping pairs, as TUM's ``evaluate_rpe.py`` and
  ``evo``'s ``all_pairs=True``), ``E = inv(inv(Q_i) Q_{i+delta}) @ (inv(P_i) P_{i+delta})`` with ``Q``
  the reference and ``P`` the estimate; the translation error is ``||t(E)||`` (metres) and the rotation
  error the angle of ``R(E)`` (degrees). RPE is independent of any rigid world alignment; a Sim(3)
  scale can be applied to the estimate's translations with ``scale``.

Poses are ``[N, 4, 4]`` float64 camera-to-world matrices (OpenCV axes, metres), see ``core/geometry.py``.

Example::

    >>> import numpy as np
    >>> T = np.tile(np.eye(4), (5, 1, 1)); T[:, 0, 3] = np.arange(5.0); T[:, 1, 3] = np.arange(5.0) ** 2
    >>> compute_ate(T, T).rmse_m < 1e-12
    True
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import ShapeError, ValidationError
from ..geometry import invert_pose
from ..trajectory import Trajectory

__all__ = [
    "AlignMode",
    "TrajectoryEvalConfig",
    "ATEResult",
    "RPEResult",
    "associate",
    "align_umeyama",
    "compute_ate",
    "compute_rpe",
]

AlignMode = Literal["se3", "sim3", "none"]
_ALIGN_MODES = ("se3", "sim3", "none")


@dataclass(frozen=True)
class TrajectoryEvalConfig:
    """Options of the trajectory metrics."""

    align: AlignMode = "se3"
    """``"se3"``: rigid Umeyama/Horn fit (scale 1); ``"sim3"``: rigid + scale; ``"none"``: anchor the
    first pose (estimate's first pose mapped onto the reference's first pose)."""
    max_diff_s: float = 0.02
    """Largest timestamp difference, seconds, for two poses to be associated (TUM's default 0.02 s)."""
    offset_s: float = 0.0
    """Added to the estimate's timestamps before association (a known clock offset), seconds."""
    rpe_delta: int = 1
    """RPE pose-pair spacing in (associated) frames."""
    min_poses: int = 3
    """Fewest associated poses accepted; fewer raise ``ValidationError`` naming the trajectory."""

    def __post_init__(self) -> None:
        if self.align not in _ALIGN_MODES:
            raise ValidationError("align", f"must be one of {_ALIGN_MODES}, got {self.align!r}")
        if not self.max_diff_s > 0:
            raise ValidationError("max_diff_s", f"must be > 0 seconds, got {self.max_diff_s}")
        if self.rpe_delta < 1:
            raise ValidationError("rpe_delta", f"must be >= 1 frame, got {self.rpe_delta}")
        if self.min_poses < 2:
            raise ValidationError("min_poses", f"must be >= 2, got {self.min_poses}")


@dataclass(frozen=True, eq=False)
class ATEResult:
    """Absolute trajectory error (camera-centre distances after alignment), metres.

    Attributes:
        rmse_m, mean_m, median_m, max_m: statistics of the per-pose errors ``errors_m``.
        n: number of associated poses used.
        aligned: ``True`` for a least-squares alignment (se3 / sim3), ``False`` for first-pose anchoring.
        scale: the fitted Sim(3) scale (1.0 unless ``align="sim3"``).
        T_align: ``[4, 4]`` float64 transform applied to the estimate's poses (rotation and translation;
            the scale multiplies positions before it: ``p_ref ≈ R (scale * p_est) + t``).
        errors_m: ``[n]`` float64 per-pose errors in reference-time order.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    n: int
    aligned: bool
    scale: float
    T_align: np.ndarray = field(repr=False)
    errors_m: np.ndarray = field(repr=False)

    def summary(self) -> dict[str, float | int | bool | list]:
        """JSON-friendly scalars (and ``T_align`` as nested lists), without the per-pose errors."""
        return {
            "rmse_m": self.rmse_m, "mean_m": self.mean_m, "median_m": self.median_m, "max_m": self.max_m,
            "n": self.n, "aligned": self.aligned, "scale": self.scale, "T_align": self.T_align.tolist(),
        }


@dataclass(frozen=True, eq=False)
class RPEResult:
    """Relative pose error over pose pairs ``delta`` frames apart.

    Attributes:
        trans_rmse_m, trans_mean_m, trans_median_m, trans_max_m: translation error statistics, metres.
        rot_rmse_deg, rot_mean_deg, rot_median_deg, rot_max_deg: rotation angle statistics, degrees.
        n: number of pose pairs.
        delta: pair spacing in associated frames.
        trans_errors_m: ``[n]`` per-pair translation errors; rot_errors_deg: ``[n]`` per-pair angles.
    """

    trans_rmse_m: float
    trans_mean_m: float
    trans_median_m: float
    trans_max_m: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_median_deg: float
    rot_max_deg: float
    n: int
    delta: int
    trans_errors_m: np.ndarray = field(repr=False)
    rot_errors_deg: np.ndarray = field(repr=False)

    def summary(self) -> dict[str, float | int]:
        """JSON-friendly scalars, without the per-pair errors."""
        keys = ("trans_rmse_m", "trans_mean_m", "trans_median_m", "trans_max_m", "rot_rmse_deg",
                "rot_mean_deg", "rot_median_deg", "rot_max_deg", "n", "delta")
        return {k: getattr(self, k) for k in keys}


def associate(t_est_s: np.ndarray, t_ref_s: np.ndarray, max_diff_s: float = 0.02,
              offset_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pair timestamps one-to-one, nearest first (TUM ``associate.py``).

    Args:
        t_est_s: ``[N]`` estimate timestamps, seconds (``offset_s`` is added to them).
        t_ref_s: ``[M]`` reference timestamps, seconds.
        max_diff_s: pairs must differ by less than this.

    Returns:
        ``(idx_est, idx_ref)``: ``[K]`` int64 index arrays, sorted by reference timestamp.
    """
    t_est = np.asarray(t_est_s, dtype=np.float64).reshape(-1) + offset_s
    t_ref = np.asarray(t_ref_s, dtype=np.float64).reshape(-1)
    order = np.argsort(t_ref, kind="stable")
    t_sorted = t_ref[order]
    lo = np.searchsorted(t_sorted, t_est - max_diff_s, side="left")
    hi = np.searchsorted(t_sorted, t_est + max_diff_s, side="right")
    counts = hi - lo
    cand_est = np.repeat(np.arange(t_est.size), counts)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    cand_ref_sorted = np.arange(cand_est.size) + starts
    cand_ref = order[cand_ref_sorted]
    diff = np.abs(t_est[cand_est] - t_ref[cand_ref])
    keep = diff < max_diff_s
    cand_est, cand_ref, diff = cand_est[keep], cand_ref[keep], diff[keep]
    used_est = np.zeros(t_est.size, dtype=bool)
    used_ref = np.zeros(t_ref.size, dtype=bool)
    pairs: list[tuple[int, int]] = []
    for k in np.lexsort((cand_ref, cand_est, diff)):
        i, j = int(cand_est[k]), int(cand_ref[k])
        if not used_est[i] and not used_ref[j]:
            used_est[i] = used_ref[j] = True
            pairs.append((i, j))
    if not pairs:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    p = np.asarray(pairs, dtype=np.int64)
    p = p[np.lexsort((p[:, 0], t_ref[p[:, 1]]))]
    return p[:, 0], p[:, 1]


def align_umeyama(src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False
                  ) -> tuple[np.ndarray, float]:
    """Least-squares ``dst ≈ s R src + t`` (Umeyama 1991; Horn's closed form when ``s = 1``).

    Args:
        src_xyz: ``[N, 3]`` points (the estimate's positions).
        dst_xyz: ``[N, 3]`` corresponding points (the reference's positions).
        with_scale: also fit the scale ``s`` (Sim(3)); otherwise ``s = 1``.

    Returns:
        ``(T, s)``: ``T`` ``[4, 4]`` float64 with ``R`` and ``t``; the scale ``s`` as a float.
    """
    src = np.asarray(src_xyz, dtype=np.float64)
    dst = np.asarray(dst_xyz, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ShapeError("src_xyz", src.shape, f"[N, 3] matching dst_xyz {dst.shape}")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    xs, ys = src - mu_src, dst - mu_dst
    cov = ys.T @ xs / src.shape[0]
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = 1.0
    if with_scale:
        var_src = float((xs**2).sum() / src.shape[0])
        if var_src <= 1e-18:
            raise ValidationError("trajectory",
                                  "all estimated positions coincide; a Sim(3) scale is undefined")
        scale = float(np.trace(np.diag(d) @ S) / var_src)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_dst - scale * R @ mu_src
    return T, scale


def _as_pose_array(x: Trajectory | np.ndarray, field_name: str) -> np.ndarray:
    T = x.T_world_cam if isinstance(x, Trajectory) else np.asarray(x, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ShapeError(field_name, T.shape, "[N, 4, 4] camera-to-world poses")
    if not np.all(np.isfinite(T)):
        raise ValidationError(field_name, "contains non-finite values")
    return T


def _paired(est: Trajectory | np.ndarray, ref: Trajectory | np.ndarray,
            config: TrajectoryEvalConfig) -> tuple[np.ndarray, np.ndarray]:
    """Associate (Trajectory inputs) or check (array inputs) and return ``[K,4,4]`` pose pairs."""
    if isinstance(est, Trajectory) != isinstance(ref, Trajectory):
        raise ValidationError("trajectory",
                              "pass both estimate and reference as Trajectory, or both as arrays")
    P, Q = _as_pose_array(est, "estimate trajectory"), _as_pose_array(ref, "reference trajectory")
    if isinstance(est, Trajectory):
        i_est, i_ref = associate(est.timestamps_s, ref.timestamps_s, config.max_diff_s, config.offset_s)
        P, Q = P[i_est], Q[i_ref]
        what = (f"only {len(P)} poses of the estimate ({len(est)} poses) and the reference ({len(ref)} "
                f"poses) associate within {config.max_diff_s} s")
    else:
        if P.shape != Q.shape:
            raise ShapeError("estimate trajectory", P.shape, f"{Q.shape} (same as the reference poses)")
        what = f"only {len(P)} poses given"
    if len(P) < config.min_poses:
        raise ValidationError("estimate trajectory", f"{what}; at least {config.min_poses} are needed")
    return P, Q


def _stats(e: np.ndarray) -> tuple[float, float, float, float]:
    return (float(np.sqrt(np.mean(e**2))), float(np.mean(e)), float(np.median(e)), float(np.max(e)))


def compute_ate(est: Trajectory | np.ndarray, ref: Trajectory | np.ndarray,
                config: TrajectoryEvalConfig | None = None) -> ATEResult:
    """Absolute trajectory error of ``est`` against ``ref`` (module docstring gives the definition).

    Args:
        est: estimated ``Trajectory``, or ``[N, 4, 4]`` poses already paired with ``ref`` row by row.
        ref: reference (ground-truth) ``Trajectory`` or ``[N, 4, 4]`` poses.
        config: alignment mode, association tolerance, minimum pose count.

    Raises:
        ValidationError: fewer than ``config.min_poses`` associated poses (names the trajectory).
    """
    config = config or TrajectoryEvalConfig()
    P, Q = _paired(est, ref, config)
    if config.align == "none":
        T_align, scale = Q[0] @ invert_pose(P[0]), 1.0
    else:
        T_align, scale = align_umeyama(P[:, :3, 3], Q[:, :3, 3], with_scale=config.align == "sim3")
    p_aligned = scale * P[:, :3, 3] @ T_align[:3, :3].T + T_align[:3, 3]
    errors = np.linalg.norm(Q[:, :3, 3] - p_aligned, axis=1)
    rmse, mean, median, mx = _stats(errors)
    return ATEResult(rmse, mean, median, mx, int(len(errors)), config.align != "none", scale, T_align, errors)


def compute_rpe(est: Trajectory | np.ndarray, ref: Trajectory | np.ndarray,
                config: TrajectoryEvalConfig | None = None, scale: float = 1.0) -> RPEResult:
    """Relative pose error of ``est`` against ``ref`` over pairs ``config.rpe_delta`` frames apart.

    Args:
        est, ref: as for :func:`compute_ate`.
        config: association tolerance, ``rpe_delta`` and minimum pose count.
        scale: multiplies the estimate's translations first (e.g. ``ATEResult.scale`` of a Sim(3) fit).

    Raises:
        ValidationError: too few associated poses, or fewer than ``rpe_delta + 1``.
    """
    config = config or TrajectoryEvalConfig()
    P, Q = _paired(est, ref, config)
    d = config.rpe_delta
    if len(P) <= d:
        raise ValidationError("rpe_delta", f"{d} frames needs more than {len(P)} associated poses")
    P = P.copy()
    P[:, :3, 3] *= scale
    Q_rel = invert_pose(Q[:-d]) @ Q[d:]
    P_rel = invert_pose(P[:-d]) @ P[d:]
    E = invert_pose(Q_rel) @ P_rel
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    return RPEResult(*_stats(t_err), *_stats(r_err), int(len(t_err)), d, t_err, r_err)
