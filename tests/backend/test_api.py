"""The REST API on a real service: real uvicorn on a free port, real Zenoh on loopback.

No sensor data here (tests/integration has the calibrating runs): sessions, errors,
authentication, formats, events, Zenoh status and queries.
"""

from __future__ import annotations

import json
import time

import httpx
import pytest
import yaml

from backend.cameras import parse_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from proto import KeypointMessage, Person, encode, keys
from proto.transport import ZenohSettings, open_session

TOKEN = "test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def svc(tmp_path_factory, lab_dir):
    port = free_port()
    settings = ServiceSettings.load(
        None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{port}",)},
        state_dir=tmp_path_factory.mktemp("state"), token=TOKEN, site="apitest",
        camera_files={"lab_intrinsics": lab_dir / "intrinsics.yaml", "lab_reference": lab_dir / "reference.yaml"},
    )
    with ServiceThread(settings) as st:
        st.zenoh_endpoint = f"tcp/127.0.0.1:{port}"
        yield st


@pytest.fixture()
def client(svc):
    with httpx.Client(base_url=svc.url, timeout=30) as c:
        yield c


@pytest.fixture(scope="module")
def lab_body(lab_dir):
    return {"intrinsics_yaml": (lab_dir / "intrinsics.yaml").read_text(),
            "initial_yaml": (lab_dir / "reference.yaml").read_text()}


def _stop_all(client):
    for s in client.get("/sessions").json():
        if s["state"] in ("waiting_for_data", "calibrating", "converged"):
            client.post(f"/sessions/{s['id']}/stop", headers=AUTH)


def test_health_and_openapi_documents_convergence(client):
    assert client.get("/healthz").json()["ok"] is True
    spec = client.get("/openapi.json").json()
    desc = spec["info"]["description"]
    assert "A camera is *converged*" in desc and "- `refine.converged_cycles` = " in desc
    for path in ("/sessions", "/sessions/{sid}", "/sessions/{sid}/stop", "/sessions/{sid}/result",
                 "/calibration", "/status", "/events", "/healthz"):
        assert path in spec["paths"], path


def test_state_changing_endpoints_need_the_token(client, lab_body):
    r = client.post("/sessions", json=lab_body)
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    r = client.post("/sessions", json=lab_body, headers={"Authorization": "Bearer nope"})
    assert r.status_code == 401 and "wrong token" in r.json()["detail"]
    assert client.post("/sessions/20990101T000000-abcd/stop").status_code == 401
    # reads are open unless protect_reads
    assert client.get("/status").status_code == 200 and client.get("/sessions").status_code == 200


@pytest.mark.parametrize("patch, status, needle", [
    ({"intrinsics_yaml": "cam_0: [1, 2"}, 422, "intrinsics_yaml:1"),
    ({"initial_yaml": "cam_0:\n  translation: [0, 0, 0]\n  rotation: [0, 0, 0, 2]\n"}, 422, "unit length"),
    ({"config": {"select": {"scope": -3}}}, 422, "select.scope"),
    ({"config": {"nonsense": {"a": 1}}}, 422, "nonsense"),
    ({"config": {"select": 5}}, 422, "select"),
    ({"intrinsics": "lab_intrinsics"}, 422, "not both"),
    ({"reference": "elsewhere"}, 422, "no camera file named 'elsewhere'"),
    ({"stop": {"duration": -1}}, 422, "stop.duration"),
    ({"surprise": 1}, 422, "surprise"),
    ({"intrinsics_yaml": None}, 422, "intrinsics"),
    # without an initial estimate the session bootstraps (tests/backend/test_live_bootstrap.py)
    ({"person_height": [3.5]}, 422, "person_height"),
    ({"person_height": []}, 422, "person_height"),
])
def test_bad_session_bodies_are_4xx_with_a_reason(client, lab_body, patch, status, needle):
    body = {**lab_body, **patch}
    body = {k: v for k, v in body.items() if v is not None}
    r = client.post("/sessions", json=body, headers=AUTH)
    assert r.status_code == status, r.text
    assert needle in r.json()["detail"]


def test_unknown_things_are_404_and_formats_400(client):
    assert client.get("/sessions/20990101T000000-abcd").status_code == 404
    assert client.get("/sessions/not-an-id/result").status_code == 404
    assert client.get("/sessions/..%2F..%2Fetc/history").status_code == 404
    r = client.post("/sessions/20990101T000000-abcd/stop", headers=AUTH)
    assert r.status_code == 404


