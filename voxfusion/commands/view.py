"""``voxfusion view``: a shaded picture of one or more meshes, seen from one camera, as a PNG.

Examples::

    voxfusion view out/desk/mesh.ply --out desk.png                      # automatic oblique overview
    voxfusion view out/desk/mesh.ply --capture ../shared/data/tum_fr1_desk_9frames --frame 4 --out f4.png
    voxfusion view out/desk/mesh.ply --pose out/desk/trajectory.txt:4 --out f4.png
    voxfusion view out/room-run/mesh.ply --compare out/room/gt_mesh.ply --label ours --label gt \\
        --look-at 4,-4,4,0,0,1 --size 800x600 --out room.png

Every mesh is ray-cast at the same camera (first hit, vertex colours, headlight shading) and the panels
are written side by side; with ``--capture`` the frame's colour image comes first. The camera is, in this
order: ``--pose`` / ``--look-at``; the capture frame's reference pose (or its device pose); an automatic
overview that frames all meshes from 35 deg above.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh
import typer

from voxfusion.core.datasets import open_capture
from voxfusion.core.errors import CaptureError, ValidationError, VoxFusionError
from voxfusion.core.geometry import scale_intrinsics
from voxfusion.core.mesh import intrinsics_from_fov, look_at, overview_pose, write_mesh_pictures
from voxfusion.core.trajectory import read_tum_trajectory

__all__ = ["register", "view_command", "parse_size", "parse_look_at", "pose_from_tum_index"]

DEFAULT_SIZE = (640, 480)
DEFAULT_FOV_DEG = 70.0


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` -> ``(640, 480)`` (width, height); raises ``ValidationError`` naming ``--size``."""
    parts = text.lower().replace(" ", "").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ValidationError("--size", f"expected WIDTHxHEIGHT in pixels, e.g. 640x480, got {text!r}") from None
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise ValidationError("--size", f"width and height must be in [1, 16384] pixels, got {text!r}")
    return width, height


def parse_look_at(text: str) -> np.ndarray:
    """``"EX,EY,EZ,TX,TY,TZ[,UX,UY,UZ]"`` (world metres; up defaults to +z) -> ``T_world_cam`` ``[4, 4]``."""
    try:
        values = [float(p) for p in text.replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) not in (6, 9) or not np.all(np.isfinite(values)):
        raise ValidationError("--look-at", "expected 6 or 9 comma-separated numbers EX,EY,EZ,TX,TY,TZ[,UX,UY,UZ] "
                                           f"(eye, target, up; world metres), got {text!r}")
    up = values[6:9] if len(values) == 9 else (0.0, 0.0, 1.0)
    return look_at(values[0:3], values[3:6], up)


def parse_vector(text: str, field: str) -> np.ndarray:
    """``"X,Y,Z"`` -> ``[3]`` float64."""
    try:
        values = np.array([float(p) for p in text.replace(" ", "").split(",")])
    except ValueError:
        values = np.zeros(0)
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise ValidationError(field, f"expected three comma-separated numbers X,Y,Z, got {text!r}")
    return values


def pose_from_tum_index(spec: str) -> np.ndarray:
    """``"TUM_FILE:INDEX"`` -> the INDEX-th pose (0-based row; negative counts from the end) of the file."""
    path_text, sep, index_text = spec.rpartition(":")
    if not sep or not path_text:
        raise ValidationError("--pose", f"expected TUM_FILE:INDEX, e.g. out/desk/trajectory.txt:0, got {spec!r}")
    try:
        index = int(index_text)
    except ValueError:
        raise ValidationError("--pose", f"INDEX must be an integer (0-based pose row), got {index_text!r}") from None
    traj = read_tum_trajectory(path_text)
    n = len(traj)
    if not -n <= index < n:
        raise ValidationError("--pose", f"pose index {index} is out of range: {path_text} has {n} poses "
                                        f"(0..{n - 1})")
    return traj.T_world_cam[index]


