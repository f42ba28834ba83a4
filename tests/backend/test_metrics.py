"""Prometheus metrics: per-app registries, totals → counters across sessions, /metrics served."""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from backend.metrics import Metrics, asgi_app, mount, observe_cycle, update_from_state
from backend.state import CalibrationState, CameraState, Counters, CycleReport
from proto.transport import free_port


def _report(cycle: int, solve: float = 0.04) -> CycleReport:
    return CycleReport(cycle=cycle, data_time=100.0 + cycle, hypotheses=50, observations=900,
                       cameras=("cam_0", "cam_1"), initial_error=2.0, final_error=1.0, iterations=4,
                       solve_seconds=solve, moved=True, accepted=True, reason="", max_change_translation=0.01,
                       max_change_rotation=0.2, reprojection_px=2.5)


def _state(cycle: int, counters: Counters, names=("cam_0", "cam_1", "cam_2"), converged=False) -> CalibrationState:
    cams = []
    for i, n in enumerate(names):
        cov = np.diag([np.radians(0.1 * (i + 1))] * 3 + [0.01 * (i + 1)] * 3) ** 2
        cams.append(CameraState(n, np.eye(3), np.zeros(3), cov, observations=100 * (i + 1), cycles=cycle,
                                change_translation=0.0, change_rotation=0.0, converged=converged or i == 0,
                                last_seen=1.0))
    return CalibrationState(100.0 + cycle, cycle, tuple(cams), converged, counters,
                            _report(cycle) if cycle else None)


def _value(m: Metrics, name: str, **labels) -> float | None:
    return m.registry.get_sample_value(name, labels)


STATUS = {
    "sensors": {"cam_0": {"messages": 10}, "cam_1": {"messages": 7}},
    "messages": {"received": 18, "rejected": {"unknown_sensor": 1, "malformed": 2}},
    "queues": {"ingest": {"length": 3, "capacity": 100, "dropped": 4}},
    "session": {"id": "s1", "accuracy": {"position_mean": 0.05, "orientation_mean": 0.4}},
}


def test_update_from_state_and_status():
    m = Metrics()
    c = Counters(messages=17, framesets=40, framesets_rejected={"span": 3, "std": 1}, views=80,
                 views_rejected={"low_confidence": 5}, hypotheses=30, queue_length=12, queue_dropped=2,
                 cycles=5, cycles_rejected=1)
    update_from_state(m, _state(5, c), STATUS)
    assert _value(m, "extrcal_messages_total", sensor="cam_0") == 10
    assert _value(m, "extrcal_messages_total", sensor="cam_1") == 7
    assert _value(m, "extrcal_messages_rejected_total", reason="malformed") == 2
    assert _value(m, "extrcal_framesets_total", result="accepted") == 40
    assert _value(m, "extrcal_framesets_total", result="rejected") == 4
    assert _value(m, "extrcal_framesets_rejected_total", reason="span") == 3
    assert _value(m, "extrcal_views_rejected_total", reason="low_confidence") == 5
    assert _value(m, "extrcal_hypotheses_total") == 30
    assert _value(m, "extrcal_hypotheses_dropped_total") == 2
    assert _value(m, "extrcal_queue_length", queue="hypotheses") == 12
    assert _value(m, "extrcal_queue_length", queue="ingest") == 3
    assert _value(m, "extrcal_ingest_dropped_total") == 4
    assert _value(m, "extrcal_cycles_total", result="accepted") == 4
    assert _value(m, "extrcal_cycles_total", result="rejected") == 1
    assert _value(m, "extrcal_cycle") == 5
    assert _value(m, "extrcal_reprojection_pixels") == 2.5
    assert _value(m, "extrcal_camera_std_translation_meters", camera="cam_1") == pytest.approx(0.02)
    assert _value(m, "extrcal_camera_std_rotation_degrees", camera="cam_2") == pytest.approx(0.3)
    assert _value(m, "extrcal_camera_observations", camera="cam_2") == 300
    assert _value(m, "extrcal_camera_converged", camera="cam_0") == 1
    assert _value(m, "extrcal_camera_converged", camera="cam_1") == 0
    assert _value(m, "extrcal_converged") == 0
    assert _value(m, "extrcal_position_error_meters") == 0.05
    assert _value(m, "extrcal_cycle_seconds_count") == 1 and _value(m, "extrcal_cycle_seconds_sum") == pytest.approx(0.04)

    # Same totals again: nothing is counted twice, the same cycle is not observed twice.
    update_from_state(m, _state(5, c), STATUS)
    assert _value(m, "extrcal_framesets_total", result="accepted") == 40
    assert _value(m, "extrcal_messages_total", sensor="cam_0") == 10
    assert _value(m, "extrcal_cycle_seconds_count") == 1

    # Growth is added.
    c2 = Counters(framesets=55, framesets_rejected={"span": 4, "std": 1}, hypotheses=41, cycles=6, cycles_rejected=1)
    st = dict(STATUS, sensors={"cam_0": {"messages": 25}, "cam_1": {"messages": 7}})
    update_from_state(m, _state(6, c2), st)
    assert _value(m, "extrcal_framesets_total", result="accepted") == 55
    assert _value(m, "extrcal_framesets_rejected_total", reason="span") == 4
    assert _value(m, "extrcal_messages_total", sensor="cam_0") == 25
    assert _value(m, "extrcal_cycle_seconds_count") == 2


