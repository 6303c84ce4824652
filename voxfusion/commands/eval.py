"""``voxfusion eval``: trajectory error (ATE / RPE), mesh quality against ground truth, and the phantom-surface
share of a mesh (no ground truth needed).

Examples::

    voxfusion eval --traj out/run/trajectory.txt --gt data/groundtruth.txt
    voxfusion eval --mesh out/run/mesh.ply --gt-mesh out/room/gt_mesh.ply --capture out/room \\
        --traj out/run/trajectory.txt --gt out/room/groundtruth.txt
    voxfusion eval --mesh out/iphone/mesh.ply --capture data/iphone --traj out/iphone/trajectory.txt

Mesh evaluation, in order:

1. ``<mesh>.frame.json`` (if present) brings the file's coordinates into the session's world frame
   (``T_world_file``) and says what that world is (:mod:`voxfusion.core.mesh.mesh_frame`).
2. With ``--capture``: the phantom-surface share, the mesh's area farther than ``--phantom-cm`` from the
   capture's depth placed with ``--traj`` (the poses the mesh was built with) or, without it, the capture's
   reference poses.
3. With ``--traj`` and ``--gt`` and ``--align se3|sim3``: the mesh follows the trajectory's ATE alignment
   (estimate -> reference, with the Sim(3) scale) onto the reference frame; ``--align none`` evaluates it as
   it is.
4. With ``--gt-mesh``: accuracy / completion / F-score against the GT culled to what the capture's reference
   cameras observed (with ``--capture``; the same culling ``voxfusion run`` does, so the figures match its
   ``metrics.json``) and against the whole GT, each labelled.

The report goes to ``--out PATH`` (never over an existing file without ``--force``) or to the first free
name of ``eval.json``, ``eval-1.json``, ... beside the estimate; the path is printed.
"""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from scipy.spatial.transform import Rotation

from voxfusion.core.datasets import open_capture
from voxfusion.core.errors import ValidationError, VoxFusionError
from voxfusion.core.eval import (
    ATEResult,
    MeshEvalConfig,
    TrajectoryEvalConfig,
    alignment_lever,
    compute_ate,
    compute_rpe,
    evaluate_mesh_against_gt,
    format_table,
    load_mesh,
    phantom_for_capture,
    read_mesh_frame,
    to_jsonable,
    transform_mesh,
    views_from_capture,
)
from voxfusion.core.trajectory import MAX_INTERPOLATION_GAP_S, Trajectory, read_tum_trajectory

__all__ = ["register", "eval_command", "report_path", "alignment_message"]

NOT_CULLED = "whole GT (not culled: pass --capture to restrict to the observed part)"


class Align(StrEnum):
    """Alignment of the estimate to the reference before ATE (and of the mesh, when one is given)."""

    se3 = "se3"
    sim3 = "sim3"
    none = "none"


class Method(StrEnum):
    """Mesh distance method."""

    exact = "exact"
    sampled = "sampled"


def _trajectory_section(est_t: Trajectory, traj: Path, gt: Path, config: TrajectoryEvalConfig,
                        interpolate: bool = True) -> tuple[dict, list[dict], ATEResult]:
    """ATE / RPE of ``est_t`` against the reference file ``gt``. With ``interpolate`` and a dense reference (median
    spacing at most half of :data:`MAX_INTERPOLATION_GAP_S`: motion capture), the reference's poses at the
    estimate's timestamps (:meth:`Trajectory.at`, as a capture reader gives ``voxfusion run`` its ground truth, so
    both report the same figures); otherwise the nearest reference pose within ``config.max_diff_s``."""
    ref_t = read_tum_trajectory(gt)
    interpolate = interpolate and len(ref_t) > 1 and (
        float(np.median(np.diff(ref_t.timestamps_s))) <= MAX_INTERPOLATION_GAP_S / 2)
    if interpolate:
        ref_t = ref_t.at(est_t.timestamps_s)
        if len(ref_t) < 2:
            raise ValidationError("--gt", f"{gt} covers fewer than 2 of the estimate's {len(est_t)} timestamps "
                                          "(pass --no-interpolate to pair nearest poses within --max-diff)")
    ate = compute_ate(est_t, ref_t, config)
    rpe = compute_rpe(est_t, ref_t, config, scale=ate.scale)
    rows = [
        {"metric": f"ATE rmse [cm] (align {config.align})", "value": 100 * ate.rmse_m},
        {"metric": "ATE mean [cm]", "value": 100 * ate.mean_m},
        {"metric": "ATE median [cm]", "value": 100 * ate.median_m},
        {"metric": "ATE max [cm]", "value": 100 * ate.max_m},
        {"metric": "associated poses", "value": ate.n},
        {"metric": f"RPE trans rmse [cm] (delta {rpe.delta})", "value": 100 * rpe.trans_rmse_m},
        {"metric": "RPE trans mean [cm]", "value": 100 * rpe.trans_mean_m},
        {"metric": "RPE rot rmse [deg]", "value": rpe.rot_rmse_deg},
        {"metric": "RPE rot mean [deg]", "value": rpe.rot_mean_deg},
    ]
    if config.align == "sim3":
        rows.append({"metric": "Sim(3) scale", "value": ate.scale})
    section = {
        "estimate": traj, "reference": gt, "align": config.align, "max_diff_s": config.max_diff_s,
        "reference_poses": "interpolated at the estimate's timestamps" if interpolate else "nearest within max_diff_s",
        "ate": ate, "rpe": rpe,
    }
    return section, rows, ate


