"""Where the live web viewer's sources and build live, and whether the build is current.

The viewer is written in ``server/viewer/`` (three.js from npm, bundled by vite) and its build,
``server/viewer/dist/``, is committed: the server serves it as files and needs no Node.js. ``make viewer``
rebuilds it and records the digest of the sources it was built from in ``dist/build-info.json``; a test
checks that digest against the sources, so a change to them without a rebuild fails ``make test``.

``make viewer`` calls :func:`write_build_info` after vite has built ``dist/``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

__all__ = ["VIEWER_DIR", "VIEWER_DIST", "BUILD_INFO", "source_files", "source_digest", "write_build_info"]

VIEWER_DIR = Path(__file__).resolve().parent / "viewer"
"""The viewer's npm project (sources: ``index.html``, ``src/``, ``package.json``, ``package-lock.json``,
``vite.config.js``)."""
VIEWER_DIST = VIEWER_DIR / "dist"
"""The built viewer: ``index.html`` and ``assets/`` (served under ``/viewer/assets/``)."""
BUILD_INFO = VIEWER_DIST / "build-info.json"

_TOP_LEVEL_SOURCES = ("index.html", "package.json", "package-lock.json", "vite.config.js")


def source_files(root: Path = VIEWER_DIR) -> list[Path]:
    """The files the build is made from, in a fixed order."""
    files = [root / name for name in _TOP_LEVEL_SOURCES if (root / name).is_file()]
    files += sorted(p for p in (root / "src").rglob("*") if p.is_file())
    return files


def source_digest(root: Path = VIEWER_DIR) -> str:
    """SHA-256 over the sources' relative paths and bytes."""
    h = hashlib.sha256()
    for path in source_files(root):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


def write_build_info(root: Path = VIEWER_DIR) -> Path:
    """Record the digest of the sources ``dist/`` was just built from."""
    out = root / "dist" / "build-info.json"
    out.write_text(json.dumps({"source_sha256": source_digest(root),
                               "files": [p.relative_to(root).as_posix() for p in source_files(root)]}, indent=1)
                   + "\n")
    return out
