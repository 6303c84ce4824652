"""``voxfusion run``: full Vox-Fusion SLAM (tracking + mapping) over a recorded capture.

Example::

    voxfusion run ../shared/data/tum_fr1_desk_9frames --out out/desk              # preset chosen: tum+cpu here
    voxfusion run ../shared/data/tum_fr1_desk_9frames --config tum --out out/desk # GPU sizes: warns on a CPU

Without ``--config`` the preset follows the capture's kind and the device
(:func:`voxfusion.core.slam.presets.preset_for`) and the chosen preset is printed with the reason.

writes ``trajectory.txt`` (TUM), ``trajectory.png`` (top view and height over time, against the reference
poses aligned as for the ATE), ``keyframes.json``, ``mesh.ply``, ``voxels.npz``/``.ply``, ``checkpoint.pt``,
``metrics.json`` (ATE, mesh metrics against the whole and the observed GT, phantom-surface share, timings, peak
memory) and ``frames.json``. An OUT holding another command's outputs (a ``voxfusion stream``'s
``session.json``, ``voxfusion eval``'s ``eval.json``) is refused unless ``--force`` deletes them
(:mod:`voxfusion.commands.outputs`).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Annotated

import typer

from voxfusion.core.datasets import open_capture
from voxfusion.core.datasets.frame import Capture
from voxfusion.core.eval import format_table
from voxfusion.core.run import run_capture, timing_summary
from voxfusion.core.slam.presets import VoxFusionConfig, load_preset, preset_for, size_warning

from .outputs import claim_output_dir

__all__ = ["register", "config_for_capture", "mesh_metric_rows", "consistency_row"]

_GT_LABELS = {"mesh_observed_gt": "vs observed GT", "mesh_full_gt": "vs whole GT"}


def mesh_metric_rows(metrics: dict) -> list[dict]:
    """Table rows for the mesh figures of ``metrics`` (``mesh_observed_gt``, ``mesh_full_gt``, ``phantom``),
    each labelled with the GT part it was measured against."""
    rows = []
    for key, label in _GT_LABELS.items():
        m = metrics.get(key)
        if m is not None:
            rows += [{"metric": f"accuracy [cm] ({label})", "value": 100 * m.accuracy_m},
                     {"metric": f"completion [cm] ({label})", "value": 100 * m.completion_m},
                     {"metric": f"completion ratio < 5 cm [%] ({label})",
                      "value": 100 * m.completion_ratio}]
    p = metrics.get("phantom")
    if p is not None:
        rows.append({"metric": f"phantom surface [%] (> {100 * p.threshold_m:g} cm from observed depth, "
                               f"{p.poses} poses)", "value": 100 * p.share})
    elif "phantom_skipped" in metrics:
        rows.append({"metric": "phantom surface [%]", "value": f"n/a: {metrics['phantom_skipped']}"})
    ph = metrics.get("photometric")
    if ph is not None and ph["n_pixels"]:
        rows += [{"metric": f"colour error [0-255] (mesh vs {len(ph['frames'])} input frames)", "value": ph["mae"]},
                 {"metric": "colour chroma / contrast vs input (1 = as vivid)",
                  "value": f"{ph['chroma_ratio']:.2f} / {ph['contrast_ratio']:.2f}"}]
    return rows


def config_for_capture(capture: Capture, config: str | None, overrides: list[str],
                       device: str | None) -> VoxFusionConfig:
    """The run's config: ``config`` (a preset name, composition or YAML path) with the capture's facts under it,
    or, with ``config=None``, the preset :func:`preset_for` picks (its reason printed). Prints the one warning
    of a GPU-sized config on the CPU (to stderr)."""
    if config is None:
        choice = preset_for(capture, device or "auto", overrides)
        typer.echo(choice.reason)
        cfg, name = choice.config, choice.preset
    else:
        cfg, name = load_preset(config, overrides, profile=capture.profile), config
    warning = size_warning(cfg, name)
    if warning is not None:
        typer.secho(warning, fg=typer.colors.YELLOW, err=True)
    return cfg


def register(app: typer.Typer) -> None:
    @app.command("run")
    def run_command(
        capture: Annotated[Path, typer.Argument(help="Capture folder or .r3d file (any format voxfusion reads).")],
        out: Annotated[Path, typer.Option("--out", help="Output folder.")],
        config: Annotated[str | None, typer.Option("--config", help="Preset in configs/ (tum, tum+cpu, ...) or a "
                                                   "YAML path; default: chosen from the capture and the device.")]
        = None,
        set_: Annotated[list[str] | None, typer.Option("--set", help="Override, e.g. tracking.iters=20.")] = None,
        max_frames: Annotated[int | None, typer.Option(help="Use only the first N frames.")] = None,
        stride: Annotated[int, typer.Option(help="Use every N-th frame.")] = 1,
        mode: Annotated[str | None, typer.Option(help="offline or realtime (overrides the config).")] = None,
        device: Annotated[str | None, typer.Option(help="auto, cpu or cuda (overrides the config).")] = None,
        speed: Annotated[float, typer.Option(help="Realtime mode: playback speed factor.")] = 1.0,
        force: Annotated[bool, typer.Option("--force", help="Delete other commands' outputs in OUT (e.g. a "
                                                            "stream's session.json) instead of refusing "
                                                            "the folder.")] = False,
    ) -> None:
        """Track and map CAPTURE; print ATE / mesh metrics / speed and write all outputs to OUT."""
        t_command = time.perf_counter() - (process_age_s() or 0.0)  # when the process started, where known
        for path in claim_output_dir(out, "run", force):
            typer.echo(f"--force: deleted {path} (another command's output)")
        overrides = list(set_ or [])
        if device:
            overrides.append(f"device={device}")
        if mode:
            overrides.append(f"mode={mode}")
        cap = open_capture(capture, stride=stride, limit=max_frames)
        cfg = config_for_capture(cap, config, overrides, device)
        result = run_capture(cap, cfg, out, speed=speed)
        st = result.stats
        timings = timing_summary(result)
        rows = [{"metric": label, "value": timings[key]} for key, label in TIMING_LABELS.items()]
        rows += [{"metric": "frames tracked / lost / limited / dropped",
                  "value": f"{st.frames_tracked} / {st.frames_lost} / {st.frames_limited} / {st.frames_dropped}"},
                 {"metric": "keyframes", "value": st.keyframes}, {"metric": "voxels", "value": st.voxels}]
        for key in ("ate_se3", "ate_none"):
            if key in result.metrics:
                ate_cm = 100 * result.metrics[key]["rmse_m"]
                rows.append({"metric": f"ATE rmse [cm] ({key[4:]} align)", "value": ate_cm})
        rows += [consistency_row(name, gaps) for name, gaps in result.metrics.get("depth_consistency", {}).items()]
        rows += mesh_metric_rows(result.metrics)
        rows.append({"metric": "the whole command until this table [s] (imports, mesh, evaluation, outputs too)",
                     "value": time.perf_counter() - t_command})
        typer.echo(format_table(rows))
        typer.echo(f"outputs in {out}")
        note = precompile_note()
        if note:
            typer.echo(note)


TIMING_LABELS = {
    "wall_s": "frames loop [s] (reading frames and the engine's work on them)",
    "load_s": "reading frames [s]",
    "fps": "frames/s (offline: the loop less reading frames; realtime: the loop's wall clock)",
    "tracking_ms_per_frame": "tracking [ms per frame]",
    "tracking_ms_per_iter": "tracking [ms per iteration]",
    "mapping_ms_per_iter": "mapping [ms per iteration]",
    "tracking_iters": "tracking iterations",
    "mapping_iters": "mapping iterations",
}
"""The printed table's names for :func:`~voxfusion.core.run.timing_summary`'s keys (``metrics.json`` keeps the keys)."""


def process_age_s() -> float | None:
    """Seconds since this process started, to 10 ms (Linux: ``/proc``; None elsewhere, where the table's last timing
    counts from the command's start instead of the process's)."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()  # from the state field (3rd) on
        start_ticks = int(fields[19])  # field 22: start time in clock ticks after boot
        return float(Path("/proc/uptime").read_text().split()[0]) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def precompile_note() -> str | None:
    """One line when this run started compiling the CPU tracker in the background (``tracking.precompiled``), so
    that the compile jobs left running are no surprise; None otherwise."""
    from voxfusion.core.slam.tracking_sdf import PRECOMPILED_LINEARIZE

    pending = PRECOMPILED_LINEARIZE.pending()
    if not pending:
        return None
    return (f"compiling the CPU tracker for later runs in the background ({len(pending)} job(s) at the lowest "
            f"priority, ~20 s of a core each, once per machine; VOXFUSION_PRECOMPILE=0 turns this off)")


def consistency_row(name: str, gaps: dict[str, float | None]) -> dict[str, str]:
    """The summary table's row of one trajectory's depth disagreement (``{"gap_15_cm": 0.94, ...}``, NaN or None
    where no pair of frames that far apart overlapped: "n/a", said why)."""
    cm = [v if v is not None and math.isfinite(v) else None for v in gaps.values()]
    value = " / ".join("n/a" if v is None else f"{v:.2f}" for v in cm) + "  at frame gaps " + " / ".join(
        k.split("_")[1] for k in gaps)
    if None in cm:
        value += "  (n/a: no frame pair that far apart sees the same surfaces)"
    return {"metric": f"depth disagreement [cm] ({name} poses)", "value": value}