def alignment_message(align: str, T: np.ndarray, scale: float) -> str:
    """One line describing the trajectory alignment applied to a mesh."""
    angle = float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))
    t = T[:3, 3]
    return (f"mesh aligned with the trajectory's {align} alignment: rotation {angle:.3f} deg, translation "
            f"[{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m, scale {scale:.6f}")


def _mesh_table(section: dict, config: MeshEvalConfig) -> list[dict]:
    thr_cm = 100 * config.threshold_m
    ratio_cm = 100 * config.completion_ratio_threshold_m
    spec = [
        ("accuracy [cm]", lambda m: 100 * m.accuracy_m),
        ("completion [cm]", lambda m: 100 * m.completion_m),
        (f"completion ratio < {ratio_cm:g} cm [%]", lambda m: 100 * m.completion_ratio),
        (f"precision < {thr_cm:g} cm [%]", lambda m: 100 * m.precision),
        (f"recall < {thr_cm:g} cm [%]", lambda m: 100 * m.recall),
        (f"F-score < {thr_cm:g} cm [%]", lambda m: 100 * m.fscore),
        ("GT samples", lambda m: m.n_gt_samples),
    ]
    columns = {"vs observed GT": section.get("mesh_observed_gt"), "vs whole GT": section["mesh_full_gt"]}
    return [{"metric": name, **{c: f(m) for c, m in columns.items() if m is not None}} for name, f in spec]


