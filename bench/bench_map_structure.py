"""How often a session's map snapshots change structure: each change is a new capture of the tracker's CUDA graphs.

Usage (from the repository root; any machine, the ``cpu`` sizes)::

    python bench/bench_map_structure.py     # synthetic room and 7-Scenes -> bench/results/map_structure.json
    python bench/bench_map_structure.py --captures synthetic --rounds 100

Each capture's frames are played back and forth (as the GPU suite's realtime feeds are) through an offline
:class:`SlamSystem` at the preset :func:`preset_for` picks on a CPU, one mapping round per frame; every new snapshot's
:func:`~voxfusion.core.slam.tracking_graphs.map_signature` is compared with the previous one's, with the static map's
spare rows and the aligned level-0 grid box (the defaults), without spare rows (capacity = rows), and with the grid's
tight box (:data:`~voxfusion.core.map.voxel_map.LEVEL0_GRID_ALIGN` = 1), in the same run. The second half of the
rounds replays frames the map has seen (what a camera revisiting mapped space does). Allocation is the same at GPU
sizes (same voxels), so the counts stand for a GPU session's recaptures per mapping round.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from bench.gpu_suite import feed_order  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.core.datasets import open_capture  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval.report import write_json  # noqa: E402
from voxfusion.core.map import voxel_map  # noqa: E402
from voxfusion.core.slam import SlamSystem, tracking_graphs  # noqa: E402
from voxfusion.core.slam.presets import preset_for  # noqa: E402

SEVENSCENES = REPO_ROOT.parent / "shared" / "data" / "sevenscenes_redkitchen"


VARIANTS = ("spare rows", "exact rows", "tight grid")


def signatures(snapshot) -> tuple[tuple, tuple, tuple]:  # noqa: ANN001
    """Map signatures of a snapshot for :data:`VARIANTS`: as the tracker's graphs see it (spare rows, aligned grid
    box), without spare rows, and with a tight grid box (built afresh on a shallow copy of the snapshot's map)."""
    spare = tracking_graphs.map_signature(snapshot.voxels, snapshot.decoder)
    default = tracking_graphs._capacity
    tracking_graphs._capacity = lambda rows: rows
    try:
        exact = tracking_graphs.map_signature(snapshot.voxels, snapshot.decoder)
    finally:
        tracking_graphs._capacity = default
    tight_map = object.__new__(type(snapshot.voxels))
    tight_map.__dict__.update(snapshot.voxels.__dict__)
    tight_map._grids = {}
    align = voxel_map.LEVEL0_GRID_ALIGN
    voxel_map.LEVEL0_GRID_ALIGN = 1
    try:
        tight = tracking_graphs.map_signature(tight_map, snapshot.decoder)
    finally:
        voxel_map.LEVEL0_GRID_ALIGN = align
    return spare, exact, tight


def count_changes(capture, rounds: int) -> dict:  # noqa: ANN001
    frames = [capture[i] for i in range(len(capture))]
    slam = SlamSystem(preset_for(capture, "cpu", ["mode=offline"]).config)
    last, previous, changes = None, None, {name: [] for name in VARIANTS}
    for frame in feed_order(frames, rounds, 30.0):
        slam.process(frame)
        snap = slam.snapshot
        if snap is last:
            continue
        sig = signatures(snap)
        if previous is not None:
            for name, now, before in zip(VARIANTS, sig, previous, strict=True):
                changes[name].append(now != before)
        last, previous = snap, sig
    n_voxels = slam.snapshot.voxels.n_voxels
    slam.close()
    out = {"capture": capture.name, "frames": len(frames), "snapshots": len(changes["spare rows"]) + 1,
           "voxels_at_end": n_voxels}
    for name, flags in changes.items():
        half = len(flags) // 2
        out[name] = {"structure_changes": int(sum(flags)), "in_second_half": int(sum(flags[half:])),
                     "second_half_snapshots": len(flags) - half}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="*", default=["synthetic", "sevenscenes"],
                    choices=["synthetic", "sevenscenes"])
    ap.add_argument("--rounds", type=int, default=200, help="frames fed (one mapping round each)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "map_structure.json")
    args = ap.parse_args(argv)
    rows = []
    for name in args.captures:
        if name == "synthetic":
            cap = SyntheticCapture(SyntheticConfig(n_frames=60, width=320, height=240))
        elif SEVENSCENES.is_dir():
            cap = open_capture(SEVENSCENES, limit=100)
        else:
            print(f"skipped sevenscenes: {SEVENSCENES} is absent")
            continue
        row = count_changes(cap, args.rounds)
        rows.append(row)
        counts = ", ".join(f"{name} {row[name]['structure_changes']} ({row[name]['in_second_half']} in the second half)"
                           for name in VARIANTS)
        print(f"{row['capture']}: {row['snapshots']} snapshots; structure changes: {counts}", flush=True)
    write_json(args.out, {"benchmark": "map_structure", "machine": machine_info(), "command": " ".join(sys.argv),
                          "rounds": args.rounds, "captures": rows})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
