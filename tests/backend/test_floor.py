"""The floor the people walk on (backend/floor.py): the plane of each hypothesis' lower ankle."""

from __future__ import annotations

import numpy as np
import pytest

from backend.floor import GATE_M, MIN_POINTS, fit_floor, held_ankles, lower_ankles


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float)).as_matrix()


def _walkers(rng, H: int, *, tilt=np.eye(3), width=3.0, length=8.0, lift=0.15, noise=0.02):
    """H hypotheses of upright people on the plane z = 0 (ankle joints 0.07 m above it),
    one foot on the floor and the other up to ``lift`` in the air, turned by ``tilt``:
    (landmarks (L, 3), lm_hyp (L,), lm_joint (L,)) with both ankles, both hips and the
    shoulders; the lower ankle of each is its first ankle landmark."""
    pts, hyp, joint = [], [], []
    for h in range(H):
        c = np.array([rng.uniform(0, length), rng.uniform(-width / 2, width / 2), 0.0])
        feet = [c + [0.1, 0.1, 0.07], c + [-0.1, -0.1, 0.07 + rng.uniform(0.02, lift)]]
        body = {15: feet[0], 16: feet[1], 11: c + [0, 0.1, 0.95], 12: c + [0, -0.1, 0.95],
                5: c + [0, 0.18, 1.45], 6: c + [0, -0.18, 1.45]}
        for j, x in body.items():
            pts.append(tilt @ (x + rng.normal(0, noise, 3)))
            hyp.append(h)
            joint.append(j)
    return np.array(pts), np.array(hyp), np.array(joint)


def test_the_plane_of_the_lower_ankles_is_found_through_noise_and_raised_feet():
    rng = np.random.default_rng(0)
    tilt = _rot([1, 0.3, 0], 12.0)  # a world frame whose z is not up: the plane's own normal
    X, hyp, joint = _walkers(rng, 300, tilt=tilt)
    f = fit_floor(X, hyp, joint, sigma=0.05)
    assert f is not None
    n_true = tilt @ [0, 0, 1]
    assert np.degrees(np.arccos(f.n @ n_true)) < 0.5
    assert f.d == pytest.approx(0.07, abs=0.01)
    assert f.points == 300 and f.spread == pytest.approx(0.05)  # the noise (2 cm) is below the stated sigma
    # each hypothesis' lower ankle (the l_ankle of _walkers) is the one held, but where
    # the other is lifted by less than the noise
    held = held_ankles(X, hyp, joint, f)
    assert len(held) == 300 and np.mean(joint[held] == 15) > 0.9


@pytest.mark.parametrize("rise", [0.4, 1.5])
def test_feet_off_the_floor_do_not_tilt_it(rise):
    rng = np.random.default_rng(1)
    X, hyp, joint = _walkers(rng, 300)
    # a fifth of the people stand on a step (0.4 m) or a stage (1.5 m) at one end: the
    # floor stays level
    on_step_hyp = np.unique(hyp[(joint == 15) & (X[:, 0] > 6.4)])
    on_step = np.isin(hyp, on_step_hyp)
    X = X + np.outer(on_step, [0, 0, rise])
    f = fit_floor(X, hyp, joint, sigma=0.05)
    assert f is not None and np.degrees(np.arccos(f.n[2])) < 1.0 and f.d == pytest.approx(0.07, abs=0.02)
    held = held_ankles(X, hyp, joint, f)
    if rise > GATE_M:  # those on the stage are not held to the floor below it
        assert not np.isin(hyp[held], on_step_hyp).any() and len(held) >= 300 - len(on_step_hyp) - 5
    else:  # a step is within any floor's noise of a bent chain: held, the robust kernel lets them go
        assert len(held) == 300


def test_a_line_of_ankles_takes_its_roll_from_the_bodies():
    rng = np.random.default_rng(2)
    # people walk one line (x), the ankles' width across it 3 cm: the roll about x is
    # the bodies' up, not the noise's least-spread direction
    X, hyp, joint = _walkers(rng, 200, width=0.02, noise=0.03)
    f = fit_floor(X, hyp, joint, sigma=0.05)
    assert f is not None and np.degrees(np.arccos(f.n[2])) < 1.5


def test_no_floor_from_too_few_ankles_or_a_plane_far_from_level():
    rng = np.random.default_rng(3)
    X, hyp, joint = _walkers(rng, MIN_POINTS - 1)
    assert fit_floor(X, hyp, joint, sigma=0.05) is None
    # the ankles on a 40° ramp, the bodies upright: not one floor people stand on
    X, hyp, joint = _walkers(rng, 200)
    ramp = np.isin(joint, (15, 16))
    X[ramp, 2] += np.tan(np.radians(40.0)) * X[ramp, 0]
    assert fit_floor(X, hyp, joint, sigma=0.05) is None
    assert fit_floor(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64), sigma=0.05) is None


