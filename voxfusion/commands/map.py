"""``voxfusion map``: reconstruct a capture with its reference poses (no tracking).

Example::

    voxfusion map ../shared/data/sevenscenes_redkitchen --config sevenscenes --max-frames 300 --out out/kitchen

writes ``mesh.ply``, ``voxels.npz``, ``voxels.ply``, ``checkpoint.pt``, ``trajectory.txt``,
``timings.json`` and ``metrics.json`` (mesh accuracy / completion when the capture has a GT mesh).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import typer

from voxfusion.core.config import config_to_dict
from voxfusion.core.datasets import open_capture
from voxfusion.core.eval import MeshEvalConfig, compute_mesh_metrics, format_table, load_mesh, write_json
from voxfusion.core.eval.mesh import views_from_frames
from voxfusion.core.reconstruct import map_capture
from voxfusion.core.slam_config import load_preset

__all__ = ["register", "evaluate_mesh_against_gt"]


def evaluate_mesh_against_gt(mesh, capture, n_samples: int = 200_000, max_views: int = 200) -> dict:  # noqa: ANN001
    """Exact accuracy / completion of ``mesh`` against the capture's GT mesh: against the whole GT and
    against the GT culled to what the capture's cameras observed (frustum + depth test)."""
    gt = getattr(capture, "gt_mesh", None)
    if gt is None and capture.gt_mesh_path is not None:
        gt = load_mesh(capture.gt_mesh_path)
    if gt is None:
        return {}
    cfg = MeshEvalConfig(n_samples=n_samples)
    step = max(1, len(capture) // max_views)
    views = views_from_frames(list(capture.frames(0, None, step)))
    return {
        "full": compute_mesh_metrics(mesh, gt, cfg),
        "observed": compute_mesh_metrics(mesh, gt, cfg, views=views),
    }


def register(app: typer.Typer) -> None:
    @app.command("map")
    def map_command(
        capture: Annotated[Path, typer.Argument(help="Capture folder or .r3d file (any format voxfusion reads).")],
        out: Annotated[Path, typer.Option("--out", help="Output folder.")],
        config: Annotated[str, typer.Option("--config", help="Preset name in configs/ or a YAML path.")] = "default",
        set_: Annotated[list[str] | None, typer.Option("--set", help="Override, e.g. mapping.iters=20.")] = None,
        max_frames: Annotated[int | None, typer.Option(help="Use only the first N frames.")] = None,
        stride: Annotated[int, typer.Option(help="Use every N-th frame.")] = 1,
        device: Annotated[str | None, typer.Option(help="auto, cpu or cuda (overrides the config).")] = None,
        eval_samples: Annotated[int, typer.Option(help="Surface samples for mesh metrics.")] = 200_000,
    ) -> None:
        """Reconstruct CAPTURE with its reference poses: mesh, voxel map, checkpoint, metrics."""
        overrides = list(set_ or [])
        if device:
            overrides.append(f"device={device}")
        cfg = load_preset(config, overrides)
        cap = open_capture(capture, stride=stride, limit=max_frames)
        result = map_capture(cap, cfg, out)
        metrics = evaluate_mesh_against_gt(result.mesh, cap, eval_samples)
        summary = result.timing_summary()
        mem = result.mapper.voxels.memory_report(result.mapper.decoder)
        write_json(out / "metrics.json", {
            "capture": str(capture), "config": config_to_dict(result.config), "timings": summary,
            "memory": dataclasses.asdict(mem), "mesh": metrics,
            "mesh_vertices": len(result.mesh.vertices), "mesh_faces": len(result.mesh.faces),
        })
        rows = [{"metric": k, "value": v} for k, v in summary.items()]
        rows += [{"metric": "voxels", "value": mem.n_voxels},
                 {"metric": "embeddings [MB]", "value": mem.embedding_bytes / 1e6},
                 {"metric": "decoder [MB]", "value": mem.decoder_bytes / 1e6}]
        for name, m in metrics.items():
            rows += [{"metric": f"accuracy [cm] ({name} GT)", "value": 100 * m.accuracy_m},
                     {"metric": f"completion [cm] ({name} GT)", "value": 100 * m.completion_m},
                     {"metric": f"completion ratio < 5 cm [%] ({name} GT)", "value": 100 * m.completion_ratio}]
        typer.echo(format_table(rows))
        typer.echo(f"outputs in {out}")
