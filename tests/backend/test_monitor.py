"""The monitor: a converged camera whose residual jumps is flagged, noise and global
changes are not."""

from __future__ import annotations

import numpy as np

from backend.config import MonitorConfig
from backend.monitor import Monitor

C = 8


def _cycle(rng, scale=1.0, bumped=None, factor=1.0):
    r = rng.normal(1.6, 0.15, C).clip(0.8) * scale
    if bumped is not None:
        r[bumped] *= factor
    return r


def test_noise_people_leaving_and_global_changes_raise_no_alarm():
    rng = np.random.default_rng(0)
    m = Monitor(MonitorConfig(), C)
    watched = np.ones(C, bool)
    views = np.full(C, 6)
    for k in range(2000):
        scale = 3.0 if 500 <= k < 600 else 1.0  # everyone's residual triples (a hard scene)
        v = views.copy()
        if 800 <= k < 900:
            v[:] = 1  # people left: one view each, nothing to test
        if k % 7 == 0:
            v[rng.integers(C)] = 0  # a camera without data this cycle
        res = np.where(v > 0, _cycle(rng, scale), np.nan)
        assert m.observe(float(k), watched, res, v) == []
    assert m.alarms == []


def test_a_camera_whose_residual_jumps_is_flagged_after_consecutive_cycles():
    rng = np.random.default_rng(1)
    cfg = MonitorConfig()
    m = Monitor(cfg, C)
    watched = np.ones(C, bool)
    views = np.full(C, 6)
    for k in range(50):
        assert m.observe(float(k), watched, _cycle(rng), views) == []
    flagged = []
    for k in range(50, 50 + cfg.consecutive):
        flagged = m.observe(float(k), watched, _cycle(rng, bumped=3, factor=3.0), views)
    assert [a.cam for a in flagged] == [3] and flagged[0].time == 50 + cfg.consecutive - 1
    assert flagged[0].ratio > 2 * flagged[0].baseline
    # flagged once: its baseline is learnt again before it can be flagged again
    assert m.observe(99.0, watched, _cycle(rng, bumped=3, factor=3.0), views) == []


def test_unwatched_cameras_and_interrupted_runs_are_not_flagged():
    rng = np.random.default_rng(2)
    cfg = MonitorConfig()
    m = Monitor(cfg, C)
    views = np.full(C, 6)
    watched = np.ones(C, bool)
    watched[5] = False  # not converged (yet, or being calibrated again)
    for k in range(50):
        m.observe(float(k), watched, _cycle(rng), views)
    for k in range(50, 80):
        res = _cycle(rng, bumped=5, factor=4.0)
        if k % cfg.consecutive == 0:
            res[2] *= 4.0  # camera 2: suspect now and then, never consecutive cycles long enough
        assert m.observe(float(k), watched, res, views) == []
    disabled = Monitor(MonitorConfig(enabled=False), C)
    for k in range(60):
        assert disabled.observe(float(k), np.ones(C, bool), _cycle(rng, bumped=1, factor=5.0), views) == []
