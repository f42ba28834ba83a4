"""backend/stamp_watch.py: the leads of the sensors' stamps as they arrive ("auto")."""

from __future__ import annotations

import pytest

from backend.stamp_watch import StampWatch

NAMES = ("a", "b", "c", "d", "e")
RATES = {"a": 30.0, "b": 30.5, "c": 29.0, "d": 31.0, "e": 29.5}  # Hz: their frames drift through each other


def _run(watch: StampWatch, seconds: float, offsets: dict[str, float], delays: dict[str, float]):
    """Five sensors at ``RATES`` whose frames arrive ``delays`` after capture, stamped
    ``offsets`` ahead; the data clock is the newest stamp, as offline. Returns the first
    non-empty answer of ``sample`` and the data time it came at (None: none)."""
    last: dict[str, float] = {}
    for k in range(int(seconds * 1000)):  # arrivals every ms
        t = k / 1000
        for s in NAMES:
            capture = int((t - delays.get(s, 0.05)) * RATES[s]) / RATES[s]  # its newest frame that has arrived
            if capture >= 0 and last.get(s) != capture + offsets.get(s, 0.0):
                last[s] = capture + offsets.get(s, 0.0)
                watch.observe(s, last[s])
        if len(last) == len(NAMES):
            far = watch.sample(max(last.values()))
            if far:
                return far, t
    return None, None


def test_a_sensor_whose_stamps_run_ahead_is_named_after_ten_seconds_of_samples():
    w = StampWatch(0.06)
    far, at = _run(w, 30.0, {"c": 0.1}, {})
    assert set(far) == {"c"} and far["c"] == pytest.approx(0.1, abs=0.015)
    assert 9.5 <= at <= 16.0  # 20 samples 0.5 s of data apart, checked every 5 s
    assert w.period("c") == pytest.approx(1 / 29, rel=1e-3)


def test_synchronised_sensors_within_the_lead_are_not_named_and_a_short_delay_reads_as_a_lead():
    delays = {"a": 0.02, "b": 0.05, "c": 0.05, "d": 0.05, "e": 0.08}
    w = StampWatch(0.06)
    assert _run(w, 30.0, {}, delays) == (None, None)
    leads = w.leads()
    # the stamps cannot tell a short delay from a clock ahead: a's delay, 30 ms shorter
    # than most, is its lead (within the bias of sampling at the newest stamp), e's the other way
    assert leads["a"] == pytest.approx(0.03, abs=0.015) and leads["e"] == pytest.approx(-0.03, abs=0.015)
    assert all(abs(leads[s]) < 0.01 for s in "bcd"), leads
    # ... and past auto_lead it starts the estimate (which then finds their clocks fine)
    far, _ = _run(StampWatch(0.02), 30.0, {}, delays)
    assert set(far) == {"a", "e"}
