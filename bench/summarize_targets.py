"""One table from the JSON files `bench/engine_targets.sh` wrote: per capture and seed, our ATE and frames/s
beside the TSDF baseline's from the same run, and the relative pose error between consecutive frames (RPE,
translation rmse: the per-frame motion error, independent of any alignment).

Usage: ``python bench/summarize_targets.py`` (prints Markdown; writes ``bench/results/targets_summary.json``).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from voxfusion.core.eval.report import write_json  # noqa: E402

RESULTS = REPO_ROOT / "bench" / "results"


def _method(d: dict, name: str) -> dict | None:
    m = d["methods"].get(name)
    if m is None:
        return None
    ate = m.get("ate_aligned") or {}
    rpe = m.get("rpe") or {}
    mesh = m.get("mesh") or {}
    return {"ate_cm": 100 * ate["rmse_m"] if ate else None,
            "rpe_mm": 1000 * rpe["trans_rmse_m"] if rpe else None,
            "rpe_deg": rpe["rot_rmse_deg"] if rpe else None, "fps": m["fps"],
            "completion_ratio_pct": 100 * mesh["completion_ratio"] if mesh else None,
            "lost": (m.get("extra") or {}).get("frames_lost")}


def main() -> int:
    rows = []
    for path in sorted(RESULTS.glob("targets_*.json")):
        if path.name == "targets_summary.json":
            continue
        d = json.loads(path.read_text())
        match = re.match(r"targets_(.+?)_seed(\d)(.*)$", path.stem)
        capture, seed, variant = (match.group(1), int(match.group(2)), match.group(3).lstrip("_")) if match \
            else (path.stem, 0, "")
        rows.append({"name": path.stem, "capture": capture, "seed": seed, "variant": variant or "default",
                     "voxfusion": _method(d, "voxfusion"), "baseline": _method(d, "baseline"),
                     "machine": d["machine"].get("cpu_model") or d["machine"].get("cpu")})

    def fmt(x: float | None, p: int = 2) -> str:
        return "-" if x is None else f"{x:.{p}f}"

    print("| capture | seed | variant | ATE cm ours | ATE cm baseline | RPE mm/frame ours | RPE mm/frame baseline "
          "| fps ours | fps baseline | completion % ours |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        v, b = r["voxfusion"] or {}, r["baseline"] or {}
        print(f"| {r['capture']} | {r['seed']} | {r['variant']} | {fmt(v.get('ate_cm'))} | {fmt(b.get('ate_cm'))} | "
              f"{fmt(v.get('rpe_mm'))} | {fmt(b.get('rpe_mm'))} | {fmt(v.get('fps'))} | {fmt(b.get('fps'))} | "
              f"{fmt(v.get('completion_ratio_pct'), 1)} |")
    write_json(RESULTS / "targets_summary.json", {"rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