def test_session_lifecycle_with_configured_files(svc, client, lab_body):
    _stop_all(client)
    r = client.post("/sessions", headers=AUTH, json={
        "name": "api test", "intrinsics": "lab_intrinsics", "initial_yaml": lab_body["initial_yaml"],
        "reference": "lab_reference", "config": {"select": {"scope": 30}}, "stop": {"max_cycles": 50}})
    assert r.status_code == 201, r.text
    s = r.json()
    sid = s["id"]
    assert r.headers["location"] == f"/sessions/{sid}"
    assert s["state"] == "waiting_for_data" and s["live"] and len(s["cameras"]) == 20
    assert s["sources"] == {"intrinsics": "file:lab_intrinsics", "initial": "upload", "reference": "file:lab_reference"}
    # one at a time
    r2 = client.post("/sessions", headers=AUTH, json=lab_body)
    assert r2.status_code == 409 and sid in r2.json()["detail"]
    assert client.get("/sessions").json()[0]["id"] == sid
    assert client.get("/status").json()["session"]["id"] == sid

    # the current calibration is the initial estimate, in JSON and in the FORMATS.md YAML
    cal = client.get("/calibration").json()
    assert cal["session"] == sid and set(cal["cameras"]) == {f"cam_{i}" for i in range(20)}
    r = client.get("/calibration", params={"format": "yaml"})
    assert r.headers["content-type"].startswith("application/yaml")
    ext = parse_extrinsics(r.text, "GET /calibration?format=yaml")
    init = parse_extrinsics(lab_body["initial_yaml"])
    assert all(ext[n].pose == init[n].pose for n in init)
    assert client.get("/calibration", params={"format": "bogus"}).status_code == 400

    # stop: the final result stays readable after the session ended
    r = client.post(f"/sessions/{sid}/stop", headers=AUTH)
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["state"] == "stopped" and d["stopped_by"] == "request" and not d["live"] and d["ended_wall"]
    assert client.get("/status").json()["session"] is None
    res = client.get(f"/sessions/{sid}/result", params={"format": "yaml"})
    assert set(parse_extrinsics(res.text)) == set(init)
    assert client.get(f"/sessions/{sid}/result").json()["state"] == "stopped"
    cv = client.get(f"/sessions/{sid}/result", params={"format": "opencv"})
    if cv.status_code != 400:  # the export module is there: OpenCV FileStorage
        assert cv.status_code == 200 and "%YAML" in cv.text
    # stopping again is harmless
    assert client.post(f"/sessions/{sid}/stop", headers=AUTH).json()["state"] == "stopped"
    # and the files are on disk
    d = svc.settings.state_dir / "sessions" / sid
    rec = json.loads((d / "session.json").read_text())
    assert rec["state"] == "stopped" and (d / "result.yaml").is_file() and (d / "snapshot.json").is_file()
    cfg = json.loads((d / "config.json").read_text())
    assert cfg["select"]["scope"] == 30 and cfg["monitor"]["enabled"] is True  # a live session watches its cameras
    assert yaml.safe_load((d / "intrinsics.yaml").read_text()) == yaml.safe_load(
        (svc.settings.camera_files["lab_intrinsics"]).read_text())


def _slow_disk(monkeypatch, store, method: str, seconds: float = 0.5) -> None:
    """The store's ``method`` takes ``seconds`` longer (a slow disk)."""
    write = getattr(store, method)

    def slow(*a, **kw):
        time.sleep(seconds)
        return write(*a, **kw)

    monkeypatch.setattr(store, method, slow)


def test_a_session_reads_stopped_only_once_its_result_is_written(svc, client, lab_body, monkeypatch):
    """Whoever polls a session until it reads "stopped" fetches the result at once: it
    must be the final one, however slowly the disk takes it."""
    _stop_all(client)
    store = svc.service.store
    _slow_disk(monkeypatch, store, "save_result")
    sid = client.post("/sessions", headers=AUTH, json={**lab_body, "name": "slow disk"}).json()["id"]
    assert client.post(f"/sessions/{sid}/stop", headers=AUTH, params={"wait": False}).status_code == 202
    deadline = time.monotonic() + 60
    while (d := client.get(f"/sessions/{sid}").json())["state"] != "stopped":
        assert time.monotonic() < deadline, d
        time.sleep(0.02)
    seen = client.get(f"/sessions/{sid}/result", params={"format": "yaml"}).text
    assert seen == (svc.settings.state_dir / "sessions" / sid / "result.yaml").read_text()
    assert not d["live"] and [s["state"] for s in client.get("/sessions").json() if s["id"] == sid] == ["stopped"]


