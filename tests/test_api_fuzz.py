"""The daemon's API fuzzed against its own OpenAPI document (schemathesis, in process).

Every operation gets generated requests, valid and invalid (the document's examples, the
coverage cases, then fuzzing), with the daemon's token, a wrong one or none; every answer
must be no server error, carry a documented status code and content type, and match the
documented schema, and an invalid request must be refused. The daemon runs in process over
ASGI with its lifespan (the simulated rig: the Modbus TCP server on loopback and the
simulated camera).

Nothing is excluded. ``GET /runs/{run_id}/events`` streams until its run ends, but when the
fuzzer calls it every run has ended (each case ends the run it may have started), so the
stream is one event long; the request timeout bounds it anyway.
"""

from __future__ import annotations

import json
import threading
import time
import zlib

import pytest
import schemathesis
from conftest import REDUCED_RIG
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)

from acquisition.daemon.app import create_app
from acquisition.daemon.catalog import CatalogError
from acquisition.daemon.engine import RunConflictError
from acquisition.daemon.settings import load_settings

TOKEN = "fuzz-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
JSON = {"Content-Type": "application/json"}
FINAL = {"complete", "aborted", "failed", "interrupted"}
# Not `positive_data_acceptance`: a schema-valid request may rightly be refused, by a rule
# across fields (poses only with preset "poses"), by the rig (soft limits, collisions: 422)
# or by the rig's state (409 while a test shot, a jog or homing holds the devices).
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    response_schema_conformance,
    content_type_conformance,
    negative_data_rejection,
]


def make_app(data_dir):
    # The host name schemathesis's and Starlette's test clients send.
    settings = load_settings(None, data_dir=data_dir, rig=REDUCED_RIG, token=TOKEN, allowed_hosts=["testserver"])
    settings.arm.simulated.speed_m_s = 0.5
    settings.arm.simulated.accel_m_s2 = 5.0
    settings.arm.simulated.angular_speed_rad_s = 10.0  # a fuzzed jog of up to 100° takes a fraction of a second
    return create_app(settings)


def wait_final(http, run_id, timeout=60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = http.get(f"/runs/{run_id}").json()
        if status["state"] in FINAL:
            return status
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} did not end: {status}")


def abort_active_run(app) -> None:
    """End whatever run a fuzzed request started (or resumed) and empty the queue, so that runs
    stay tiny and the next request sees an idle rig."""
    engine = app.state.engine
    for queued in engine.catalog.queued_runs():
        try:
            engine.remove_queued(queued.id)
        except CatalogError:
            pass  # it started meanwhile: aborted below
    active = engine.catalog.active_run()
    if active is not None and engine.busy:
        try:
            engine.abort(active.id)
        except (RunConflictError, CatalogError):
            pass  # it ended on its own meanwhile
    engine.wait(timeout=30)
    assert not engine.busy


@pytest.fixture(scope="module")
def daemon_app(tmp_path_factory):
    """The daemon under test, its catalog seeded with runs in several states and a job so
    that the fuzzer can aim at ids that exist (its lifespan is run once here to seed it)."""
    app = make_app(tmp_path_factory.mktemp("fuzz") / "data")
    known: dict[str, list[str]] = {"run_id": [], "job_id": []}
    with TestClient(app, headers=AUTH | JSON) as http:
        bracket = {"mode": "fixed", "exposures_s": [0.001]}
        done = http.post("/runs", json={"count": 1, "bracket": bracket}).json()
        assert wait_final(http, done["id"])["state"] == "complete"
        aborted = http.post("/runs", json={"count": 3, "bracket": bracket}).json()
        http.post(f"/runs/{aborted['id']}/abort")
        assert wait_final(http, aborted["id"])["state"] == "aborted"
        job = http.post(f"/runs/{done['id']}/process", json={"steps": "hdr"}).json()
        known["run_id"] += [done["id"], aborted["id"]]
        known["job_id"].append(job["id"])
    app.state.known_ids = known
    yield app
    # Schemathesis starts the lifespan on the first fuzzed request and its pytest plugin
    # ends it after each test; this is the backstop (daemon shutdown: an active run
    # aborted, the simulated devices closed).
    asgi.shutdown_lifespans()
    leftover = [t.name for t in threading.enumerate() if t.name.startswith(("run-", "write-"))]
    assert leftover == [], f"run threads outlived the daemon: {leftover}"


