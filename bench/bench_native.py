"""The engine's C kernels (``core/native``) against the PyTorch operators they replace, in one process.

Two measurements on the synthetic room (320x240, the preset ``voxfusion run`` picks on a CPU, ``synthetic+cpu``):

* **a mapping iteration** (:meth:`~voxfusion.core.slam.mapping.Mapper.step` on the window of a map fused from the
  first 30 frames at their reference poses): rounds of ``--step-calls`` steps with the kernels on and off in turn
  (``VOXFUSION_NATIVE``), medians of the rounds' mean milliseconds per step;
* **whole frames**: two engines, one with the kernels and one without, given each frame in turn (the order swapped
  every frame, as ``bench/fps_pair.py`` pairs methods), frames/s of each and their ratio, with the ratio over
  10-frame blocks; both engines' ATE as a sanity check (the kernels round differently, so trajectories differ
  within a seed's spread).

"Without" is what a CPU ran before the kernels: the interpolation and the compositing and losses as PyTorch
operators through autograd (``VOXFUSION_NATIVE=0`` and the unfused compositing of :func:`~voxfusion.core.slam.mapping
.band_loss`); "with" is the default. Usage (from the repository root)::

    python bench/bench_native.py --seed 1           # writes bench/results/native_kernels_seed1.json

Numbers belong to the machine in the JSON; the ratios are what carries over.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.fps_pair import block_ratios, interleave  # noqa: E402
from bench.machine import machine_info  # noqa: E402
from voxfusion.core import native  # noqa: E402
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig  # noqa: E402
from voxfusion.core.eval import TrajectoryEvalConfig, compute_ate, write_json  # noqa: E402
from voxfusion.core.framedata import frame_to_device  # noqa: E402
from voxfusion.core.slam import SlamSystem  # noqa: E402
from voxfusion.core.slam import mapping as mapping_module  # noqa: E402
from voxfusion.core.slam.presets import load_preset  # noqa: E402
from voxfusion.core.trajectory import Trajectory  # noqa: E402

PRESET = "synthetic+cpu"
_FUSED_BAND_LOSS = mapping_module.band_loss


def _operators_band_loss(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
    kwargs["fused"] = False
    return _FUSED_BAND_LOSS(*args, **kwargs)


def use_kernels(on: bool) -> None:
    """The C kernels and the fused compositing (on), or the PyTorch operators through autograd (off)."""
    os.environ[native.ENV_SWITCH] = "1" if on else "0"
    mapping_module.band_loss = _FUSED_BAND_LOSS if on else _operators_band_loss


def step_rounds(seed: int, rounds: int, calls: int) -> dict[str, list[float]]:
    """Mean ms per mapping step in ``rounds`` rounds of ``calls`` steps, kernels on and off in turn."""
    cfg = load_preset(PRESET, ["device=cpu"])
    capture = SyntheticCapture(SyntheticConfig(n_frames=31, seed=seed))
    mapper = mapping_module.make_mapper(cfg)
    for frame in capture.frames(0, 30):
        mapper.integrate(frame_to_device(frame, "cpu"), frame.T_world_cam)
    newest = mapper.keyframes[-1]
    out: dict[str, list[float]] = {"kernels": [], "operators": []}
    for on in (True, False):  # warm-up of both paths
        use_kernels(on)
        for _ in range(5):
            mapper.step(mapper._window(newest))
    for _ in range(rounds):
        for name, on in (("kernels", True), ("operators", False)):
            use_kernels(on)
            t0 = time.perf_counter()
            for _ in range(calls):
                mapper.step(mapper._window(newest))
            out[name].append((time.perf_counter() - t0) / calls * 1e3)
    return out


def frame_pairs(seed: int, n_frames: int) -> dict:
    """Two engines over the same frames in turn, one with the kernels and one without."""
    cfg = load_preset(PRESET, ["device=cpu"])
    capture = SyntheticCapture(SyntheticConfig(n_frames=n_frames, seed=seed))
    frames = list(capture.frames(0, n_frames))
    engines = {True: SlamSystem(cfg), False: SlamSystem(cfg)}

    def stepper(on: bool):  # noqa: ANN202
        def step(frame) -> None:  # noqa: ANN001
            use_kernels(on)
            engines[on].process(frame)
        return step

    ms_on, ms_off = interleave(frames, stepper(True), stepper(False))
    use_kernels(True)
    reference = Trajectory(np.array([f.timestamp_s for f in frames]), np.stack([f.T_world_cam for f in frames]))
    ate = {name: compute_ate(engines[on].trajectory(), reference, TrajectoryEvalConfig(align="se3")).rmse_m * 100
           for on, name in ((True, "kernels"), (False, "operators"))}
    blocks = block_ratios(ms_on, ms_off, 10)  # frames/s with the kernels over without, per block
    return {"frames": n_frames, "fps_kernels": n_frames / (ms_on.sum() / 1e3),
            "fps_operators": n_frames / (ms_off.sum() / 1e3), "ratio": float(ms_off.sum() / ms_on.sum()),
            "ratio_per_10_frames": [float(b) for b in blocks], "ate_cm": ate}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--step-calls", type=int, default=20)
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    args = p.parse_args(argv)
    if native.interpolation_kernels() is None or native.band_loss_kernels() is None:
        print("the C kernels are not built here (no C compiler?): nothing to compare", file=sys.stderr)
        return 2
    torch.manual_seed(0)
    steps = step_rounds(args.seed, args.rounds, args.step_calls)
    med = {k: statistics.median(v) for k, v in steps.items()}
    pairs = frame_pairs(args.seed, args.frames)
    result = {
        "name": f"native_kernels_seed{args.seed}",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": shlex.join(["python", "bench/bench_native.py", *(argv if argv is not None else sys.argv[1:])]),
        "machine": machine_info(),
        "preset": PRESET,
        "mapping_step_ms": {"median_kernels": med["kernels"], "median_operators": med["operators"],
                            "ratio": med["operators"] / med["kernels"], "rounds": steps},
        "frames": pairs,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path = write_json(args.out / f"native_kernels_seed{args.seed}.json", result)
    print(f"mapping step: {med['kernels']:.2f} ms with the kernels, {med['operators']:.2f} without "
          f"(x{result['mapping_step_ms']['ratio']:.3f}, medians of {args.rounds} rounds of {args.step_calls})")
    print(f"whole frames: {pairs['fps_kernels']:.2f} frames/s with, {pairs['fps_operators']:.2f} without "
          f"(x{pairs['ratio']:.3f}; per 10 frames {min(pairs['ratio_per_10_frames']):.3f} / "
          f"{float(np.median(pairs['ratio_per_10_frames'])):.3f} / {max(pairs['ratio_per_10_frames']):.3f}); "
          f"ATE cm {pairs['ate_cm']}")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
