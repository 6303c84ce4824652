"""Render a mesh to a PNG for checking by eye (matplotlib, no display needed).

    python bench/mesh_view.py out/mesh.ply out/mesh.png [--faces 40000] [--elev 35 --azim -60]

Faces are drawn with their vertex colours (random subset when the mesh is large), flat shaded by the
angle to a fixed light, from one oblique viewpoint.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402


def render_mesh_png(mesh: trimesh.Trimesh, out: Path, max_faces: int = 40000, elev: float = 35.0,
                    azim: float = -60.0, title: str = "") -> Path:
    """Write a PNG view of ``mesh`` to ``out``."""
    faces = mesh.faces
    if len(faces) > max_faces:
        faces = faces[np.random.default_rng(0).choice(len(faces), max_faces, replace=False)]
    tris = mesh.vertices[faces]
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3][faces].mean(1) / 255.0
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    shade = 0.45 + 0.55 * np.abs(normals @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    fig = plt.figure(figsize=(9, 7), dpi=110)
    ax = fig.add_subplot(projection="3d")
    ax.add_collection3d(Poly3DCollection(tris, facecolors=np.clip(colors * shade[:, None], 0, 1), linewidths=0))
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    ax.set_title(title or f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, bbox_inches="tight")
    plt.close(fig)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mesh", type=Path)
    p.add_argument("png", type=Path)
    p.add_argument("--faces", type=int, default=40000)
    p.add_argument("--elev", type=float, default=35.0)
    p.add_argument("--azim", type=float, default=-60.0)
    p.add_argument("--title", default="")
    a = p.parse_args()
    mesh = trimesh.load(a.mesh, process=False, force="mesh")
    print(render_mesh_png(mesh, a.png, a.faces, a.elev, a.azim, a.title))


if __name__ == "__main__":
    main()
