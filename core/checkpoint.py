"""Versioned map checkpoints, written atomically (temporary file, then rename).

A checkpoint holds the voxel map (codes, vertex ids, embeddings), the decoder, the keyframes' indices,
timestamps and poses, the trajectory and the full config; loading it reproduces the same mesh exactly.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .config import config_from_dict, config_to_dict
from .errors import CaptureError, ValidationError
from .map import VoxelMap
from .slam.mapping import Mapper, make_mapper
from .slam.presets import VoxFusionConfig
from .trajectory import Trajectory

if TYPE_CHECKING:
    from .slam.system import MapSnapshot

__all__ = [
    "CHECKPOINT_VERSION", "LoadedCheckpoint", "save_checkpoint", "load_checkpoint", "atomic_write_bytes",
]

CHECKPOINT_VERSION = 1


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a reader sees the old file or the new one, never a torn one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass
class LoadedCheckpoint:
    """A checkpoint read back: the config, a mapper holding the map, and the trajectory (if saved)."""

    config: VoxFusionConfig
    mapper: Mapper
    trajectory: Trajectory | None
    keyframe_indices: list[int]
    keyframe_poses: np.ndarray
    """``[K, 4, 4]`` camera-to-world poses of the keyframes."""


def save_checkpoint(path: str | Path, mapper: Mapper | MapSnapshot, config: VoxFusionConfig,
                    trajectory: Trajectory | None = None) -> Path:
    """Save a map (a :class:`Mapper` at rest, or a :class:`~.slam.MapSnapshot`, which any thread may save) with
    its decoder and keyframe poses, ``config`` (and ``trajectory``) to ``path``."""
    import io

    state = {
        "format": "voxfusion-checkpoint",
        "version": CHECKPOINT_VERSION,
        "config": config_to_dict(config),
        "voxels": mapper.voxels.state_dict(),
        "decoder": {k: v.detach().cpu().clone() for k, v in mapper.decoder.state_dict().items()},
        "keyframes": {
            "index": [kf.data.index for kf in mapper.keyframes],
            "timestamp_s": [kf.data.timestamp_s for kf in mapper.keyframes],
            # the poses other threads may read (published with each map); the live ones before any publish
            "T_world_cam": np.stack([kf.published if kf.published is not None else kf.T_world_cam.cpu().numpy()
                                     for kf in mapper.keyframes])
            if mapper.keyframes else np.zeros((0, 4, 4)),
        },
        "trajectory": None if trajectory is None else {
            "timestamps_s": trajectory.timestamps_s, "T_world_cam": trajectory.T_world_cam},
        "map_version": mapper.version,
    }
    buf = io.BytesIO()
    torch.save(state, buf)
    return atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> LoadedCheckpoint:
    """Load a checkpoint written by :func:`save_checkpoint` onto ``device``."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(path, "checkpoint not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a corrupt file
        raise CaptureError(path, f"not a readable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(state, dict) or state.get("format") != "voxfusion-checkpoint":
        raise CaptureError(path, "not a voxfusion checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise ValidationError(
            "checkpoint.version",
            f"{path} has version {state.get('version')!r}; this build reads {CHECKPOINT_VERSION}")
    config = config_from_dict(VoxFusionConfig, state["config"])
    # a depth-only capture's decoder has no colour head (make_mapper drops it); rebuild the same shape
    has_color = any(k.startswith("color_net.") for k in state["decoder"])
    mapper = make_mapper(config, has_color=has_color, device=device)
    mapper.voxels = VoxelMap.from_state_dict(state["voxels"], device=device, seed=config.seed)
    mapper.decoder.load_state_dict(state["decoder"])
    mapper.rebuild_optimizer()
    mapper.version = int(state.get("map_version", 0))
    kf = state["keyframes"]
    traj = state.get("trajectory")
    trajectory = None if traj is None else Trajectory(traj["timestamps_s"], traj["T_world_cam"])
    return LoadedCheckpoint(config=config, mapper=mapper, trajectory=trajectory,
                            keyframe_indices=list(kf["index"]), keyframe_poses=np.asarray(kf["T_world_cam"]))
