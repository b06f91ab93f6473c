"""Fuzzing every route of the daemon from its OpenAPI schema: schemathesis makes valid
(positive) and invalid (negative) requests — random and boundary JSON bodies, query values,
headers and path ids — and hypothesis runs them against one daemon on the real runner. No answer
is a 500, none takes over a second (a hang guard, as the issue asks), ``/healthz`` answers at
once after every request, and a normal scan still completes afterwards.

Bounded so that the suite stays fast (``SCANSTATION_FUZZ_EXAMPLES`` per route and mode, default
12); scans that the fuzzer starts are cancelled at once (a default plan would train for a
minute on the shared cores).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
import pytest

schemathesis = pytest.importorskip("schemathesis")
from daemon_helpers import capture_plan, station_urls, wait_for_state  # noqa: E402
from fastapi.testclient import TestClient  # noqa: E402
from hypothesis import HealthCheck, assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from capture.daemon.app import create_app  # noqa: E402

EXAMPLES = int(os.environ.get("SCANSTATION_FUZZ_EXAMPLES", "12"))
HANG_S = 1.0  # the bound for any answer: a hang guard, not a speed target
SPEC = create_app(Path("unused")).app.openapi()  # the schema needs no running daemon
OPERATIONS = {f"{op.method.upper()} {op.path}": op for op in (
    result.ok() for result in schemathesis.openapi.from_dict(SPEC).get_all_operations())}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    state_dir = tmp_path_factory.mktemp("fuzz") / "state"
    with TestClient(create_app(state_dir, max_running=1, max_queued=1)) as client:
        client.get("/api/v1/devices")  # the first discovery (USB, network) may take a second
        yield client


def _cancel_everything(client) -> None:
    jobs = client.app.app.state.jobs
    for record in jobs.list(1000, 0):
        if record.state not in ("done", "failed", "interrupted"):
            client.post(f"/api/v1/scans/{record.id}/cancel")


def test_the_schema_covers_every_route():
    assert {"POST /api/v1/scans", "GET /api/v1/scans/{scan_id}/events", "GET /healthz",
            "POST /api/v1/scans/{scan_id}/refine"} <= set(OPERATIONS)


@pytest.mark.parametrize("label", sorted(OPERATIONS))
def test_no_route_answers_500_or_hangs(daemon, label):
    operation = OPERATIONS[label]
    strategy = st.one_of(operation.as_strategy(schemathesis.GenerationMode.POSITIVE),
                         operation.as_strategy(schemathesis.GenerationMode.NEGATIVE))

    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(strategy)
    def check(case):
        kwargs = case.as_transport_kwargs(base_url="http://testserver")
        request = {"method": kwargs["method"], "url": kwargs["url"],
                   "headers": kwargs.get("headers") or {}, "params": kwargs.get("params")}
        if "json" in kwargs:
            request["json"] = kwargs["json"]
        elif kwargs.get("data") is not None:
            request["content"] = kwargs["data"]
        started = time.monotonic()
        try:
            response = daemon.request(**request)
        except (httpx.InvalidURL, httpx.LocalProtocolError, UnicodeEncodeError, ValueError):
            assume(False)  # not sendable over HTTP at all (e.g. a header with a newline)
        took = time.monotonic() - started
        if response.status_code == 201:  # a scan started: stop it (CPU on shared cores)
            daemon.post(f"/api/v1/scans/{response.json()['id']}/cancel")
        assert response.status_code < 500, (case.as_curl_command(), response.text)
        assert took < HANG_S, (case.as_curl_command(), took)
        started = time.monotonic()
        assert daemon.get("/healthz").status_code == 200
        assert time.monotonic() - started < HANG_S

    try:
        check()
    finally:
        _cancel_everything(daemon)


def test_a_normal_scan_completes_after_the_fuzzing(daemon):
    jobs = daemon.app.app.state.jobs
    _cancel_everything(daemon)
    for record in jobs.list(1000, 0):
        wait_for_state(daemon, record.id, "done", "failed", "interrupted", timeout=120)
    created = daemon.post("/api/v1/scans", json={"plan": capture_plan(3), **station_urls()})
    assert created.status_code == 201, created.text
    done = wait_for_state(daemon, created.json()["id"], "done", "failed", timeout=60)
    assert done["state"] == "done", done["reason"]