def test_a_failed_session_reads_failed_only_with_its_files_written(svc, client, lab_body, monkeypatch):
    """A session that fails (here: told so on the service's loop, as a failing front end
    does) reads "failed" at once, from its record on disk once the slow disk has it,
    and the next session starts after that."""
    _stop_all(client)
    store = svc.service.store
    sid = client.post("/sessions", headers=AUTH, json={**lab_body, "name": "to fail"}).json()["id"]
    _slow_disk(monkeypatch, store, "save_record")
    svc.call(lambda: svc.service._fail(svc.service.active, "the front end failed: a test"))
    d = client.get(f"/sessions/{sid}").json()
    assert d["state"] == "failed" and not d["live"] and d["reason"] == "the front end failed: a test", d
    assert store.load_record(sid).state.value == "failed"
    nxt = client.post("/sessions", headers=AUTH, json={**lab_body, "name": "after the failure"})
    assert nxt.status_code == 201, nxt.text
    _stop_all(client)


def test_events_stream_session_changes(svc, client, lab_body):
    _stop_all(client)
    with httpx.Client(base_url=svc.url, timeout=30) as ev, ev.stream("GET", "/events") as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        lines = stream.iter_lines()
        first = _next_event(lines)
        assert first[0] == "hello" and "session" in first[1]
        sid = client.post("/sessions", headers=AUTH, json=lab_body).json()["id"]
        r = client.post(f"/sessions/{sid}/stop", headers=AUTH, params={"wait": "false"})
        assert r.status_code in (200, 202)  # 202 while the final batch adjustment runs
        if r.status_code == 202:
            assert r.json()["stopping"] is True
        seen = []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            kind, data = _next_event(lines)
            if kind == "session" and data["id"] == sid:
                seen.append(data["state"])
                if data["state"] == "stopped":
                    break
        assert seen == ["waiting_for_data", "stopped"]


def test_events_of_the_kinds_asked_for_only(svc, client):
    """?kind=...: a client waiting for some kinds gets only those (after ``hello``): a
    flood of others larger than its queue cannot push them out; an unknown kind is a 422."""
    from typing import get_args

    from backend.api.routers.events import EventKind
    from backend.events import EventBus

    assert frozenset(get_args(EventKind)) == EventBus.KINDS
    assert client.get("/events", params={"kind": "cycles"}).status_code == 422
    bus = svc.service.events
    with httpx.Client(base_url=svc.url, timeout=10) as ev, \
            ev.stream("GET", "/events", params={"kind": ["calibration", "camera_moved"]}) as stream:
        lines = stream.iter_lines()
        assert _next_event(lines)[0] == "hello"

        def flood() -> None:  # on the service's loop, as the service publishes
            for k in range(2 * bus._maxlen):
                bus.publish("cycle", {"cycle": k})
            bus.publish("calibration", {"version": 7})
            bus.publish("hypotheses", {"persons": []})
            bus.publish("camera_moved", {"camera": "cam_3"})

        svc.loop.call_soon_threadsafe(flood)
        assert _next_event(lines) == ("calibration", {"version": 7})  # nothing dropped: no "dropped"
        assert _next_event(lines) == ("camera_moved", {"camera": "cam_3"})


def _next_event(lines) -> tuple[str, dict]:
    kind = None
    for line in lines:
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: ") and kind is not None:
            return kind, json.loads(line[6:])
    raise AssertionError("stream ended")


