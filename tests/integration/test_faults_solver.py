"""The optimizer fails on a live service (real Zenoh on loopback, real uvicorn, simulated
sensors, the real worker process): the solve raises, the geometry is degenerate, the
worker dies. The service keeps running, reports the fault in /status and in the
session, keeps the last good estimate, and recovers with the next cycle."""

from __future__ import annotations

import time

import httpx
import pytest

from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from solver_faults import faulty_solve
from test_faults_live import _live

pytestmark = pytest.mark.slow
FAULTS = ["raise", "raise", "degenerate", "degenerate", "crash"]  # fewer than the 10 that fail a session


def test_optimizer_failures_are_reported_and_the_service_recovers(tmp_path, lab_dir, monkeypatch):
    live = _live()
    plan = tmp_path / "faults"
    monkeypatch.setenv("EXTRCAL_TEST_SOLVER_FAULTS", str(plan))  # before the worker is spawned
    endpoint, site = f"tcp/127.0.0.1:{free_port()}", "solverfaults"
    settings = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (endpoint,)},
                                    state_dir=tmp_path / "state", site=site, clock="data", speed=4.0)
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c:
        st.service.solve_fn = faulty_solve
        with live.Sensors(endpoint, site, lab_dir, seed=3):
            sid = c.post("/sessions", json={**live._session_body(lab_dir), "stop": {"duration": 36000}}).json()["id"]
            live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 2, 90, "no 2 cycles")
            assert c.get("/status").json()["cycles"]["solver_fault"] is None
            plan.write_text("".join(f"{x}\n" for x in FAULTS))
            seen_failing = seen_reason = False
            errors: set[str] = set()
            deadline = time.monotonic() + 120
            while True:  # while it fails, /status and the session say so
                status, sess = c.get("/status").json(), c.get(f"/sessions/{sid}").json()
                f = status["cycles"]["solver_fault"]
                seen_failing |= f is not None and f["failing"] > 0
                if f is not None:
                    errors.add(f["error"])
                if sess["solver_fault"] is not None and sess["solver_fault"]["failing"]:
                    seen_reason |= "optimizer failed" in sess["reason"]
                if f is not None and f["count"] >= len(FAULTS) and not f["failing"]:
                    break
                assert time.monotonic() < deadline, f"no recovery: {f}"
                assert sess["state"] != "failed", sess["reason"]
                time.sleep(0.05)
            assert seen_failing and seen_reason
            assert not plan.read_text().strip()  # every fault was taken
            # recovered: the next cycle was good, the service and the session run on
            assert f["recovered_cycle"] > f["cycle"] and f["kept_cycle"] is not None and f["kept_cycle"] < f["cycle"] - 3
            # the worker process died (a cycle with too little data may also have failed meanwhile)
            assert any("died" in e for e in errors), errors
            assert status["cycles"]["solver_restarts"] == 1 and status["cycles"]["solver_faults"] >= len(FAULTS)
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= f["recovered_cycle"] + 1, 90, "no more cycles")
            assert s["live"] and s["state"] in ("calibrating", "converged") and "optimizer failed" not in s["reason"]
            assert s["solver_fault"]["recovered_cycle"] == f["recovered_cycle"]
            assert c.get("/healthz").json()["ok"]
        # the failed cycles were rejected and left the estimate as it was; the next one moved it
        hist = {h["cycle"]: h for h in c.get(f"/sessions/{sid}/history").json()}
        failed = [hist[k] for k in range(f["kept_cycle"] + 1, f["recovered_cycle"])]
        assert len(failed) >= len(FAULTS)
        for h in failed:
            assert not h["accepted"] and h["max_change_translation"] == 0 and h["max_change_rotation"] == 0, h
        assert any(h["accepted"] for k, h in hist.items() if k >= f["recovered_cycle"])
        assert hist[f["kept_cycle"]]["accepted"]
