"""The split-half check of the stated std (backend/split_check.py)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.geometry import so3_exp
from backend.split_check import SQRT3, SplitCheck, compare_halves, interleaved_halves


def _rig(C: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = np.stack([so3_exp(rng.normal(0, 0.5, 3)) for _ in range(C)])
    t = rng.uniform(-5, 5, (C, 3))
    return R, t


def _cov(C: int, std_m: float, std_rad: float) -> np.ndarray:
    return np.repeat(np.diag([std_rad**2] * 3 + [std_m**2] * 3)[None], C, axis=0)


def test_halves_alternate_blocks_of_data_time():
    half = interleaved_halves(np.array([100.0, 105.0, 110.0, 119.9, 120.0, 135.0]), 10.0)
    assert half.tolist() == [0, 0, 1, 1, 0, 1]
    assert interleaved_halves(np.zeros(0), 10.0).shape == (0,)


def test_halves_that_agree_within_their_stds_change_nothing():
    R, t = _rig()
    C, std = len(t), 0.01
    rng = np.random.default_rng(1)
    # each half off by its own noise of sqrt(2) std per axis, and saying so: honest stds
    half = _cov(C, np.sqrt(2) * std, 1e-3)
    halves = [(R, t + rng.normal(0, np.sqrt(2) * std, t.shape), np.ones(C, bool), half) for _ in range(2)]
    chk = compare_halves([f"cam_{c}" for c in range(C)], _cov(C, std, 1e-3), halves, ratio=2.5)
    assert chk.widened == [] and np.all(chk.factor == 1.0)
    assert np.all(chk.apart_m < 2.5 * SQRT3 * 2 * std)
    assert "as the stated std predicts" in chk.summary()


def test_a_half_with_little_data_that_says_so_is_no_surprise():
    R, t = _rig()
    C = len(t)
    t1 = t.copy()
    t1[3] += [0.0, 0.2, 0.0]
    wide = _cov(C, 0.014, 1e-3)
    wide[3] = np.diag([1e-4] * 3 + [0.15**2] * 3)  # the second half barely saw cam_3
    halves = [(R, t, np.ones(C, bool), _cov(C, 0.014, 1e-3)), (R, t1, np.ones(C, bool), wide)]
    chk = compare_halves([f"cam_{c}" for c in range(C)], _cov(C, 0.01, 1e-3), halves, ratio=2.5)
    assert chk.apart_m[3] > 0.15 and chk.widened == []


def test_a_camera_the_halves_place_far_apart_gets_the_std_the_data_show():
    R, t = _rig()
    C, std = len(t), 0.01
    t1 = t.copy()
    t1[2] += [0.3, 0.0, 0.0]  # 30 cm apart, where the halves' stds allow sqrt(3) * 2 cm: 8.7 times that
    half = _cov(C, np.sqrt(2) * std, 1e-3)
    halves = [(R, t, np.ones(C, bool), half), (R, t1, np.ones(C, bool), half)]
    chk = compare_halves([f"cam_{c}" for c in range(C)], _cov(C, std, 1e-3), halves, ratio=2.5)
    assert chk.widened == ["cam_2"]
    # the robust alignment leaves cam_2's difference to cam_2 (least squares would spread
    # it over the others: 0.03-0.10 m each, and name them too)
    assert chk.apart_m[2] == pytest.approx(0.3, rel=0.1)
    assert np.all(np.delete(chk.apart_m, 2) < 0.03)
    assert chk.factor[2] == pytest.approx(chk.apart_m[2] / SQRT3 / (2 * std), rel=1e-9) and chk.factor[2] > 7
    assert "cam_2" in chk.summary() and f"{chk.factor[2]:.1f}x" in chk.summary()
    back = SplitCheck.from_dict(chk.to_dict())
    assert back.widened == ["cam_2"] and back.factor[2] == pytest.approx(chk.factor[2], abs=0.01)


def test_a_turn_the_halves_disagree_on_counts_too():
    R, t = _rig()
    C = len(t)
    R1 = R.copy()
    R1[4] = so3_exp(np.array([0.0, 0.0, np.radians(2.0)])) @ R[4]  # 2° apart, stated 0.05°
    half = _cov(C, 0.014, np.radians(0.05) * np.sqrt(2))
    halves = [(R, t, np.ones(C, bool), half), (R1, t, np.ones(C, bool), half)]
    chk = compare_halves([f"cam_{c}" for c in range(C)], _cov(C, 0.01, np.radians(0.05)), halves, ratio=2.5)
    # the robust mean leaves nearly all of the 2° to cam_4: a factor of about 2 / sqrt(3) / 0.1 = 11.5
    assert chk.widened == ["cam_4"] and chk.factor[4] == pytest.approx(2.0 / SQRT3 / 0.1, rel=0.03)
    assert np.all(np.delete(chk.apart_deg, 4) < 0.1)


def test_a_camera_missing_from_a_half_is_not_judged():
    R, t = _rig()
    C = len(t)
    gone = np.ones(C, bool)
    gone[1] = False
    t1 = t.copy()
    t1[1] += 5.0
    half = _cov(C, 0.014, 1e-3)
    chk = compare_halves([f"cam_{c}" for c in range(C)], _cov(C, 0.01, 1e-3),
                         [(R, t, np.ones(C, bool), half), (R, t1, gone, half)], ratio=2.5)
    assert np.isnan(chk.apart_m[1]) and chk.factor[1] == 1.0 and chk.widened == []
