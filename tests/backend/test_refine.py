"""Refinement: the Kalman filter on SE(3) per camera and the scale of the initial estimate."""

from __future__ import annotations

import numpy as np
import pytest

from backend.config import RefineConfig
from backend.geometry import pose_local, pose_retract, rotation_angle_deg, so3_exp, umeyama
from backend.refine import Refiner, initial_covariance

C = 4


def _initial():
    rng = np.random.default_rng(0)
    R = np.array([so3_exp(rng.normal(size=3)) for _ in range(C)])
    t = rng.uniform(-5, 5, (C, 3))
    return R, t


def _moved(R, t, xi):
    """Every camera moved by the tangent vector xi (C, 6) (right perturbation)."""
    out = [pose_retract(R[c], t[c], xi[c]) for c in range(len(R))]
    return np.array([a for a, _ in out]), np.array([b for _, b in out])


def test_posterior_update_takes_the_solution_and_its_covariance():
    R0, t0 = _initial()
    rf = Refiner(RefineConfig(keep_scale=False), R0, t0)
    xi = np.tile([0.01, -0.02, 0.005, 0.03, 0.0, -0.01], (C, 1))
    R1, t1 = _moved(R0, t0, xi)
    cov = np.repeat(np.diag([1e-5] * 3 + [1e-4] * 3)[None], C, axis=0)
    active = np.array([True, True, False, True])
    upd = rf.update(active, R1, t1, cov)
    for c in range(C):
        if active[c]:
            assert np.allclose(rf.R[c], R1[c]) and np.allclose(rf.t[c], t1[c])
            assert np.allclose(rf.P[c], cov[c])
        else:
            assert np.array_equal(rf.R[c], R0[c]) and np.array_equal(rf.t[c], t0[c])
    assert rf.cycles.tolist() == [1, 1, 0, 1]
    assert upd.changed_translation[2] == 0.0 and upd.changed_translation[0] == pytest.approx(np.linalg.norm(t1[0] - t0[0]))
    assert upd.changed_rotation[0] == pytest.approx(rotation_angle_deg(R0[0], R1[0]))
    # a camera whose marginal is not finite keeps its state
    bad = cov.copy()
    bad[1] = np.nan
    R2, t2 = _moved(R1, t1, xi)
    rf.update(np.ones(C, bool), R2, t2, bad)
    assert np.allclose(rf.t[1], t1[1]) and np.allclose(rf.t[0], t2[0])


def test_marginal_update_moves_part_of_the_way_and_shrinks_the_covariance():
    R0, t0 = _initial()
    cfg = RefineConfig(measurement="marginal", keep_scale=False)
    rf = Refiner(cfg, R0, t0)
    Pp = rf.predicted_covariance()
    xi = np.tile([0.02, 0.01, -0.01, 0.02, -0.03, 0.01], (C, 1))
    R1, t1 = _moved(R0, t0, xi)
    S = Pp.copy()  # measurement as uncertain as the prediction: gain 1/2
    rf.update(np.ones(C, bool), R1, t1, S)
    for c in range(C):
        step = pose_local(R0[c], t0[c], rf.R[c], rf.t[c])
        assert np.allclose(step, 0.5 * xi[c], atol=1e-9)
        assert np.allclose(rf.P[c], 0.5 * Pp[c])
    # a precise measurement (S << P) is followed almost all the way
    rf2 = Refiner(cfg, R0, t0)
    rf2.update(np.ones(C, bool), R1, t1, Pp * 1e-4)
    for c in range(C):
        assert np.allclose(pose_local(R0[c], t0[c], rf2.R[c], rf2.t[c]), xi[c], atol=1e-5)
        assert np.all(np.linalg.eigvalsh(rf2.P[c]) < 1e-3 * np.linalg.eigvalsh(Pp[c]).min())


def test_process_noise_grows_the_covariance_of_cameras_without_data():
    R0, t0 = _initial()
    cfg = RefineConfig(measurement="marginal", keep_scale=False, process_noise=0.05)
    rf = Refiner(cfg, R0, t0)
    P0 = rf.P.copy()
    Q = np.diag([np.radians(cfg.filter_std_rotation)] * 3 + [cfg.filter_std_translation] * 3) ** 2 * 0.05**2
    assert np.allclose(rf.predicted_covariance(), P0 + Q)
    active = np.array([True, False, False, False])
    for k in range(3):
        rf.update(active, R0, t0, np.repeat(P0[:1], C, axis=0) * 0.01)
    for c in (1, 2, 3):
        assert np.allclose(rf.P[c], P0[c] + 3 * Q)  # grows by Q each cycle
        assert np.array_equal(rf.t[c], t0[c])
    assert np.trace(rf.P[0]) < np.trace(P0[0])
    assert rf.cycles.tolist() == [3, 0, 0, 0]
    # the posterior mode does the same for cameras outside the cycle
    rp = Refiner(RefineConfig(keep_scale=False), R0, t0)
    rp.update(active, R0, t0, np.repeat(P0[:1], C, axis=0) * 0.01)
    assert np.allclose(rp.P[1], P0[1] + Q)


