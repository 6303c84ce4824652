"""``voxfusion map``: reconstruct a capture with its reference poses (no tracking).

Example::

    voxfusion map ../shared/data/sevenscenes_redkitchen --max-frames 300 --out out/kitchen   # sevenscenes+cpu here

Without ``--config`` the preset follows the capture and the device, as for ``voxfusion run``. It writes
``mesh.ply``, ``voxels.npz``, ``voxels.ply``, ``checkpoint.pt``, ``trajectory.txt``, ``timings.json`` and
``metrics.json`` (mesh accuracy / completion against the whole and the observed GT when the capture has a GT
mesh, keys ``mesh_full_gt`` / ``mesh_observed_gt`` under ``mesh``; the phantom-surface share, ``phantom``).
An OUT holding another command's outputs is refused unless ``--force`` deletes them
(:mod:`voxfusion.commands.outputs`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import typer

from voxfusion.commands.run import config_for_capture, mesh_metric_rows
from voxfusion.core.config import config_to_dict
from voxfusion.core.datasets import open_capture
from voxfusion.core.eval import format_table, write_json
from voxfusion.core.reconstruct import map_capture
from voxfusion.core.run import evaluate_mesh, evaluate_phantom

from .outputs import claim_output_dir

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    @app.command("map")
    def map_command(
        capture: Annotated[Path, typer.Argument(help="Capture folder or .r3d file (any format voxfusion reads).")],
        out: Annotated[Path, typer.Option("--out", help="Output folder.")],
        config: Annotated[str | None, typer.Option("--config", help="Preset in configs/ (tum, tum+cpu, ...) or a "
                                                   "YAML path; default: chosen from the capture and the device.")]
        = None,
        set_: Annotated[list[str] | None, typer.Option("--set", help="Override, e.g. mapping.iters=20.")] = None,
        max_frames: Annotated[int | None, typer.Option(help="Use only the first N frames.")] = None,
        stride: Annotated[int, typer.Option(help="Use every N-th frame.")] = 1,
        device: Annotated[str | None, typer.Option(help="auto, cpu or cuda (overrides the config).")] = None,
        eval_samples: Annotated[int, typer.Option(help="Surface samples for mesh metrics.")] = 200_000,
        force: Annotated[bool, typer.Option("--force", help="Delete other commands' outputs in OUT (e.g. a "
                                                            "stream's session.json) instead of refusing "
                                                            "the folder.")] = False,
    ) -> None:
        """Reconstruct CAPTURE with its reference poses: mesh, voxel map, checkpoint, metrics."""
        for path in claim_output_dir(out, "map", force):
            typer.echo(f"--force: deleted {path} (another command's output)")
        overrides = list(set_ or [])
        if device:
            overrides.append(f"device={device}")
        cap = open_capture(capture, stride=stride, limit=max_frames)
        cfg = config_for_capture(cap, config, overrides, device)
        result = map_capture(cap, cfg, out)
        metrics = evaluate_mesh(result.mesh, cap, len(cap), eval_samples)
        phantom = evaluate_phantom(result.mesh, cap, len(cap), None, eval_samples)  # mapped with reference poses
        summary = result.timing_summary()
        mem = result.mapper.voxels.memory_report(result.mapper.decoder)
        write_json(out / "metrics.json", {
            "capture": str(capture), "config": config_to_dict(result.config), "timings": summary,
            "memory": dataclasses.asdict(mem), "mesh": metrics, **phantom,
            "mesh_vertices": len(result.mesh.vertices), "mesh_faces": len(result.mesh.faces),
        })
        rows = [{"metric": k, "value": v} for k, v in summary.items()]
        rows += [{"metric": "voxels", "value": mem.n_voxels},
                 {"metric": "embeddings [MB]", "value": mem.embedding_bytes / 1e6},
                 {"metric": "decoder [MB]", "value": mem.decoder_bytes / 1e6}]
        rows += mesh_metric_rows({**metrics, **phantom})
        typer.echo(format_table(rows))
        typer.echo(f"outputs in {out}")
