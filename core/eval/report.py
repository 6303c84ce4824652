"""Plain-text tables and JSON files for evaluation results (shared by ``voxfusion eval`` and ``bench/``)."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["format_table", "to_jsonable", "write_json"]


def _cell(value: object, float_fmt: str) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return "nan" if math.isnan(value) else format(float(value), float_fmt)
    return str(value)


def format_table(rows: Sequence[Mapping[str, object]], columns: Sequence[str] | None = None,
                 float_fmt: str = ".3f") -> str:
    """Render ``rows`` as an aligned text table.

    Args:
        rows: one mapping per row; missing keys print as ``-``.
        columns: column keys in order (default: the keys of the first row, in order).
        float_fmt: ``format`` spec for floats.

    Numbers are right-aligned, text left-aligned. Example::

        >>> print(format_table([{"metric": "ATE rmse [cm]", "value": 1.5}]))
        metric         value
        -------------  -----
        ATE rmse [cm]  1.500
    """
    columns = list(columns) if columns is not None else (list(rows[0].keys()) if rows else [])
    cells = [[_cell(r.get(c), float_fmt) for c in columns] for r in rows]
    numeric = [
        all(isinstance(r.get(c), int | float | np.number) and not isinstance(r.get(c), bool) for r in rows)
        and bool(rows)
        for c in columns
    ]
    widths = [max([len(str(c))] + [len(row[k]) for row in cells]) for k, c in enumerate(columns)]

    def line(values: Sequence[str]) -> str:
        parts = [v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric, strict=True)]
        return "  ".join(parts).rstrip()

    out = [line([str(c) for c in columns]), "  ".join("-" * w for w in widths)]
    out += [line(row) for row in cells]
    return "\n".join(out)


def to_jsonable(obj: object) -> object:
    """Convert numpy scalars/arrays, dataclasses, paths, tuples and non-finite floats to JSON values.

    NaN and infinities become ``None`` (JSON has no such numbers).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        summary = getattr(obj, "summary", None)
        if callable(summary):
            return to_jsonable(summary())
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, list | tuple | set):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, str):
        return obj
    raise TypeError(f"cannot convert {type(obj).__name__} to JSON")


def write_json(path: str | Path, obj: object) -> Path:
    """Write ``obj`` (see :func:`to_jsonable`) as indented JSON, creating parent folders; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(obj), indent=2) + "\n")
    return path
