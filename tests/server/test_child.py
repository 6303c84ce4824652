"""``voxfusion serve`` as a child process (server/child.py), and ``--zenoh-listen``."""

from __future__ import annotations

import pytest

from voxfusion.core.errors import ConfigError
from voxfusion.server import ServerSettings
from voxfusion.server.child import ServeProcess, ServerStartError

pytest.importorskip("zenoh")

from voxfusion.clients.zenoh_client import ZenohClient  # noqa: E402


def test_serve_with_zenoh_listen_answers_on_that_endpoint_and_stops_cleanly(tmp_path):
    with ServeProcess(tmp_path / "data", zenoh=True) as srv:
        assert srv.health["zenoh"] is True
        client = ZenohClient(connect=[srv.zenoh_endpoint], timeout_s=60)
        try:
            created = client.create_session("child", {"tracking": {"rays": 64}})
            assert client.status().id == created.id
        finally:
            client.close()
    assert srv.proc.returncode == 0, srv.log_tail()


def test_a_child_that_cannot_start_raises_with_its_log(tmp_path):
    with pytest.raises(ServerStartError, match="zenoh_listen"):
        ServeProcess(tmp_path / "data", "--zenoh-listen", "not-an-endpoint", zenoh=True, start_timeout_s=60)


def test_zenoh_listen_setting_is_checked():
    assert ServerSettings(zenoh_listen=["tcp/0.0.0.0:7447"]).zenoh_listen == ("tcp/0.0.0.0:7447",)
    with pytest.raises(ConfigError, match="zenoh_listen"):
        ServerSettings(zenoh_listen=[])


def test_zenoh_listen_with_no_zenoh_is_refused():
    from typer.testing import CliRunner

    from voxfusion.cli import app

    result = CliRunner().invoke(app, ["serve", "--no-zenoh", "--zenoh-listen", "tcp/127.0.0.1:7447"])
    assert result.exit_code == 2
    assert "--no-zenoh" in result.output


def test_serve_on_a_busy_port_is_one_line_before_anything_starts(tmp_path):
    """uvicorn binds after the app's startup (sessions opened, zenoh started, "ready" logged), then exits on
    [Errno 98]; the command checks the port first."""
    import socket

    from typer.testing import CliRunner

    from voxfusion.cli import app

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = CliRunner().invoke(app, ["serve", "--no-zenoh", "--port", str(port), "--data-dir",
                                          str(tmp_path / "data")])
    assert result.exit_code == 2, result.output
    assert f"cannot listen on 127.0.0.1:{port}" in result.output and "--port" in result.output
    assert "server ready" not in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(app, ["serve", "--no-zenoh", "--host", "no-such-host.invalid", "--data-dir",
                                      str(tmp_path / "data")])
    assert result.exit_code == 2 and "cannot resolve --host 'no-such-host.invalid'" in result.output, result.output
