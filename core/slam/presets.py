"""The engine's top-level configuration: one frozen tree of every component's own config, its presets, and
the one function that picks a preset for a capture and a device (:func:`preset_for`).

Presets live in ``configs/<name>.yaml``; any key can be overridden with ``--set dotted.key=value`` on the
command line. There are two sorts, one concept per name:

* **kind presets** say what a family of captures needs (``tum``, ``sevenscenes``, ``replica``, ``scannet``,
  ``iphone``, ``synthetic``; ``default`` = the built-ins). They leave sizes (rays, iterations, network widths)
  at the built-in GPU sizes.
* **size presets** declare ``sized_for`` and set only sizes: ``cpu`` (every CPU number, in one file) and
  ``paper`` (the paper's GPU sizes). A size preset may add ``per_kind:`` sections, applied on top of it when it
  is composed with that kind (the iPhone's own CPU numbers, say).

Names compose with ``+``: ``tum+cpu`` is the TUM preset at CPU sizes. Kind presets are merged left to right,
then the size preset (at most one, wherever it is named) and its section for each named kind, so sizes always
win over kinds. Below all of them lie the capture's facts (:func:`profile_overrides`, when a capture is at hand)
and above them the ``--set`` overrides:

    built-ins < capture profile < kind presets < size preset < its per_kind sections < --set

A config whose ``sized_for`` is ``gpu`` (every kind preset alone, ``paper``) run on a CPU gets one warning with
the speed to expect (:func:`size_warning`). ``cpu-small`` and ``iphone-small`` are the old names of ``cpu``
and ``iphone+cpu`` (:data:`PRESET_ALIASES`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from ..config import apply_overrides, config_from_dict, merge_dicts, read_config_file
from ..datasets.frame import Capture
from ..datasets.profile import CAPTURE_KINDS, CaptureProfile
from ..errors import ConfigError
from ..losses import LossConfig
from ..map.field import FieldConfig
from ..render.volume import RenderConfig
from .mapping import MappingConfig
from .tracking import TrackingConfig

__all__ = [
    "VoxFusionConfig",
    "CONFIG_DIR",
    "CPU_PRESET",
    "KIND_PRESETS",
    "PRESET_ALIASES",
    "UNREGISTERED_COLOR_WEIGHT",
    "GPU_SIZES_ON_CPU_FPS",
    "PAPER_SIZES_ON_CPU_FPS",
    "CPU_SIZES_ON_CPU_FPS",
    "PREVIEW_LATTICE_M",
    "PresetChoice",
    "preset_path",
    "preset_names",
    "check_preset_name",
    "load_preset",
    "profile_overrides",
    "preset_for",
    "size_warning",
    "resolve_device",
]

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
"""Folder of the named presets (``configs/`` of the repository / the installed ``voxfusion.configs``)."""

CPU_PRESET = "cpu"
"""The size preset :func:`preset_for` composes with the kind preset when there is no CUDA device."""

KIND_PRESETS: dict[str, str] = {kind: ("default" if kind == "unknown" else kind) for kind in CAPTURE_KINDS}
"""Capture kind (:attr:`CaptureProfile.kind`) -> its preset name."""

PRESET_ALIASES: dict[str, str] = {"cpu-small": "cpu", "iphone-small": "iphone+cpu"}
"""Old preset names -> what they are now (kept so scripts, stored sessions and benchmark commands still run)."""

PREVIEW_LATTICE_M = 0.025
"""Lattice spacing of preview meshes, metres (:meth:`VoxFusionConfig.preview_mesh_res`)."""

UNREGISTERED_COLOR_WEIGHT = 0.1
"""``loss.w_color`` for captures whose colour is not registered to depth (7-Scenes: 0.5 blurs geometry)."""

# Speeds that size_warning quotes, measured on the project's 2-core CPU (AMD EPYC, 2026-11-28, `voxfusion run
# CAPTURE --config PRESET --out DIR`, frames/s of processing as metrics.json's timings give it). Re-measure when the
# sizes in configs/ or the engine's speed change.
GPU_SIZES_ON_CPU_FPS = (0.8, 1.1)
"""GPU sizes of the kind presets and the built-ins on the 2-core CPU: ``--config tum`` on TUM fr1 desk (9 frames)
0.88 frames/s (the first frame's 100 mapping iterations at ~51 ms: ~5 s), ``--config sevenscenes`` on 7-Scenes
(20 frames) 1.09, ``--config synthetic`` on the 320x240 synthetic room (20 frames) 0.98."""
PAPER_SIZES_ON_CPU_FPS = (0.05, 0.07)
"""The ``paper`` preset's sizes (4096 mapping rays, decoder width 256) on the same CPU: 0.06 frames/s on the
synthetic room (20 frames; a mapping iteration ~0.8 s, the first frame's 200 of them ~2.5 min)."""
CPU_SIZES_ON_CPU_FPS = (7, 20)
"""CPU sizes (``KIND+cpu``, what ``voxfusion run`` picks without CUDA) on the same CPU: TUM fr1 desk 7-9 frames/s,
7-Scenes 9-10, the synthetic room 11-13, the Stray iPhone capture ~20 (the README's table)."""


@dataclass(frozen=True)
class VoxFusionConfig:
    """Everything a run needs. Example: ``load_preset("tum+cpu", ["mapping.iters=5"])``."""

    voxel_size_m: float = 0.2
    """Voxel edge in metres (paper: 0.2)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """``auto`` picks CUDA when available."""
    seed: int = 0
    """Seeds ray sampling, keyframe windows and embedding initialisation (reproducible on CPU)."""
    mesh_res: int = 20
    """Marching-cubes samples per voxel edge for mesh extraction (20 at 0.2 m voxels: a 1 cm lattice,
    sampled in two levels so only cells near the surface cost fine samples, :mod:`.mesh.extract`)."""
    mesh_colors: Literal["images", "field"] = "images"
    """Vertex colours: ``images``: from the keyframes that see each vertex (sharp, as saturated as the
    input; the colour head where no keyframe sees it), ``field``: the colour head only (smooth and
    desaturated at 0.2 m voxels, see :mod:`.mesh.colors`)."""
    mesh_support: bool = True
    """Mesh only surface that observations support: faces farther than about one to two 1.25 cm cells
    from every observed depth point are dropped (:mod:`.mesh.support`)."""
    mode: Literal["offline", "realtime"] = "offline"
    """``offline``: every frame tracked, mapping interleaved deterministically (reproducible on CPU).
    ``realtime``: tracking and mapping run concurrently; the tracker takes the newest frame and drops
    what it cannot keep up with (counted)."""
    realtime_cpu_threads: int | None = None
    """Realtime mode on a CPU: torch's intra-op threads while the two workers run (process-wide; restored when
    they stop). None: half the usable cores, never more than torch's current setting (a server worker that
    was given fewer keeps them); 0: leave torch's setting. The workers run at once, each with torch's thread
    pool: at torch's default (every core) they oversubscribe the CPU. Measured on the 2-core AMD EPYC, 320x240
    synthetic room seed 1 fed at 30 Hz for 10 s (3 alternating pairs, 2 -> 1 thread): tracked 15.1-18.1 ->
    19.0-20.7 frames/s, mapping rounds 5.4-5.8 -> 5.7-6.0 per second, ATE 1.27-1.64 -> 0.52-0.76 cm."""
    first_pose: Literal["reference", "device", "identity"] = "reference"
    """Pose of the first frame: its reference pose (so trajectories live in the ground-truth frame), else
    its device pose, else identity; ``device`` skips the reference, ``identity`` always starts at I."""
    sized_for: Literal["gpu", "cpu"] = "gpu"
    """The machine the sizes (rays, iterations, network widths) are chosen for: ``cpu`` in ``configs/cpu.yaml``,
    ``gpu`` for the built-ins and every other preset. A ``gpu`` config run on a CPU warns once
    (:func:`size_warning`)."""
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
        if self.realtime_cpu_threads is not None and self.realtime_cpu_threads < 0:
            raise ConfigError("realtime_cpu_threads", f"must be >= 0 or None, got {self.realtime_cpu_threads}")

    def preview_mesh_res(self) -> int:
        """Samples per voxel edge of a preview mesh (the live viewer's): a lattice of about
        :data:`PREVIEW_LATTICE_M`, never finer than ``mesh_res``. At 0.2 m voxels: 8 against 20, about 7x
        cheaper to extract (1.2 s vs 8 s for an 80-frame synthetic room on one CPU core)."""
        return max(2, min(self.mesh_res, round(self.voxel_size_m / PREVIEW_LATTICE_M)))


def resolve_device(device: str) -> torch.device:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; ``cuda`` without a GPU raises."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("device", "CUDA was requested but no CUDA device is available (use cpu or auto)")
    return torch.device(device)


def preset_names() -> list[str]:
    """Names of the shipped presets (the YAML files in :data:`CONFIG_DIR`), sorted; aliases not included."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))


def check_preset_name(name: str) -> None:
    """Raise :class:`ConfigError` (field ``preset``) unless ``name`` is a shipped preset, an alias or a ``+``
    composition of those: never a file path (what a server accepts from a client)."""
    known = preset_names()
    for part in str(name).split("+"):
        part = PRESET_ALIASES.get(part.strip(), part.strip())
        if not all(p in known for p in part.split("+")):
            raise ConfigError("preset", f"unknown preset {name!r}; known presets: {known}, composed with '+' "
                                        "(e.g. iphone+cpu)")


def preset_path(name_or_path: str | Path) -> Path:
    """A preset name (``tum``) or a path to a YAML file -> the file's path.

    A bare name of a shipped preset wins over a file or folder of that name in the working directory.
    """
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        return p
    cand = CONFIG_DIR / f"{name_or_path}.yaml"
    if p.name == str(name_or_path) and cand.is_file():
        return cand
    if p.is_file():
        return p
    raise ConfigError("config", f"no preset named {str(name_or_path)!r}; known presets: {preset_names()} "
                      "(compose a kind and a size with '+', e.g. tum+cpu)")


def _preset_parts(name_or_path: str | Path) -> list[str | Path]:
    """``"iphone-small+x"`` -> ``["iphone", "cpu", "x"]``: aliases expanded, ``+`` split (not in file paths)."""
    if isinstance(name_or_path, Path):
        return [name_or_path]
    p = Path(name_or_path)
    if (p.suffix in (".yaml", ".yml") or "/" in str(name_or_path)) and p.is_file():  # a file path with a '+' in it
        return [name_or_path]
    name = str(name_or_path)
    parts: list[str | Path] = []
    for part in name.split("+"):
        part = part.strip()
        if not part:
            raise ConfigError("config", f"empty name in preset composition {name!r}")
        alias = PRESET_ALIASES.get(part)
        parts += _preset_parts(alias) if alias is not None else [part]
    return parts


def _preset_data(name_or_path: str | Path) -> dict:
    """The merged plain dict of a preset name, composition (``kind+size``) or YAML path (module docstring)."""
    kinds: list[tuple[str, dict]] = []
    sizes: list[tuple[str, dict]] = []
    for part in _preset_parts(name_or_path):
        data = read_config_file(preset_path(part))
        stem = Path(part).stem if isinstance(part, Path) or Path(part).suffix else str(part)
        (sizes if "sized_for" in data else kinds).append((stem, data))
        if "per_kind" in data and "sized_for" not in data:
            raise ConfigError("per_kind", f"preset {stem!r}: only a size preset (one that sets sized_for) may have "
                                          "per_kind sections")
    if len(sizes) > 1:
        raise ConfigError("config", f"at most one size preset per composition, got {[n for n, _ in sizes]}")
    merged: dict = {}
    for _, data in kinds + sizes:
        merged = merge_dicts(merged, {k: v for k, v in data.items() if k != "per_kind"})
    for size_name, data in sizes:
        sections = data.get("per_kind") or {}
        if not isinstance(sections, dict) or not all(isinstance(v, dict) for v in sections.values()):
            raise ConfigError("per_kind", f"preset {size_name!r}: must map kind names to config sections")
        unknown = sorted(set(sections) - set(CAPTURE_KINDS))
        if unknown:
            raise ConfigError(f"per_kind.{unknown[0]}", f"preset {size_name!r}: not a capture kind; kinds: "
                                                        f"{list(CAPTURE_KINDS)}")
        for kind_name, _ in kinds:
            if kind_name in sections:
                merged = merge_dicts(merged, sections[kind_name])
    return merged


def profile_overrides(profile: CaptureProfile) -> dict:
    """The config values a capture's facts call for, as a nested dict (what :func:`load_preset` puts under the
    presets when it is given a profile).

    * ``max_depth_m`` -> ``mapping.max_depth_m`` (depth beyond is dropped);
    * ``has_confidence`` -> ``mapping.min_confidence: 1`` (low-confidence pixels dropped);
    * no colour -> ``loss.w_color: 0``; colour not registered to depth -> ``loss.w_color``
      :data:`UNREGISTERED_COLOR_WEIGHT` and ``tracking.sdf_w_photo: 0`` (a pixel's colour would not be its
      depth point's).

    Example: a 7-Scenes capture -> ``{"mapping": {"max_depth_m": 4.0}, "loss": {"w_color": 0.1},
    "tracking": {"sdf_w_photo": 0.0}}``.
    """
    mapping: dict = {}
    out: dict = {}
    if profile.max_depth_m is not None:
        mapping["max_depth_m"] = float(profile.max_depth_m)
    if profile.has_confidence:
        mapping["min_confidence"] = 1
    if mapping:
        out["mapping"] = mapping
    if not profile.has_color:
        out["loss"] = {"w_color": 0.0}
    elif not profile.color_registered:
        out["loss"] = {"w_color": UNREGISTERED_COLOR_WEIGHT}
        out["tracking"] = {"sdf_w_photo": 0.0}
    return out


def load_preset(name_or_path: str | Path | None = None, overrides: list[str] | None = None,
                profile: CaptureProfile | None = None) -> VoxFusionConfig:
    """Load a preset and apply ``key=value`` overrides.

    Args:
        name_or_path: a preset name (``tum``), a composition (``tum+cpu``), an old name (``cpu-small``), a YAML
            path, or ``None`` for the built-in defaults.
        overrides: ``["tracking.iters=20", ...]``, applied last.
        profile: the capture's facts; their values (:func:`profile_overrides`) lie under the presets.

    Example: ``load_preset("sevenscenes+cpu", ["mapping.iters=5"], profile=capture.profile)``.
    """
    data = profile_overrides(profile) if profile is not None else {}
    if name_or_path is not None:
        data = merge_dicts(data, _preset_data(name_or_path))
    cfg = config_from_dict(VoxFusionConfig, data)
    if overrides:
        cfg = apply_overrides(cfg, list(overrides))
    return cfg


@dataclass(frozen=True)
class PresetChoice:
    """What :func:`preset_for` picked."""

    config: VoxFusionConfig
    preset: str
    """The preset name it loaded, e.g. ``"tum+cpu"``."""
    reason: str
    """One line for people: what was picked and why (kind, facts, device)."""


def preset_for(capture: Capture, device: str = "auto", overrides: list[str] | None = None,
               cpu_why: str | None = None) -> PresetChoice:
    """Pick the preset for ``capture`` on ``device`` and load it with the capture's facts.

    The capture's kind (``capture.profile.kind``) names the kind preset (:data:`KIND_PRESETS`); with no CUDA
    device (``device`` ``auto`` without a GPU, or ``cpu``) it is composed with :data:`CPU_PRESET`. The
    profile's facts lie under the presets, ``overrides`` on top. ``cpu_why``: why the sizes are the CPU's, for
    the reason (default: "CPU requested" or "no CUDA device").

    Raises:
        ConfigError: ``device`` is ``cuda`` and no CUDA device is available, or a bad override.

    Example::

        choice = preset_for(open_capture("../shared/data/tum_fr1_desk_9frames"))
        print(choice.reason)   # preset tum+cpu: ... TUM RGB-D, Kinect v1 640x480 ...; no CUDA device: CPU sizes
    """
    profile = capture.profile
    dev = resolve_device(device)
    kind_preset = KIND_PRESETS[profile.kind]
    if dev.type == "cuda":
        name, size_why = kind_preset, "a CUDA device is present: GPU sizes"
    else:
        name = CPU_PRESET if kind_preset == "default" else f"{kind_preset}+{CPU_PRESET}"
        size_why = (cpu_why or ("CPU requested" if device.startswith("cpu") else "no CUDA device")) + \
            f": CPU sizes ({CPU_PRESET}.yaml)"
    config = load_preset(name, overrides, profile=profile)
    what = profile.sensor or "a capture of unknown kind"
    reason = f"preset {name}: {capture.name} is {what} (kind {profile.kind}; {profile.describe()}); {size_why}"
    return PresetChoice(config, name, reason)


def _cpu_variant(preset: str | Path | None) -> str:
    """The preset to suggest instead of ``preset`` on a CPU: its kind parts composed with :data:`CPU_PRESET`."""
    if preset is None:
        return CPU_PRESET
    kinds = [str(p) for p in _preset_parts(preset) if "sized_for" not in read_config_file(preset_path(p))]
    kinds = [k for k in kinds if k != "default"]
    return "+".join([*kinds, CPU_PRESET])


def size_warning(config: VoxFusionConfig, preset: str | Path | None = None) -> str | None:
    """One line warning that a GPU-sized ``config`` (``sized_for: gpu``) will run on the CPU, with the speed to
    expect and the preset to use instead; ``None`` when the sizes fit the device (or the device is CUDA).

    ``preset``: the name the config was loaded from (to name its CPU variant), ``None`` for the built-ins.
    """
    if config.sized_for != "gpu" or config.device.startswith("cuda"):
        return None
    if config.device == "auto" and torch.cuda.is_available():
        return None
    what = f"preset {str(preset)!r}" if preset is not None else "the built-in configuration"
    paper = preset is not None and "paper" in _preset_parts(preset)
    slow, fast = (f"{lo:g}-{hi:g}" for lo, hi in (PAPER_SIZES_ON_CPU_FPS if paper else GPU_SIZES_ON_CPU_FPS,
                                                  CPU_SIZES_ON_CPU_FPS))
    first = "about 2.5 min" if paper else "about 5 s"
    return (f"warning: {what} is sized for a GPU but runs on the CPU: expect about {slow} frames/s (measured on a "
            f"2-core CPU; the first frame alone {first}). Use --config {_cpu_variant(preset)} for CPU "
            f"sizes (about {fast} frames/s there), or leave out --config to let voxfusion choose.")