def test_lower_ankles_needs_both_ankles_and_something_above_them():
    X = np.array([[0, 0, 0.07], [0.2, 0, 0.1], [0, 0, 1.0],  # hypothesis 0: both ankles, a hip
                  [1, 0, 0.07], [1, 0, 1.0],  # 1: one ankle
                  [2, 0, 0.07], [2.2, 0, 0.07]], float)  # 2: ankles only
    hyp = np.array([0, 0, 0, 1, 1, 2, 2])
    joint = np.array([15, 16, 11, 15, 11, 15, 16])
    ank, up, which = lower_ankles(X, hyp, joint)
    assert which.tolist() == [0] and ank.tolist() == [[0, 1]]
    assert up[0] == pytest.approx(np.array([-0.1, 0, 0.915]) / np.linalg.norm([-0.1, 0, 0.915]))


@pytest.fixture(scope="module")
def corridor_batch():
    """A 3-camera corridor, 1 walker for 60 s, twice the simulator's pixel noise, from
    0.25 m / 10°: the final batch's problem over the archived frames."""
    from backend.cameras import CameraSet, Extrinsics
    from backend.config import EngineConfig
    from backend.perturb import perturb_extrinsics
    from backend.pipeline import Pipeline
    from edge_clients.sim import SimConfig, Simulator
    from edge_clients.sim.scenes import corridor

    scene = corridor(3)
    sim = Simulator(scene, SimConfig(persons=1, duration=60.0, seed=5, heights=(1.80,), noise_scale=2.0))
    ref = {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}
    cams = CameraSet.combine(dict(scene.intrinsics), perturb_extrinsics(ref, 0.25, 10.0, seed=5))
    p = Pipeline(cams, EngineConfig())
    for _, msg in sim.messages():
        p.push(msg)
        p.advance(p.clock)
    p.advance(p.clock + 1.0)
    return p._batch_problem(1000, 0.1, final=True)


def test_an_adjustment_with_bones_holds_the_lower_ankles_to_one_plane(corridor_batch):
    from dataclasses import replace

    from backend.geometry import so3_log
    from backend.optimize import solve

    prob = corridor_batch
    on, off = (solve(replace(prob, config=prob.config.model_copy(update={"bones": "batch", "floor": f})))
               for f in (True, False))
    assert on.ok and off.ok, (on.reason, off.reason)
    assert off.floor is None and off.floor_points == 0 and on.floor is not None
    assert on.floor_points >= MIN_POINTS
    # the initial estimate keeps cam_0's pose, so its world is the truth's: z up, within the start's 10°
    assert np.degrees(np.arccos(on.floor.n[2])) < 10.0
    # the floor turns with the network: holding the ankles to it does not turn the network
    # (a plane held fixed in each round did, by 4° a round: docs/bones.md, "Session 34")
    turn = [np.degrees(np.linalg.norm(so3_log(a.T @ b))) for a, b in zip(on.R, off.R)]
    assert max(turn) < 1.0, turn
    # without bones (a network with three-way views) no floor either: it goes with them
    plain = solve(replace(prob, config=prob.config.model_copy(update={"bones": "off", "floor": True})))
    assert plain.ok and plain.floor is None and plain.floor_points == 0


def test_the_world_frame_of_a_floor_puts_the_first_camera_over_its_origin():
    from backend.floor import world_frame

    rng = np.random.default_rng(3)
    n = _rot([1.0, 0.3, 0.0], 14.0) @ [0.0, 0.0, 1.0]
    centres = rng.normal(size=(4, 3)) * 3.0 + 2.5 * n
    centres[1] = centres[0] + 0.05 * rng.normal(size=3) + 2.0 * n  # over the first: no x axis from it
    F, o, k = world_frame(n, 0.4, centres)
    assert np.allclose(F @ F.T, np.eye(3)) and np.isclose(np.linalg.det(F), 1.0)
    assert np.allclose(F @ n, [0.0, 0.0, 1.0]) and np.isclose(o @ n, 0.4)
    new = (centres - o) @ F.T
    assert k == 2 and np.allclose(new[0, :2], 0.0) and np.isclose(new[k, 1], 0.0) and new[k, 0] > 0.1
    assert np.allclose(new[:, 2], centres @ n - 0.4)  # heights above the floor kept
    assert world_frame(n, 0.4, centres[:2]) is None
