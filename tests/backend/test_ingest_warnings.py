"""Per-sensor clock and latency warnings in /status."""

from __future__ import annotations

from backend.ingest import SensorTable


def _feed(table: SensorTable, name: str, lag: float, n: int = 20) -> None:
    s = table.get(name)
    for k in range(n):
        s.seen(1000.0 + 0.05 * k)
        s.timing(1000.0 + 0.05 * k - lag, 1000.0 + 0.05 * k, k)


def test_a_sensor_whose_clock_is_off_is_warned_about_and_the_others_are_not():
    t = SensorTable()
    for name in ("cam_0", "cam_1", "cam_2"):
        _feed(t, name, 0.010)
    _feed(t, "cam_3", 0.010 + 0.120)  # its clock runs 120 ms behind
    d = t.to_dict(1001.0)
    assert d["cam_3"]["warnings"] and "ms from the other sensors" in d["cam_3"]["warnings"][0]
    assert "-120 ms" in d["cam_3"]["warnings"][0]
    assert all(not d[n]["warnings"] for n in ("cam_0", "cam_1", "cam_2"))


def test_late_messages_are_warned_about():
    t = SensorTable()
    for name in ("cam_0", "cam_1", "cam_2"):
        _feed(t, name, 0.400)  # all late by the same amount: no offset warning, a latency one
    d = t.to_dict(1001.0)
    for name in ("cam_0", "cam_1", "cam_2"):
        assert len(d[name]["warnings"]) == 1 and "later than framesets wait" in d[name]["warnings"][0]
