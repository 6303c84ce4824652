"""Tracking (paper §4.2): one camera pose per frame, optimised against a frozen map snapshot.

The pose is ``T_world_cam = T_prior @ exp(xi)`` with ``xi`` a 6-vector (translation, rotation vector)
in the camera frame (right perturbation, see :mod:`..lie`), optimised with Adam through the volume
renderer on ``rays`` pixels sampled each iteration where depth is valid (and confident).

Priors (:func:`predict_pose`): constant velocity (default), the paper's zero motion, or, when frames
carry a device pose (ARKit), the device's relative motion since the previous frame.

Robustness: rays whose depth residual exceeds ``outlier_k x median`` (at most ``outlier_max_m``) are
dropped from the depth and SDF terms. A frame is marked lost (its pose is the prior, and it is never fused
into the map) when too few rays hit the map and agree with it, or when its loss spikes: the loss exceeds
``loss_spike_factor`` times the median of recent tracked frames AND the median depth residual exceeds
``spike_residual_m`` (metres). The second condition keeps a view that turns towards new, far or barely
mapped surfaces (whose SDF terms are large while the pose is fine, common with noisy LiDAR depth) from
counting as a tracking failure.

Device priors: with ARKit-style poses the prior is already good to about a millimetre, so tracking takes
smaller steps (``lr_device_prior``) and may add a soft term holding the pose near it
(``device_prior_weight``).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from ..errors import ConfigError
from ..framedata import FrameData, sample_pixels
from ..geometry import invert_pose, nearest_rigid, scale_motion
from ..lie import perturb_right
from ..losses import LossConfig, compute_losses
from ..map import VoxelMap
from ..map.field import SDFDecoder
from ..optim import adam, adam_step
from ..precompiled import PrecompiledVariants
from ..render.volume import RenderConfig, camera_rays, render_rays
from .tracking_graphs import SolverGraphs
from .tracking_sdf import (
    PRECOMPILED_LINEARIZE,
    DepthReference,
    GrayImages,
    SdfSolverConfig,
    depth_reference,
    gray_images,
    map_costs,
    sample_points,
    solve_pose,
    with_older_frames,
)

COST_RATIO_MIN_HISTORY = 3
"""Tracked frames a frame's cost ratio (:func:`.system.cost_ratio`, ``TrackingConfig.limited_cost_factor``) needs
before it (fewer: no ratio, never ``limited``)."""

FRAME_REFS_MIN_WEIGHT = 0.25
"""The older frame-to-frame references (``sdf_frame_refs``) are dropped once their weight would fall below this
(after ``4 sdf_frame_refs_fade`` accepted frames, ~2 s at 30 Hz): by then the map has taken over, and three cost
5-10 % of a CPU frame at 320x240 for as long as they are kept (``bench/fps_pair.py``, 2026-12-07); the CUDA graphs are
captured once more when they go."""

__all__ = ["TrackingConfig", "FRAME_REFS_MIN_WEIGHT", "TrackResult", "Tracker", "device_prior_applies", "predict_pose",
           "masked_median"]


@dataclass(frozen=True)
class TrackingConfig:
    """Tracking options (paper symbols in brackets)."""

    method: Literal["render", "sdf"] = "sdf"
    """``sdf`` (default): Levenberg-Marquardt on point-to-SDF residuals (:mod:`.tracking_sdf`; one field query
    per point per iteration, ``sdf_points`` points, ``sdf_iters`` iterations per level), optionally followed
    by ``refine_iters`` iterations of the render tracker. ``render``: the paper's tracker (Adam through the
    volume renderer, ``rays`` rays per iteration). Measured on the synthetic room (100 frames, CPU sizes):
    ATE 0.26-0.28 cm with ``sdf`` against 0.38 cm with ``render``, and under fast rotation (180 deg/s) a
    mean error of 1.3 against 2.6 cm, at ~50 ms against ~300 ms per frame (~22 ms since a level stops once
    converged, ``sdf_converge_tol``)."""
    rays: int = 1024
    """[N_t] pixels sampled per iteration."""
    iters: int = 30
    """Maximum iterations per frame."""
    min_iters: int = 5
    """Iterations always run before early stopping is considered."""
    lr: float = 1e-2
    """Adam learning rate on the 6-vector (about metres / radians per iteration) at the first iteration."""
    lr_device_prior: float = 1e-3
    """Learning rate used instead of ``lr`` when the start is already close: a prior from device poses
    (visual-inertial relative motion, ARKit, is good to about a millimetre between frames) and the render
    refinement after the ``sdf`` tracker (``refine_iters``). Adam's steps (about the learning rate each) would
    otherwise throw the pose centimetres away and leave it off by about the last step."""
    lr_rot_ratio: float = 1.0
    """Rotation steps are this times the translation steps (1: the same, in radians and metres)."""
    lr_final_ratio: float = 0.1
    """The learning rate decays exponentially to ``lr * lr_final_ratio`` at the last iteration."""
    converge_tol: float = 2e-4
    """Stop when the pose moved less than this (m and rad) for ``patience`` consecutive iterations."""
    patience: int = 3
    check_every: int = 4
    """Both trackers: read the convergence test back from the device every this many iterations (each read
    waits for the device: on a GPU 3-5 keeps the loop from stalling, at the price of at most that many extra
    steps; on a CPU a read-back is free and the ``cpu`` preset's 1 stops soonest)."""
    motion_model: Literal["constant_velocity", "zero"] = "constant_velocity"
    """Prior without a device pose: constant velocity, or the paper's zero-motion model."""
    use_device_prior: bool = True
    """Use the device's relative motion (e.g. ARKit) as the prior when frames carry device poses."""
    device_prior_weight: float = 0.0
    """Weight of a soft prior that keeps the pose near the device prior (0: the device motion only
    initialises the optimisation, as in the paper's motion models). When > 0 and the prior came from device
    poses, tracking adds ``weight x (|dt| / device_prior_sigma_m)^2 + weight x (|dr| / sigma)^2`` for the
    correction ``(dt, dr)`` away from the prior: short-term visual-inertial motion (ARKit) is far more
    precise than alignment to a coarse map, while the map still pulls accumulated drift back."""
    device_prior_sigma_m: float = 0.01
    """Translation scale of the device-prior term (metres)."""
    device_prior_sigma_deg: float = 0.5
    """Rotation scale of the device-prior term (degrees)."""
    outlier_k: float = 5.0
    """Rays with |rendered - observed depth| > outlier_k x median residual are dropped."""
    outlier_max_m: float = 0.3
    """...and so are rays whose residual exceeds this (metres) whatever the median: where most of a view
    disagrees with the map (a surface the map has not yet carved away, a region not yet mapped) the median
    itself is large, and the frame must be tracked on the rays that do agree."""
    min_valid_fraction: float = 0.1
    """A frame is lost when fewer than this fraction of rays hit a rendered surface and are inliers."""
    loss_spike_factor: float = 10.0
    """Loss-spike rule, first condition: the loss exceeds this times the median loss of recent tracked frames."""
    spike_residual_m: float = 0.1
    """Loss-spike rule, second condition: the median |rendered - observed| depth over the rays that hit the
    map exceeds this (metres), i.e. the geometry really disagrees at the tracked pose."""
    t_far_margin_m: float = 0.3
    """Samples stop this far (camera z) behind the observed depth."""
    sdf_points: int = 4096
    """``sdf`` method: back-projected points at the finest level (each coarser level has 4x fewer)."""
    sdf_levels: int = 2
    """``sdf`` method: coarse-to-fine levels."""
    sdf_iters: int = 6
    """``sdf`` method: Levenberg-Marquardt iterations per level at most."""
    sdf_converge_tol: float = 3e-4
    """``sdf`` method: a level ends once the next step would move the pose less than this (metres and
    radians, largest component; 3e-4 = 0.3 mm / 0.017 deg), tested every ``check_every`` iterations;
    0: always ``sdf_iters`` (then the loop never waits for the device). Was 1e-4 before the frame-to-frame
    term: its nearest-pixel association re-pairs points between iterations, so steps jitter at ~1e-4 and
    most levels ran all ``sdf_iters`` (7-Scenes, 100 frames: 10.8 iterations per frame against 8.0 with
    3e-4, ATE 1.31 cm either way)."""
    sdf_coarse_converge_tol: float = 3e-3
    """``sdf`` method: the same test at the coarser levels (3e-3 = 3 mm / 0.17 deg). They only have to bring
    the pose within the finest level's reach, which polishes it to ``sdf_converge_tol``; held to that
    tolerance too, the coarse level took ~40 % of the tracker's time on the synthetic room. Measured on the
    2-core Intel Xeon, `cpu` sizes, same seeds (3e-4 -> 3e-3): tracking 13.8 -> 12.5 ms per frame on the
    synthetic room (seed 1), ATE within the float-rounding spread of a run (synthetic room 0.18 / 0.29 /
    0.26 -> 0.16 / 0.30 / 0.23 cm, fast rotation 0.44 / 0.45 / 0.40 -> 0.43 / 0.43 / 0.41)."""
    sdf_huber_m: float = 0.01
    """``sdf`` method: Huber scale of the point-to-SDF residual (metres)."""
    sdf_max_residual_m: float = 0.08
    """``sdf`` method: points with |SDF| beyond this (metres) are outliers for that iteration. Keep it
    below the truncation (0.1 m): the field saturates there and its gradient says nothing."""
    sdf_inlier_m: float = 0.03
    """``sdf`` method: |SDF| below this (metres) counts as an inlier for lost-frame detection."""
    sdf_w_color: float = 0.0
    """``sdf`` method: weight of the photometric residual (gray level from the colour head at the surface
    point against the pixel, in [0, 1]) relative to the SDF residual in metres (0: geometry only)."""
    sdf_w_frame: float = 1.0
    """``sdf`` method: weight of a frame-to-frame point-to-plane residual against the previous accepted
    frame's depth (projective association; metres, like the SDF residual; 0: track against the map only).
    The map's SDF is only as sharp as its voxels allow; the previous frame's depth is sharp at any voxel
    size, and the map term keeps the sum from drifting. Measured on the 2-core CPU, `cpu` sizes, ATE cm
    (weight 0 -> 1, with ``sdf_converge_tol`` 3e-4): synthetic room seeds 0/1/2 0.24/0.29/0.46 ->
    0.20/0.21/0.33, fast rotation seeds 0/1 0.54/0.57 -> 0.45/0.48, TUM fr1 desk 0.42/0.54/0.51 ->
    0.29/0.37/0.34, 7-Scenes 500 frames seed 0 3.80 -> 3.83. Weight 2 was better on the synthetic room and
    TUM (0.28/0.30/0.22) but worse on 7-Scenes (4.23: it drifts like odometry over 500 frames); 10 (frame
    to frame alone, in effect) TUM 0.34."""
    sdf_frame_max_m: float = 0.05
    """``sdf`` method: point pairs of the frame-to-frame term further apart than this (metres) are ignored."""
    sdf_frame_refs: int = 3
    """``sdf`` method: older accepted frames (before the previous one) that the point-to-plane term also compares
    with, each at its tracked pose (0: the previous frame only). Their weight relative to the previous frame's is
    ``min(1, sdf_frame_refs_fade / n)`` after ``n`` accepted frames: while the map has been fitted to a handful of
    noisy frames its SDF is no better an anchor than a frame's depth, and references whose noise and pose errors
    are independent average it out; as the map integrates more frames it takes over. One projective association
    per reference and field evaluation, no field query. Measured (2026-12-07, ATE cm, 2-core AMD EPYC, one thread,
    tracker uncompiled; 0 -> 3): TUM fr1 desk seeds 0/1/2 0.233/0.175/0.168 -> 0.163/0.144/0.118 (TSDF baseline
    0.173), 7-Scenes 0-499 4.06/3.86/3.78 -> 4.08/3.87/3.85, synthetic room 0.136/0.182/0.213 -> 0.114/0.209/0.186,
    fast rotation 0.375/0.285/0.254 -> 0.220/0.230/0.258, held-out synthetic seeds 3-6 0.700/0.147/0.140/0.146 ->
    0.925/0.136/0.143/0.141, held-out fast rotation seeds 3-9 0.520/0.344/0.302/0.372/0.265/0.239/0.205 ->
    0.560/0.419/0.283/0.205/0.285/0.201/0.321. Three references at full weight throughout cost 7-Scenes 17-23 %;
    one reference at four times the weight drifted to 12 cm there (docs/engine-history.md)."""
    sdf_frame_refs_fade: int = 16
    """``sdf`` method: accepted frames over which the older references keep the previous frame's weight
    (``sdf_frame_refs``; half a second at 30 Hz); after them it falls as 1 / frames, and below
    :data:`FRAME_REFS_MIN_WEIGHT` they are dropped."""
    sdf_w_photo: float = 0.1
    """``sdf`` method: weight of a photometric frame-to-frame residual (the previous accepted frame's smoothed
    gray image at the point's projection against the point's own gray level, in [0, 1]) relative to the SDF
    residual in metres (0: none). Only at the finest level, once geometry has brought the pose close: at
    every level it pulled fast rotations into wrong minima. It needs colour that lines up with the depth
    (captures whose reader says otherwise get 0: ``presets.profile_overrides``); without colour it is
    off. Measured on the 2-core Xeon, `cpu` sizes, ATE cm over seeds 0 / 1 / 2 (0 -> 0.1): TUM fr1 desk
    0.32 / 0.30 / 0.28 -> 0.22 / 0.22 / 0.22, fast rotation 0.31 / 0.34 / 0.36 -> 0.26 / 0.25 / 0.34,
    synthetic room 0.16 / 0.27 / 0.20 -> 0.14 / 0.28 / 0.20 (exact rendered depth leaves it little to add);
    0.2: TUM 0.18 / 0.25 / 0.20 but fast rotation 0.30 / 0.38 / 0.37."""
    sdf_huber_photo: float = 0.05
    """``sdf`` method: Huber scale of the photometric frame-to-frame residual (gray levels)."""
    sdf_w_photo_blur: float = 0.3
    """``sdf`` method: weight of the photometric term in a stage between the geometric coarse level and the
    finest, comparing the points' gray levels in their own image and the previous frame's, both blurred by a
    Gaussian of ``sdf_photo_blur_px`` (0: no such stage; off wherever ``sdf_w_photo`` is). Where geometry is
    degenerate (a wall, the floor and a box end: held-out synthetic room seed 3 slid 4.5-8.4 mm per frame for
    8 frames) the coarse level, geometry only, can slide out of the sharp term's one- or two-pixel basin; the
    blurred images' basin is as wide as their blur, and the finest level then polishes against the sharp
    image. Measured on the 2-core AMD EPYC, `cpu` sizes, ATE cm (0 -> 0.3, blur 2 px; `bench/run.py`):
    synthetic room seed 3 1.72 -> 0.96 (TSDF baseline 0.61), seeds 0 / 1 / 2 / 4 / 5 / 6 0.14 / 0.29 / 0.21 /
    0.19 / 0.18 / 0.18 -> 0.16 / 0.27 / 0.22 / 0.21 / 0.18 / 0.17; fast rotation seeds 0-5 0.33 / 0.24 / 0.35 /
    0.47 / 7.35 / 0.29 -> 0.28 / 0.43 / 0.41 / 0.52 / 1.36 / 0.34 (the baseline loses all six); TUM fr1 desk
    0.22 / 0.23 / 0.23 -> 0.16 / 0.21 / 0.21. Also measured, with the reference's image blurred alone (seed 3;
    fast rotation seed 4): 0.3 / 2 px 0.80, 1.44 (within the spread, but that term's minimum is off the true
    pose: ~2 mm on a test wall); weight 0.1 1.53; 0.5 0.82, 4.06; blur 1.5 px 0.75, 4.87; 3 px 0.83; the
    blurred term at the coarse level's points instead of a stage of its own 0.78, but fast rotation seeds 0 / 1
    0.41 / 0.72."""
    sdf_photo_blur_px: float = 2.0
    """``sdf`` method: standard deviation (pixels of the tracked image) of the Gaussian blur of that stage's
    image, on top of the photometric term's 3x3 smoothing."""
    sdf_lost_residual_m: float = 0.04
    """``sdf`` method: a frame is lost when the median |SDF| of its points inside the map exceeds this."""
    cpu_threads: int = 1
    """Intra-op CPU threads while tracking in offline mode (0: leave torch's setting). The tracker's operations
    are small (a few thousand points), so thread wake-ups outweigh the work: on the 2-core development CPU the
    sdf tracker took ~130 ms per frame with two threads and ~80 ms with one. On the 2-core Intel Xeon the project
    moved to, two threads were faster (2026-11-24, synthetic room: 14.0 against 16.3 ms per frame); on the 2-core
    AMD EPYC of 2026-11-25 whole frames with one and two threads could not be told apart (4 A/B pairs within
    its +-10 % noise; `docs/engine-history.md`), so the default stays 1."""
    compile: bool = False
    """``sdf`` method: run each solver iteration's residuals and normal equations
    (:func:`.tracking_sdf.linearize_terms`) through :func:`torch.compile` (dynamic shapes; one graph per solver
    stage, compiled on a session's first frames, whose realtime feed is dropped meanwhile; eager with one warning
    where compilation fails). Off in every preset: on the 2-core AMD EPYC a call at 4096 points took 3.2 instead of
    6.8 ms and a session's frames ~8 ms less of ~90, but compiling took 7 s per process with torch's on-disk cache
    warm and ~30 s cold, more than a run of a few hundred frames saves (``python bench/bench_accel.py``, variant
    ``tracking compile``; ``make bench-gpu`` measures it on a GPU)."""
    precompiled: bool = False
    """``sdf`` method on a CPU: run each solver iteration's residuals and normal equations from ahead-of-time
    compiled artifacts cached on disk (:mod:`.precompiled`; ``VOXFUSION_PRECOMPILE=0`` turns them off), one per
    solver stage's options. A session meeting a stage that has none runs it eagerly (the reference) and starts
    compiling it in a background process at the lowest CPU priority (~20 s of a core each, 3-4 stages per
    capture), so later sessions load it (before their first frame: ~2 s once per process, then ~0.1 s each). A
    session never switches mid-run. On in the ``cpu`` preset: on the 2-core AMD EPYC a call at 4096 points took
    4.2-4.5 against 7.0-8.4 ms eager, and a synthetic-room frame ~10 % less time (eager and precompiled in one
    process, 2026-11-28; ``python bench/fps_pair.py --warm`` measures it against the TSDF baseline)."""
    cuda_graphs: bool = True
    """``sdf`` method on a CUDA device: replay each solver stage from CUDA graphs (:mod:`.tracking_graphs`), captured
    once per map structure (a snapshot of the same structure is copied in), instead of launching its ~340 operators
    per iteration one by one (the eager solver, the reference, runs on a CPU, with ``compile``, and wherever capture
    fails, after one warning). Same operators, same results: on an H100 machine a tracked frame took 9.05 against
    83.1 ms eager (``bench/results/gpu-nvidia-h100-80gb-hbm3-graph-checks.log``)."""
    retry_cost_factor: float = 3.0
    """Recovery after a gap: a frame that comes after lost frames, or ``retry_gap`` times the usual interval between
    tracked frames or more after the last tracked one, and whose tracking is lost or costs (``TrackResult.loss``)
    more than this times the median cost of the last ``retry_window`` tracked frames, is tracked again (once per
    gap: not again before a frame is tracked) from other start poses: the last tracked pose turned about the
    camera's own vertical axis (pan) by 0, +-``retry_step_deg``, ... up to +-``retry_max_deg`` and about its
    horizontal axis (tilt) by +-``retry_step_deg``, each moved by the translation the motion prior extrapolated over
    the gap or by an offset of a grid in the camera's horizontal plane (``retry_reach_m``, ``retry_step_m``). They
    are ranked by how well the frame's depth fits the map there (:meth:`Tracker.pose_costs`), and the best
    ``retry_tracks`` are tracked in that order until one costs no more than the factor. A retry replaces the first
    result only when it is not lost and costs under half the first's (:data:`.slam.RETRY_MIN_GAIN`), or, where the
    first was lost (and so not fused), costs as usual; the lowest such cost wins.

    The motion prior extrapolates the last velocity over the gap, so a camera that turned, stopped or walked on
    while frames were missing starts far from where it is, and the solver can settle in a wrong minimum without
    being lost, after which the map grows a second copy of the scene: the synthetic room swinging at up to 180
    deg/s with frames 40-54 without depth (seed 1) tracked frame 55 13 cm / 22 deg off (cost 8.6) from the
    extrapolated prior, 0.7 cm / 0.1 deg (cost 1.05) from the last pose. A frame is retried only after a gap (a
    view turning into unmapped space costs more too, and is not a wrong start), and never with a device prior
    (``T_world_cam_device``: the device measured the motion over the gap). 0 turns it off."""
    first_motion_step_deg: float = 4.0
    first_motion_max_deg: float = 12.0
    """The first frame tracked after the map's first frame has no motion to extrapolate: it starts at that frame's pose,
    however far the camera turned in between, and a fast turn there can settle in a wrong minimum that every later
    frame inherits (the synthetic room swinging at up to 180 deg/s, 6.3-6.6 deg between its first two frames:
    held-out seeds 6 and 8 put their second frame 24 and 15 cm off, ATE 2.4 and 4.6 cm). So that frame is also
    tracked from the first frame's pose turned by a grid of pans and tilts, every ``first_motion_step_deg`` up to
    ``first_motion_max_deg`` either way, from the two turned starts where its depth fits the map best
    (:meth:`Tracker.pose_costs`), and a result replaces the first when it is not lost and costs under 0.75 times the
    first's (:data:`.slam.system.FIRST_MOTION_MIN_GAIN`), the lowest winning. Never with a device prior;
    ``first_motion_max_deg`` 0 (or below one step) turns it off. The starts are ranked at 256 points (the 49 of the
    default grid in one batched field query); the search costs ~0.13 s once per session at 320x240, ~0.24 s at
    640x480 (two tracks and the ranking; 2-core AMD EPYC, one thread). Fast rotation held-out seeds 6 / 8 (320x240,
    100 frames): ATE 2.45 / 4.61 -> 0.25 / 0.22 cm (the second frame's cost 4.08 / 3.86 -> 1.68 / 1.71); on every
    other capture measured with the tracker uncompiled (synthetic room seeds 0-6, fast rotation seeds 0-5, 7, 9, TUM
    fr1 desk, 7-Scenes seeds 0-2) the first result stood and every pose is the one tracked without the search
    (:meth:`.SlamSystem._search_first_motion` puts the tracker's random stream back); with the precompiled tracker,
    which rounds differently, it also replaced fast rotation seed 4's (0.59 -> 0.38 cm, ``bash
    bench/engine_targets.sh --heldout``)."""
    retry_window: int = 10
    """Tracked frames whose median cost is the reference of ``retry_cost_factor`` (no retry before this many)."""
    retry_gap: float = 2.5
    """A frame this many times the usual interval between tracked frames (the median of the last ``retry_window``
    with no lost frame between them) or more after the last tracked one comes after a gap (``retry_cost_factor``);
    so does a frame after lost ones. Realtime tracking that drops frames because it is slower than the feed has
    long intervals as its usual ones."""
    retry_step_deg: float = 15.0
    retry_max_deg: float = 90.0
    """The turns ``retry_cost_factor`` tries: pan every ``retry_step_deg`` up to ``retry_max_deg`` either way."""
    retry_reach_m: float = 0.2
    retry_step_m: float = 0.1
    """The moves ``retry_cost_factor`` tries besides the prior's: a grid over the camera's x and z axes (its image
    horizontal and optical axis), every ``retry_step_m`` up to ``retry_reach_m`` metres either way."""
    retry_tracks: int = 4
    """The most start poses ``retry_cost_factor`` tracks from (the best-fitting ones) around the last tracked pose,
    and again the most from ``retry_keyframes``' poses where none of those did."""
    retry_keyframes: int = 64
    """Relocalisation: where no start pose around the last tracked one gives a result that costs as usual
    (``retry_cost_factor``), the retry ranks the poses of up to this many keyframes of the published map (all of
    them, or as many spread evenly over them), each turned as the last pose is (pan, tilt), keeps each keyframe's
    best turn and tracks the best ``retry_tracks`` keyframes' against their own depth; a result from there must
    cost as usual (it may be anywhere in the map). A camera that comes back after a gap to a place it mapped,
    however far it went meanwhile, as long as the first frame after the gap sees it (once per gap, as every
    retry). 0: none. The synthetic room (seed 1), frames 0-59, then after a 1 s pause frames 15-29 again (the camera
    38 cm and 26 deg from where it was last tracked, beyond the turns and the grid): without them every later frame
    stayed ~32-36 cm off."""
    limited_cost_factor: float = 3.0
    """A tracked frame costing more than this times the median cost of the tracked frames before it (the last
    ``retry_window``, at least three) has the tracking state ``limited`` (:attr:`.system.FrameRecord.tracking_state`:
    on every pose the server returns, counted in a session's status): its pose may be wrong. It is still fused,
    since a view turning into space the map has not seen costs more too. 0: never limited. Decides nothing in the
    engine: a signal for clients (an AR app can hold its anchors while the state is limited). The first frames
    after the map's first are compared with frames that had fewer older references (``sdf_frame_refs``) and so
    fewer terms: frame 4, the first with all of them, is where every dev capture had its largest ratio at its own
    rate (at most 2.22), later frames stay under ~1.9."""
    refine_iters: int = 0
    """``sdf`` method: iterations of the render tracker run after it (0: none), with the small steps of
    ``lr_device_prior`` (it starts at the ``sdf`` tracker's pose, a few millimetres from the answer)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss weights used for tracking."""

    def __post_init__(self) -> None:
        for name in ("retry_cost_factor", "limited_cost_factor"):
            if not getattr(self, name) >= 0:
                raise ConfigError(name, f"must be >= 0 (0: off), got {getattr(self, name)}")
        if self.retry_keyframes < 0:
            raise ConfigError("retry_keyframes", f"must be >= 0 (0: none), got {self.retry_keyframes}")
        if not (self.retry_gap > 1 and self.retry_step_deg > 0 and self.retry_max_deg >= 0 and self.retry_step_m > 0
                and self.retry_reach_m >= 0):
            raise ConfigError("retry_gap", "need retry_gap > 1, retry_step_deg > 0, retry_max_deg >= 0, "
                              "retry_step_m > 0 and retry_reach_m >= 0")
        if self.limited_cost_factor > 0 and self.retry_window < COST_RATIO_MIN_HISTORY:
            raise ConfigError("retry_window", "the tracking state's cost ratio needs a window of at least "
                              f"{COST_RATIO_MIN_HISTORY} frames "
                              f"(or limited_cost_factor=0), got {self.retry_window}")
        for name in ("rays", "iters", "patience", "check_every", "sdf_points", "sdf_levels", "sdf_iters",
                     "retry_window", "retry_tracks"):
            if getattr(self, name) < 1:
                raise ConfigError(name, f"must be >= 1, got {getattr(self, name)}")
        if not (self.lr > 0 and self.lr_device_prior > 0 and self.lr_rot_ratio > 0):
            raise ConfigError("lr", "lr, lr_device_prior and lr_rot_ratio must be > 0")
        if not (self.device_prior_weight >= 0 and self.device_prior_sigma_m > 0 and self.device_prior_sigma_deg > 0):
            raise ConfigError("device_prior_weight", "weight must be >= 0 and both sigmas > 0")
        if not self.outlier_max_m > 0:
            raise ConfigError("outlier_max_m", f"must be > 0, got {self.outlier_max_m}")
        if not 0 <= self.min_valid_fraction < 1:
            raise ConfigError("min_valid_fraction", "must be in [0, 1)")
        for name in ("sdf_huber_m", "sdf_max_residual_m", "sdf_inlier_m", "sdf_lost_residual_m", "sdf_frame_max_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(name, f"must be > 0 metres, got {getattr(self, name)}")
        if not self.sdf_huber_photo > 0:
            raise ConfigError("sdf_huber_photo", f"must be > 0 gray levels, got {self.sdf_huber_photo}")
        if not (self.first_motion_step_deg > 0 and self.first_motion_max_deg >= 0):
            raise ConfigError("first_motion_step_deg", "the step must be > 0 degrees and first_motion_max_deg >= 0, "
                              f"got {self.first_motion_step_deg} and {self.first_motion_max_deg}")
        for name in ("sdf_converge_tol", "sdf_coarse_converge_tol"):
            if not getattr(self, name) >= 0:
                raise ConfigError(name, f"must be >= 0 (metres / radians), got {getattr(self, name)}")
        for name in ("sdf_w_color", "sdf_w_frame", "sdf_w_photo", "sdf_w_photo_blur", "sdf_photo_blur_px",
                     "refine_iters", "cpu_threads", "sdf_frame_refs", "sdf_frame_refs_fade"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        if self.sdf_points >> (2 * (self.sdf_levels - 1)) < 16:
            raise ConfigError("sdf_points", f"the coarsest of {self.sdf_levels} levels would have fewer than 16 "
                              f"points ({self.sdf_points} / 4^{self.sdf_levels - 1})")


@dataclass(frozen=True)
class TrackResult:
    """Outcome of tracking one frame. ``T_world_cam`` and ``T_prior`` are ``[4, 4]`` float64."""

    frame_index: int
    timestamp_s: float
    T_world_cam: np.ndarray
    T_prior: np.ndarray
    loss: float
    iterations: int
    valid_rays: int
    depth_residual_m: float
    """Median |rendered - observed| depth (metres) over the rays that hit the map, at the last iteration."""
    lost: bool
    reason: str
    time_ms: float


def device_prior_applies(config: TrackingConfig, device_prev: np.ndarray | None,
                         device_cur: np.ndarray | None) -> bool:
    """Whether :func:`predict_pose` takes the device's relative motion (on, and both frames carry a pose)."""
    return config.use_device_prior and device_prev is not None and device_cur is not None


MAX_DT_RATIO = 4.0
"""Constant velocity is extrapolated over at most this many inter-frame intervals (a few dropped frames);
beyond that (e.g. after a run of lost frames) the last velocity says little."""


def predict_pose(T_prev: np.ndarray, T_prev2: np.ndarray | None, config: TrackingConfig,
                 device_prev: np.ndarray | None = None, device_cur: np.ndarray | None = None,
                 dt_ratio: float = 1.0) -> np.ndarray:
    """Prior pose of the next frame from the last tracked poses (and device poses, if any).

    Constant velocity is in the camera's own frame (``T_prev @ T_rel``, ``T_rel = T_prev2^-1 @ T_prev``), so a
    turning camera keeps turning: a constant angular velocity. ``dt_ratio`` = (time from the previous frame
    to this one) / (time between the two previous frames) stretches ``T_rel`` when frames were skipped
    (realtime tracking drops frames it cannot keep up with) or arrive unevenly.
    """
    if device_prior_applies(config, device_prev, device_cur):
        return T_prev @ (invert_pose(device_prev) @ device_cur)
    if config.motion_model == "constant_velocity" and T_prev2 is not None:
        ratio = float(dt_ratio) if np.isfinite(dt_ratio) and dt_ratio > 0 else 1.0
        return T_prev @ scale_motion(invert_pose(T_prev2) @ T_prev, min(ratio, MAX_DT_RATIO))
    return T_prev.copy()


class Tracker:
    """Tracks frames against the newest published map snapshot (``set_map``) with ``config.method``."""

    def __init__(self, config: TrackingConfig, render: RenderConfig, use_color: bool, seed: int = 0) -> None:
        self.config = config
        self.render_config = render
        self.use_color = use_color
        self._seed = seed + 1
        self.generator = torch.Generator().manual_seed(self._seed)
        """Draws the tracked pixels; re-made on the map's device by :meth:`set_map` (no host copy per frame)."""
        self.voxels: VoxelMap | None = None
        self.decoder: SDFDecoder | None = None
        self._recent_losses: deque[float] = deque(maxlen=20)
        self._reference: DepthReference | None = None
        self._accepted = 0
        """Frames remembered so far (:meth:`remember`): how far the older references' weight has faded."""
        self._images: tuple[FrameData, GrayImages] | None = None
        """The last frame whose gray images were made, and those images (:meth:`_gray_images`)."""
        self._graphs: SolverGraphs | None = None
        """The ``sdf`` solver's CUDA graphs (``cuda_graphs`` on a CUDA device), made with the first frame there."""
        self.precompiled: PrecompiledVariants | None = None
        """The ``sdf`` solver's precompiled evaluations (``precompiled`` on a CPU), made with the first frame there;
        this tracker's own view, so a session keeps one choice per stage (:mod:`.precompiled`)."""

    def set_map(self, voxels: VoxelMap, decoder: SDFDecoder) -> None:
        """Swap in a new frozen map snapshot (a reference assignment; the tracker never waits)."""
        self.voxels, self.decoder = voxels, decoder
        if self.generator.device != voxels.device:  # the first map, or a map moved to another device
            self.generator = torch.Generator(device=voxels.device).manual_seed(self._seed)

    def remember(self, frame: FrameData, T_world_cam: np.ndarray) -> None:
        """Keep ``frame``, placed at ``T_world_cam [4, 4]``, as the reference of the next frame's frame-to-frame
        terms (``sdf_w_frame``, and ``sdf_w_photo`` with its smoothed gray image; nothing is kept without
        them). The caller passes every frame it accepts (tracked and not lost, or the first)."""
        cfg = self.config
        if cfg.method == "sdf" and (cfg.sdf_w_frame > 0 or self._photo_weight() > 0):
            reference = depth_reference(frame, T_world_cam, images=self._gray_images(frame))
            self._accepted += 1
            weight = min(1.0, cfg.sdf_frame_refs_fade / self._accepted)
            if cfg.sdf_frame_refs > 0 and cfg.sdf_w_frame > 0 and weight >= FRAME_REFS_MIN_WEIGHT:
                reference = with_older_frames(reference, self._reference, cfg.sdf_frame_refs, weight)
            self._reference = reference

    @contextmanager
    def referenced_to(self, frame: FrameData, T_world_cam: np.ndarray) -> Iterator[None]:
        """Within the block the frame-to-frame terms compare with ``frame`` at ``T_world_cam [4, 4]`` instead of the
        last remembered frame, which is kept again after it: relocalisation tracks a frame from a keyframe's pose
        against that keyframe, near it, rather than against the last tracked frame, which may be far away."""
        saved, accepted = self._reference, self._accepted
        self._reference = None  # the keyframe alone: the older frames were seen from far away
        self.remember(frame, T_world_cam)
        try:
            yield
        finally:
            self._reference, self._accepted = saved, accepted

    def _photo_weight(self) -> float:
        """The photometric frame-to-frame term's weight: ``sdf_w_photo`` where the tracker has colour, else 0."""
        return self.config.sdf_w_photo if self.use_color else 0.0

    def _gray_images(self, frame: FrameData) -> GrayImages | None:
        """``frame``'s gray images for the photometric terms (None where they are off or it has no colour),
        made once: the frame tracked now becomes the next frame's reference (:meth:`remember`)."""
        if self._photo_weight() <= 0 or frame.color is None:
            return None
        if self._images is None or self._images[0] is not frame:
            blur = self.config.sdf_photo_blur_px if self._photo_blur_weight() > 0 else 0.0
            self._images = (frame, gray_images(frame.color, blur))
        return self._images[1]

    def _photo_blur_weight(self) -> float:
        """The blurred photometric stage's weight: ``sdf_w_photo_blur`` where the sharp term is on, else 0."""
        c = self.config
        return c.sdf_w_photo_blur if self._photo_weight() > 0 and c.sdf_photo_blur_px > 0 else 0.0

    def sdf_stages(self) -> int:
        """Solver stages of the ``sdf`` method per frame, with the reference it holds now: its levels, and the
        blurred photometric stage where that runs. Each stage evaluates its starting pose once before its
        first step, so a frame makes ``iterations + sdf_stages()`` evaluations (what benchmarks count per
        evaluation); the finest stage's first one reuses the blurred stage's field query where that stage runs
        (eager), so it costs only the photometric term and the normal equations."""
        ref = self._reference
        blurred = self._photo_blur_weight() > 0 and ref is not None and ref.gray_blurred is not None
        return self.config.sdf_levels + int(blurred)

    def track(self, frame: FrameData, T_prior: np.ndarray, prior_from_device: bool = False) -> TrackResult:
        """Optimise the pose of ``frame`` starting from ``T_prior`` (``[4, 4]`` camera-to-world).

        ``prior_from_device``: ``T_prior`` came from device poses, so the soft device prior applies (when
        ``device_prior_weight > 0``).
        """
        t0 = time.perf_counter()
        if self.voxels is None or self.decoder is None:
            raise ConfigError("map", "tracker has no map snapshot yet (the first frame initialises the map)")
        if self.config.method == "sdf":
            out = self._track_sdf(frame, T_prior, prior_from_device)
            if self.config.refine_iters > 0 and not out.lost:
                ref = self._track_render(frame, out.T_world_cam, prior_from_device, self.config.refine_iters,
                                         close_start=True)
                if not ref.lost:
                    out = dataclasses.replace(out, T_world_cam=ref.T_world_cam,
                                              iterations=out.iterations + ref.iterations)
        else:
            out = self._track_render(frame, T_prior, prior_from_device, self.config.iters)
        if out.lost:
            out = dataclasses.replace(out, T_world_cam=np.asarray(T_prior, dtype=np.float64).copy())
        return dataclasses.replace(out, T_prior=np.asarray(T_prior, dtype=np.float64),
                                   time_ms=(time.perf_counter() - t0) * 1e3)

    def pose_costs(self, frame: FrameData, poses: np.ndarray, n_points: int = 1024) -> np.ndarray:
        """How well ``frame``'s depth fits the map at each of ``poses [K, 4, 4]`` (camera-to-world), without moving
        them: the mean robust point-to-SDF cost of ``n_points`` of its points (the same points at every pose; a point
        outside the map costs as much as one at the residual cap), as ``[K]`` float64, in units of ``sdf_huber_m``
        squared (the ``sdf`` method's map term). Ranks start poses for :meth:`track` (recovery after a gap), whatever
        the tracking method: the poses in batched field queries (:func:`.tracking_sdf.map_costs`, no gradient; 2^18
        points each, so two for 390 poses at 1024 points), one read-back."""
        voxels, decoder = self.voxels, self.decoder  # one snapshot for every pose (mapping may publish meanwhile)
        if voxels is None or decoder is None:
            raise ConfigError("map", "tracker has no map snapshot yet (the first frame initialises the map)")
        cfg = self.config
        pts = sample_points(frame, n_points, self.generator)
        solver = SdfSolverConfig(huber_m=cfg.sdf_huber_m, max_residual_m=cfg.sdf_max_residual_m)
        T = torch.as_tensor(np.asarray(poses, dtype=np.float64), device=voxels.device)
        return map_costs(voxels, decoder, pts.p_cam, T, solver).cpu().numpy()

    # ------------------------------------------------------------------ sdf (geometric) tracker
    def _track_sdf(self, frame: FrameData, T_prior: np.ndarray, prior_from_device: bool) -> TrackResult:
        cfg = self.config
        voxels, decoder = self.voxels, self.decoder
        dev = voxels.device
        n_levels = cfg.sdf_levels
        images = self._gray_images(frame) if self._reference is not None else None
        finest = sample_points(frame, cfg.sdf_points, self.generator,
                               with_gray=self.use_color and (cfg.sdf_w_color > 0 or self._photo_weight() > 0),
                               blurred=None if images is None else images.blurred)
        # coarser levels: prefixes of the random finest sample
        levels = [finest.prefix(cfg.sdf_points >> (2 * lvl)) for lvl in range(n_levels - 1, 0, -1)] + [finest]
        w = cfg.device_prior_weight if prior_from_device else 0.0
        sigma_rad = float(np.deg2rad(cfg.device_prior_sigma_deg))
        solver = SdfSolverConfig(
            iters=cfg.sdf_iters, converge_tol=cfg.sdf_converge_tol, coarse_converge_tol=cfg.sdf_coarse_converge_tol,
            check_every=cfg.check_every,
            huber_m=cfg.sdf_huber_m, max_residual_m=cfg.sdf_max_residual_m,
            inlier_m=cfg.sdf_inlier_m, w_color=cfg.sdf_w_color,
            prior_info=(w / cfg.device_prior_sigma_m ** 2, w / sigma_rad ** 2),
            w_frame=cfg.sdf_w_frame, frame_max_m=cfg.sdf_frame_max_m,
            w_photo=self._photo_weight(), huber_photo=cfg.sdf_huber_photo, w_photo_blurred=self._photo_blur_weight(),
            compile=cfg.compile)
        T0 = torch.as_tensor(T_prior, dtype=torch.float64, device=dev)
        sol = None
        if cfg.cuda_graphs and dev.type == "cuda":
            if self._graphs is None:
                self._graphs = SolverGraphs(dev)
            sol = self._graphs.solve(voxels, decoder, levels, T0, solver, self._reference)
        if sol is None:  # on a CPU, compiled, or where capture failed
            if cfg.precompiled and not cfg.compile and dev.type == "cpu" and self.precompiled is None:
                self.precompiled = PrecompiledVariants(PRECOMPILED_LINEARIZE)
            variants = self.precompiled if dev.type == "cpu" else None
            # the reference is None unless a term needs one
            sol = solve_pose(voxels, decoder, levels, T0, solver, self._reference, variants)
        # the one read-back of the frame: the pose and the statistics together
        stats = torch.stack([sol.cost, sol.inlier_fraction, sol.median_residual_m, sol.n_valid.to(torch.float64)])
        host = torch.cat([sol.T.reshape(-1), stats]).cpu().numpy()  # float64 throughout
        T_est = nearest_rigid(host[:16].reshape(4, 4))
        cost, inlier, med, n_valid = float(host[16]), float(host[17]), float(host[18]), int(host[19])
        lost, reason = False, ""
        if inlier < cfg.min_valid_fraction or n_valid < 8:
            lost, reason = True, f"too few inliers ({inlier * 100:.1f} % of {cfg.sdf_points} points)"
        elif not np.isfinite(cost) or not np.all(np.isfinite(T_est)):
            lost, reason = True, "non-finite cost or pose"
        elif med > cfg.sdf_lost_residual_m:
            lost, reason = True, f"median point-to-surface distance {med * 100:.1f} cm"
        return TrackResult(frame.index, frame.timestamp_s, T_est, T_prior, cost,
                           sol.iterations, n_valid, med, lost, reason, 0.0)

    # ------------------------------------------------------------------ render (paper) tracker
    def _track_render(self, frame: FrameData, T_prior: np.ndarray, prior_from_device: bool,
                      iters: int, close_start: bool = False) -> TrackResult:
        """Adam through the volume renderer. The loop keeps its statistics on the device and reads them back
        only every ``check_every`` iterations (convergence) and once at the end. ``close_start``: ``T_prior``
        is already near the answer (a refinement), so steps are ``lr_device_prior``-sized."""
        cfg = self.config
        voxels, decoder = self.voxels, self.decoder
        dev = voxels.device
        T0 = torch.as_tensor(T_prior, dtype=torch.float64, device=dev)
        # Adam moves every coordinate by about the learning rate per step; optimise z with xi = z * scale so
        # that the rotation steps are lr_rot_ratio times the translation steps (radians vs metres)
        scale = torch.tensor([1.0] * 3 + [cfg.lr_rot_ratio] * 3, dtype=torch.float64, device=dev)
        z = torch.zeros(6, dtype=torch.float64, device=dev, requires_grad=True)
        lr = cfg.lr_device_prior if prior_from_device or close_start else cfg.lr
        opt = adam([z], lr=lr)
        prior_weight = cfg.device_prior_weight if prior_from_device else 0.0
        sigma_rad = np.deg2rad(cfg.device_prior_sigma_deg)
        decay = cfg.lr_final_ratio ** (1.0 / max(iters - 1, 1))
        min_valid = max(8.0, cfg.min_valid_fraction * cfg.rays)
        max_step = torch.zeros((), dtype=torch.float64, device=dev)  # largest move since the last check
        loss_t = resid_t = torch.full((), float("nan"), dtype=torch.float64, device=dev)
        valid_t = torch.zeros((), dtype=torch.int64, device=dev)
        it = still = 0
        for it in range(1, iters + 1):
            for group in opt.param_groups:
                group["lr"] = lr * decay ** (it - 1)
            px = sample_pixels(frame, cfg.rays, self.generator)
            xi = z * scale
            T = perturb_right(T0, xi)
            o, d = camera_rays(frame.K, T, px.uv)
            out = render_rays(voxels, decoder, o, d, self.render_config, training=False,
                              t_far=px.depth_m + cfg.t_far_margin_m)
            with torch.no_grad():
                ok = out.hit & out.surface
                resid = (out.depth.detach() - px.depth_m).abs()
                med = masked_median(resid, ok)
                inlier = ok & (resid <= (cfg.outlier_k * med.clamp(min=1e-3)).clamp(max=cfg.outlier_max_m))
                valid_t = inlier.sum()
                enough = (valid_t >= min_valid).to(resid.dtype)  # too few inliers: this step does nothing
            depth_gt = torch.where(inlier, px.depth_m, torch.zeros_like(px.depth_m))
            color_gt = px.color if self.use_color else None
            terms = compute_losses(out, depth_gt, color_gt, cfg.loss)
            total = terms.total * enough
            if prior_weight > 0:
                total = total + prior_weight * ((xi[:3] / cfg.device_prior_sigma_m).square().sum()
                                                + (xi[3:] / sigma_rad).square().sum()).to(total.dtype)
            opt.zero_grad(set_to_none=True)
            total.backward()
            before = xi.detach().clone()
            adam_step(opt)
            with torch.no_grad():
                max_step = torch.maximum(max_step, ((z * scale) - before).abs().max())
                loss_t, resid_t = terms.total.detach().to(torch.float64), med.to(torch.float64)
            if it % cfg.check_every == 0 or it == iters:  # one read-back every check_every iterations
                if int(valid_t) < min_valid:
                    break
                still = still + cfg.check_every if float(max_step) < cfg.converge_tol else 0
                max_step = torch.zeros_like(max_step)
                if it >= cfg.min_iters and still >= cfg.patience:
                    break
        with torch.no_grad():
            T_est = nearest_rigid(perturb_right(T0, z * scale).cpu().numpy())
        loss_val, valid, resid_m = float(loss_t), int(valid_t), float(resid_t)
        lost, reason = False, ""
        if valid < min_valid:
            lost, reason = True, f"too few valid rays ({valid} of {cfg.rays})"
        elif not np.isfinite(loss_val) or not np.all(np.isfinite(T_est)):
            lost, reason = True, "non-finite loss or pose"
        elif (len(self._recent_losses) >= 5 and loss_val > cfg.loss_spike_factor * float(
                np.median(self._recent_losses)) and resid_m > cfg.spike_residual_m):
            lost, reason = True, (f"loss spike ({loss_val:.4g} vs median {np.median(self._recent_losses):.4g}, "
                                  f"depth residual {resid_m * 100:.1f} cm)")
        if not lost:
            self._recent_losses.append(loss_val)
        return TrackResult(frame.index, frame.timestamp_s, T_est, T_prior, loss_val, it, valid, resid_m, lost,
                           reason, 0.0)


def masked_median(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Lower median of ``x [N]`` where ``mask [N]`` (0 when the mask is empty), without a host sync."""
    n = mask.sum()
    vals = torch.where(mask, x, torch.full_like(x, float("inf"))).sort().values
    mid = ((n - 1).clamp(min=0) // 2).reshape(1)  # a tensor index, gathered: x[t] would read t back
    return torch.where(n > 0, vals.gather(0, mid)[0], x.new_zeros(()))
