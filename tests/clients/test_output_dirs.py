"""Output folders shared by commands: ``voxfusion stream`` into a ``voxfusion run`` folder (the README's old
``--out out/desk`` twice) is refused before any session exists, and ``--force`` leaves no stale run output
beside the streamed mesh; ``voxfusion run`` refuses a stream's folder; the rule itself."""

from __future__ import annotations

import json

import pytest
from clientutil import TINY, LiveServer
from typer.testing import CliRunner

from voxfusion.cli import app
from voxfusion.commands.outputs import OUTPUT_FILES, claim_output_dir, foreign_outputs
from voxfusion.core.datasets.synthetic import SyntheticCapture, SyntheticConfig, write_capture
from voxfusion.core.errors import ValidationError

SETS = [arg for item in TINY for arg in ("--set", item)]
RUN_SETS = [arg for item in ("mapping.first_frame_iters=3", "mapping.iters=1", "mapping.rays_per_frame=64",
                             "tracking.iters=2", "tracking.rays=64", "mesh_res=2", "field.sdf_hidden=16",
                             "field.color_hidden=16") for arg in ("--set", item)]


def _touch(folder, *names):
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text("x")


def test_other_commands_outputs_are_refused_and_forced_away(tmp_path):
    out = tmp_path / "desk"
    _touch(out, *OUTPUT_FILES["run"], "eval.json", "eval-2.json", "evaluation.json", "notes.txt")
    with pytest.raises(ValidationError) as err:
        claim_output_dir(out, "stream")
    assert err.value.field == "out"
    assert "voxfusion run: trajectory.png" in str(err.value) and "metrics.json" in str(err.value)
    assert "voxfusion eval: eval-2.json, eval.json" in str(err.value) and "evaluation.json" not in str(err.value)
    assert (out / "metrics.json").exists()  # refusing touches nothing
    removed = {p.name for p in claim_output_dir(out, "stream", force=True)}
    assert removed == set(OUTPUT_FILES["run"]) - set(OUTPUT_FILES["stream"]) | {"eval.json", "eval-2.json"}
    assert sorted(p.name for p in out.iterdir()) == ["evaluation.json", "mesh.ply", "notes.txt", "trajectory.txt"]
    assert claim_output_dir(out, "run") == []  # what is left is the run's own (rewritten) or nobody's
    assert claim_output_dir(tmp_path / "absent", "run") == [] and claim_output_dir(None, "run") == []


def test_the_same_command_may_rewrite_its_folder_and_bridge_is_stream(tmp_path):
    out = tmp_path / "live"
    _touch(out, *OUTPUT_FILES["stream"])
    assert foreign_outputs(out, "stream") == {} and foreign_outputs(out, "bridge") == {}
    assert set(foreign_outputs(out, "run").values()) == {"stream"}  # session.json: another session's
    assert [p.name for p in foreign_outputs(out, "map")] == ["session.json"]
    with pytest.raises(ValidationError) as err:
        foreign_outputs(out, "view")
    assert err.value.field == "command"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    srv = LiveServer(tmp_path_factory.mktemp("outdirs") / "data")
    yield srv
    srv.stop()


def test_stream_into_a_run_folder(server, tmp_path):
    capture = write_capture(SyntheticCapture(SyntheticConfig(n_frames=3, width=32, height=24)), tmp_path / "room")
    out = tmp_path / "desk"
    result = CliRunner().invoke(app, ["run", str(capture), "--out", str(out), *RUN_SETS])
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert (out / "metrics.json").exists() and (out / "trajectory.png").exists()

    sessions = len(server.manager.store.all())
    args = ["stream", str(capture), "--server", server.url, "--out", str(out), *SETS]
    result = CliRunner().invoke(app, args)
    assert isinstance(result.exception, ValidationError) and result.exception.field == "out", result.output
    assert "metrics.json" in str(result.exception)
    assert len(server.manager.store.all()) == sessions  # refused before any session was created
    assert (out / "metrics.json").exists()

    result = CliRunner().invoke(app, [*args, "--force"])
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "--force: deleted" in result.output and "metrics.json" in result.output
    left = sorted(p.name for p in out.iterdir())
    assert left == ["mesh.ply", "session.json", "trajectory.txt"], left  # nothing of the run's is left
    sid = json.loads((out / "session.json").read_text())["id"]
    assert server.manager.status(sid).state.value == "finished"

    # and back: a run into the stream's folder is refused (its session.json names another result)
    result = CliRunner().invoke(app, ["run", str(capture), "--out", str(out), *RUN_SETS])
    assert isinstance(result.exception, ValidationError) and "session.json" in str(result.exception)