def _load_mesh(path: Path) -> trimesh.Trimesh:
    if not path.is_file():
        raise CaptureError(path, "mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for corrupt files
        raise CaptureError(path, f"cannot read mesh: {e}") from e
    if not isinstance(mesh, trimesh.Trimesh):
        raise CaptureError(path, f"not a triangle mesh (trimesh read a {type(mesh).__name__})")
    return mesh


def _labels(meshes: list[Path], labels: list[str]) -> list[str]:
    if labels:
        if len(labels) != len(meshes):
            raise ValidationError("--label", f"got {len(labels)} labels for {len(meshes)} meshes (give one per "
                                             "mesh, in order: MESH, then each --compare)")
        if len(set(labels)) < len(labels):
            raise ValidationError("--label", f"labels must differ, got {labels}")
        return labels
    names = [p.stem for p in meshes]
    if len(set(names)) < len(names):  # e.g. run-a/mesh.ply vs run-b/mesh.ply
        names = [f"{p.parent.name}/{p.name}" for p in meshes]
    if len(set(names)) < len(names):
        names = [str(p) for p in meshes]
    if len(set(names)) < len(names):  # the same file twice
        names = [f"{i + 1}: {name}" for i, name in enumerate(names)]
    return names


def view_command(
    mesh: Annotated[Path, typer.Argument(help="Mesh to draw (PLY / OBJ / GLB).")],
    out: Annotated[Path, typer.Option("--out", help="Output picture (.png).")],
    compare: Annotated[list[Path] | None, typer.Option("--compare", help="Another mesh drawn beside it at the same "
                                                       "camera (repeatable).")] = None,
    label: Annotated[list[str] | None, typer.Option("--label", help="Panel label, one per mesh in order (default: "
                                                    "file names; repeatable).")] = None,
    pose: Annotated[str | None, typer.Option("--pose", help="TUM_FILE:INDEX: the INDEX-th pose (0-based row) of a "
                                             "TUM trajectory (camera-to-world, OpenCV axes).")] = None,
    look_at_: Annotated[str | None, typer.Option("--look-at", help="EX,EY,EZ,TX,TY,TZ[,UX,UY,UZ]: camera at the eye "
                                                 "looking at the target, world metres (up default +z).")] = None,
    capture: Annotated[Path | None, typer.Option("--capture", help="Capture folder: use a frame's intrinsics, size "
                                                 "and pose, and show its colour image.")] = None,
    frame: Annotated[int | None, typer.Option("--frame", help="Frame index in --capture (0-based; default 0).")]
    = None,
    fov_deg: Annotated[float | None, typer.Option("--fov-deg", help="Horizontal field of view in degrees without "
                                                  "--capture (default 70).")] = None,
    size: Annotated[str | None, typer.Option("--size", help="WIDTHxHEIGHT in pixels (default 640x480, or the "
                                             "capture frame's size).")] = None,
    up: Annotated[str, typer.Option("--up", help="World up X,Y,Z for the automatic overview (y for ARKit "
                                    "worlds: 0,1,0).")] = "0,0,1",
    cull_back_faces: Annotated[bool | None, typer.Option(
        "--cull-back-faces/--show-back-faces", help="See through faces that turn their back to the camera "
        "(a closed room seen from outside shows its inside). Default: cull for the automatic overview only.")]
        = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --out if it exists.")] = False,
) -> None:
    """Draw MESH (and --compare meshes) from one camera as shaded pictures, side by side, in one PNG."""
    try:
        if out.suffix.lower() != ".png":
            raise ValidationError("--out", f"must be a .png file, got {out.name!r}")
        if out.exists() and not force:
            raise ValidationError("--out", f"{out} exists; pass --force to overwrite it")
        if pose is not None and look_at_ is not None:
            raise ValidationError("--pose/--look-at", "give one camera, not both")
        if frame is not None and capture is None:
            raise ValidationError("--frame", "needs --capture (the capture the frame comes from)")
        if fov_deg is not None and capture is not None:
            raise ValidationError("--fov-deg", "conflicts with --capture (the frame's own intrinsics are used)")
        mesh_paths = [mesh, *(compare or [])]
        labels = _labels(mesh_paths, list(label or []))
        meshes = [_load_mesh(p) for p in mesh_paths]
        T_world_cam = pose_from_tum_index(pose) if pose is not None else (
            parse_look_at(look_at_) if look_at_ is not None else None)

        input_rgb = None
        if capture is not None:
            cap = open_capture(capture)
            index = 0 if frame is None else frame
            if not -len(cap) <= index < len(cap):
                raise ValidationError("--frame", f"frame {index} is out of range: {capture} has {len(cap)} frames "
                                                 f"(0..{len(cap) - 1})")
            f = cap[index]
            width, height = (f.width, f.height) if size is None else parse_size(size)
            K = scale_intrinsics(f.K, (f.width, f.height), (width, height))
            input_rgb = f.color
            if T_world_cam is None:
                T_world_cam = f.T_world_cam if f.T_world_cam is not None else f.T_world_cam_device
            if T_world_cam is None:
                typer.echo(f"note: frame {index} of {capture} has no pose; using the automatic overview")
        else:
            width, height = DEFAULT_SIZE if size is None else parse_size(size)
            K = intrinsics_from_fov(width, height, DEFAULT_FOV_DEG if fov_deg is None else fov_deg)

        overview = T_world_cam is None
        if overview:
            T_world_cam = overview_pose(meshes, K, width, height, up=parse_vector(up, "--up"))
        cull = overview if cull_back_faces is None else cull_back_faces
        for p, m in zip(mesh_paths, meshes, strict=True):
            if len(m.faces) == 0:
                typer.echo(f"note: {p} has no triangles; its panel is background only")
        written = write_mesh_pictures(out.parent, dict(zip(labels, meshes, strict=True)), K, T_world_cam, width,
                                      height, input_rgb=input_rgb, name=out.name, cull_back_faces=cull)
        n_panels = len(meshes) + (input_rgb is not None)
        typer.echo(f"wrote {written} ({n_panels} panel{'s' * (n_panels > 1)} of {width}x{height})")
    except VoxFusionError as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from e


def register(app: typer.Typer) -> None:
    """Add ``view`` to the ``voxfusion`` app."""
    app.command("view")(view_command)
