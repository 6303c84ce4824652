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

from voxfusion.commands.eval import register
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
    trimesh.creation.icosphere(subdivisions=3, radius=1.02).export(paths["mesh"])
    return paths


def test_eval_trajectory_and_mesh(app, files, tmp_path):
    out = tmp_path / "report.json"
    result = CliRunner().invoke(app, [
        "eval", "--traj", str(files["est"]), "--gt", str(files["gt"]), "--mesh", str(files["mesh"]),
        "--gt-mesh", str(files["gt_mesh"]), "--samples", "2000", "--json", str(out),
    ])
    assert result.exit_code == 0, result.output
    assert "ATE rmse [cm] (align se3)" in result.output
    assert "accuracy [cm]" in result.output and "sampled" in result.output
    ate_line = next(line for line in result.output.splitlines() if line.startswith("ATE rmse"))
    assert float(ate_line.split()[-1]) == pytest.approx(1.0, abs=0.05)
    data = json.loads(out.read_text())
    ate = data["trajectory"]["ate"]
    assert ate["n"] == 30 and ate["rmse_m"] == pytest.approx(0.01, abs=5e-4)
    assert data["trajectory"]["rpe"]["delta"] == 1
    assert data["trajectory"]["estimate"] == str(files["est"])
    assert data["mesh"]["exact"]["accuracy_m"] == pytest.approx(0.02, abs=1e-3)
    assert data["mesh"]["sampled"]["accuracy_m"] > data["mesh"]["exact"]["accuracy_m"]
    assert data["mesh"]["exact"]["n_samples"] == 2000


def test_default_json_beside_estimate_and_align_modes(app, files):
    runner = CliRunner()
    result = runner.invoke(app, ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]),
                                 "--align", "none", "--delta", "2"])
    assert result.exit_code == 0, result.output
    data = json.loads((files["est"].parent / "eval.json").read_text())
    assert data["trajectory"]["align"] == "none"
    assert data["trajectory"]["ate"]["aligned"] is False
    assert data["trajectory"]["rpe"]["delta"] == 2
    assert "mesh" not in data
    result = runner.invoke(app, ["eval", "--traj", str(files["est"]), "--gt", str(files["gt"]),
                                 "--align", "sim3"])
    assert result.exit_code == 0 and "Sim(3) scale" in result.output
    result = runner.invoke(app, ["eval", "--mesh", str(files["mesh"]), "--gt-mesh", str(files["gt_mesh"]),
                                 "--samples", "500"])
    assert result.exit_code == 0, result.output
    assert "ATE" not in result.output and "F-score" in result.output
    assert "mesh" in json.loads((files["mesh"].parent / "eval.json").read_text())


def test_errors_exit_2_and_name_the_problem(app, files, tmp_path):
    runner = CliRunner()
    missing = tmp_path / "missing_traj.txt"
    result = runner.invoke(app, ["eval", "--traj", str(missing), "--gt", str(files["gt"])])
    assert result.exit_code == 2
    assert "missing_traj.txt" in result.stderr and "not found" in result.stderr
    result = runner.invoke(app, ["eval", "--mesh", str(tmp_path / "nomesh.ply"),
                                 "--gt-mesh", str(files["gt_mesh"])])
    assert result.exit_code == 2 and "nomesh.ply" in result.stderr
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
