"""``voxfusion synth``: render a synthetic RGB-D capture with exact ground truth to disk.

Example::

    voxfusion synth out/synth_tum --frames 100 --seed 0                 # TUM layout, 320x240
    voxfusion synth out/synth_replica --layout replica --width 640 --height 480
    voxfusion synth out/synth_lidar --lidar                             # 256x192 noisy depth + confidence
    voxfusion synth out/synth_tum --frames 30 --force                   # replace the capture written there

The folder then opens with ``voxfusion.core.datasets.open_capture`` (TUM or Replica reader) and holds
``gt_mesh.ply`` beside the frames (layouts: :mod:`voxfusion.core.datasets.synthetic`).
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer
from tqdm import tqdm

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
from voxfusion.core.errors import VoxFusionError

__all__ = ["register", "synth_command"]


class Layout(StrEnum):
    """On-disk layout of the written capture."""

    tum = "tum"
    replica = "replica"


def synth_command(
    out_dir: Annotated[Path, typer.Argument(help="Output folder (must not exist or be empty; see --force).")],
    layout: Annotated[Layout, typer.Option("--layout", help="tum or replica.")] = Layout.tum,
    frames: Annotated[int, typer.Option("--frames", help="Number of frames.")] = 100,
    width: Annotated[int | None, typer.Option("--width", help="Image width in pixels (default 320, "
                                                              "256 with --lidar).")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Image height in pixels (default 240, "
                                                                "192 with --lidar).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Scene, trajectory and noise seed.")] = 0,
    lidar: Annotated[bool, typer.Option("--lidar", help="LiDAR-like depth: noise growing with range, "
                                                        "edge dropouts, confidence maps.")] = False,
    motion_scale: Annotated[float, typer.Option("--motion-scale", help="Multiplies per-frame camera "
                                                                       "motion.")] = 1.0,
    force: Annotated[bool, typer.Option("--force", help="Replace the capture an earlier voxfusion synth wrote "
                                                        "in OUT_DIR (a folder holding anything else is refused).")
                     ] = False,
) -> None:
    """Render a synthetic indoor capture (exact depth, poses and mesh) in the TUM or Replica layout."""
    try:
        config = SyntheticConfig(n_frames=frames, seed=seed, width=width, height=height, lidar=lidar,
                                 motion_scale=motion_scale)
        capture = SyntheticCapture(config)
        bars: list[tqdm] = []  # opened on the first frame, so a refused out_dir prints no empty bar

        def progress(_i: int) -> None:
            if not bars:
                bars.append(tqdm(total=len(capture), desc="rendering", unit="frame"))
            bars[0].update(1)

        try:
            out = write_capture(capture, out_dir, layout.value, progress=progress, overwrite=force)
        finally:
            for bar in bars:
                bar.close()
        w, h = config.image_size
        typer.echo(f"wrote {len(capture)} frames ({w}x{h}, {layout.value} layout"
                   f"{', lidar' if lidar else ''}) and gt_mesh.ply to {out}")
    except VoxFusionError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from e


def register(app: typer.Typer) -> None:
    """Add ``synth`` to the ``voxfusion`` app."""
    app.command("synth")(synth_command)
