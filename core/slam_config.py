"""The engine's top-level configuration: one frozen tree of every component's own config.

Presets live in ``configs/<name>.yaml`` (see :func:`load_preset`); any key can be overridden with
``--set dotted.key=value`` on the command line.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from .config import load_config
from .errors import ConfigError
from .field import FieldConfig
from .losses import LossConfig
from .mapping import MappingConfig
from .render import RenderConfig
from .tracking import TrackingConfig

__all__ = ["VoxFusionConfig", "CONFIG_DIR", "preset_path", "load_preset", "resolve_device"]

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
"""Folder of the named presets (``configs/`` of the repository / the installed ``voxfusion.configs``)."""


@dataclass(frozen=True)
class VoxFusionConfig:
    """Everything a run needs. Example: ``load_preset("cpu-small", ["mapping.iters=5"])``."""

    voxel_size_m: float = 0.2
    """Voxel edge in metres (paper: 0.2)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """``auto`` picks CUDA when available."""
    seed: int = 0
    """Seeds ray sampling, keyframe windows and embedding initialisation (reproducible on CPU)."""
    mesh_res: int = 8
    """Marching-cubes samples per voxel edge for mesh extraction."""
    mode: Literal["offline", "realtime"] = "offline"
    """``offline``: every frame tracked, mapping interleaved deterministically (reproducible on CPU).
    ``realtime``: tracking and mapping run concurrently; the tracker takes the newest frame and drops
    what it cannot keep up with (counted)."""
    first_pose: Literal["reference", "device", "identity"] = "reference"
    """Pose of the first frame: its reference pose (so trajectories live in the ground-truth frame), else
    its device pose, else identity; ``device`` skips the reference, ``identity`` always starts at I."""
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    mapping: MappingConfig = dataclasses.field(default_factory=MappingConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)

    def __post_init__(self) -> None:
        if not self.voxel_size_m > 0:
            raise ConfigError("voxel_size_m", f"must be > 0, got {self.voxel_size_m}")
        if self.mesh_res < 1:
            raise ConfigError("mesh_res", f"must be >= 1, got {self.mesh_res}")


def resolve_device(device: str) -> torch.device:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; ``cuda`` without a GPU raises."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device", "CUDA was requested but no CUDA device is available (use cpu or auto)")
    return torch.device(device)


def preset_path(name_or_path: str | Path) -> Path:
    """A preset name (``tum``) or a path to a YAML file -> the file's path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    cand = CONFIG_DIR / f"{name_or_path}.yaml"
    if not cand.is_file():
        known = sorted(q.stem for q in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError("config", f"no preset named {str(name_or_path)!r}; known presets: {known}")
    return cand


def load_preset(name_or_path: str | Path | None = None,
                overrides: list[str] | None = None) -> VoxFusionConfig:
    """Load a named preset or YAML file (None: the built-in defaults) and apply ``key=value`` overrides."""
    path = preset_path(name_or_path) if name_or_path is not None else None
    return load_config(VoxFusionConfig, path, overrides)