def _mesh_section(mesh: Path, gt_mesh: Path | None, capture: Path | None, est_t: Trajectory | None,
                  ate: ATEResult | None, align: str, config: MeshEvalConfig, phantom_m: float,
                  max_frames: int | None, stride: int, max_diff_s: float) -> dict:
    """Everything about the mesh; prints as it goes; returns the JSON section."""
    est = load_mesh(mesh)
    frame = read_mesh_frame(mesh)
    warnings: list[str] = []

    def warn(text: str) -> None:
        warnings.append(text)
        typer.secho(f"warning: {text}", fg=typer.colors.YELLOW, err=True)

    foreign = frame.world not in ("reference", "unknown")  # the sidecar says: not the reference frame
    section: dict = {"estimate": mesh, "reference": gt_mesh, "capture": capture, "method": config.method,
                     "n_samples": config.n_samples, "frame": frame}
    if frame.path is not None:
        typer.echo(f"mesh frame: {frame.path.name} says world={frame.world}"
                   + ("" if frame.is_identity else "; T_world_file applied (file -> session world)"))
    if not frame.is_identity:
        est = transform_mesh(est, frame.T_world_file)
    cap = open_capture(capture, stride=stride, limit=max_frames) if capture is not None else None

    if cap is not None:  # phantom share, in the session's world (where --traj's poses live)
        try:
            phantom = phantom_for_capture(est, cap, est_t, threshold_m=phantom_m, n_samples=config.n_samples,
                                          seed=config.seed, max_diff_s=max_diff_s)
        except ValidationError as e:
            if est_t is None and e.field == "poses":
                raise ValidationError("--traj", f"{capture} has no reference poses: pass --traj with the "
                                                "poses the mesh was built with for the phantom share") from e
            raise
        section["phantom"] = phantom
        if foreign and est_t is None:
            warn(f"the mesh is not in the reference frame (its sidecar says world={frame.world}) but the phantom "
                 "share placed the depth with the capture's reference poses: pass --traj (the session's poses)")
        src = "--traj" if est_t is not None else "the capture's reference"
        typer.echo(f"phantom surface: {100 * phantom.share:.2f} % of {phantom.area_m2:.3f} m^2 "
                   f"({phantom.phantom_area_m2:.3f} m^2) is farther than {100 * phantom.threshold_m:g} cm from "
                   f"the observed depth ({phantom.n_views} views, {src} poses)")
        if gt_mesh is None and cap.gt_mesh_path is not None:
            typer.echo(f"(the capture has a GT mesh, {cap.gt_mesh_path}: pass --gt-mesh to evaluate against it)")
    if gt_mesh is None:
        section["warnings"] = warnings
        return section

    aligned = ate is not None and align != "none"
    lever = None
    if aligned:
        message = alignment_message(align, ate.T_align, ate.scale)
        lever = alignment_lever(ate.scale * est_t.positions, ate.rmse_m, transform_mesh(est, np.eye(4), ate.scale))
        est = transform_mesh(est, ate.T_align, ate.scale)
    elif ate is not None:
        message = "mesh evaluated as is (--align none)"
    else:
        message = "mesh evaluated as is (no --traj/--gt pair to align it with)"
    section["alignment"] = {"applied": aligned, "source": "trajectory" if aligned else None, "align": align,
                            "T_align": ate.T_align if aligned else np.eye(4),
                            "scale": ate.scale if aligned else 1.0, "message": message, "lever": lever}
    typer.echo(message)
    if lever is not None and lever.mesh_shift_m > 0.2 * config.threshold_m:
        sd = " / ".join(f"{100 * v:.1f}" for v in lever.spread_m)
        warn(f"the trajectory constrains its {align} alignment's rotation weakly (camera centres spread {sd} cm "
             f"along their principal axes): with {100 * ate.rmse_m:.2f} cm ATE residuals over {len(est_t)} poses "
             f"the rotation is uncertain by about {lever.rotation_deg:.2f} deg, which can move a mesh reaching "
             f"{lever.reach_m:.1f} m from the cameras by about {100 * lever.mesh_shift_m:.1f} cm; if the session "
             "started at the reference's first pose, --align none evaluates the mesh as it was built")
    if foreign and not aligned:
        warn(f"the mesh is not in the reference frame (its sidecar says world={frame.world}); without "
             "a trajectory alignment (--traj/--gt --align se3|sim3) these results are meaningless")

    gt_m = load_mesh(gt_mesh)
    views = None
    if cap is not None:
        views = views_from_capture(cap) or None
        if views is None:
            warn(f"{capture} has no reference poses: the GT cannot be culled to the observed part")
    ev = evaluate_mesh_against_gt(est, gt_m, views, config)
    section.update(ev.summary())
    section["gt_culled"] = views is not None
    section["n_views"] = 0 if views is None else len(views)
    typer.echo("mesh vs observed GT and vs whole GT" if views is not None else f"mesh vs {NOT_CULLED}")
    rows = _mesh_table(section, config)
    typer.echo(format_table(rows, ["metric", *[c for c in rows[0] if c != "metric"]]))
    section["warnings"] = warnings
    return section


def report_path(out: Path | None, beside: Path, force: bool) -> Path:
    """Where the report goes: ``out`` (an error if it exists and not ``force``), else the first of
    ``eval.json``, ``eval-1.json``, ... that does not exist in the folder ``beside``."""
    if out is not None:
        if out.exists() and not force:
            raise ValidationError("--out", f"{out} already exists; pass --force to overwrite it or choose "
                                           "another --out")
        return out
    k = 0
    while (path := beside / ("eval.json" if k == 0 else f"eval-{k}.json")).exists():
        k += 1
    return path


