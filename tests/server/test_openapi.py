"""The OpenAPI schema against the live server, with schemathesis: for generated requests to every operation
(valid and invalid ones), the answer's status code is one the schema documents for that operation, no answer
is a 5xx, and error bodies are ``ErrorOut``.

Requests on one session (``{session_id}``) are aimed at a real session with its token half of the time (so the
handlers, not only the token check, see the generated bodies); ``finish`` and ``DELETE`` keep their generated
ids so that the session survives the run. The server has room for every session the run creates (a 503 for a
full server is documented, but it is a 5xx).
"""

from __future__ import annotations

import random

import pytest
from srvutil import FAST, ServerThread, make_scene

from voxfusion.server import ServerSettings

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from schemathesis.checks import not_a_server_error, response_schema_conformance, status_code_conformance  # noqa: E402

_SERVER: dict = {}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    srv = ServerThread(ServerSettings(data_dir=tmp_path_factory.mktemp("openapi") / "data", device="cpu", zenoh=False,
                                      max_sessions=32))
    sid, token = srv.api.create("fuzzed", config=FAST, mode="offline")
    scene = make_scene(2, seed=51)
    for m in scene.messages:
        assert srv.api.post_frame(sid, token, m).status_code == 202
    _SERVER.update(srv=srv, sid=sid, token=token)
    yield srv
    srv.stop()


def _fuzz(op, failures: list[str], answered: list[tuple[str, int]]) -> None:
    """Send generated requests to one operation; failures and answers are appended to the lists."""
    label = f"{op.method.upper()} {op.path}"

    @given(case=op.as_strategy())
    @settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True,
              database=None)
    def run(case):
        rng = random.Random(f"{case.path_parameters}{str(case.body)[:64]}")
        own = case.method.upper() != "DELETE" and not case.path.endswith("/finish")
        if "session_id" in (case.path_parameters or {}) and own and rng.random() < 0.5:
            case.path_parameters["session_id"] = _SERVER["sid"]
            case.headers = {**(case.headers or {}), "Authorization": f"Bearer {_SERVER['token']}"}
        response = case.call_and_validate(checks=[not_a_server_error, status_code_conformance,
                                                  response_schema_conformance])
        answered.append((op.path, response.status_code))

    try:
        run()
    except (Exception, BaseExceptionGroup) as e:  # noqa: BLE001 - hypothesis re-raises the failing example
        causes = "".join(f"\n  caused by {type(c).__name__}: {str(c)[:600]}" for c in getattr(e, "exceptions", ()))
        failures.append(f"{label}: {type(e).__name__}: {str(e)[:600]}{causes}")


def test_every_answer_is_documented_and_no_5xx(live):
    api_schema = schemathesis.openapi.from_url(f"{live.url}/openapi.json")
    operations = [result.ok() for result in api_schema.get_all_operations()]
    assert len(operations) >= 15
    failures: list[str] = []
    answered: list[tuple[str, int]] = []
    for op in operations:
        _fuzz(op, failures, answered)
    assert not failures, "\n\n".join(failures)
    # the run reached the handlers: answers from every operation, and more than refusals
    assert {path for path, _ in answered} == {op.path for op in operations}
    statuses = {code for _, code in answered}
    assert {200, 202, 401, 404, 422} <= statuses, sorted(statuses)
    print(f"{len(answered)} answers over {len(operations)} operations; statuses {sorted(statuses)}")
