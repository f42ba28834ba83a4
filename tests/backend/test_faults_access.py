"""Access control: the bearer token on every state-changing route (enumerated from the
app, not listed by hand), protected reads, no non-loopback address without a token, and
data only from the session's cameras."""

from __future__ import annotations

import re
import time

import httpx
import msgpack
import pytest
import yaml

from backend.api import create_app
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings

TOKEN = "acl-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SAFE = {"GET", "HEAD", "OPTIONS"}


def _settings(tmp_path, **kw) -> ServiceSettings:
    return ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0},
                                zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)},
                                state_dir=tmp_path, token=TOKEN, site="acl", **kw)


def _routes(settings: ServiceSettings) -> list[tuple[str, str]]:
    """(method, path) of every HTTP route the app serves, from the app itself."""
    from types import SimpleNamespace

    app = create_app(settings, service=SimpleNamespace(cycle_listeners=[]))  # type: ignore[arg-type]  # routes only
    out = []

    def walk(routes) -> None:
        for r in routes:
            if hasattr(r, "effective_candidates"):  # FastAPI >= 0.16x: included routers resolve lazily
                walk(r.effective_candidates())
            elif getattr(r, "methods", None) and getattr(r, "path", None):
                path = re.sub(r"\{[^}]+\}", "20990101T000000-abcd", r.path)
                out.extend((m, path) for m in r.methods)

    walk(app.routes)
    return out


@pytest.fixture(scope="module")
def protected(tmp_path_factory):
    with ServiceThread(_settings(tmp_path_factory.mktemp("s"), protect_reads=True)) as st:
        yield st


def test_every_state_changing_route_needs_the_token(tmp_path, protected):
    routes = _routes(protected.settings)
    writes = [(m, p) for m, p in routes if m not in SAFE]
    assert ("POST", "/sessions") in writes and len(writes) >= 2
    with httpx.Client(base_url=protected.url, timeout=30) as c:
        for m, p in writes:
            for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic " + TOKEN}):
                r = c.request(m, p, headers=headers, json={})
                assert r.status_code == 401, (m, p, headers, r.status_code)
                assert r.headers.get("www-authenticate") == "Bearer"
            # with the token it gets past authentication (whatever the body makes of it)
            assert c.request(m, p, headers=AUTH, json={}).status_code != 401, (m, p)


def test_reads_can_be_protected(protected):
    reads = [(m, p) for m, p in _routes(protected.settings) if m == "GET"]
    open_ = {"/healthz", "/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"}  # probes and documentation
    with httpx.Client(base_url=protected.url, timeout=30) as c:
        checked = 0
        for m, p in reads:
            if p in open_ or p.startswith("/static") or p == "/" or p.startswith("/dashboard"):
                continue
            if p == "/events":
                with c.stream("GET", p) as r:
                    assert r.status_code == 401
                continue
            assert c.get(p).status_code == 401, p
            assert c.get(p, headers=AUTH).status_code != 401, p
            checked += 1
        assert checked >= 5
        assert c.get("/status", headers=AUTH).status_code == 200


def test_refuses_a_non_loopback_address_without_a_token(tmp_path):
    with pytest.raises(ValueError, match="not loopback"):
        ServiceSettings.load(None, http={"host": "0.0.0.0", "port": 8000}, state_dir=tmp_path)
    # with a token it is allowed
    assert ServiceSettings.load(None, http={"host": "0.0.0.0", "port": 8000}, state_dir=tmp_path,
                                token="t").http.host == "0.0.0.0"


def test_only_sensors_of_the_sessions_camera_set_are_taken(tmp_path, lab_dir):
    """A sensor outside the session's camera files publishes real, valid messages
    through Zenoh: they are counted as unknown_sensor, the session's cameras are taken."""
    from backend.cameras import dump_extrinsics, load_extrinsics
    from proto.transport import ZenohSettings, open_session

    intr = yaml.safe_load((lab_dir / "intrinsics.yaml").read_text())
    ref = load_extrinsics(lab_dir / "reference.yaml")
    cams = ["cam_0", "cam_1"]
    s = _settings(tmp_path)
    with ServiceThread(s) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        r = c.post("/sessions", headers=AUTH, json={"intrinsics_yaml": yaml.safe_dump({k: intr[k] for k in cams}),
                                                    "initial_yaml": dump_extrinsics({k: ref[k] for k in cams})})
        assert r.status_code == 201, r.text
        zs = open_session(ZenohSettings(mode="peer", connect=s.zenoh.listen))
        try:
            pubs = {n: zs.declare_publisher(f"extrcal/acl/sensors/{n}/keypoints") for n in ("cam_0", "cam_7", "intruder")}
            deadline = time.monotonic() + 30
            seq = 0
            while time.monotonic() < deadline:
                seq += 1
                for n, pub in pubs.items():
                    pub.put(msgpack.packb({"v": 1, "sensor": n, "seq": seq, "stamp": time.time(), "size": [848, 480],
                                           "persons": []}))
                st_ = c.get("/status").json()["sensors"]
                if all(n in st_ for n in pubs) and st_["intruder"]["rejected"].get("unknown_sensor", 0) >= 3 \
                        and st_["cam_0"]["accepted"] >= 3:
                    break
                time.sleep(0.05)
            sensors = c.get("/status").json()["sensors"]
            assert sensors["cam_0"]["accepted"] >= 3 and not sensors["cam_0"]["rejected"]
            for n in ("cam_7", "intruder"):  # cam_7 is in the lab, not in this session
                assert sensors[n]["accepted"] == 0 and sensors[n]["rejected"]["unknown_sensor"] >= 3, sensors[n]
        finally:
            for p in pubs.values():
                p.undeclare()
            zs.close()
