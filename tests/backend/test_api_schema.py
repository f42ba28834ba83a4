"""The REST API against its own OpenAPI schema (schemathesis), and bad input by hand.

A real service (uvicorn on a free port, Zenoh on loopback) with a token; schemathesis
generates requests from /openapi.json for every operation, with and without the token.
The bar: no 5xx, ever. Bad bodies, unknown sessions, broken YAML and oversized uploads
are 4xx whose ``detail`` says what to fix.
"""

from __future__ import annotations

from collections import Counter

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings

TOKEN = "schema-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def api(tmp_path_factory, lab_dir):
    s = ServiceSettings.load(
        None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)},
        state_dir=tmp_path_factory.mktemp("state"), token=TOKEN, site="schema",
        camera_files={"lab_intrinsics": lab_dir / "intrinsics.yaml", "lab_reference": lab_dir / "reference.yaml"})
    with ServiceThread(s) as st:
        yield st


def test_no_server_errors(api):
    """Every operation of the schema, examples generated from it (schemathesis), with
    and without the token: never a 5xx, and every 4xx says why."""
    # /events is an endless stream: it has its own tests (test_api.py)
    schema = schemathesis.openapi.from_url(api.url + "/openapi.json").exclude(path="/events")
    ops = [r.ok() for r in schema.get_all_operations()]
    assert len(ops) >= 7, [o.label for o in ops]
    calls = Counter()

    for op in ops:
        @given(case=op.as_strategy())
        @settings(max_examples=30, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        def check(case):
            for headers in (AUTH, None):
                r = case.call(base_url=api.url, headers=headers, timeout=30)
                calls[r.status_code // 100] += 1
                assert r.status_code < 500, f"{case.method} {case.formatted_path} -> {r.status_code}: {r.text[:300]}"
                if r.status_code >= 400:
                    assert r.json().get("detail"), r.text  # says what is wrong
            # a session the generator started would make later POSTs 409: stop it
            if case.method == "POST" and r.status_code == 201:
                httpx.post(f"{api.url}/sessions/{r.json()['id']}/stop", headers=AUTH, timeout=60)

        check()
    assert httpx.get(api.url + "/healthz", timeout=10).json()["ok"]  # whatever it was sent
    assert calls[5] == 0 and calls[2] > 0 and calls[4] > 0, calls


def _post(api, **kw) -> httpx.Response:
    return httpx.post(api.url + "/sessions", headers={**AUTH, **kw.pop("headers", {})}, timeout=30, **kw)


@pytest.mark.parametrize("content, needle", [
    (b"{", "JSON"),
    (b"[]", "object"),
    (b'{"intrinsics_yaml": 5, "initial_yaml": []}', "intrinsics_yaml"),
    (b'{"intrinsics_yaml": "cam_0: {intrinsics: [1,2,3,4], resolution: [10, 10]}", "initial_yaml": "a: :"}',
     "initial_yaml"),
    (b'{"intrinsics_yaml": "- 1\\n- 2", "initial_yaml": "x"}', "intrinsics_yaml"),
    (b'{"intrinsics": "lab_intrinsics", "initial_yaml": "cam_zz:\\n  translation: [0, 0, 0]\\n  rotation: [0, 0, 0, 1]\\n"}',
     "cam_"),  # inconsistent: the initial file names a camera the intrinsics do not have
    (b'{"intrinsics": "lab_intrinsics", "initial": "lab_reference", "stop": {"duration": "soon"}}', "stop.duration"),
    (b'{"intrinsics": "lab_intrinsics", "initial": "lab_reference", "seed": 1e400}', "seed"),
])
def test_malformed_bodies_are_4xx_with_what_to_fix(api, content, needle):
    r = _post(api, content=content, headers={"Content-Type": "application/json"})
    assert 400 <= r.status_code < 500, r.text
    assert needle.lower() in r.json()["detail"].lower(), r.text


def test_oversized_uploads_are_413(api):
    big = "#" * (9 * 1024 * 1024)
    r = _post(api, json={"intrinsics_yaml": big, "initial_yaml": "x"})
    assert r.status_code == 413 and "limit" in r.json()["detail"]

    def chunks():  # no Content-Length: the limit holds while streaming too
        for _ in range(10):
            yield b"x" * (1024 * 1024)

    r = _post(api, content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and "limit" in r.json()["detail"]
    assert httpx.get(api.url + "/healthz", timeout=10).json()["ok"]


def test_unknown_sessions_are_404_everywhere(api):
    for path in ("/sessions/nope", "/sessions/nope/result", "/sessions/nope/history",
                 "/sessions/20990101T000000-abcd/result?format=yaml"):
        r = httpx.get(api.url + path, timeout=30)
        assert r.status_code == 404 and r.json()["detail"], (path, r.text)
    r = httpx.post(api.url + "/sessions/nope/stop", headers=AUTH, timeout=30)
    assert r.status_code == 404 and "nope" in r.json()["detail"]
