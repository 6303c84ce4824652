"""Render a mesh to a PNG for checking by eye: a thin wrapper around ``voxfusion.core.mesh.view``
(the same ray-cast renderer as ``voxfusion view``, which has more options: poses, captures, comparisons).

    python bench/mesh_view.py out/mesh.ply out/mesh.png [--compare gt.ply] [--elev 35 --azim -60]
                              [--size 960x720] [--up 0,0,1]

The meshes are drawn side by side from one automatic oblique viewpoint that frames them all, with their
vertex colours, headlight shading and correct depth ordering; back faces are culled, so a closed room
shows its inside.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import trimesh

from voxfusion.core.mesh import intrinsics_from_fov, overview_pose, write_mesh_pictures


def render_mesh_png(mesh: trimesh.Trimesh, out: Path, elev: float = 35.0, azim: float = -60.0,
                    title: str = "", size: tuple[int, int] = (960, 720), up: tuple[float, float, float] = (0, 0, 1),
                    others: dict[str, trimesh.Trimesh] | None = None) -> Path:
    """Write a PNG view of ``mesh`` (and ``others``, label -> mesh, beside it) to ``out``."""
    width, height = size
    K = intrinsics_from_fov(width, height, 60.0)
    panels = {title or f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces": mesh, **(others or {})}
    T = overview_pose(list(panels.values()), K, width, height, up=up, elevation_deg=elev, azimuth_deg=azim)
    return write_mesh_pictures(out.parent, panels, K, T, width, height, name=out.name, cull_back_faces=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mesh", type=Path)
    p.add_argument("png", type=Path)
    p.add_argument("--compare", type=Path, nargs="*", default=[], help="meshes drawn beside it")
    p.add_argument("--elev", type=float, default=35.0)
    p.add_argument("--azim", type=float, default=-60.0)
    p.add_argument("--size", default="960x720", help="WIDTHxHEIGHT of each panel")
    p.add_argument("--up", default="0,0,1", help="world up X,Y,Z (0,1,0 for ARKit worlds)")
    p.add_argument("--title", default="")
    a = p.parse_args()
    load = lambda path: trimesh.load(path, process=False, force="mesh")  # noqa: E731
    width, height = (int(v) for v in a.size.lower().split("x"))
    up = tuple(float(v) for v in a.up.split(","))
    others = {str(path): load(path) for path in a.compare}
    print(render_mesh_png(load(a.mesh), a.png, a.elev, a.azim, a.title, (width, height), up, others))


if __name__ == "__main__":
    main()