def test_zenoh_status_liveliness_rejections_and_queries(svc, client, lab_body):
    _stop_all(client)
    sid = client.post("/sessions", headers=AUTH, json=lab_body).json()["id"]
    site = svc.settings.site
    zs = open_session(ZenohSettings(connect=(svc.zenoh_endpoint,)))
    try:
        token = zs.liveliness().declare_token(keys.alive(site, "cam_3"))
        pub = zs.declare_publisher(keys.keypoints(site, "cam_3"))
        deadline = time.monotonic() + 30
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        kp = [[400.0, 200.0, 0.9]] * 17
        t = time.time()
        good = KeypointMessage("cam_3", 1, t, (848, 480), (Person(__import__("numpy").array(kp)),))
        pub.put(encode(good))
        pub.put(b"\x93not a map")  # malformed
        pub.put(encode(KeypointMessage("cam_3", 2, t + 3600, (848, 480))))  # an hour ahead
        zs.put(keys.keypoints(site, "cam_77"), encode(KeypointMessage("cam_77", 1, t, (848, 480))))  # unknown
        zs.put(keys.keypoints(site, "cam_4"), encode(KeypointMessage("cam_3", 3, t, (848, 480))))  # wrong key

        def status_has(pred):
            end = time.monotonic() + 10
            while time.monotonic() < end:
                st = client.get("/status").json()
                if pred(st):
                    return st
                time.sleep(0.05)
            raise AssertionError(json.dumps(st, indent=1)[:3000])

        st = status_has(lambda st: st["messages"]["received"] >= 5 and "cam_3" in st["sensors"]
                        and st["sensors"]["cam_3"]["online"])
        cam3 = st["sensors"]["cam_3"]
        assert cam3["accepted"] == 1 and cam3["messages"] == 3
        assert cam3["rejected"] == {"malformed:payload": 1, "stamp_in_future": 1}
        assert st["sensors"]["cam_77"]["rejected"] == {"unknown_sensor": 1}
        assert st["sensors"]["cam_4"]["rejected"] == {"sensor_mismatch": 1}
        assert 0 <= cam3["latency"]["median"] < 5
        assert st["queues"]["ingest"]["dropped"] == 0

        # the calibration answers Zenoh queries
        replies = list(zs.get(keys.calibration(site), timeout=10))
        assert len(replies) == 1 and replies[0].ok is not None
        cal = json.loads(replies[0].ok.payload.to_bytes())
        assert cal["session"] == sid and len(cal["cameras"]) == 20

        token.undeclare()
        status_has(lambda st: st["sensors"]["cam_3"]["online"] is False)
        pub.undeclare()
    finally:
        zs.close()
        client.post(f"/sessions/{sid}/stop", headers=AUTH)


def test_resume_after_restart(tmp_path, lab_body):
    port = free_port()
    settings = ServiceSettings.load(None, http={"port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{port}",)},
                                    state_dir=tmp_path)
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        sid = c.post("/sessions", json={**lab_body, "stop": {"duration": 600}}).json()["id"]
    # stopped cleanly with a running session: it comes back
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        s = c.get(f"/sessions/{sid}").json()
        assert s["live"] and s["state"] == "waiting_for_data" and s["resumed"] == 1
        assert "resumed at cycle 0" in s["reason"]
        assert s["stop"]["duration"] == 600
        # while it waits for data (the reason is refreshed every second) it still says so
        deadline = time.monotonic() + 30
        while "no messages from the session's cameras yet" not in (s := c.get(f"/sessions/{sid}").json())["reason"]:
            assert time.monotonic() < deadline, s["reason"]
            time.sleep(0.1)
        assert s["reason"].startswith("resumed at cycle 0 after a restart")
        assert c.post(f"/sessions/{sid}/stop").json()["state"] == "stopped"
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        s = c.get(f"/sessions/{sid}").json()
        assert not s["live"] and s["state"] == "stopped" and c.get("/status").json()["session"] is None


def test_optional_parts_are_wired(client):
    """Metrics and dashboard come with create_app when this build has them."""
    pytest.importorskip("backend.metrics")
    r = client.get("/metrics")
    assert r.status_code == 200 and "extrcal_" in r.text
    pytest.importorskip("backend.api.dashboard")
    assert client.get("/").status_code == 200


def test_create_app_alone_runs_its_service_in_the_lifespan(tmp_path):
    """create_app(settings) without a service is a complete app (e.g. for uvicorn --factory)."""
    import asyncio

    import uvicorn

    from backend.api import create_app

    port = free_port()
    settings = ServiceSettings.load(None, zenoh={"listen": (f"tcp/127.0.0.1:{port}",)}, state_dir=tmp_path)

    async def main() -> tuple[dict, dict]:
        server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=0, log_level="warning"))
        server.capture_signals = __import__("contextlib").nullcontext  # a test: leave signals alone
        task = asyncio.create_task(server.serve())
        while not server.started:
            assert not task.done(), "uvicorn did not start"
            await asyncio.sleep(0.01)
        http_port = server.servers[0].sockets[0].getsockname()[1]
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{http_port}") as c:
            health = (await c.get("/healthz")).json()
            status = (await c.get("/status")).json()
        server.should_exit = True
        await task
        return health, status

    health, status = asyncio.run(main())
    assert health["ok"] is True and status["zenoh"]["listen"] == [f"tcp/127.0.0.1:{port}"]


def test_protected_reads(tmp_path):
    settings = ServiceSettings.load(None, http={"port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)},
                                    state_dir=tmp_path, token=TOKEN, protect_reads=True)
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        for path in ("/status", "/sessions", "/calibration", "/events"):
            assert c.get(path).status_code == 401, path
        assert c.get("/status", headers=AUTH).status_code == 200
        assert c.get("/healthz").status_code == 200  # probes stay open
