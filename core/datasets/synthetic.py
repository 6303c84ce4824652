"""Synthetic RGB-D captures with exact ground truth: a furnished room seen by a hand-held camera.

:class:`SyntheticCapture` renders frame ``i`` on demand (ray casting, no per-pixel Python loops) from
the room of :func:`.synthetic_scene.make_room_scene` and the trajectory of :func:`make_trajectory`.
Everything is a pure function of :class:`SyntheticConfig` (seed included): frame ``i`` is the same
whatever order frames are asked for, and LiDAR noise for frame ``i`` is drawn from ``(seed, i)``.

Outputs per frame (an :class:`RGBDFrame`): colour uint8 RGB (Lambertian-shaded procedural textures);
depth float32 metres, **z-depth** along the optical axis (not ray length), 0 = invalid, exact to ~1e-6 m
without noise; ``T_world_cam`` the exact camera-to-world pose (OpenCV axes; world z is up); timestamps
``i / fps`` rounded to the microsecond (so they survive the 6-decimal TUM file names exactly).

Camera: pinhole, no distortion, one ray through each pixel centre (integer pixel coordinates). Default
intrinsics ``fx = fy = 0.6 * width``, ``cx = (width - 1) / 2``, ``cy = (height - 1) / 2``: a horizontal
field of view of 2 * atan(1 / 1.2) = 79.6 deg (320 x 240: fx = 192, HFOV 79.6 deg, VFOV 64 deg).

LiDAR mode (``lidar=True``, an iPhone/iPad-like depth sensor, see :class:`LidarNoise`): images are
256 x 192 (colour is rendered at the depth resolution, as every reader delivers it); depth gets Gaussian
noise with ``sigma(z) = sigma_a_m + sigma_b_per_m * z**2`` (1 mm + 2 mm/m^2: 3 mm at 1 m, 19 mm at 3 m);
pixels at depth discontinuities (a 4-neighbour more than ``edge_jump_rel`` of the depth away, or an
invalid neighbour) are dropped (depth 0, confidence 0); a confidence map uint8 is produced: 2 (high) on
surfaces closer than ``high_confidence_max_m`` seen at less than ~73 deg incidence away from edges,
1 (medium) next to dropped edges, at grazing incidence or farther away, 0 (low) where dropped, invalid or
beyond ``max_range_m`` (depth kept there, as ARKit does).

Range: depth beyond ``max_depth_m`` (default and maximum 10 m, what both on-disk encodings can hold:
Replica's 65535 / 6553.5 = 10 m) is set to 0. The room's far corners are ~5 m away, so nothing is clipped
at the default.

Writers: :func:`write_tum_layout`, :func:`write_replica_layout` and the front door :func:`write_capture`
write a capture in the layouts :class:`.tum.TUMCapture` and :class:`.replica.ReplicaCapture` read (see
each function); ``voxfusion synth`` is their command line.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import trimesh
from scipy.ndimage import binary_dilation

from ..errors import CaptureError, ConfigError, ValidationError
from ..geometry import make_intrinsics
from ..trajectory import Trajectory, write_tum_trajectory
from .frame import BaseCapture, RGBDFrame
from .profile import CaptureProfile
from .synthetic_scene import (
    CAMERA_ZONE_MAX_M,
    CAMERA_ZONE_MIN_M,
    RenderedView,
    RoomScene,
    SceneRenderer,
    make_room_scene,
)

__all__ = [
    "LIDAR_SIZE",
    "TUM_DEPTH_SCALE",
    "REPLICA_DEPTH_SCALE",
    "LidarNoise",
    "SyntheticConfig",
    "SyntheticCapture",
    "make_trajectory",
    "apply_lidar_noise",
    "write_tum_layout",
    "write_replica_layout",
    "write_capture",
]

LIDAR_SIZE = (256, 192)
"""``(width, height)`` of LiDAR-mode images (the ARKit scene-depth resolution)."""
TUM_DEPTH_SCALE = 5000.0
"""TUM depth PNGs: metres = value / 5000."""
REPLICA_DEPTH_SCALE = 6553.5
"""Replica depth PNGs: metres = value / 6553.5."""
_MAX_DEPTH_LIMIT_M = 65535 / REPLICA_DEPTH_SCALE


@dataclass(frozen=True)
class LidarNoise:
    """Noise and confidence model of LiDAR mode (see the module docstring)."""

    sigma_a_m: float = 0.001
    """Depth noise standard deviation at zero range (metres)."""
    sigma_b_per_m: float = 0.002
    """Growth of the noise std with squared range: ``sigma = sigma_a_m + sigma_b_per_m * z**2``."""
    edge_jump_rel: float = 0.05
    """A pixel whose depth differs from a 4-neighbour's by more than this fraction of its own depth (or
    that has an invalid neighbour) is a discontinuity pixel: dropped (depth 0, confidence 0)."""
    high_confidence_max_m: float = 3.0
    """Confidence 2 only closer than this (metres)."""
    max_range_m: float = 5.0
    """Confidence 0 beyond this range (metres); the depth value is kept."""
    grazing_cos: float = 0.3
    """Confidence at most 1 where ``|cos(incidence)|`` is below this (~73 deg from the normal)."""

    def __post_init__(self) -> None:
        for name in ("sigma_a_m", "sigma_b_per_m"):
            if not getattr(self, name) >= 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        for name in ("edge_jump_rel", "high_confidence_max_m", "max_range_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be > 0, got {getattr(self, name)}")
        if not 0 <= self.grazing_cos <= 1:
            raise ConfigError("grazing_cos", f"must be in [0, 1], got {self.grazing_cos}")


@dataclass(frozen=True)
class SyntheticConfig:
    """Options of :class:`SyntheticCapture`.

    Example::

        SyntheticConfig()                                  # 100 frames, 320x240, seed 0
        SyntheticConfig(n_frames=20, width=64, height=48)  # tiny, for tests
        SyntheticConfig(lidar=True)                        # 256x192 noisy depth + confidence
    """

    n_frames: int = 100
    """Number of frames."""
    seed: int = 0
    """Seeds the room (furniture, textures), the trajectory and the LiDAR noise."""
    width: int | None = None
    """Image width in pixels; ``None``: 320, or 256 with ``lidar``."""
    height: int | None = None
    """Image height in pixels; ``None``: 240, or 192 with ``lidar``."""
    fx: float | None = None
    """Focal length in pixels; ``None``: ``0.6 * width`` (79.6 deg horizontal field of view)."""
    fy: float | None = None
    """``None``: same as ``fx``."""
    cx: float | None = None
    """Principal point x in pixels (pixel centres at integers); ``None``: ``(width - 1) / 2``."""
    cy: float | None = None
    """``None``: ``(height - 1) / 2``."""
    motion_scale: float = 1.0
    """Multiplies the per-frame motion (translation and rotation) by running along the same path faster;
    at 1.0 the camera moves ~1-2 cm and ~0.5-1 deg per frame."""
    yaw_rate_deg_s: float = 0.0
    """Fast-rotation mode: peak yaw rate (deg/s) of an extra swing of the camera about the world's vertical
    axis through its own centre, ``yaw(t) = A sin(rate / A * t)`` with amplitude ``A = yaw_swing_deg``
    (0: off). 180 deg/s at 30 Hz is 6 deg between frames at the fastest point."""
    yaw_swing_deg: float = 60.0
    """Amplitude of that swing (degrees); the period is ``2 pi A / rate`` (60 deg at 180 deg/s: 2.1 s)."""
    fps: float = 30.0
    """Frame rate: frame ``i`` has timestamp ``i / fps`` seconds (rounded to 1 us)."""
    max_depth_m: float = 10.0
    """Depth beyond this is invalid (0); at most 10 m (the Replica encoding's range)."""
    lidar: bool = False
    """LiDAR-like depth: 256x192 by default, noisy, edge dropouts, confidence map."""
    lidar_noise: LidarNoise = field(default_factory=LidarNoise)
    """Noise model used when ``lidar`` is set."""

    def __post_init__(self) -> None:
        if int(self.n_frames) != self.n_frames or self.n_frames < 1:
            raise ConfigError("n_frames", f"must be a positive integer, got {self.n_frames}")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ConfigError("seed", f"must be a non-negative integer, got {self.seed}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 2):
                raise ConfigError(name, f"must be an integer >= 2, got {v}")
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ConfigError(name, f"must be > 0 pixels, got {v}")
        if not self.motion_scale > 0:
            raise ConfigError("motion_scale", f"must be > 0, got {self.motion_scale}")
        if not (self.yaw_rate_deg_s >= 0 and self.yaw_swing_deg > 0):
            raise ConfigError("yaw_rate_deg_s", "yaw_rate_deg_s must be >= 0 and yaw_swing_deg > 0, got "
                              f"{self.yaw_rate_deg_s} and {self.yaw_swing_deg}")
        if not self.fps > 0:
            raise ConfigError("fps", f"must be > 0, got {self.fps}")
        if not 0 < self.max_depth_m <= _MAX_DEPTH_LIMIT_M:
            raise ConfigError("max_depth_m",
                              f"must be in (0, {_MAX_DEPTH_LIMIT_M:g}] m, got {self.max_depth_m}")
        if not isinstance(self.lidar_noise, LidarNoise):
            raise ConfigError("lidar_noise", f"must be a LidarNoise, got {type(self.lidar_noise).__name__}")
        w, h = self.image_size
        cx = self.cx if self.cx is not None else (w - 1) / 2
        cy = self.cy if self.cy is not None else (h - 1) / 2
        if not (0 <= cx <= w and 0 <= cy <= h):
            raise ConfigError("cx/cy", f"principal point ({cx}, {cy}) lies outside the {w}x{h} image")

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels, defaults resolved."""
        dw, dh = LIDAR_SIZE if self.lidar else (320, 240)
        return (int(self.width) if self.width is not None else dw,
                int(self.height) if self.height is not None else dh)

    @property
    def K(self) -> np.ndarray:
        """``[3, 3]`` float64 intrinsics for :attr:`image_size`, defaults resolved."""
        w, h = self.image_size
        fx = self.fx if self.fx is not None else 0.6 * w
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else (w - 1) / 2
        cy = self.cy if self.cy is not None else (h - 1) / 2
        return make_intrinsics(fx, fy, cx, cy)

    @property
    def timestamps_s(self) -> np.ndarray:
        """``[n_frames]`` float64 timestamps ``i / fps`` rounded to the microsecond."""
        return np.round(np.arange(self.n_frames) / self.fps, 6)


# -------------------------------------------------------------------------------------------- trajectory


def make_trajectory(config: SyntheticConfig) -> np.ndarray:
    """The hand-held camera path: ``[n_frames, 4, 4]`` float64 camera-to-world poses, OpenCV axes.

    The camera looks across the room: a look-at target moves around a ring near the walls (where the
    furniture stands, 0.5-1.0 m high) with bearing ``theta`` drifting ~0.5 deg per frame plus a slow swing,
    while the camera centre sits on the opposite side of the room centre (so the table is usually in
    view), plus low-frequency sinusoids per axis (periods 60-100 frames) and a 2 mm tremor. The centre
    always stays inside ``CAMERA_ZONE_MIN_M .. CAMERA_ZONE_MAX_M`` (1.4-1.7 m high, >= 0.3 m from any
    surface); the view pitches 10-37 deg down (median ~22); a slow roll of up to 3 deg is added. Phases, drift
    direction and start bearing come from ``config.seed``; the path parameter is ``motion_scale * i``,
    so ``motion_scale`` scales per-frame motion without leaving the zone.
    """
    rng = np.random.default_rng([config.seed, 0x7A7])
    s = config.motion_scale * np.arange(config.n_frames, dtype=np.float64)

    def wave(period: float) -> np.ndarray:
        return np.sin(2.0 * np.pi * s / period + rng.uniform(0.0, 2.0 * np.pi))

    drift = np.deg2rad(0.5) * (1.0 if rng.uniform() < 0.5 else -1.0)
    theta = rng.uniform(0.0, 2.0 * np.pi) + drift * s + 0.3 * wave(220.0)
    ring = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    target = np.empty((len(s), 3))
    target[:, :2] = ring * [1.8, 1.35]
    target[:, 2] = 0.75 + 0.25 * wave(170.0)

    centre = (CAMERA_ZONE_MIN_M + CAMERA_ZONE_MAX_M) / 2
    pos = np.empty((len(s), 3))
    pos[:, :2] = centre[:2] - ring * [0.45, 0.35]
    pos[:, 0] += 0.12 * wave(97.0) + 0.002 * wave(11.0)
    pos[:, 1] += 0.12 * wave(83.0) + 0.002 * wave(13.0)
    pos[:, 2] = centre[2] + 0.1 * wave(150.0) + 0.04 * wave(61.0) + 0.002 * wave(9.0)
    roll = 0.05 * wave(130.0) + 0.003 * wave(19.0)

    z_cam = target - pos
    z_cam /= np.linalg.norm(z_cam, axis=1, keepdims=True)
    x_cam = np.cross(z_cam, np.array([0.0, 0.0, 1.0]))
    x_cam /= np.linalg.norm(x_cam, axis=1, keepdims=True)
    y_cam = np.cross(z_cam, x_cam)  # points down in the image
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x_r, y_r = cr * x_cam + sr * y_cam, -sr * x_cam + cr * y_cam  # roll about the optical axis
    T = np.zeros((len(s), 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x_r, y_r, z_cam, pos
    if config.yaw_rate_deg_s > 0:  # fast rotation: swing about the world vertical through the camera centre
        amp = np.deg2rad(config.yaw_swing_deg)
        yaw = amp * np.sin(np.deg2rad(config.yaw_rate_deg_s) / amp * np.arange(len(s)) / config.fps)
        c, si = np.cos(yaw), np.sin(yaw)
        Rz = np.zeros((len(s), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -si, si, c, 1.0
        T[:, :3, :3] = Rz @ T[:, :3, :3]
    T[:, 3, 3] = 1.0
    return T


# ----------------------------------------------------------------------------------------------- LiDAR


def apply_lidar_noise(depth_m: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                      noise: LidarNoise) -> tuple[np.ndarray, np.ndarray]:
    """Turn exact depth into LiDAR-like depth plus confidence (model in the module docstring).

    Args:
        depth_m: ``[H, W]`` float32 exact z-depth in metres, 0 = invalid.
        cos_incidence: ``[H, W]`` ``|cos|`` of the angle between viewing ray and surface normal.
        rng: noise source (seed it per frame for reproducibility).
        noise: the model's parameters.

    Returns:
        ``(depth_m, confidence)``: ``[H, W]`` float32 noisy depth (0 = dropped/invalid) and ``[H, W]``
        uint8 confidence in {0, 1, 2}.
    """
    z = np.asarray(depth_m, dtype=np.float32)
    if np.asarray(cos_incidence).shape != z.shape:
        raise ValidationError("cos_incidence",
                              f"shape {np.shape(cos_incidence)} differs from depth {z.shape}")
    valid = z > 0
    pad = np.pad(z, 1, mode="edge")
    h, w = z.shape
    jump = np.zeros_like(z)
    nb_invalid = np.zeros(z.shape, dtype=bool)
    for dv, du in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dv:dv + h, du:du + w]
        jump = np.maximum(jump, np.abs(nb - z))
        nb_invalid |= nb <= 0
    edge = valid & ((jump > noise.edge_jump_rel * z) | nb_invalid)
    near_edge = binary_dilation(edge, structure=np.ones((3, 3), dtype=bool)) & ~edge

    sigma = noise.sigma_a_m + noise.sigma_b_per_m * z.astype(np.float64) ** 2
    noisy = z + (rng.standard_normal(z.shape) * sigma).astype(np.float32)
    keep = valid & ~edge & (noisy > 0)
    out = np.where(keep, noisy, 0.0).astype(np.float32)

    conf = np.zeros(z.shape, dtype=np.uint8)
    conf[keep] = 1
    high = keep & ~near_edge & (z <= noise.high_confidence_max_m) & (cos_incidence >= noise.grazing_cos)
    conf[high] = 2
    conf[keep & (z > noise.max_range_m)] = 0
    return out, conf


# --------------------------------------------------------------------------------------------- capture


class SyntheticCapture(BaseCapture):
    """A rendered capture of the synthetic room (see the module docstring); frames render lazily.

    Attributes:
        config: the options.
        scene: the :class:`RoomScene` (``scene.mesh`` is the ground-truth mesh).
        trajectory: timestamps and ground-truth ``T_world_cam`` of every frame.
        K: ``[3, 3]`` intrinsics for ``width`` x ``height``.

    Example::

        cap = SyntheticCapture(SyntheticConfig(n_frames=30, seed=1))
        f = cap[7]   # f.depth_m [240, 320] float32 z-depth, f.color [240, 320, 3], f.T_world_cam [4, 4]
        write_capture(cap, "out/synth_tum", "tum")
    """

    def __init__(self, config: SyntheticConfig | None = None) -> None:
        self.config = config if config is not None else SyntheticConfig()
        if not isinstance(self.config, SyntheticConfig):
            raise ValidationError("config", f"must be a SyntheticConfig, got {type(self.config).__name__}")
        c = self.config
        self.name = f"synthetic_seed{c.seed}" + ("_lidar" if c.lidar else "")
        self.path = Path(f"<synthetic seed={c.seed}>")
        self.width, self.height = c.image_size
        self.K = c.K
        self.scene: RoomScene = make_room_scene(c.seed)
        self.trajectory = Trajectory(c.timestamps_s, make_trajectory(c))
        self._renderer = SceneRenderer(self.scene)
        self._profile = CaptureProfile("synthetic", c.max_depth_m, has_confidence=c.lidar,
                                       sensor=f"voxfusion synthetic room {self.width}x{self.height}"
                                       + (" (LiDAR mode)" if c.lidar else ""))

    def __len__(self) -> int:
        return self.config.n_frames

    @property
    def gt_mesh(self) -> trimesh.Trimesh:
        """The exact scene mesh (world frame, metres, vertex colours = albedo)."""
        return self.scene.mesh

    def write_gt_mesh(self, path: str | Path) -> Path:
        """Write the ground-truth mesh (PLY/OBJ/GLB by suffix); afterwards ``gt_mesh_path`` points at it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.scene.mesh.export(path)
        self._gt_mesh_path = path
        return path

    def render_view(self, i: int) -> RenderedView:
        """Exact (noise-free) render of frame ``i``: depth, colour, normals, object ids."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {self.name} ({len(self)} frames)")
        return self._renderer.render(self.trajectory.T_world_cam[i], self.K, self.width, self.height,
                                     max_depth_m=self.config.max_depth_m)

    def _load(self, i: int) -> RGBDFrame:
        view = self.render_view(i)
        depth, conf = view.depth_m, None
        if self.config.lidar:
            rng = np.random.default_rng([self.config.seed, i])
            depth, conf = apply_lidar_noise(depth, view.cos_incidence, rng, self.config.lidar_noise)
        return RGBDFrame(
            depth_m=depth, K=self.K, timestamp_s=float(self.trajectory.timestamps_s[i]), color=view.color,
            confidence=conf, T_world_cam=self.trajectory.T_world_cam[i], index=i,
            meta={"source": "synthetic", "seed": self.config.seed},
        )


# --------------------------------------------------------------------------------------------- writers

Progress = Callable[[int], None]
"""Called with the index of each frame after it is written."""


WRITTEN_NAMES = frozenset({"rgb", "depth", "confidence", "rgb.txt", "depth.txt", "confidence.txt",
                           "groundtruth.txt", "intrinsics.txt", "results", "traj.txt", "cam_params.json",
                           "gt_mesh.ply"})
"""What the writers below put in a capture folder (either layout): all that ``overwrite`` may delete."""


def _prepare_out_dir(out_dir: str | Path, overwrite: bool = False) -> Path:
    """``out_dir``, created if missing; it must be empty, or with ``overwrite`` hold a capture these writers wrote
    (``gt_mesh.ply`` and nothing but :data:`WRITTEN_NAMES`), which is then deleted."""
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not out.is_dir():
            raise ValidationError("out_dir", f"{out} exists and is not a folder; choose a new one")
        if not overwrite:
            raise ValidationError("out_dir", f"{out} exists and is not an empty folder; choose a new one, or "
                                  "replace the synthetic capture written there with --force")
        entries = sorted(p.name for p in out.iterdir())
        foreign = [name for name in entries if name not in WRITTEN_NAMES]
        if foreign or "gt_mesh.ply" not in entries:
            what = f"{foreign[0]!r}, which" if foreign else "no gt_mesh.ply, so it"
            raise ValidationError("out_dir", f"{out} holds {what} is not a synthetic capture's; --force only "
                                  "replaces a capture written by voxfusion synth: choose a new folder")
        for name in entries:
            path = out / name
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
    out.mkdir(parents=True, exist_ok=True)
    return out


def _imwrite(path: Path, img: np.ndarray, params: tuple[int, ...] = ()) -> None:
    if not cv2.imwrite(str(path), img, list(params)):
        raise CaptureError(path, "could not write image")


def _depth_u16(depth_m: np.ndarray, scale: float) -> np.ndarray:
    return np.clip(np.round(depth_m.astype(np.float64) * scale), 0, 65535).astype(np.uint16)


def write_tum_layout(capture: SyntheticCapture, out_dir: str | Path,
                     progress: Progress | None = None, overwrite: bool = False) -> Path:
    """Write ``capture`` as a TUM RGB-D sequence folder; returns ``out_dir``.

    Layout (read by :class:`voxfusion.core.datasets.tum.TUMCapture`)::

        rgb/<ts>.png  depth/<ts>.png     colour (8-bit RGB PNG) and depth (uint16, metres = value / 5000),
                                         ``<ts>`` = timestamp with 6 decimals
        rgb.txt  depth.txt               "timestamp rgb/<ts>.png" lists
        groundtruth.txt                  TUM trajectory (camera-to-world, OpenCV axes)
        intrinsics.txt                   one line "fx fy cx cy" (the TUM reader honours it)
        gt_mesh.ply                      the ground-truth mesh
        confidence/<ts>.png, confidence.txt   LiDAR mode only: uint8 PNG with values 0/1/2

    ``out_dir`` must not exist or be empty (``overwrite``: or hold a capture written here, replaced).
    """
    out = _prepare_out_dir(out_dir, overwrite)
    lidar = capture.config.lidar
    subdirs = ("rgb", "depth", "confidence") if lidar else ("rgb", "depth")
    for sub in subdirs:
        (out / sub).mkdir()
    lists: dict[str, list[str]] = {sub: [] for sub in subdirs}
    for frame in capture.frames():
        ts = f"{frame.timestamp_s:.6f}"
        _imwrite(out / "rgb" / f"{ts}.png", cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR))
        _imwrite(out / "depth" / f"{ts}.png", _depth_u16(frame.depth_m, TUM_DEPTH_SCALE))
        if lidar:
            _imwrite(out / "confidence" / f"{ts}.png", frame.confidence)
        for sub in subdirs:
            lists[sub].append(f"{ts} {sub}/{ts}.png")
        if progress is not None:
            progress(frame.index)
    for sub, lines in lists.items():
        header = f"# {sub} images of voxfusion synthetic capture {capture.name}\n# timestamp filename\n"
        (out / f"{sub}.txt").write_text(header + "\n".join(lines) + "\n")
    write_tum_trajectory(out / "groundtruth.txt", capture.trajectory)
    K = capture.K
    fx_fy_cx_cy = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    (out / "intrinsics.txt").write_text(" ".join(repr(float(v)) for v in fx_fy_cx_cy) + "\n")
    capture.write_gt_mesh(out / "gt_mesh.ply")
    return out


def write_replica_layout(capture: SyntheticCapture, out_dir: str | Path,
                         progress: Progress | None = None, overwrite: bool = False) -> Path:
    """Write ``capture`` in the Replica (NICE-SLAM) layout; returns ``out_dir``.

    Layout::

        results/frame%06d.jpg            colour, JPEG quality 95 without chroma subsampling (4:4:4)
        results/depth%06d.png            uint16, metres = value / 6553.5
        traj.txt                         one line per frame: the 4x4 camera-to-world pose (OpenCV axes),
                                         16 numbers row-major
        cam_params.json                  {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale": 6553.5}}
        gt_mesh.ply                      the ground-truth mesh

    LiDAR confidence is not written (the layout has no place for it). ``out_dir`` must not exist or be
    empty (``overwrite``: or hold a capture written here, replaced).
    """
    out = _prepare_out_dir(out_dir, overwrite)
    (out / "results").mkdir()
    for frame in capture.frames():
        i = frame.index
        _imwrite(out / "results" / f"frame{i:06d}.jpg", cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR),
                 (cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                  cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444))
        _imwrite(out / "results" / f"depth{i:06d}.png", _depth_u16(frame.depth_m, REPLICA_DEPTH_SCALE))
        if progress is not None:
            progress(i)
    rows = capture.trajectory.T_world_cam.reshape(-1, 16)
    (out / "traj.txt").write_text("\n".join(" ".join(f"{v:.12g}" for v in r) for r in rows) + "\n")
    K = capture.K
    cam = {"w": capture.width, "h": capture.height, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
           "cx": float(K[0, 2]), "cy": float(K[1, 2]), "scale": REPLICA_DEPTH_SCALE}
    (out / "cam_params.json").write_text(json.dumps({"camera": cam}, indent=2) + "\n")
    capture.write_gt_mesh(out / "gt_mesh.ply")
    return out


def write_capture(capture: SyntheticCapture, out_dir: str | Path, layout: Literal["tum", "replica"] = "tum",
                  progress: Progress | None = None, overwrite: bool = False) -> Path:
    """Write ``capture`` to ``out_dir`` in ``layout`` (``"tum"`` or ``"replica"``); returns ``out_dir``.
    ``overwrite``: an ``out_dir`` holding a capture written by these writers (either layout) is replaced."""
    if layout == "tum":
        return write_tum_layout(capture, out_dir, progress, overwrite)
    if layout == "replica":
        return write_replica_layout(capture, out_dir, progress, overwrite)
    raise ValidationError("layout", f"must be 'tum' or 'replica', got {layout!r}")
