"""The monitor: a converged camera whose data-only pose keeps disagreeing with its
prediction is flagged; noise, single bad cycles and unwatched cameras are not."""

from __future__ import annotations

import numpy as np
import pytest

from backend.config import MonitorConfig
from backend.geometry import pose_retract
from backend.monitor import Monitor, innovation

C = 6
CFG = MonitorConfig(enabled=True)


def _noise(rng, std_rot_deg=0.3, std_t=0.03):
    """One cycle's innovation: (d, S) with d drawn from S."""
    S = np.diag([np.radians(std_rot_deg) ** 2] * 3 + [std_t**2] * 3)
    return rng.multivariate_normal(np.zeros(6), S), S


def test_noise_and_moderately_bad_cycles_raise_no_alarm():
    rng = np.random.default_rng(0)
    m = Monitor(CFG, C)
    watched = np.ones(C, bool)
    for k in range(3000):
        inn = [_noise(rng) if rng.random() > 0.2 else None for _ in range(C)]
        if k % 97 == 0:  # a cycle of wrong associations: one camera's data 0.2 m / 1° off, once
            d, S = inn[k % C] or _noise(rng)
            inn[k % C] = (d + np.r_[np.radians([1.0, 0, 0]), 0.2, 0, 0], S)
        assert m.observe(float(k), watched, inn) == [], k
    assert m.alarms == []


def test_a_camera_whose_data_keep_disagreeing_is_flagged_within_a_window():
    rng = np.random.default_rng(1)
    m = Monitor(CFG, C)
    watched = np.ones(C, bool)
    for k in range(40):
        assert m.observe(float(k), watched, [_noise(rng) for _ in range(C)]) == []
    bump = np.r_[np.radians([0.0, 2.0, 0.0]), 0.05, 0.0, 0.0]  # 2° and 5 cm
    alarms = []
    for k in range(40, 40 + CFG.window):
        inn = [_noise(rng) for _ in range(C)]
        inn[2] = (inn[2][0] + bump, inn[2][1])
        alarms += m.observe(float(k), watched, inn)
    assert [a.cam for a in alarms] == [2]
    assert alarms[0].rotation == pytest.approx(2.0, abs=0.5) and alarms[0].chi2 > CFG.chi2


def test_unwatched_or_disabled_cameras_are_never_flagged():
    rng = np.random.default_rng(2)
    bump = np.r_[np.radians([0.0, 0.0, 3.0]), 0.0, 0.1, 0.0]
    watched = np.ones(C, bool)
    watched[4] = False
    for cfg, w in ((CFG, watched), (MonitorConfig(enabled=False), np.ones(C, bool))):
        m = Monitor(cfg, C)
        for k in range(30):
            inn = [_noise(rng) for _ in range(C)]
            inn[4] = (inn[4][0] + bump, inn[4][1])
            assert m.observe(float(k), w, inn) == []


def test_innovation_recovers_the_data_only_deviation():
    """A prior and a measurement fused as a Kalman update: the innovation is the
    measurement's offset from the prior, with the sum of both covariances."""
    rng = np.random.default_rng(3)
    R0 = np.eye(3)
    t0 = np.array([1.0, 2.0, 3.0])
    P = np.diag([1e-4] * 3 + [1e-3] * 3)
    Rm = np.diag([4e-4] * 3 + [4e-3] * 3)
    z = rng.normal(size=6) * 0.01  # the data-only deviation
    K = P @ np.linalg.inv(P + Rm)
    R1, t1 = pose_retract(R0, t0, K @ z)
    post = (np.eye(6) - K) @ P
    d, S = innovation(R0, t0, P, R1, t1, post)
    np.testing.assert_allclose(d, z, atol=2e-5)
    np.testing.assert_allclose(S, P + Rm, rtol=1e-6)
    assert innovation(R0, t0, P, R1, t1, np.full((6, 6), np.nan)) is None
    assert innovation(R0, t0, P, R1, t1, P) is None  # no information from the data
