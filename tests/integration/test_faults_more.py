"""More live faults (real Zenoh on loopback, real uvicorn, simulated lab cameras): one
sensor goes silent mid-session and comes back; one sensor's clock jumps ahead.

The sensors are a publisher thread with its own Zenoh session replaying pre-simulated
messages of five lab cameras at SPEED x real time (the service's data clock follows
them); the thread can mute one sensor or shift one sensor's stamps while it runs.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path

import httpx
import pytest
import yaml

from backend.cameras import dump_extrinsics, load_extrinsics
from backend.perturb import perturb_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from edge_clients.publisher import SensorPublisher
from proto.transport import ZenohSettings, open_session
from live_sim import poll as _poll

pytestmark = pytest.mark.slow

SPEED = 4.0
CAMS = ["cam_9", "cam_14", "cam_15", "cam_18", "cam_19"]
LOOSE = {"refine": {"converged_translation": 0.02, "converged_rotation": 0.3, "converged_cycles": 3}}


class Replay(threading.Thread):
    """Publishes the simulated messages in a loop at SPEED, stamps moved forward each round."""

    def __init__(self, endpoint: str, site: str, msgs: list):
        super().__init__(daemon=True)
        self.endpoint, self.site, self.msgs = endpoint, site, msgs
        self.mute: set[str] = set()
        self.shift: dict[str, float] = {}  # sensor -> s added to its stamps (its clock jumped)
        self.ready, self.stop = threading.Event(), threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            zs = open_session(ZenohSettings(connect=(self.endpoint,)))
            try:
                with SensorPublisher(zs, self.site, block=True) as pub:
                    pub.wait_matched(CAMS, timeout=30, stop=self.stop)
                    self.ready.set()
                    span = self.msgs[-1][0] - self.msgs[0][0] + 1.0 / 30
                    a0, t0, loop = self.msgs[0][0], time.monotonic(), 0
                    while not self.stop.is_set():
                        for arrival, m in self.msgs:
                            delay = t0 + (loop * span + arrival - a0) / SPEED - time.monotonic()
                            if delay > 0 and self.stop.wait(delay):
                                return
                            if m.sensor in self.mute:
                                continue
                            pub.publish(replace(m, stamp=m.stamp + loop * span + self.shift.get(m.sensor, 0.0),
                                                seq=m.seq + loop * 1_000_000))
                        loop += 1
            finally:
                zs.close()
        except BaseException as e:  # noqa: BLE001 - reported by the test
            self.error = e
            self.ready.set()


@pytest.fixture(scope="module")
def lab_msgs(lab_dir):
    from edge_clients.sim import Scene, SimConfig, Simulator

    sim = Simulator(Scene.load(lab_dir), SimConfig(persons=2, duration=60.0, seed=7))
    return list(sim.messages(CAMS))


def _body(lab: Path, config: dict | None = None) -> dict:
    intr = yaml.safe_load((lab / "intrinsics.yaml").read_text())
    ref = {k: e for k, e in load_extrinsics(lab / "reference.yaml").items() if k in CAMS}
    return {"intrinsics_yaml": yaml.safe_dump({c: intr[c] for c in CAMS}),
            "initial_yaml": dump_extrinsics(perturb_extrinsics(ref, 0.1, 3.0, seed=1)),
            "reference_yaml": dump_extrinsics(ref), "config": {**LOOSE, **(config or {})},
            "stop": {"duration": 36000}}


def _live_service(tmp_path, site: str):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (endpoint,)},
                                    state_dir=tmp_path / "state", site=site, clock="data", speed=SPEED)
    return endpoint, ServiceThread(settings)


def _sensor(status: dict, name: str) -> dict:
    return status["sensors"][name]


def test_sensor_silent_then_back(tmp_path, lab_dir, lab_msgs):
    endpoint, svc = _live_service(tmp_path, "silent")
    with svc as st, httpx.Client(base_url=st.url, timeout=30) as c:
        rp = Replay(endpoint, "silent", lab_msgs)
        rp.start()
        try:
            assert rp.ready.wait(60) and rp.error is None, rp.error
            sid = c.post("/sessions", json=_body(lab_dir)).json()["id"]
            _poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 2, 120, "no 2 cycles")
            quiet = "cam_14"
            rp.mute.add(quiet)
            status = _poll(c, "/status", lambda x: _sensor(x, quiet)["rate"] == 0, 30, f"{quiet} still shown active")
            assert all(_sensor(status, s)["rate"] > 0 for s in CAMS if s != quiet)  # the others go on
            at_quiet = _sensor(status, quiet)["accepted"]
            cycles = c.get(f"/sessions/{sid}").json()["cycles"]
            s = _poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= cycles + 2, 120, "stalled by a silent sensor")
            assert s["live"] and s["state"] in ("calibrating", "converged")
            assert _sensor(c.get("/status").json(), quiet)["accepted"] == at_quiet
            # it comes back: shown active again, and its messages are taken again
            rp.mute.clear()
            status = _poll(c, "/status", lambda x: _sensor(x, quiet)["rate"] > 0
                           and _sensor(x, quiet)["accepted"] > at_quiet + 30, 60, f"{quiet} not taken again")
            assert not _sensor(status, quiet)["rejected"], _sensor(status, quiet)["rejected"]
            cycles = c.get(f"/sessions/{sid}").json()["cycles"]
            _poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= cycles + 2, 120, "no cycles after the return")
            assert rp.error is None, rp.error
        finally:
            rp.stop.set()
            rp.join(30)


@pytest.mark.parametrize("max_future", [
    1.0,
    None,
], ids=["max_stamp_future=1s", "default"])
def test_sensor_clock_jumps_ahead(tmp_path, lab_dir, lab_msgs, max_future):
    """+2 s on one sensor: its messages are rejected by reason, the data clock is not
    dragged along, the others are still used."""
    endpoint, svc = _live_service(tmp_path, "jump")
    with svc as st, httpx.Client(base_url=st.url, timeout=30) as c:
        rp = Replay(endpoint, "jump", lab_msgs)
        rp.start()
        try:
            assert rp.ready.wait(60) and rp.error is None, rp.error
            sid = c.post("/sessions", json=_body(lab_dir, {"sync": {"max_stamp_future": max_future}} if max_future else None)).json()["id"]
            _poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 2, 120, "no 2 cycles")
            jumped = "cam_15"
            before = c.get("/status").json()
            rp.shift[jumped] = 2.0
            if max_future:  # beyond the limit: rejected by reason
                status = _poll(c, "/status", lambda x: sum(_sensor(x, jumped)["rejected"].values()) >= 30, 20,
                               "the jumped sensor's messages are not rejected")
                reasons = _sensor(status, jumped)["rejected"]
                assert set(reasons) <= {"stamp_in_future"}, reasons
            else:  # within it: taken, but /status warns about that sensor's clock, and only that one
                status = _poll(c, "/status", lambda x: bool(_sensor(x, jumped).get("warnings")), 20,
                               "no warning about the jumped sensor's clock")
                assert "from the other sensors" in _sensor(status, jumped)["warnings"][0]
                assert not any(_sensor(status, s).get("warnings") for s in CAMS if s != jumped)
            others = [s for s in CAMS if s != jumped]
            taken = {s: _sensor(status, s)["accepted"] for s in others}
            cycles = c.get(f"/sessions/{sid}").json()["cycles"]
            s = _poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= cycles + 2, 120, "stalled by a clock jump")
            assert s["live"] and s["state"] in ("calibrating", "converged")
            after = c.get("/status").json()
            for o in others:  # still used, and not rejected because the clock ran ahead with the jumped one
                assert _sensor(after, o)["accepted"] > taken[o], o
                late = _sensor(after, o)["rejected"].get("late", 0) - _sensor(before, o)["rejected"].get("late", 0)
                assert late <= 3, (o, _sensor(after, o)["rejected"])
            if max_future:
                assert after["messages"]["rejected"].get("stamp_in_future", 0) >= 30
            assert c.get("/healthz").json()["ok"]
            assert rp.error is None, rp.error
        finally:
            rp.stop.set()
            rp.join(30)
