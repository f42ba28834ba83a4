"""The initial estimate's scale against the people's (backend/scale_check.py)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.cameras import load_extrinsics
from backend.config import BootstrapConfig
from backend.people import ScaleEstimate
from backend.scale_check import ScaleCheck, check_scale, initial_scale_std


@pytest.fixture(scope="module")
def centres(lab_dir) -> np.ndarray:
    ref = load_extrinsics(lab_dir / "reference.yaml")
    return np.array([e.pose.t for e in ref.values()])


def _people(factor: float, rel_std: float, method: str = "known height") -> ScaleEstimate:
    return ScaleEstimate(factor, rel_std, method, 2, (1.9, 1.7))


def _lsq_scale(src: np.ndarray, dst: np.ndarray) -> float:
    a, b = src - src.mean(0), dst - dst.mean(0)
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    return float((S[0] + S[1] + d * S[2]) / np.sum(a**2))


def test_the_initial_estimates_scale_std_is_what_its_scatter_predicts(centres):
    # 0.75 m per camera (0.433 m per axis): the least-squares scale of 20 such centres
    rng = np.random.default_rng(3)
    errors, predicted = [], []
    for _ in range(300):
        init = centres + rng.normal(0, 0.433, centres.shape)
        std, keep = initial_scale_std(init, centres)
        if keep.all():
            predicted.append(std)
            errors.append(np.log(_lsq_scale(centres, init)))
    assert len(errors) > 200
    spread = np.sqrt(np.sum((centres - centres.mean(0)) ** 2))
    assert np.median(predicted) == pytest.approx(0.433 / spread, rel=0.15)
    assert np.std(errors) == pytest.approx(np.median(predicted), rel=0.2)


@pytest.mark.parametrize("mode, expect", [("keep", 1.0), ("people", 1.04), ("combine", None)])
def test_each_mode_corrects_the_scale_as_it_says(centres, mode, expect):
    rng = np.random.default_rng(0)
    final = centres * 1.0  # the run's result: the initial estimate's scale
    init = centres + rng.normal(0, 0.25, centres.shape)
    people = _people(1.04, 0.01)  # the people: the result's metre is 1.04 true metres
    c = check_scale(init, final, np.ones(len(centres), bool), people, BootstrapConfig(), mode=mode)
    assert c is not None and c.mode == mode and not c.refused
    if expect is not None:
        assert c.factor == pytest.approx(expect, abs=1e-12)
    else:  # between the two, by their variances
        w = c.initial_rel_std**2 / (c.initial_rel_std**2 + 0.01**2)
        assert 0.05 < w < 0.95
        assert c.factor == pytest.approx(1.04**w, rel=1e-9)
        assert c.rel_std < min(c.initial_rel_std, 0.01)
    # the correction scales about the cameras' centroid: the frame stays
    got = c.apply(final)
    assert np.allclose(got.mean(0), final.mean(0))
    assert np.linalg.norm(got[0] - got[1]) == pytest.approx(c.factor * np.linalg.norm(final[0] - final[1]))
    assert ScaleCheck.from_dict(c.to_dict()).to_dict() == c.to_dict()


def test_auto_combines_with_known_heights_and_keeps_with_the_population_prior(centres):
    used = np.ones(len(centres), bool)
    init = centres + np.random.default_rng(2).normal(0, 0.25, centres.shape)
    known = check_scale(init, centres, used, _people(1.03, 0.01), BootstrapConfig())
    prior = check_scale(init, centres, used, _people(1.03, 0.04, "population prior"), BootstrapConfig())
    assert known.mode == "combine" and known.corrected
    assert prior.mode == "keep" and not prior.corrected and "kept" in prior.summary()


def test_a_scale_the_two_disagree_on_is_not_corrected(centres):
    # an initial estimate in feet: the people say its unit is 0.3048 m
    rng = np.random.default_rng(1)
    init = centres + rng.normal(0, 0.1, centres.shape)
    c = check_scale(init, centres, np.ones(len(centres), bool), _people(0.3048, 0.015), BootstrapConfig(),
                    mode="people")
    assert c.refused and not c.corrected and c.factor == 1.0
    assert "NOT corrected" in c.summary() and c.sigmas > BootstrapConfig().refuse_sigma


def test_too_few_cameras_give_no_check(centres):
    used = np.zeros(len(centres), bool)
    used[:3] = True
    assert check_scale(centres, centres, used, _people(1.0, 0.01), BootstrapConfig()) is None
