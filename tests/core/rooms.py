"""The small synthetic room the tracker tests map once per module (imported as ``rooms``: pytest puts this folder
on the path)."""

from __future__ import annotations

from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig
from voxfusion.core.framedata import frame_to_device
from voxfusion.core.reconstruct import make_mapper
from voxfusion.core.slam.presets import VoxFusionConfig, load_preset


def mapped_room(preset: str, overrides: dict, mapped: int = 6):
    """A 96x72, 8-frame synthetic room (seed 5) with its first ``mapped`` frames integrated at their true poses
    on CPU. Returns ``(capture, config, mapper)``."""
    cap = SyntheticCapture(SyntheticConfig(n_frames=8, width=96, height=72, seed=5))
    cfg: VoxFusionConfig = load_preset(preset, overrides)
    mapper = make_mapper(cfg)
    for f in cap.frames(0, mapped):
        mapper.integrate(frame_to_device(f, "cpu"), f.T_world_cam)
    return cap, cfg, mapper