def _write_report(report: dict, out: Path | None, beside: Path, force: bool) -> Path:
    text = json.dumps(to_jsonable(report), indent=2) + "\n"
    path = report_path(out, beside, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        try:
            with path.open("w" if out is not None and force else "x") as f:
                f.write(text)
            return path
        except FileExistsError:  # created since we looked
            if out is not None:
                raise ValidationError("--out", f"{out} already exists; pass --force to overwrite it") from None
            path = report_path(None, beside, force)


def eval_command(
    traj: Annotated[Path | None, typer.Option("--traj", help="Estimated trajectory, TUM format.")] = None,
    gt: Annotated[Path | None, typer.Option("--gt", help="Reference trajectory, TUM format.")] = None,
    mesh: Annotated[Path | None, typer.Option("--mesh", help="Estimated mesh (PLY / OBJ / GLB); a "
                                              "<mesh>.frame.json sidecar beside it is applied.")] = None,
    gt_mesh: Annotated[Path | None, typer.Option("--gt-mesh", help="Ground-truth mesh.")] = None,
    capture: Annotated[Path | None, typer.Option("--capture", help="The capture the mesh was built from: culls "
                                                 "the GT to what its cameras observed and gives the phantom "
                                                 "share.")] = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Use only the capture's first N frames "
                                                   "(as the run did).")] = None,
    stride: Annotated[int, typer.Option("--stride", help="Use every N-th capture frame (as the run did).")] = 1,
    align: Annotated[Align, typer.Option("--align", help="ATE alignment: se3, sim3 or none (first pose "
                                                        "anchored). With --mesh, the mesh follows the se3 / "
                                                        "sim3 alignment; none: mesh as is.")] = Align.se3,
    method: Annotated[Method, typer.Option("--method", help="Mesh distances: exact point-to-surface, or the "
                                                           "papers' sampled variant.")] = Method.exact,
    samples: Annotated[int, typer.Option("--samples", help="Surface samples per mesh.")] = 200_000,
    threshold_cm: Annotated[float, typer.Option("--threshold-cm",
                                                help="Precision/recall/F-score threshold, cm.")] = 5.0,
    phantom_cm: Annotated[float, typer.Option("--phantom-cm", help="Phantom-surface distance threshold, "
                                                                   "cm.")] = 5.0,
    max_diff_s: Annotated[float, typer.Option("--max-diff",
                                              help="Timestamp association tolerance, s.")] = 0.02,
    delta: Annotated[int, typer.Option("--delta", help="RPE pair spacing, frames.")] = 1,
    interpolate: Annotated[bool, typer.Option("--interpolate/--no-interpolate",
                                              help="Interpolate a dense --gt (samples <= 50 ms apart, e.g. "
                                                   "motion capture) at the estimate's timestamps, as voxfusion "
                                                   "run reads a capture's ground truth; "
                                                   "--no-interpolate pairs each estimate with the nearest --gt "
                                                   "pose within --max-diff.")] = True,
    seed: Annotated[int, typer.Option("--seed", help="Surface sampling seed.")] = 0,
    out: Annotated[Path | None, typer.Option("--out", "--json", help="JSON report path (default: eval.json, "
                                             "eval-1.json, ... beside the estimate).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --out if it exists.")] = False,
) -> None:
    """Evaluate a trajectory (ATE / RPE) and/or a mesh (accuracy, completion, F-score vs the observed and
    the whole GT; phantom-surface share) and write a JSON report."""
    try:
        if gt is not None and traj is None:
            raise ValidationError("--traj/--gt", "give both the estimated and the reference trajectory")
        if traj is not None and gt is None and (mesh is None or capture is None):
            raise ValidationError("--traj/--gt", "give both the estimated and the reference trajectory (--traj "
                                                 "alone only places the capture's depth for --mesh --capture)")
        if gt_mesh is not None and mesh is None:
            raise ValidationError("--mesh/--gt-mesh", "give both the estimated and the ground-truth mesh")
        if mesh is not None and gt_mesh is None and capture is None:
            raise ValidationError("--mesh", "give --gt-mesh (accuracy / completion) and/or --capture (phantom "
                                            "share) with it")
        if capture is not None and mesh is None:
            raise ValidationError("--capture", "is used to evaluate a mesh: pass --mesh")
        if traj is None and mesh is None:
            raise ValidationError("arguments", "nothing to evaluate: pass --traj/--gt and/or --mesh with "
                                               "--gt-mesh or --capture")
        beside = (traj if traj is not None else mesh).parent
        report_path(out, beside, force)  # fail now, not after minutes of work
        traj_config = TrajectoryEvalConfig(align=align.value, max_diff_s=max_diff_s, rpe_delta=delta)
        mesh_config = MeshEvalConfig(n_samples=samples, threshold_m=threshold_cm / 100, seed=seed,
                                     method=method.value)
        if not phantom_cm > 0:
            raise ValidationError("--phantom-cm", f"must be > 0, got {phantom_cm}")
        report: dict = {}
        est_t = read_tum_trajectory(traj) if traj is not None else None
        ate = None
        if est_t is not None and gt is not None:
            report["trajectory"], rows, ate = _trajectory_section(est_t, traj, gt, traj_config, interpolate)
            typer.echo(format_table(rows, ["metric", "value"]))
            typer.echo("")
        if mesh is not None:
            report["mesh"] = _mesh_section(mesh, gt_mesh, capture, est_t, ate, align.value, mesh_config,
                                           phantom_cm / 100, max_frames, stride, max_diff_s)
        path = _write_report(report, out, beside, force)
        typer.echo(f"\nwrote {path}")
    except VoxFusionError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from e


def register(app: typer.Typer) -> None:
    """Add ``eval`` to the ``voxfusion`` app."""
    app.command("eval")(eval_command)
