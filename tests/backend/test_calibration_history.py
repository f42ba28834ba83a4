"""Calibration versions and rollback on a real service (uvicorn, Zenoh on loopback), across a restart."""

from __future__ import annotations

import json

import httpx
import numpy as np

from backend.cameras import Extrinsics, Pose, dump_extrinsics, parse_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from proto import keys
from proto.transport import ZenohSettings, open_session

TOKEN = "history-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _shifted(text: str, dx: float) -> str:
    ext = parse_extrinsics(text)
    return dump_extrinsics({n: Extrinsics(Pose(e.pose.R, e.pose.t + np.array([dx, 0.0, 0.0])), e.resolution)
                            for n, e in ext.items()})


def _poses(doc: dict) -> dict[str, np.ndarray]:
    return {n: np.array(c["translation"] + c["rotation"]) for n, c in doc["cameras"].items()}


def _run_session(c: httpx.Client, body: dict) -> str:
    r = c.post("/sessions", headers=AUTH, json=body)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert c.post(f"/sessions/{sid}/stop", headers=AUTH).json()["state"] == "stopped"
    return sid


def test_versions_rollback_and_restart(tmp_path, lab_dir):
    port = free_port()
    settings = ServiceSettings.load(None, http={"port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{port}",)},
                                    state_dir=tmp_path, token=TOKEN, site="histtest")
    intr = (lab_dir / "intrinsics.yaml").read_text()
    ref = (lab_dir / "reference.yaml").read_text()
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        assert c.get("/calibrations").json() == []
        assert c.get("/calibrations/1").status_code == 404
        s1 = _run_session(c, {"intrinsics_yaml": intr, "initial_yaml": _shifted(ref, 0.1)})
        s2 = _run_session(c, {"intrinsics_yaml": intr, "initial_yaml": _shifted(ref, -0.2)})
        versions = c.get("/calibrations").json()
        assert [v["version"] for v in versions] == [2, 1]
        assert [v["session"] for v in versions] == [s2, s1]
        assert all(s1 in v["by"] or s2 in v["by"] for v in versions) and versions[0]["created"].endswith("Z")
        v1 = c.get("/calibrations/1").json()
        v2 = c.get("/calibrations/2").json()
        assert v1["version"] == 1 and v1["session"] == s1 and len(v1["cameras"]) == 20
        d = {n: _poses(v1)[n] - _poses(v2)[n] for n in v1["cameras"]}
        assert all(abs(x[0] - 0.3) < 1e-9 for x in d.values())  # the two sessions' results differ
        y1 = parse_extrinsics(c.get("/calibrations/1", params={"format": "yaml"}).text)
        assert all(np.allclose(y1[n].pose.t, v1["cameras"][n]["translation"], atol=1e-12) for n in y1)
        assert c.get("/calibrations/1", params={"format": "bogus"}).status_code == 400

        # activation needs the token, and a version that exists
        assert c.post("/calibrations/1/activate").status_code == 401
        assert c.post("/calibrations/9/activate", headers=AUTH).status_code == 404
        r = c.post("/calibrations/1/activate", headers=AUTH, json={"reason": "v2 looks wrong"})
        assert r.status_code == 200, r.text
        meta = r.json()
        assert meta["version"] == 3 and meta["source_version"] == 1 and meta["active"]
        assert meta["reason"] == "v2 looks wrong" and meta["by"] == "api"
        cal = c.get("/calibration").json()
        assert cal["version"] == 3 and cal["source_version"] == 1 and cal["session"] == s1
        p1, pc = _poses(v1), _poses(cal)
        assert set(pc) == set(p1) and all(np.abs(pc[n] - p1[n]).max() <= 1e-12 for n in p1)
        assert [v["active"] for v in c.get("/calibrations").json()] == [True, False, False]
        # rollback to 2, then back to 1 (recorded as a rollback)
        assert c.post("/calibrations/2/activate", headers=AUTH).json()["version"] == 4
        back = c.post("/calibrations/1/activate", headers=AUTH).json()
        assert back["version"] == 5 and back["by"] == "rollback" and "version 1" in back["reason"]
        for f in ("5.yaml", "5.json", "5.intrinsics.yaml", "active.json"):
            assert (tmp_path / "calibrations" / f).is_file(), f

    # a restart on the same state directory: version 5 (= 1) is still active
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        cal = c.get("/calibration").json()
        assert cal["version"] == 5 and cal["source_version"] == 1
        pc = _poses(cal)
        assert all(np.abs(pc[n] - p1[n]).max() <= 1e-12 for n in p1)
        assert c.get("/calibration", params={"format": "yaml"}).text == \
            c.get("/calibrations/1", params={"format": "yaml"}).text
        # and Zenoh queries on the calibration key answer with it
        zs = open_session(ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",)))
        try:
            replies = list(zs.get(keys.calibration("histtest"), timeout=10))
        finally:
            zs.close()
        assert len(replies) == 1 and replies[0].ok is not None
        zc = json.loads(replies[0].ok.payload.to_bytes())
        assert zc["version"] == 5 and zc["source_version"] == 1
        pz = _poses(zc)
        assert all(np.abs(pz[n] - p1[n]).max() <= 1e-12 for n in p1)


def test_broken_version_files_are_skipped(tmp_path, lab_dir):
    from backend.history import CalibrationHistory

    h = CalibrationHistory(tmp_path)
    h.record({"session": "s", "cameras": {}}, "{}\n", "{}\n", by="api", reason="test", activate=True)
    (tmp_path / "2.json").write_text("{not json")
    h2 = CalibrationHistory(tmp_path)
    assert [m["version"] for m in h2.list()] == [1] and h2.active == 1
    assert h2.record({"cameras": {}}, "", "", by="api", reason="x", activate=False)["version"] == 2