# The daemon's own OpenAPI document (what it serves at /openapi.json; it does not depend on
# the settings, so an app that is never started gives it at collection time). Not
# `from_asgi`, which would start the daemon at collection, nor `schemathesis.pytest.
# from_fixture` (broken on pytest 9.2: `Function._nodeid`). Requests go to the fixture's
# app (`app=` below); schemathesis starts its lifespan on the first one.
schema = schemathesis.openapi.from_dict(make_app("unused").openapi())
schema.config.update(request_timeout=30.0)  # a bound on any request, the event stream included


def pick(case, salt: str, options: list):
    """A choice that is a function of the generated request only: reproducible (and stable
    while Hypothesis shrinks), unlike a draw that ``@schema.given`` would bring (which
    cannot be combined with the schema's own examples)."""
    request = [case.method, case.path_parameters, case.query, case.body]
    key = salt + json.dumps(request, sort_keys=True, default=lambda value: type(value).__name__)
    return options[zlib.crc32(key.encode()) % len(options)]


@schema.parametrize()
@settings(
    max_examples=50,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large],
)
def test_api_conforms_to_its_openapi_document(case, daemon_app):
    # Aim half of the path ids at records that exist, so that the handlers past the 404 run.
    for name, ids in daemon_app.state.known_ids.items():
        if name in (case.path_parameters or {}) and pick(case, name, [True, False]):
            case.path_parameters[name] = pick(case, name + " value", ids)
    # Mostly the daemon's token; sometimes none (401) or a wrong one (403).
    auth = pick(case, "auth", ["good", "good", "good", "none", "wrong"])
    headers = {"good": AUTH, "none": {}, "wrong": {"Authorization": "Bearer not-the-token"}}[auth]
    if case.media_type is None:  # no body: sent as JSON all the same, as a request that changes something must be
        headers = headers | JSON
    try:
        case.call_and_validate(headers=headers, checks=CHECKS, app=daemon_app)
    finally:
        abort_active_run(daemon_app)


# --- explicit checks ---------------------------------------------------------------------
@pytest.fixture()
def http(tmp_path):
    with TestClient(make_app(tmp_path / "data"), headers=AUTH | JSON) as client:
        yield client
        abort_active_run(client.app)


def test_a_bad_exposure_is_a_422_naming_the_field(http):
    answer = http.post("/runs", json={"bracket": {"mode": "fixed", "exposures_s": [-1]}})
    assert answer.status_code == 422, answer.text
    assert "exposures_s" in answer.text
    assert any("exposures_s" in error["loc"] for error in answer.json()["detail"])


def test_an_unknown_field_is_a_422(http):
    answer = http.post("/runs", json={"preset": "light-sweep", "colour": "blue"})
    assert answer.status_code == 422, answer.text
    assert any("colour" in error["loc"] for error in answer.json()["detail"])


def test_a_second_run_while_one_is_active_is_queued_with_a_202(http):
    first = http.post("/runs", json={"bracket": {"mode": "fixed", "exposures_s": [0.001]}})
    assert first.status_code == 201, first.text
    second = http.post("/runs", json={"count": 1})
    assert second.status_code == 202, second.text
    assert second.json()["state"] == "queued" and second.json()["queue_position"] == 1


@pytest.mark.parametrize(
    ("path", "body", "field"),
    [
        ("/runs", '{"count": NaN}', "count"),  # Python's JSON parser takes NaN and Infinity
        ("/runs", '{"bracket": {"mode": "fixed", "exposures_s": [Infinity]}}', "exposures_s"),
        ("/runs", '{"notes": "\\ud800"}', "notes"),  # valid JSON, not valid Unicode
        ("/runs/any/process", '{"steps": "hdr,hdr"}', "steps"),
    ],
)
def test_input_that_strict_json_cannot_echo_is_a_422_not_a_500(http, path, body, field):
    answer = http.post(path, content=body, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422, answer.text
    assert any(field in error["loc"] for error in answer.json()["detail"])


def test_the_token_is_required_to_change_anything(http):
    assert http.post("/runs", json={"count": 1}, headers={"Authorization": ""}).status_code == 401
    assert http.post("/arm/stop", headers={"Authorization": "Bearer wrong"}).status_code == 403
    assert http.get("/runs").status_code == 200
    assert http.get("/runs", headers={"Authorization": ""}).status_code == 401  # the token guards reads too
    assert http.get("/health", headers={"Authorization": ""}).status_code == 200
