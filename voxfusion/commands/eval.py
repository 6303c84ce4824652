"""``voxfusion eval``: trajectory error (ATE / RPE) and mesh quality against ground truth.

Example::

    voxfusion eval --traj out/traj.txt --gt data/groundtruth.txt --mesh out/mesh.ply --gt-mesh gt.ply

prints the tables and writes ``eval.json`` beside the estimate (or ``--json PATH``).
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from voxfusion.core.errors import ValidationError, VoxFusionError
from voxfusion.core.eval import (
    MeshEvalConfig,
    TrajectoryEvalConfig,
    compute_ate,
    compute_mesh_metrics,
    compute_rpe,
    format_table,
    load_mesh,
    write_json,
)
from voxfusion.core.trajectory import read_tum_trajectory

__all__ = ["register", "eval_command"]


class Align(StrEnum):
    """Alignment of the estimate to the reference before ATE."""

    se3 = "se3"
    sim3 = "sim3"
    none = "none"


def _trajectory_section(traj: Path, gt: Path, config: TrajectoryEvalConfig) -> tuple[dict, list[dict]]:
    est_t, ref_t = read_tum_trajectory(traj), read_tum_trajectory(gt)
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
        "ate": ate, "rpe": rpe,
    }
    return section, rows


def _mesh_section(mesh: Path, gt_mesh: Path, config: MeshEvalConfig) -> tuple[dict, list[dict]]:
    est_m, gt_m = load_mesh(mesh), load_mesh(gt_mesh)
    results = {
        method: compute_mesh_metrics(est_m, gt_m, MeshEvalConfig(
            n_samples=config.n_samples, threshold_m=config.threshold_m,
            completion_ratio_threshold_m=config.completion_ratio_threshold_m, seed=config.seed,
            method=method))
        for method in ("exact", "sampled")
    }
    thr_cm = 100 * config.threshold_m
    ratio_cm = 100 * config.completion_ratio_threshold_m
    spec = [
        ("accuracy [cm]", lambda m: 100 * m.accuracy_m),
        ("completion [cm]", lambda m: 100 * m.completion_m),
        (f"completion ratio < {ratio_cm:g} cm [%]", lambda m: 100 * m.completion_ratio),
        (f"precision < {thr_cm:g} cm [%]", lambda m: 100 * m.precision),
        (f"recall < {thr_cm:g} cm [%]", lambda m: 100 * m.recall),
        (f"F-score < {thr_cm:g} cm [%]", lambda m: 100 * m.fscore),
    ]
    rows = [{"metric": name, **{k: f(v) for k, v in results.items()}} for name, f in spec]
    section = {"estimate": mesh, "reference": gt_mesh, "n_samples": config.n_samples, **results}
    return section, rows


def eval_command(
    traj: Annotated[Path | None, typer.Option("--traj", help="Estimated trajectory, TUM format.")] = None,
    gt: Annotated[Path | None, typer.Option("--gt", help="Reference trajectory, TUM format.")] = None,
    mesh: Annotated[Path | None, typer.Option("--mesh", help="Estimated mesh (PLY / OBJ / GLB).")] = None,
    gt_mesh: Annotated[Path | None, typer.Option("--gt-mesh", help="Ground-truth mesh.")] = None,
    align: Annotated[Align, typer.Option("--align", help="ATE alignment: se3, sim3 or none "
                                                        "(first pose anchored).")] = Align.se3,
    samples: Annotated[int, typer.Option("--samples", help="Surface samples per mesh.")] = 200_000,
    threshold_cm: Annotated[float, typer.Option("--threshold-cm",
                                                help="Precision/recall/F-score threshold, cm.")] = 5.0,
    max_diff_s: Annotated[float, typer.Option("--max-diff",
                                              help="Timestamp association tolerance, s.")] = 0.02,
    delta: Annotated[int, typer.Option("--delta", help="RPE pair spacing, frames.")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="Surface sampling seed.")] = 0,
    json_path: Annotated[Path | None, typer.Option("--json", help="JSON output (default: eval.json beside "
                                                                 "the estimate).")] = None,
) -> None:
    """Evaluate a trajectory (ATE / RPE) and/or a mesh (accuracy, completion, F-score) against GT."""
    try:
        if (traj is None) != (gt is None):
            raise ValidationError("--traj/--gt", "give both the estimated and the reference trajectory")
        if (mesh is None) != (gt_mesh is None):
            raise ValidationError("--mesh/--gt-mesh", "give both the estimated and the ground-truth mesh")
        if traj is None and mesh is None:
            raise ValidationError("arguments",
                                  "nothing to evaluate: pass --traj/--gt and/or --mesh/--gt-mesh")
        traj_config = TrajectoryEvalConfig(align=align.value, max_diff_s=max_diff_s, rpe_delta=delta)
        mesh_config = MeshEvalConfig(n_samples=samples, threshold_m=threshold_cm / 100, seed=seed)
        report: dict = {}
        if traj is not None and gt is not None:
            report["trajectory"], rows = _trajectory_section(traj, gt, traj_config)
            typer.echo(format_table(rows, ["metric", "value"]))
        if mesh is not None and gt_mesh is not None:
            report["mesh"], rows = _mesh_section(mesh, gt_mesh, mesh_config)
            if "trajectory" in report:
                typer.echo("")
            typer.echo(format_table(rows, ["metric", "exact", "sampled"]))
        beside = traj if traj is not None else mesh
        out = json_path if json_path is not None else beside.parent / "eval.json"
        write_json(out, report)
        typer.echo(f"\nwrote {out}")
    except VoxFusionError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from e


def register(app: typer.Typer) -> None:
    """Add ``eval`` to the ``voxfusion`` app."""
    app.command("eval")(eval_command)
