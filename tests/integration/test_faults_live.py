"""Faults on a live service (real Zenoh on loopback, real uvicorn, simulated sensors in
their own process): the state directory becomes unwritable, all sensors stop. The
service keeps running, reports the fault in /status and in the session, recovers when
the cause goes, and keeps the last good calibration."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import httpx
import pytest

from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]


def _live():
    spec = importlib.util.spec_from_file_location("live_helpers_faults", REPO / "tests/integration/test_service_live.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["live_helpers_faults"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_unwritable_state_dir_and_silent_sensors(tmp_path, lab_dir):
    live = _live()
    zport = free_port()
    endpoint, site = f"tcp/127.0.0.1:{zport}", "faults"
    state = tmp_path / "state"
    settings = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (endpoint,)},
                                    state_dir=state, site=site, clock="data", speed=4.0)
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        sensors = live.Sensors(endpoint, site, lab_dir, seed=5).__enter__()
        try:
            sid = c.post("/sessions", json={**live._session_body(lab_dir), "stop": {"duration": 36000}}).json()["id"]
            live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 2, 90, "no 2 cycles")
            d = state / "sessions" / sid
            # the fault: the session's directory is replaced by a file (root ignores chmod,
            # and no read-only mount or full disk can be made here): every write fails
            aside = tmp_path / "aside"
            shutil.move(d, aside)
            while True:  # the writer thread may make the directory again before the file is there
                try:
                    d.write_text("not a directory")
                    break
                except IsADirectoryError:
                    shutil.rmtree(d)  # only what was written after the move
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["storage_error"], 60, "the fault is not reported")
            at_fault = s["cycles"]
            live._poll(c, "/status", lambda x: x["storage"]["error"] and x["storage"]["errors"] >= 1, 30,
                       "/status does not show the error")
            # it goes on calibrating, and the calibration is served from memory
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= at_fault + 2, 90, "stalled by the fault")
            assert s["state"] in ("calibrating", "converged")
            assert len(c.get("/calibration").json()["cameras"]) == len(live.CAMS)
            # the cause goes: writes succeed again and the error clears
            d.unlink()
            shutil.move(aside, d)
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["storage_error"] is None, 60, "no recovery")
            # /status may be the snapshot the service published up to a second ago (as_of): poll
            live._poll(c, "/status", lambda x: x["storage"]["error"] is None, 30, "/status still shows the error")
            live._poll(c, f"/sessions/{sid}", lambda _: json.loads((d / "snapshot.json").read_text())["cycle"] > at_fault + 2,
                       60, "the snapshot is not written again")

            # all sensors stop: the service runs on, reports them idle, keeps the calibration
            before = c.get("/calibration").json()
            sensors.__exit__(None, None, None)
            sensors = None
            status = live._poll(c, "/status", lambda x: x["sensors"] and all(v["rate"] == 0 for v in x["sensors"].values()),
                                30, "sensors still shown active")
            assert status["session"]["id"] == sid
            s = c.get(f"/sessions/{sid}").json()
            assert s["live"] and s["state"] in ("calibrating", "converged")
            after = c.get("/calibration").json()
            assert after["cameras"] and sorted(after["cameras"]) == sorted(before["cameras"])  # kept
            assert c.get("/healthz").json()["ok"]
        finally:
            if sensors is not None:
                sensors.__exit__(None, None, None)