def test_keep_scale_restores_the_initial_scale():
    R0, t0 = _initial()
    rf = Refiner(RefineConfig(keep_scale=True), R0, t0)
    # the solution moved the cameras a little and blew the layout up by 4 %
    rng = np.random.default_rng(1)
    centre = t0.mean(0)
    t1 = centre + 1.04 * (t0 - centre) + rng.normal(0, 0.01, t0.shape)
    R1 = np.array([so3_exp(rng.normal(0, 0.005, 3)) @ R0[c] for c in range(C)])
    cov = np.repeat(np.diag([1e-6] * 3 + [1e-4] * 3)[None], C, axis=0)
    upd = rf.update(np.ones(C, bool), R1, t1, cov)
    assert upd.scale_applied == pytest.approx(1 / 1.04, rel=0.01)
    s, _, _ = umeyama(rf.t, t0, with_scale=True)
    assert s == pytest.approx(1.0, abs=1e-3)  # a robust (median) scale: equal up to the noise
    # only the scale was undone: the shape and the orientations are the solution's
    s1, Ra, ta = umeyama(t1, rf.t, with_scale=True)
    assert np.allclose(Ra, np.eye(3), atol=1e-9)
    assert np.allclose(rf.R, R1)
    assert np.allclose(rf.P[:, 3:, 3:], cov[:, 3:, 3:] * upd.scale_applied**2)
    # without keep_scale the solution's scale stays
    rf2 = Refiner(RefineConfig(keep_scale=False), R0, t0)
    rf2.update(np.ones(C, bool), R1, t1, cov)
    assert umeyama(rf2.t, t0, with_scale=True)[0] == pytest.approx(1 / 1.04, rel=0.01)


def test_converged_needs_enough_cycles_small_change_and_small_std():
    R0, t0 = _initial()
    cfg = RefineConfig(keep_scale=False, converged_cycles=5)
    tight = np.repeat(np.diag([np.radians(0.01) ** 2] * 3 + [0.0005**2] * 3)[None], C, axis=0)
    rf = Refiner(cfg, R0, t0)
    assert not rf.converged(0) and rf.change(0) == (float("inf"), float("inf"))
    for k in range(4):
        rf.update(np.ones(C, bool), R0, t0, tight)
        assert not rf.converged(0)  # too few cycles
    rf.update(np.ones(C, bool), R0, t0, tight)
    assert rf.converged(0) and rf.change(0) == (0.0, 0.0)
    st, sr = rf.std(0)
    assert st == pytest.approx(0.0005) and sr == pytest.approx(0.01)
    # a large std is not convergence, however still the pose is
    loose = np.repeat(np.diag([np.radians(2.0) ** 2] * 3 + [0.1**2] * 3)[None], C, axis=0)
    rl = Refiner(cfg, R0, t0)
    for k in range(6):
        rl.update(np.ones(C, bool), R0, t0, loose)
    assert rl.std(0) == pytest.approx((0.1, 2.0)) and not rl.converged(0)
    # nor is a pose still moving 5 cm per cycle, however small the std
    rm = Refiner(cfg, R0, t0)
    R, t = R0.copy(), t0.copy()
    for k in range(6):
        t = t + [0.05, 0.0, 0.0]
        rm.update(np.ones(C, bool), R, t, tight)
    assert rm.change(0)[0] >= 0.05 and not rm.converged(0)
    # ...nor one still turning 1° per cycle
    rr = Refiner(cfg, R0, t0)
    R = R0.copy()
    for k in range(6):
        R = np.array([so3_exp([0.0, np.radians(1.0), 0.0]) @ R[c] for c in range(C)])
        rr.update(np.ones(C, bool), R, t0, tight)
    assert rr.change(0)[1] >= 1.0 and not rr.converged(0)
    # ...until it settles for converged_cycles cycles
    for k in range(5):
        rm.update(np.ones(C, bool), rm.R.copy(), rm.t.copy(), tight)
    assert rm.change(0) == (0.0, 0.0) and rm.converged(0)


