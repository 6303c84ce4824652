"""Output folders: a command never leaves another command's results beside its own looking current.

``voxfusion run``, ``map``, ``stream`` and ``bridge`` write fixed file names into ``--out`` (:data:`OUTPUT_FILES`),
and ``voxfusion eval`` writes ``eval.json`` / ``eval-<k>.json`` beside the files it judged. When a folder holds
files of another command that this one does not rewrite (``voxfusion stream`` into a ``voxfusion run`` folder:
the run's ``metrics.json``, ``frames.json``, ``view_*.png``, ``mesh.ply.frame.json`` would stay beside the
streamed mesh and describe the run's), the command refuses the folder before doing any work, naming those files,
unless ``--force``, which deletes exactly them first. Files the command itself rewrites, and files no command
here writes, are never touched.

Refusing (rather than always deleting) keeps one mistyped ``--out`` from destroying a long run's results; the
same command run again into its own folder is not refused (it rewrites its files).

Example::

    removed = claim_output_dir(Path("out/desk"), "stream", force=False)   # ValidationError if run wrote there
"""

from __future__ import annotations

from pathlib import Path

from voxfusion.core.errors import ValidationError

__all__ = ["OUTPUT_FILES", "foreign_outputs", "claim_output_dir"]

_RUN = ("trajectory.txt", "trajectory.png", "keyframes.json", "mesh.ply", "mesh.ply.frame.json", "view_frame.png",
        "view_overview.png", "voxels.npz", "voxels.ply", "checkpoint.pt", "metrics.json", "frames.json")
_MAP = ("mesh.ply", "mesh.ply.frame.json", "view_frame.png", "view_overview.png", "voxels.npz", "voxels.ply",
        "checkpoint.pt", "trajectory.txt", "timings.json", "metrics.json")
_STREAM = ("session.json", "mesh.ply", "trajectory.txt")

OUTPUT_FILES: dict[str, tuple[str, ...]] = {"run": _RUN, "map": _MAP, "stream": _STREAM, "bridge": _STREAM}
"""Command -> the file names it writes into its ``--out`` folder (``bridge`` writes what ``stream`` does)."""


def _eval_reports(out: Path) -> list[Path]:
    """``voxfusion eval``'s default reports in ``out``: ``eval.json``, ``eval-1.json``, ..."""
    return sorted(p for p in out.glob("eval*.json")
                  if p.is_file() and (p.name == "eval.json" or p.stem.removeprefix("eval-").isdigit()))


def foreign_outputs(out: Path, command: str) -> dict[Path, str]:
    """Files in ``out`` that another command wrote and ``command`` does not rewrite -> that command's name.

    Raises:
        ValidationError: ``command`` is not one of :data:`OUTPUT_FILES`.
    """
    if command not in OUTPUT_FILES:
        raise ValidationError("command", f"must be one of {sorted(OUTPUT_FILES)}, got {command!r}")
    if not out.is_dir():
        return {}
    mine = set(OUTPUT_FILES[command])
    found: dict[Path, str] = {}
    for other, names in OUTPUT_FILES.items():
        for name in names:
            path = out / name
            if name not in mine and path not in found and path.is_file():
                found[path] = other
    for path in _eval_reports(out):
        found[path] = "eval"
    return found


def claim_output_dir(out: Path | None, command: str, force: bool = False) -> list[Path]:
    """Make ``out`` ready for ``command``'s outputs (module docstring); returns the files deleted (``force``).

    Raises:
        ValidationError: (field ``out``) ``out`` holds other commands' outputs and ``force`` is not set; the
            message lists them.
    """
    if out is None:
        return []
    found = foreign_outputs(out, command)
    if not found:
        return []
    by_command: dict[str, list[str]] = {}
    for path, other in found.items():
        by_command.setdefault(other, []).append(path.name)
    listing = "; ".join(f"voxfusion {other}: {', '.join(names)}" for other, names in by_command.items())
    if not force:
        raise ValidationError("out", f"{out} holds outputs of another command that `voxfusion {command}` does not "
                                     f"rewrite, so they would describe an older result as if it were this one's "
                                     f"({listing}); choose another --out, or add --force to delete them first")
    for path in found:
        path.unlink()
    return list(found)
