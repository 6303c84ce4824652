"""``voxfusion eval`` end to end on files in tmp_path."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh
import typer
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from voxfusion.commands.eval import NOT_CULLED, register
from voxfusion.core.trajectory import Trajectory, write_tum_trajectory


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def root() -> None:
        """Keeps ``eval`` a subcommand (a one-command Typer app would collapse it)."""

    register(app)
    return app


@pytest.fixture()
def files(tmp_path):
    n = 30
    ts = np.arange(n) * 0.1
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", 3.0 * np.arange(n)[:, None], degrees=True).as_matrix()
    T[:, 0, 3] = 0.1 * np.arange(n)
    T[:, 1, 3] = 0.02 * np.arange(n) ** 1.5
    E = T.copy()
    E[:, 2, 3] += 0.01 * (-1.0) ** np.arange(n)  # +-1 cm zig-zag: ATE 1 cm after any alignment
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix()
    G[:3, 3] = [1.0, 2.0, 3.0]
    paths = {
        "gt": write_tum_trajectory(tmp_path / "gt.txt", Trajectory(ts, T)),
        "est": write_tum_trajectory(tmp_path / "run" / "est.txt", Trajectory(ts + 0.004, G @ E)),
        "gt_mesh": tmp_path / "gt.ply",
        "mesh": tmp_path / "run" / "mesh.ply",
    }
    trimesh.creation.icosphere(subdivisions=3, radius=1.0).export(paths["gt_mesh"])
    # The session's mesh lives where its trajectory does: G away from the reference frame.
    trimesh.creation.icosphere(subdivisions=3, radius=1.02).apply_transform(G).export(paths["mesh"])
    return paths


def test_eval_trajectory_and_mesh(app, files, tmp_path):
    out = tmp_path / "report.json"
    args = ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]), "--mesh", str(files["mesh"]),
            "--gt-mesh", str(files["gt_mesh"]), "--samples", "2000"]
    result = CliRunner().invoke(app, [*args, "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "ATE rmse [cm] (align se3)" in result.output
    assert "accuracy [cm]" in result.output and "vs whole GT" in result.output
    assert NOT_CULLED in result.output and "vs observed GT" not in result.output
    assert "mesh aligned with the trajectory's se3 alignment" in result.output
    ate_line = next(line for line in result.output.splitlines() if line.startswith("ATE rmse"))
    assert float(ate_line.split()[-1]) == pytest.approx(1.0, abs=0.05)
    data = json.loads(out.read_text())
    ate = data["trajectory"]["ate"]
    assert ate["n"] == 30 and ate["rmse_m"] == pytest.approx(0.01, abs=5e-4)
    assert data["trajectory"]["rpe"]["delta"] == 1
    assert data["trajectory"]["estimate"] == str(files["est"])
    mesh = data["mesh"]
    assert mesh["alignment"]["applied"] is True and mesh["alignment"]["align"] == "se3"
    assert mesh["alignment"]["message"].startswith("mesh aligned with the trajectory's se3 alignment")
    np.testing.assert_allclose(mesh["alignment"]["T_align"], ate["T_align"])
    lever = mesh["alignment"]["lever"]  # 1 cm residuals, 30 poses along a gently curved 4 m path
    assert 0.1 < lever["rotation_deg"] < 2.0 and lever["reach_m"] > 2.0
    assert ("weakly" in result.stderr) == (lever["mesh_shift_m"] > 0.01)
    full = mesh["mesh_full_gt"]
    assert full["gt_part"] == "full" and "mesh_observed_gt" not in mesh and mesh["gt_culled"] is False
    assert full["accuracy_m"] == pytest.approx(0.02, abs=1e-3)  # the 2 cm radius gap, after alignment
    assert full["method"] == "exact" and full["n_samples"] == 2000
    sampled_out = tmp_path / "sampled.json"
    result = CliRunner().invoke(app, [*args, "--method", "sampled", "--json", str(sampled_out)])
    assert result.exit_code == 0, result.output
    sampled = json.loads(sampled_out.read_text())["mesh"]["mesh_full_gt"]
    assert sampled["method"] == "sampled" and sampled["accuracy_m"] > full["accuracy_m"]


def test_reference_poses_are_interpolated_at_the_estimates_timestamps(app, tmp_path):
    """A 100 Hz reference (as TUM's motion capture) and an estimate that is exactly that motion at camera times
    between its samples: interpolated (the default, as ``voxfusion run`` reads ground truth) the ATE is ~0; paired
    with the nearest reference pose it is the motion of up to 5 ms, ~1 cm here."""
    def motion(t: np.ndarray) -> np.ndarray:
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = Rotation.from_euler("y", 60.0 * t[:, None], degrees=True).as_matrix()
        T[:, 0, 3] = 2.0 * t
        T[:, 2, 3] = 0.5 * t ** 2
        return T

    t_ref = np.arange(0.0, 3.0, 0.01)
    t_est = 0.1 + np.arange(40) * (1 / 30) + 0.0047  # camera frames between the reference's samples
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum_trajectory(gt, Trajectory(t_ref, motion(t_ref)))
    write_tum_trajectory(est, Trajectory(t_est, motion(t_est)))
    np.testing.assert_allclose(Trajectory(t_ref, motion(t_ref)).at(t_est).T_world_cam, motion(t_est), atol=2e-4)
    rmse = {}
    for flag in ("--interpolate", "--no-interpolate"):
        out = tmp_path / f"{flag}.json"
        result = CliRunner().invoke(app, ["eval", "--traj", str(est), "--gt", str(gt), flag, "--json", str(out)])
        assert result.exit_code == 0, result.output
        section = json.loads(out.read_text())["trajectory"]
        assert section["ate"]["n"] == 40
        rmse[flag] = section["ate"]["rmse_m"]
        assert section["reference_poses"].startswith("interpolated" if flag == "--interpolate" else "nearest")
    assert rmse["--interpolate"] < 2e-4 < 5e-3 < rmse["--no-interpolate"]
    # a reference that does not cover the estimate is refused with the way out named
    short = tmp_path / "short.txt"
    write_tum_trajectory(short, Trajectory(t_ref[:5], motion(t_ref[:5])))
    result = CliRunner().invoke(app, ["eval", "--traj", str(est), "--gt", str(short)])
    assert result.exit_code == 2 and "--no-interpolate" in result.output


def test_default_json_beside_estimate_never_overwrites(app, files):
    runner = CliRunner()
    result = runner.invoke(app, ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]),
                                 "--align", "none", "--delta", "2"])
    assert result.exit_code == 0, result.output
    first = files["est"].parent / "eval.json"
    assert f"wrote {first}" in result.output
    data = json.loads(first.read_text())
    assert data["trajectory"]["align"] == "none"
    assert data["trajectory"]["ate"]["aligned"] is False
    assert data["trajectory"]["rpe"]["delta"] == 2
    assert "mesh" not in data
    before = first.read_text()
    result = runner.invoke(app, ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]),
                                 "--align", "sim3"])
    assert result.exit_code == 0 and "Sim(3) scale" in result.output
    second = files["est"].parent / "eval-1.json"
    assert f"wrote {second}" in result.output and first.read_text() == before
    assert json.loads(second.read_text())["trajectory"]["align"] == "sim3"
    result = runner.invoke(app, ["eval", "--mesh", str(files["mesh"]), "--gt-mesh", str(files["gt_mesh"]),
                                 "--samples", "500"])
    assert result.exit_code == 0, result.output
    assert "ATE" not in result.output and "F-score" in result.output
    assert "mesh evaluated as is (no --traj/--gt pair" in result.output
    assert "mesh" in json.loads((files["mesh"].parent / "eval-2.json").read_text())


def test_out_on_an_existing_file_needs_force(app, files, tmp_path):
    out = tmp_path / "mine.json"
    out.write_text("keep me")
    args = ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]), "--out", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2
    assert "mine.json already exists" in result.stderr and "--force" in result.stderr
    assert out.read_text() == "keep me" and "ATE" not in result.output  # refused before any work
    result = CliRunner().invoke(app, [*args, "--force"])
    assert result.exit_code == 0, result.output
    assert json.loads(out.read_text())["trajectory"]["ate"]["n"] == 30


def _se3(rotvec: list[float], t: list[float]) -> np.ndarray:
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    G[:3, 3] = t
    return G


@pytest.mark.parametrize("mode", ["se3", "sim3"])
def test_align_moves_the_mesh_with_the_trajectory(app, tmp_path, mode):
    n = 20
    ts = np.arange(n) * 0.1
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("y", 4.0 * np.arange(n)[:, None], degrees=True).as_matrix()
    T[:, 0, 3] = 0.1 * np.arange(n)
    T[:, 2, 3] = 0.05 * np.arange(n) ** 1.2
    G = _se3([0.4, -0.3, 0.2], [2.0, -1.0, 0.5])  # reference -> session world
    s = 1.0 if mode == "se3" else 0.5  # the session's metres are half the reference's (sim3)
    E = G @ T
    E[:, :3, 3] *= s
    gt = trimesh.creation.box(extents=(1.0, 0.8, 0.6))
    S = np.diag([s, s, s, 1.0]) @ G
    paths = {"gt": write_tum_trajectory(tmp_path / "gt.txt", Trajectory(ts, T)),
             "est": write_tum_trajectory(tmp_path / "run" / "traj.txt", Trajectory(ts, E)),
             "gt_mesh": tmp_path / "gt.ply", "mesh": tmp_path / "run" / "mesh.ply"}
    gt.export(paths["gt_mesh"])
    gt.copy().apply_transform(S).export(paths["mesh"])
    base = ["eval", "--traj", str(paths["est"]), "--gt", str(paths["gt"]), "--mesh", str(paths["mesh"]),
            "--gt-mesh", str(paths["gt_mesh"]), "--samples", "1000"]

    def run(align: str) -> dict:
        out = tmp_path / f"{align}.json"
        result = CliRunner().invoke(app, [*base, "--align", align, "--out", str(out)])
        assert result.exit_code == 0, result.output
        return json.loads(out.read_text())["mesh"]

    aligned = run(mode)
    assert aligned["alignment"]["applied"] and aligned["alignment"]["scale"] == pytest.approx(1 / s, rel=1e-6)
    assert aligned["mesh_full_gt"]["accuracy_m"] < 1e-4 and aligned["mesh_full_gt"]["completion_m"] < 1e-4
    as_is = run("none")
    assert not as_is["alignment"]["applied"] and as_is["alignment"]["message"] == "mesh evaluated as is (--align none)"
    assert as_is["mesh_full_gt"]["accuracy_m"] > 0.5
    if mode == "sim3":  # a rigid fit cannot undo the scale
        assert run("se3")["mesh_full_gt"]["accuracy_m"] > 0.05


def test_sidecar_brings_the_mesh_to_world_axes_and_warns_when_not_reference(app, tmp_path):
    gt = trimesh.creation.box(extents=(1.0, 0.8, 0.6))
    gt.apply_translation([0.5, 0.2, 1.0])
    gt_path, mesh_path = tmp_path / "gt.ply", tmp_path / "session" / "mesh.glb"
    mesh_path.parent.mkdir()
    gt.export(gt_path)
    M = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # Y-up file -> Z-up world
    gt.copy().apply_transform(np.linalg.inv(M)).export(mesh_path)
    args = ["eval", "--mesh", str(mesh_path), "--gt-mesh", str(gt_path), "--samples", "1000"]

    def run(*extra: str) -> tuple[dict, str]:
        out = tmp_path / f"r{len(list(tmp_path.glob('r*.json')))}.json"
        result = CliRunner().invoke(app, [*args, *extra, "--out", str(out)])
        assert result.exit_code == 0, result.output
        return json.loads(out.read_text())["mesh"], result.stderr

    plain, _ = run()
    assert plain["frame"]["sidecar"] is None and plain["mesh_full_gt"]["accuracy_m"] > 0.1
    side = mesh_path.with_name("mesh.glb.frame.json")
    side.write_text(json.dumps({"T_world_file": M.tolist(), "world": "reference"}))
    fixed, err = run()
    assert fixed["frame"]["world"] == "reference" and fixed["mesh_full_gt"]["accuracy_m"] < 1e-4
    assert "warning" not in err and fixed["warnings"] == []
    side.write_text(json.dumps({"T_world_file": M.tolist(), "world": "first_camera"}))
    foreign, err = run()
    assert "not in the reference frame" in err and "meaningless" in err and "--align" in err
    assert any("first_camera" in w for w in foreign["warnings"])


def test_errors_exit_2_and_name_the_problem(app, files, tmp_path):
    runner = CliRunner()
    missing = tmp_path / "missing_traj.txt"
    result = runner.invoke(app, ["eval", "--traj", str(missing), "--gt", str(files["gt"])])
    assert result.exit_code == 2
    assert "missing_traj.txt" in result.stderr and "not found" in result.stderr
    result = runner.invoke(app, ["eval", "--mesh", str(tmp_path / "nomesh.ply"),
                                 "--gt-mesh", str(files["gt_mesh"])])
    assert result.exit_code == 2 and "nomesh.ply" in result.stderr
    binary = tmp_path / "mesh_as_traj.ply"  # a mesh given as the trajectory: named, no traceback
    binary.write_bytes(b"ply\nformat binary_little_endian 1.0\n\xbf\xff\x00\x81")
    result = runner.invoke(app, ["eval", "--traj", str(binary), "--gt", str(files["gt"])])
    assert result.exit_code == 2 and "mesh_as_traj.ply" in result.stderr and "not a text file" in result.stderr
    # Timestamps that associate with nothing: a ValidationError naming the trajectory.
    far = Trajectory(np.arange(5) + 1000.0, np.tile(np.eye(4), (5, 1, 1)))
    far_path = write_tum_trajectory(tmp_path / "far.txt", far)
    result = runner.invoke(app, ["eval", "--traj", str(far_path), "--gt", str(files["gt"])])
    assert result.exit_code == 2 and "estimate trajectory" in result.stderr
    result = runner.invoke(app, ["eval", "--traj", str(files["est"])])
    assert result.exit_code == 2 and "--gt" in result.stderr
    result = runner.invoke(app, ["eval"])
    assert result.exit_code == 2 and "nothing to evaluate" in result.stderr
    result = runner.invoke(app, ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]),
                                 "--align", "affine"])
    assert result.exit_code == 2  # rejected by the option's choices


def test_installed_command_end_to_end(files, tmp_path):
    """The real entry point (``python -m voxfusion.cli``), as a user runs it."""
    cmd = [sys.executable, "-m", "voxfusion.cli", "eval",
           "--traj", str(files["est"]), "--gt", str(files["gt"])]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "ATE rmse" in done.stdout
    assert (files["est"].parent / "eval.json").is_file()
    missing = tmp_path / "absent_gt.txt"
    done = subprocess.run(cmd[:-1] + [str(missing)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "absent_gt.txt" in done.stderr


# ---------------------------------------------------------------------------------------------------
# With a capture: GT culling, phantom share, and the same numbers as ``voxfusion run``'s evaluation.


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from voxfusion.core.datasets import open_capture
    from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
    from voxfusion.core.eval import cull_to_views, views_from_capture

    root = tmp_path_factory.mktemp("room")
    cap_dir = write_capture(SyntheticCapture(SyntheticConfig(n_frames=6, width=40, height=30)), root / "room")
    gt = trimesh.load(cap_dir / "gt_mesh.ply", force="mesh", process=False).subdivide().subdivide()
    # The estimate: the GT triangles the cameras saw, 1 cm off (a reconstruction of what was observed).
    seen = cull_to_views(gt.triangles_center, views_from_capture(open_capture(cap_dir)))
    est = gt.submesh([np.nonzero(seen)[0]], append=True)
    est.apply_translation([0.01, 0.0, 0.0])
    mesh_path = root / "run" / "mesh.ply"
    mesh_path.parent.mkdir()
    est.export(mesh_path)
    return {"capture": cap_dir, "gt_mesh": cap_dir / "gt_mesh.ply", "mesh": mesh_path, "root": root}


def test_eval_with_capture_matches_run_evaluation(app, room, tmp_path):
    from voxfusion.core.datasets import open_capture
    from voxfusion.core.eval import load_mesh, to_jsonable
    from voxfusion.core.run import evaluate_mesh, evaluate_phantom, evaluate_run, reference_trajectory

    out = tmp_path / "eval.json"
    result = CliRunner().invoke(app, ["eval", "--mesh", str(room["mesh"]), "--gt-mesh", str(room["gt_mesh"]),
                                      "--capture", str(room["capture"]), "--samples", "3000", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "vs observed GT" in result.output and "vs whole GT" in result.output and NOT_CULLED not in result.output
    assert "phantom surface:" in result.output
    data = json.loads(out.read_text())["mesh"]
    observed, full = data["mesh_observed_gt"], data["mesh_full_gt"]
    # 6 frames see a corner of the room: completion asks much less of the observed part.
    assert observed["gt_part"] == "observed" and full["gt_part"] == "full"
    assert observed["completion_ratio"] > 0.9 and full["completion_ratio"] < 0.3
    assert observed["n_gt_samples"] < 0.7 * full["n_gt_samples"]
    assert data["gt_culled"] is True and data["n_views"] == 6

    cap = open_capture(room["capture"])
    mesh = load_mesh(room["mesh"])
    run_mesh = evaluate_mesh(mesh, cap, len(cap), mesh_samples=3000)
    assert to_jsonable(run_mesh) == {"mesh_full_gt": full, "mesh_observed_gt": observed}  # identical numbers
    run_phantom = evaluate_phantom(mesh, cap, len(cap), None, mesh_samples=3000)["phantom"]
    assert to_jsonable(run_phantom) == data["phantom"]
    assert data["phantom"]["poses"] == "reference" and data["phantom"]["share"] < 0.3
    # The whole GT room as the "reconstruction": its unseen walls are phantom (only ~20 % of it was seen).
    whole = evaluate_phantom(load_mesh(room["gt_mesh"]), cap, len(cap), None, mesh_samples=3000)["phantom"]
    assert whole.share > 0.6 and whole.share > data["phantom"]["share"] + 0.4

    # voxfusion run's evaluation (the reference poses standing in for the estimate): same keys and figures.
    ref = reference_trajectory(cap, len(cap))
    metrics = evaluate_run(ref, mesh, cap, len(cap), mesh_samples=3000)
    assert to_jsonable(metrics["mesh_observed_gt"]) == observed
    assert metrics["phantom"].poses == "estimate"
    assert metrics["phantom"].share == pytest.approx(data["phantom"]["share"], abs=1e-3)
    # ... and eval with that trajectory as --traj places the depth the same way.
    traj_path = write_tum_trajectory(tmp_path / "traj.txt", ref)
    out2 = tmp_path / "eval2.json"
    result = CliRunner().invoke(app, ["eval", "--mesh", str(room["mesh"]), "--capture", str(room["capture"]),
                                      "--traj", str(traj_path), "--samples", "3000", "--out", str(out2)])
    assert result.exit_code == 0, result.output
    assert "--traj poses" in result.output and "pass --gt-mesh" in result.output  # phantom only, GT hinted
    only = json.loads(out2.read_text())["mesh"]
    assert "mesh_full_gt" not in only and only["phantom"]["poses"] == "estimate"
    assert only["phantom"]["share"] == pytest.approx(metrics["phantom"].share, abs=1e-3)


def test_capture_without_poses_needs_traj(app, room, tmp_path):
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(room["capture"], bare)
    (bare / "groundtruth.txt").unlink()
    (bare / "gt_mesh.ply").unlink()
    result = CliRunner().invoke(app, ["eval", "--mesh", str(room["mesh"]), "--capture", str(bare),
                                      "--samples", "500", "--out", str(tmp_path / "x.json")])
    assert result.exit_code == 2
    assert "no reference poses" in result.stderr and "--traj" in result.stderr
    result = CliRunner().invoke(app, ["eval", "--mesh", str(room["mesh"])])
    assert result.exit_code == 2 and "--gt-mesh" in result.stderr and "--capture" in result.stderr
    result = CliRunner().invoke(app, ["eval", "--capture", str(bare), "--traj", str(tmp_path / "t.txt")])
    assert result.exit_code == 2