def test_initial_covariance_is_the_configured_std():
    P = initial_covariance(RefineConfig(initial_std_translation=0.025, initial_std_rotation=1.0))
    assert np.allclose(np.sqrt(np.diag(P)), [np.radians(1.0)] * 3 + [0.025] * 3)
    R0, t0 = _initial()
    rf = Refiner(RefineConfig(initial_std_translation=0.025, initial_std_rotation=1.0), R0, t0)
    assert rf.std(2) == pytest.approx((0.025, 1.0))


def test_one_camera_placed_far_off_does_not_rescale_the_others():
    # a network of 12 (with 4, half the camera pairs would involve the bad one)
    rng = np.random.default_rng(3)
    n = 12
    R0 = np.array([so3_exp(rng.normal(size=3)) for _ in range(n)])
    t0 = rng.uniform(-5, 5, (n, 3))
    rf = Refiner(RefineConfig(keep_scale=True), R0, t0)
    t1 = t0.copy()
    t1[0] += [15.0, 0.0, 0.0]  # one camera metres off (a wrong re-localisation)
    cov = np.repeat(np.diag([1e-6] * 3 + [1e-4] * 3)[None], n, axis=0)
    upd = rf.update(np.ones(n, bool), R0.copy(), t1, cov)
    assert upd.scale_applied == pytest.approx(1.0, abs=0.05)
    others = np.arange(1, n)
    d = np.linalg.norm(rf.t[others][:, None] - rf.t[others][None], axis=2)
    d0 = np.linalg.norm(t0[others][:, None] - t0[others][None], axis=2)
    assert np.allclose(d, d0, rtol=0.05, atol=1e-9)


def test_held_cameras_keep_their_pose_scale_and_covariance_through_cycles_but_not_a_batch():
    R0, t0 = _initial()
    rf = Refiner(RefineConfig(measurement="marginal", keep_scale=True), R0, t0)
    rf.held = np.array([True, True, False, True])
    P_held = rf.P.copy()
    xi = np.tile([0.02, 0.01, -0.01, 0.05, -0.03, 0.01], (C, 1))
    R1, t1 = _moved(R0, t0, xi)
    cov = np.repeat(np.diag([1e-6] * 3 + [1e-5] * 3)[None], C, axis=0)
    rf.update(np.ones(C, bool), R1, t1, cov)
    for c in (0, 1, 3):  # held: not moved, not rescaled, no more certain
        assert np.array_equal(rf.R[c], R0[c]) and np.array_equal(rf.t[c], t0[c])
        assert np.array_equal(rf.P[c], P_held[c])
    assert rf.cycles.tolist() == [0, 0, 1, 0]
    assert np.linalg.norm(rf.t[2] - t0[2]) > 0.01  # the free camera took its data
    # a batch over all data is every camera's posterior, held or not
    rf.update(np.ones(C, bool), R1, t1, cov, posterior=True, final=True)
    assert np.allclose(rf.t, t1)


def test_a_new_world_frame_moves_every_pose_and_keeps_the_covariances_and_the_drift():
    R0, t0 = _initial()
    rf = Refiner(RefineConfig(keep_scale=False), R0, t0)
    xi = np.tile([0.01, -0.02, 0.005, 0.03, 0.0, -0.01], (C, 1))
    cov = np.repeat(np.diag([1e-5] * 3 + [1e-4] * 3)[None], C, axis=0)
    for k in range(3):
        rf.update(np.ones(C, bool), *_moved(rf.R, rf.t, xi), cov)
    before = (rf.R.copy(), rf.t.copy(), rf.P.copy(), rf.S.copy(), [rf.change(c) for c in range(C)])
    F, o = so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, -2.0, 0.5])
    rf.reframe(F, o)
    assert np.allclose(rf.R, F @ before[0]) and np.allclose(rf.t, (before[1] - o) @ F.T)
    assert np.allclose(rf.t0, (t0 - o) @ F.T) and np.allclose(rf.prior_R, F @ R0)
    assert np.array_equal(rf.P, before[2]) and np.array_equal(rf.S, before[3])  # each camera's own tangent space
    assert np.allclose([rf.change(c) for c in range(C)], before[4])  # its recent moves are no drift
    with pytest.raises(AssertionError):
        rf.reframe(2.0 * F, o)
