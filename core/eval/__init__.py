"""Evaluation: trajectory error (ATE / RPE), multi-view depth consistency, mesh accuracy / completion /
F-score (against the whole and the observed GT), the phantom-surface share (no GT needed), the mesh-frame
sidecar, depth L1, the render-back depth probe (and its outlier / pose perturbations), and the table / JSON
helpers the CLI and the benchmarks share, and the trajectory plot (top view and height over time)."""

from ..mesh.mesh_frame import MeshFrame, MeshWorld, read_mesh_frame, sidecar_path
from .consistency import DepthConsistency, depth_consistency, pair_disagreement
from .depth import DepthL1Result, depth_l1
from .mesh import (
    CameraView,
    GTPart,
    MeshEvalConfig,
    MeshGTEvaluation,
    MeshMethod,
    MeshMetrics,
    compute_mesh_metrics,
    cull_to_views,
    evaluate_mesh_against_gt,
    load_mesh,
    point_to_surface_distance,
    sample_surface,
    views_from_capture,
    views_from_frames,
)
from .mesh_alignment import AlignmentLever, alignment_lever, transform_mesh
from .phantom import (
    PhantomResult,
    auto_stride_px,
    observed_points_from_frames,
    phantom_for_capture,
    phantom_share,
)
from .render_probe import DepthProbe, add_depth_outliers, anchor_first_pose, depth_probe, oblique_rotation
from .report import format_table, to_jsonable, write_json
from .trajectory_error import (
    AlignMode,
    ATEResult,
    RPEResult,
    TrajectoryEvalConfig,
    align_umeyama,
    associate,
    compute_ate,
    compute_rpe,
)
from .trajectory_plot import PlotAxes, plot_axes, plot_trajectory

__all__ = [
    "DepthConsistency",
    "depth_consistency",
    "pair_disagreement",
    "AlignMode",
    "ATEResult",
    "RPEResult",
    "TrajectoryEvalConfig",
    "associate",
    "align_umeyama",
    "compute_ate",
    "compute_rpe",
    "PlotAxes",
    "plot_axes",
    "plot_trajectory",
    "MeshMethod",
    "MeshEvalConfig",
    "MeshMetrics",
    "CameraView",
    "views_from_frames",
    "load_mesh",
    "sample_surface",
    "point_to_surface_distance",
    "cull_to_views",
    "compute_mesh_metrics",
    "GTPart",
    "MeshGTEvaluation",
    "evaluate_mesh_against_gt",
    "views_from_capture",
    "MeshWorld",
    "MeshFrame",
    "read_mesh_frame",
    "sidecar_path",
    "transform_mesh",
    "AlignmentLever",
    "alignment_lever",
    "PhantomResult",
    "phantom_share",
    "observed_points_from_frames",
    "phantom_for_capture",
    "auto_stride_px",
    "DepthL1Result",
    "depth_l1",
    "DepthProbe",
    "depth_probe",
    "add_depth_outliers",
    "oblique_rotation",
    "anchor_first_pose",
    "format_table",
    "to_jsonable",
    "write_json",
]
