"""The Zenoh router between the sensors and the backend is restarted (no zenohd here: a
Zenoh session in router mode in its own process, killed with SIGKILL and started again
on the same port). The backend connects to it as a client, the simulated sensors as
peers. The backend reports the lost link in /status, keeps its session and calibration,
and takes data again when the router is back, without a restart."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from test_faults_live import _live

pytestmark = pytest.mark.slow
ROUTER = Path(__file__).with_name("zenoh_router.py")


def _router(endpoint: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, str(ROUTER), endpoint], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    return p


def _accepted(status: dict) -> int:
    return sum(s["accepted"] for s in status["sensors"].values())


def test_router_restart_is_reported_and_ingest_resumes(tmp_path, lab_dir):
    live = _live()
    endpoint, site = f"tcp/127.0.0.1:{free_port()}", "routerfault"
    router = _router(endpoint)
    try:
        settings = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0},
                                        zenoh={"mode": "client", "connect": (endpoint,)},
                                        state_dir=tmp_path / "state", site=site, clock="data", speed=4.0)
        with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c, \
                live.Sensors(endpoint, site, lab_dir, seed=11):
            sid = c.post("/sessions", json={**live._session_body(lab_dir), "stop": {"duration": 36000}}).json()["id"]
            live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 1, 90, "no cycle")
            status = live._poll(c, "/status", lambda x: x["zenoh"]["routers"] == 1, 10, "the router is not seen")
            assert status["zenoh"]["lost_since"] is None and status["zenoh"]["losses"] == 0

            router.send_signal(signal.SIGKILL)  # the router dies
            router.wait(10)
            router.stdout.close()
            t_kill = time.time()
            status = live._poll(c, "/status", lambda x: x["zenoh"]["lost_since"] is not None
                                and x["zenoh"]["last_message_ago"] > 1.0, 30, "the lost link is not reported")
            assert status["zenoh"]["routers"] == 0 and status["zenoh"]["losses"] == 1
            assert status["zenoh"]["lost_since"] >= t_kill - 1.5
            status = live._poll(c, "/status", lambda x: all(s["rate"] == 0 for s in x["sensors"].values()), 30,
                                "sensors still shown active")
            before = _accepted(status)
            s = c.get(f"/sessions/{sid}").json()
            assert s["live"] and s["state"] in ("calibrating", "converged", "waiting_for_data")
            cycles = s["cycles"]

            router = _router(endpoint)  # the same port again
            status = live._poll(c, "/status", lambda x: x["zenoh"]["routers"] == 1 and x["zenoh"]["lost_since"] is None
                                and _accepted(x) > before + 50, 60, "ingest did not resume")
            assert status["zenoh"]["losses"] == 1 and status["zenoh"]["last_message_ago"] < 5
            live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] > cycles, 60, "no cycle after the restart")
            assert c.get("/healthz").json()["ok"]
    finally:
        if router.poll() is None:
            router.kill()
            router.wait(10)
        router.stdout.close()