def test_new_session_resets_totals_but_counters_keep_growing():
    m = Metrics()
    update_from_state(m, _state(5, Counters(framesets=40, hypotheses=30, cycles=5)), {"session": "a"})
    # a new session: its pipeline counts from zero again, with other cameras
    update_from_state(m, _state(1, Counters(framesets=6, hypotheses=2, cycles=1), names=("cam_0", "cam_9"),
                                converged=True), {"session": "b"})
    assert _value(m, "extrcal_framesets_total", result="accepted") == 46
    assert _value(m, "extrcal_hypotheses_total") == 32
    assert _value(m, "extrcal_camera_std_translation_meters", camera="cam_2") is None  # gone
    assert _value(m, "extrcal_camera_std_translation_meters", camera="cam_9") == pytest.approx(0.02)
    assert _value(m, "extrcal_converged") == 1
    # cycle 1 of session b is a new cycle even if a's history had a cycle 1
    assert _value(m, "extrcal_cycle_seconds_count") == 2
    update_from_state(m, None, {})
    assert _value(m, "extrcal_camera_std_translation_meters", camera="cam_9") is None
    assert _value(m, "extrcal_converged") == 0


def test_registries_are_per_app_and_bad_numbers_are_ignored():
    a, b = Metrics(), Metrics()  # would raise "Duplicated timeseries" on a shared registry
    update_from_state(a, None, {"messages_by_sensor": {"cam_0": 5}, "rejected_by_reason": {"nan": float("nan")},
                                "ingest_dropped": -3})
    update_from_state(b, None, {"messages_by_sensor": {"cam_0": "lots", "cam_1": True}})
    assert _value(a, "extrcal_messages_total", sensor="cam_0") == 5
    assert _value(b, "extrcal_messages_total", sensor="cam_0") is None
    assert _value(a, "extrcal_messages_rejected_total", reason="nan") is None
    assert _value(a, "extrcal_ingest_dropped_total") == 0
    observe_cycle(b, _report(3, solve=0.2), wall_seconds=0.3)
    observe_cycle(b, _report(3, solve=0.2), wall_seconds=0.3)
    assert _value(b, "extrcal_cycle_seconds_bucket", le="0.25") == 1
    assert _value(b, "extrcal_cycle_seconds_bucket", le="0.1") == 0
    assert _value(b, "extrcal_cycle_wall_seconds_count") == 1
    assert _value(a, "extrcal_cycle_seconds_count") == 0


def test_metrics_endpoint_on_a_real_server():
    import uvicorn
    from fastapi import FastAPI

    m = Metrics()
    scrapes = []

    def refresh() -> None:
        scrapes.append(1)
        update_from_state(m, _state(len(scrapes), Counters(framesets=10 * len(scrapes), cycles=len(scrapes))), STATUS)

    app = FastAPI()
    mount(app, m, refresh)
    app.mount("/plain", asgi_app(m))
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="off"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline and th.is_alive(), "uvicorn did not start"
            time.sleep(0.01)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", follow_redirects=False) as cl:
            r1 = cl.get("/metrics")
            r2 = cl.get("/metrics")
            assert r1.status_code == r2.status_code == 200
            assert r1.headers["content-type"].startswith("text/plain")
            fams = {f.name: f for f in text_string_to_metric_families(r2.text)}
            fs = {tuple(sorted(s.labels.items())): s.value for s in fams["extrcal_framesets"].samples
                  if s.name == "extrcal_framesets_total"}
            assert fs[(("result", "accepted"),)] == 20  # refreshed at each scrape
            assert fams["extrcal_cycle_seconds"].type == "histogram"
            assert "python_gc_objects_collected_total" not in r2.text  # not the global registry
            assert len(scrapes) == 2
            r3 = cl.get("/plain/")
            assert r3.status_code == 200 and "extrcal_framesets_total" in r3.text and len(scrapes) == 2
    finally:
        server.should_exit = True
        th.join(10)
