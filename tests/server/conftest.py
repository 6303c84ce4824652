"""Fixtures of the server tests (helpers in ``srvutil.py``)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from srvutil import ServerThread

from voxfusion.server import ServerSettings


@pytest.fixture
def server_factory(tmp_path) -> Iterator:
    """Start in-process servers with given settings (data in a temp folder); all stopped afterwards."""
    started: list[ServerThread] = []

    def start(**settings) -> ServerThread:
        settings.setdefault("data_dir", tmp_path / "data")
        settings.setdefault("device", "cpu")
        settings.setdefault("zenoh", False)
        srv = ServerThread(ServerSettings(**settings))
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.stop()
