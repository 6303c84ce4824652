"""A picture of a trajectory: top view and height over time, the estimate beside the reference.

``voxfusion run`` writes it as ``trajectory.png`` next to its other outputs. The **top view** shows the two
horizontal axes of the world: the world axis closest to "up" (:attr:`~voxfusion.core.mesh.mesh_frame.WorldAxes.up_m`,
e.g. ARKit's +y, a first-camera world's -y, a motion-capture world's +z) is the vertical one and the other two
are drawn as seen from above (right-handed: looking down, never mirrored). The **height** panel is the position
along that axis (signed so that up is up) over time in seconds from the first pose.

With a reference, the estimate is moved onto it exactly as the ATE does (:func:`.trajectory_error.compute_ate` with
the same :class:`.trajectory_error.TrajectoryEvalConfig`: Umeyama SE(3) by default, first-pose anchoring for
``align="none"``), so the picture shows the error the ATE figure measures; the title gives that figure.

Drawn with matplotlib's Agg canvas directly (no ``pyplot``, no global backend switch: safe in servers and
threads); matplotlib is imported only when a plot is made.

Example::

    from voxfusion.core.eval.trajectory_plot import plot_trajectory

    plot_trajectory("out/desk/trajectory.png", estimate, up_m=(0.0, -1.0, 0.0), reference=gt)
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ShapeError, ValidationError
from ..trajectory import Trajectory
from .trajectory_error import ATEResult, TrajectoryEvalConfig, compute_ate

__all__ = ["PlotAxes", "plot_axes", "plot_trajectory"]

_NAMES = "xyz"


@dataclass(frozen=True)
class PlotAxes:
    """Which world axes a trajectory plot draws.

    Attributes:
        horizontal: ``(a, b)`` world axis indices of the top view's x and y (``a x b`` points up, so the view
            is from above).
        vertical: index of the world axis closest to up.
        sign: ``+1`` or ``-1``: height is ``sign * p[vertical]`` (metres).
    """

    horizontal: tuple[int, int]
    vertical: int
    sign: float

    def label(self, i: int) -> str:
        """``"x [m]"``-style label of world axis ``i``."""
        return f"{_NAMES[i]} [m]"

    @property
    def height_label(self) -> str:
        """``"height (-y) [m]"``: the height axis and the world direction it follows."""
        return f"height ({'+' if self.sign > 0 else '-'}{_NAMES[self.vertical]}) [m]"


def plot_axes(up_m: Sequence[float] | np.ndarray) -> PlotAxes:
    """The top view's axes for a world whose "up" is ``up_m`` ``[3]`` (any length > 0).

    Example: ``plot_axes((0, -1, 0))`` (a first-camera world, OpenCV y down) draws x across and z up the page;
    ``plot_axes((0, 0, 1))`` draws x across and y up the page.

    Raises:
        ShapeError: ``up_m`` is not 3 numbers; ValidationError: it is zero or not finite.
    """
    up = np.asarray(up_m, dtype=np.float64).reshape(-1)
    if up.shape != (3,):
        raise ShapeError("up_m", up.shape, "[3]")
    if not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-12:
        raise ValidationError("up_m", f"must be a finite non-zero direction, got {up.tolist()}")
    k = int(np.argmax(np.abs(up)))
    sign = 1.0 if up[k] > 0 else -1.0
    a, b = (k + 1) % 3, (k + 2) % 3  # e_a x e_b = +e_k (cyclic order)
    if sign < 0:
        a, b = b, a  # e_b x e_a = -e_k: still seen from above
    return PlotAxes((a, b), k, sign)


def _aligned_positions(estimate: Trajectory, ate: ATEResult) -> np.ndarray:
    """``[N, 3]`` every estimated camera centre moved as the ATE moved the associated ones."""
    T = ate.T_align
    return ate.scale * estimate.positions @ T[:3, :3].T + T[:3, 3]


def plot_trajectory(path: str | Path, estimate: Trajectory, up_m: Sequence[float] | np.ndarray,
                    reference: Trajectory | None = None, config: TrajectoryEvalConfig | None = None, *,
                    lost: np.ndarray | None = None, limited: np.ndarray | None = None, title: str | None = None,
                    dpi: int = 100) -> Path:
    """Write a PNG of ``estimate`` (and ``reference``): top view and height over time (module docstring).

    Args:
        path: the PNG to write (its folder is created).
        estimate: the estimated trajectory (``[N]`` timestamps in seconds, ``[N, 4, 4]`` camera-to-world poses).
        up_m: ``[3]`` "up" in the world the plot is drawn in: the reference's world when a reference is
            drawn (the estimate is aligned onto it), else the estimate's.
        reference: reference poses, or ``None`` to draw the estimate alone.
        config: how the estimate is aligned onto the reference (the ATE's options; default
            :class:`TrajectoryEvalConfig`). When the two cannot be associated (too few poses within
            ``config.max_diff_s``) the estimate is drawn alone and the title says why.
        lost: ``[N]`` bool, frames tracking reported lost (marked with red crosses), or ``None``.
        limited: ``[N]`` bool, frames whose tracking state was ``limited`` (purple triangles), or ``None``.
        title: first title line (default: the file's folder name).
        dpi: pixels per inch (the figure is 11 x 4.6 inches: 1100 x 460 pixels at 100).

    Returns:
        ``path``.

    Raises:
        ValidationError: ``estimate`` has no pose; ShapeError: ``lost`` or ``limited`` does not have one flag per
            pose.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    if len(estimate) == 0:
        raise ValidationError("estimate", "has no pose to plot")
    marks = []  # (flags [N], matplotlib format, colour, label)
    for name, flags, fmt, colour in (("lost", lost, "x", "tab:red"), ("limited", limited, "^", "tab:purple")):
        if flags is None:
            continue
        flags = np.asarray(flags, dtype=bool).reshape(-1)
        if flags.shape != (len(estimate),):
            raise ShapeError(name, flags.shape, f"[{len(estimate)}] (one flag per estimated pose)")
        if flags.any():
            marks.append((flags, fmt, colour, name))
    axes = plot_axes(up_m)
    a, b = axes.horizontal
    est_p = estimate.positions
    note = "estimate only (no reference poses)"
    ref_p = ref_t = None
    if reference is not None and len(reference):
        config = config or TrajectoryEvalConfig()
        try:
            ate = compute_ate(estimate, reference, config)
        except ValidationError as e:
            note = f"reference not drawn: {e}"
        else:
            est_p, ref_p, ref_t = _aligned_positions(estimate, ate), reference.positions, reference.timestamps_s
            how = "first pose anchored" if config.align == "none" else f"{config.align.upper()}-aligned"
            note = f"ATE rmse {100 * ate.rmse_m:.2f} cm over {ate.n} poses (estimate {how} to the reference)"
    t0 = float(estimate.timestamps_s.min() if ref_t is None else min(estimate.timestamps_s.min(), ref_t.min()))

    fig = Figure(figsize=(11.0, 4.6), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    top, height = fig.subplots(1, 2, width_ratios=(1.0, 1.35))
    fig.suptitle(f"{title or path.parent.name}: {len(estimate)} poses\n{textwrap.shorten(note, 150)}", fontsize=10)
    if ref_p is not None and ref_t is not None:
        top.plot(ref_p[:, a], ref_p[:, b], color="tab:orange", lw=1.2, ls="--", label="reference")
        height.plot(ref_t - t0, axes.sign * ref_p[:, axes.vertical], color="tab:orange", lw=1.2,
                    ls="--", label="reference")
    top.plot(est_p[:, a], est_p[:, b], color="tab:blue", lw=1.4, label="estimate")
    top.plot(est_p[:1, a], est_p[:1, b], "o", color="tab:green", ms=6, label="start")
    top.plot(est_p[-1:, a], est_p[-1:, b], "s", color="tab:blue", ms=5, label="end")
    height.plot(estimate.timestamps_s - t0, axes.sign * est_p[:, axes.vertical], color="tab:blue", lw=1.4,
                label="estimate")
    for flags, fmt, colour, label in marks:
        top.plot(est_p[flags, a], est_p[flags, b], fmt, color=colour, ms=6, label=label)
        height.plot(estimate.timestamps_s[flags] - t0, axes.sign * est_p[flags, axes.vertical], fmt,
                    color=colour, ms=6, label=label)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel(axes.label(a))
    top.set_ylabel(axes.label(b))
    top.set_title(f"top view (seen from {'+' if axes.sign > 0 else '-'}{_NAMES[axes.vertical]}, up)", fontsize=9)
    height.set_xlabel("time [s] from the first pose")
    height.set_ylabel(axes.height_label)
    height.set_title("height over time", fontsize=9)
    for ax in (top, height):
        ax.grid(True, lw=0.5, alpha=0.5)
        ax.legend(fontsize=8, loc="best")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path
