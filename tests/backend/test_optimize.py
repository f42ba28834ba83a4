"""One cycle's factor graph, solved with real GTSAM."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from backend.associate import Hypothesis
from backend.cameras import Pose
from backend.config import AssociateConfig, OptimizeConfig, RefineConfig
from backend.evaluate import evaluate
from backend.geometry import pose_std, rotation_angle_deg, so3_exp
from backend.optimize import Problem, _drop_inconsistent_views, build_graph, residuals_px, shape_covariance, solve
from backend.preprocess import TORSO, Detection
from backend.refine import initial_covariance

F = 450.0
SIZE = np.array([640.0, 480.0])
C = 5


def look_at(centre, target) -> np.ndarray:
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def rig(n: int = C, radius: float = 4.5, height: float = 2.6):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    t = np.c_[radius * np.cos(a), radius * np.sin(a), height + 0.2 * np.sin(3 * a)]
    R = np.array([look_at(c, [0.0, 0.0, 1.0]) for c in t])
    return R, t


def body(pos, heading, height=1.8) -> np.ndarray:
    """(17, 3) joints of a standing person (world z up) with some random limb offsets."""
    h = height
    lat = np.array([0, 0.03, -0.03, 0.07, -0.07, 0.0877, -0.0877, 0.12, -0.12, 0.13, -0.13,
                    0.0763, -0.0763, 0.08, -0.08, 0.08, -0.08])
    up = np.array([0.93, 0.95, 0.95, 0.94, 0.94, 0.818, 0.818, 0.63, 0.63, 0.47, 0.47,
                   0.526, 0.526, 0.28, 0.28, 0.04, 0.04])
    fwd = np.zeros(17)
    fwd[:3] = [0.06, 0.05, 0.05]
    f = np.array([np.cos(heading), np.sin(heading), 0.0])
    left = np.array([-np.sin(heading), np.cos(heading), 0.0])
    return (np.array([pos[0], pos[1], 0.0]) + h * (lat[:, None] * left + fwd[:, None] * f)
            + np.c_[np.zeros((17, 2)), h * up])


def observe(R, t, c, J, noise_px=0.0, rng=None) -> np.ndarray:
    """(17, 2) normalised coordinates of J in camera c (NaN outside a 640x480 image)."""
    Xc = (J - t[c]) @ R[c]
    xy = Xc[:, :2] / Xc[:, 2:]
    if noise_px:
        xy = xy + rng.normal(0, noise_px / F, xy.shape)
    uv = xy * F + SIZE / 2
    xy[(Xc[:, 2] <= 0.1) | np.any((uv < 0) | (uv > SIZE), axis=1)] = np.nan
    return xy


def people(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [body(rng.uniform(-1.8, 1.8, 2), rng.uniform(0, 2 * np.pi), rng.uniform(1.65, 1.95)) for _ in range(n)]


def hypotheses(R, t, bodies, noise_px=0.0, seed=0) -> list[Hypothesis]:
    """One hypothesis per body with every camera that sees its whole torso."""
    rng = np.random.default_rng(seed)
    out = []
    for i, J in enumerate(bodies):
        cams, xy = [], []
        for c in range(len(R)):
            o = observe(R, t, c, J, noise_px, rng)
            if np.all(np.isfinite(o[list(TORSO)])):
                cams.append(c)
                xy.append(o)
        assert len(cams) >= 3
        xy = np.array(xy)
        sigma = np.where(np.isfinite(xy[..., 0]), max(noise_px, 1.0) / F, np.nan)
        out.append(Hypothesis(float(i), np.array(cams), xy, sigma, J[list(TORSO)].mean(0)))
    return out


def problem(R, t, hyps, *, prior_R=None, prior_t=None, std_t=0.025, std_deg=1.0, config=None, **kw) -> Problem:
    cov = initial_covariance(RefineConfig(initial_std_translation=std_t, initial_std_rotation=std_deg))
    return Problem(cycle=1, R=R.copy(), t=t.copy(),
                   prior_R=(R if prior_R is None else prior_R).copy(),
                   prior_t=(t if prior_t is None else prior_t).copy(),
                   prior_cov=np.repeat(cov[None], len(R), axis=0), focal=np.full(len(R), F),
                   config=config or OptimizeConfig(), hypotheses=tuple(hyps), **kw)


def perturbed(R, t, trans, deg, seed):
    rng = np.random.default_rng(seed)
    R2, t2 = R.copy(), t.copy()
    for c in range(len(R)):
        u = rng.normal(size=3)
        v = rng.normal(size=3)
        R2[c] = so3_exp(np.radians(deg) * u / np.linalg.norm(u)) @ R[c]
        t2[c] = t[c] + trans * v / np.linalg.norm(v)
    return R2, t2


def poses(R, t):
    return {f"c{c}": Pose(R[c], t[c]) for c in range(len(R))}


@pytest.fixture(scope="module")
def truth():
    return rig()


def test_true_poses_and_exact_data_stay_exact(truth):
    R, t = truth
    hyps = hypotheses(R, t, people(25, 0))
    sol = solve(problem(R, t, hyps))
    assert sol.ok and sol.reason == ""
    assert sol.active.all() and np.all(sol.obs_per_camera >= 30)
    assert np.abs(sol.t - t).max() < 1e-6
    assert max(rotation_angle_deg(sol.R[c], R[c]) for c in range(C)) < 1e-6
    assert sol.hypotheses == 25
    assert len(sol.residual_px) == sol.obs_per_camera.sum() and sol.residual_px.max() < 1e-4
    assert np.all(np.isfinite(sol.cov)) and sol.cov.shape == (C, 6, 6)
    for c in range(C):  # marginals: symmetric, positive, tighter than the prior
        assert np.allclose(sol.cov[c], sol.cov[c].T, atol=1e-15)
        assert np.linalg.eigvalsh(sol.cov[c]).min() > 0
    assert np.all(np.diag(sol.cov[0]) < np.diag(initial_covariance(RefineConfig())))


def test_perturbed_poses_with_a_weak_prior_and_noisy_data_improve_a_lot(truth):
    R, t = truth
    hyps = hypotheses(R, t, people(40, 1), noise_px=1.0, seed=1)
    R0, t0 = perturbed(R, t, 0.05, 1.0, seed=2)
    before = evaluate(poses(R0, t0), poses(R, t))
    sol = solve(problem(R0, t0, hyps, std_t=0.1, std_deg=5.0))
    assert sol.ok, sol.reason
    after = evaluate(poses(sol.R, sol.t), poses(R, t))
    # scale and frame come from the (perturbed) prior only: judge the shape
    assert before.shape_position.mean > 0.02 and before.shape_orientation.mean > 0.5
    assert after.shape_position.mean < before.shape_position.mean / 8
    assert after.shape_orientation.mean < before.shape_orientation.mean / 8
    assert sol.final_error < sol.initial_error / 10
    assert np.median(sol.residual_px) < 1.5  # ~ the 1 px noise
    assert sol.iterations >= 1 and sol.seconds > 0


def _with_wrong_view(R, t, hyps, bodies):
    """Hypothesis 0's view in its last camera replaced by that camera's view of another
    person far away (an association error)."""
    h = hyps[0]
    k = len(h.cams) - 1
    c = int(h.cams[k])
    J0 = bodies[0]
    other = min((J for J in bodies[1:] if np.all(np.isfinite(observe(R, t, c, J)[list(TORSO)]))),
                key=lambda J: -np.linalg.norm(J[0] - J0[0]))
    xy = h.xy.copy()
    xy[k] = observe(R, t, c, other)
    sigma = np.where(np.isfinite(xy[..., 0]), h.sigma[0, 0], np.nan)
    bad = Hypothesis(h.time, h.cams, xy, sigma, h.com)
    n_bad = int(np.isfinite(xy[k, :, 0]).sum())
    assert len(h.cams) >= 3 and np.linalg.norm(other[0] - J0[0]) > 1.0
    return [bad] + hyps[1:], c, n_bad


def test_a_wrong_view_is_dropped_by_the_outlier_rounds(truth):
    R, t = truth
    bodies = people(30, 3)
    hyps = hypotheses(R, t, bodies, noise_px=0.5, seed=3)
    bad_hyps, cam, n_bad = _with_wrong_view(R, t, hyps, bodies)
    R0, t0 = perturbed(R, t, 0.02, 0.5, seed=4)
    clean = solve(problem(R0, t0, hyps))
    sol = solve(problem(R0, t0, bad_hyps))
    assert sol.ok, sol.reason
    assert sol.residual_px.max() < 5.0  # noise 0.5 px: nothing wrong left
    assert sol.obs_per_camera[cam] == clean.obs_per_camera[cam] - n_bad
    # elsewhere at most hypothesis 0's joints that only the wrong view made 2-view landmarks
    lost = np.delete(clean.obs_per_camera - sol.obs_per_camera, cam)
    assert np.all((lost >= 0) & (lost <= 17)), lost
    assert max(rotation_angle_deg(sol.R[c], clean.R[c]) for c in range(C)) < 0.02
    assert np.abs(sol.t - clean.t).max() < 0.002
    # without outlier rounds the wrong view stays in and shows
    kept = solve(problem(R0, t0, bad_hyps, config=OptimizeConfig(outlier_rounds=0)))
    assert kept.obs_per_camera[cam] >= sol.obs_per_camera[cam] + n_bad - 3
    assert kept.residual_px.max() > 20.0


def test_a_problem_without_data_fails_cleanly(truth):
    R, t = truth
    sol = solve(problem(R, t, []))
    assert not sol.ok and "no camera" in sol.reason
    assert np.array_equal(sol.R, R) and np.array_equal(sol.t, t)
    assert np.all(np.isnan(sol.cov)) and sol.hypotheses == 0 and not sol.active.any()
    # too few observations for any camera: the same clean failure
    hyps = hypotheses(R, t, people(1, 5))
    sol = solve(problem(R, t, hyps, config=OptimizeConfig(min_camera_observations=100)))
    assert not sol.ok and sol.reason and np.array_equal(sol.t, t)


def test_landmarks_seen_along_nearly_parallel_rays_are_left_out(truth):
    R, t = truth
    hyps = hypotheses(R, t, people(5, 6))
    g = build_graph(hyps, R, t, OptimizeConfig(min_camera_observations=1))
    assert len(g.landmarks) > 50
    assert np.abs(residuals_px(R, t, g.landmarks, g.obs_cam, g.obs_lm, g.obs_xy, np.full(C, F))).max() < 1e-6
    # two cameras side by side (10 cm apart) see a point 4 m away under ~1.4°
    R2 = np.stack([R[0], R[0]])
    t2 = np.stack([t[0], t[0] + R[0][:, 0] * 0.1])
    J = body([0.0, 0.0], 0.0)
    xy = np.stack([observe(R2, t2, 0, J), observe(R2, t2, 1, J)])
    h = Hypothesis(0.0, np.array([0, 1]), xy, np.full((2, 17), 1 / F), J[list(TORSO)].mean(0))
    assert len(build_graph([h], R2, t2, OptimizeConfig(min_camera_observations=1, min_triangulation_angle=2.0)).landmarks) == 0
    assert len(build_graph([h], R2, t2, OptimizeConfig(min_camera_observations=1, min_triangulation_angle=0.5)).landmarks) > 10


def _frames(R, t, bodies_per_frame):
    frames = []
    for k, bodies in enumerate(bodies_per_frame):
        views = []
        for c in range(len(R)):
            dets = []
            for i, J in enumerate(bodies):
                xy = observe(R, t, c, J)
                if np.all(np.isfinite(xy[list(TORSO)])):
                    dets.append(Detection(c, xy, np.where(np.isfinite(xy[:, 0]), 1.0, np.nan), F, k, i))
            if dets:
                views.append(tuple(dets))
        frames.append((float(k), tuple(views)))
    return tuple(frames)


def test_frames_are_associated_in_the_solve(truth):
    R, t = truth
    rng = np.random.default_rng(8)
    frames = _frames(R, t, [[body([-1.5, rng.uniform(-1, 1)], 0.0), body([1.5, rng.uniform(-1, 1)], 2.0)]
                            for _ in range(12)])
    R0, t0 = perturbed(R, t, 0.02, 0.5, seed=9)
    p = Problem(cycle=3, R=R0, t=t0, prior_R=R0, prior_t=t0,
                prior_cov=np.repeat(initial_covariance(RefineConfig())[None], C, axis=0),
                focal=np.full(C, F), config=OptimizeConfig(), frames=frames, associate=AssociateConfig(),
                max_hypotheses=10, spacing=0.0, seed=1, kind="batch")
    sol = solve(p)
    assert sol.ok, sol.reason
    assert sol.hypotheses == 10  # 24 found, thinned to max_hypotheses
    assert np.median(sol.residual_px) < 1e-3
    err = evaluate(poses(sol.R, sol.t), poses(R, t))
    assert err.shape_position.mean < evaluate(poses(R0, t0), poses(R, t)).shape_position.mean / 5


def test_problem_and_solution_survive_pickling(truth):
    R, t = truth
    hyps = hypotheses(R, t, people(20, 10), noise_px=1.0, seed=10)
    R0, t0 = perturbed(R, t, 0.03, 1.0, seed=11)
    frames = _frames(R, t, [[body([0.0, 0.5], 1.0)]])
    p = problem(R0, t0, hyps, frames=frames, associate=AssociateConfig(), gate_px=np.full(C, 30.0))
    p2 = pickle.loads(pickle.dumps(p))
    assert p2 is not p and p2.config == p.config and p2.associate == p.associate
    for name in ("R", "t", "prior_R", "prior_t", "prior_cov", "focal", "gate_px"):
        np.testing.assert_array_equal(getattr(p2, name), getattr(p, name))
    for a, b in zip(p.hypotheses, p2.hypotheses):
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.cams, b.cams)
    assert p2.frames[0][1][0][0].xy.tobytes() == p.frames[0][1][0][0].xy.tobytes()
    s1 = solve(p)
    s2 = pickle.loads(pickle.dumps(solve(p2)))
    assert s2.ok == s1.ok and s2.reason == s1.reason and s2.hypotheses == s1.hypotheses
    np.testing.assert_allclose(s2.R, s1.R, atol=1e-12)
    np.testing.assert_allclose(s2.t, s1.t, atol=1e-12)
    np.testing.assert_allclose(s2.cov, s1.cov, rtol=1e-9, atol=1e-18)
    np.testing.assert_array_equal(s2.obs_per_camera, s1.obs_per_camera)


def _gauge(R, t):
    """(6K, 7) the similarity's directions in the poses' body-frame tangents (the same
    construction as shape_covariance's, written out per camera)."""
    K = len(R)
    G = np.zeros((6 * K, 7))
    for k in range(K):
        for a in range(3):
            w = np.eye(3)[a]
            G[6 * k:6 * k + 3, a] = R[k].T @ w
            G[6 * k + 3:6 * k + 6, a] = R[k].T @ np.cross(w, t[k])
            G[6 * k + 3:6 * k + 6, 3 + a] = R[k].T @ w
        G[6 * k + 3:6 * k + 6, 6] = R[k].T @ t[k]
    return G


@pytest.mark.parametrize("K", [2, 3, 5])
def test_shape_covariance_removes_the_similarity_and_keeps_a_relative_move(K):
    """Uncertainty along the gauge (the world's turn, shift, scale) is no shape
    uncertainty; one camera's own move is. With two cameras the move of one across
    their baseline stays in their centres (half each, as evaluate aligns them by their
    orientations), not in their orientations."""
    rng = np.random.default_rng(K)
    R = np.array([so3_exp(rng.normal(size=3)) for _ in range(K)])
    t = rng.uniform(-4, 4, (K, 3))
    G = _gauge(R, t)
    A = rng.normal(size=(7, 7))
    assert np.abs(shape_covariance(R, t, G @ A @ A.T @ G.T)).max() < 1e-9
    b = t[1] - t[0]
    d = np.cross(b, rng.normal(size=3))
    d *= 0.01 / np.linalg.norm(d)  # 1 cm across the line of cameras 0 and 1
    v = np.zeros(6 * K)
    v[9:12] = R[1].T @ d  # camera 1's centre moves, its orientation stays
    S = shape_covariance(R, t, np.outer(v, v))
    rot = np.sqrt(max(np.trace(S[:3, :3]), np.trace(S[6:9, 6:9])))
    if K == 2:
        assert rot < 1e-7  # not a turn of the orientations
        assert np.sqrt(np.trace(S[3:6, 3:6])) == pytest.approx(0.005, rel=1e-3)
        assert np.sqrt(np.trace(S[9:12, 9:12])) == pytest.approx(0.005, rel=1e-3)
    else:  # a move of one camera is shape: part of it is left with that camera
        assert np.sqrt(np.trace(S[9:12, 9:12])) > 0.002


def test_a_batch_drops_a_view_its_hypothesis_s_other_views_miss_before_the_first_solve():
    """One camera's view of the wrong person in a hypothesis of >= 3 views: dropped when
    the camera's pose is known, kept when it is not (the batch may have to put it right);
    right views stay; two views at odds drop the hypothesis."""
    R, t = rig()
    bodies = people(6, seed=4)
    hyps = hypotheses(R, t, bodies, noise_px=1.0)
    wrong = [i for i, h in enumerate(hyps) if len(h.cams) >= 4][:2]
    other = {i: bodies[(i + 1) % len(bodies)] for i in wrong}
    bad = list(hyps)
    for n, i in enumerate(wrong):  # the first wrong in one view, the second in two
        h = hyps[i]
        xy = h.xy.copy()
        for k in range(n + 1):
            xy[k] = observe(R, t, int(h.cams[k]), other[i])
        bad[i] = Hypothesis(h.time, h.cams, xy, h.sigma, h.com)
    person = np.arange(len(bad))
    known = np.full(C, 2.0)  # px: poses known to a couple of px
    p = problem(R, t, bad, kind="batch", pose_px=known)
    out, pers = _drop_inconsistent_views(list(bad), person, p)
    first = wrong[0]
    assert [len(h.cams) for h in out if h.time == first] == [len(hyps[first].cams) - 1]
    assert hyps[first].cams[0] not in next(h.cams for h in out if h.time == first)
    assert wrong[1] not in pers and len(out) == len(bad) - 1
    for h in out:  # every other hypothesis as it was
        if h.time not in wrong:
            assert len(h.cams) == len(hyps[int(h.time)].cams)
    # a camera the filter is unsure of keeps its view: the batch may be what puts it right
    unsure = known.copy()
    unsure[hyps[first].cams[0]] = 500.0
    out, _ = _drop_inconsistent_views(list(bad), person, problem(R, t, bad, kind="batch", pose_px=unsure))
    assert [len(h.cams) for h in out if h.time == first] == [len(hyps[first].cams)]


def _through_lenses(hyps: list[Hypothesis], lenses: np.ndarray) -> list[Hypothesis]:
    """The hypotheses as lenses (C, 4) off their files see them (fx, fy fractions,
    principal point in focal lengths): K_file^-1 K_lens x."""
    out = []
    for h in hyps:
        d = lenses[h.cams]
        xy = h.xy * (1.0 + d[:, None, :2]) + d[:, None, 2:]
        out.append(Hypothesis(h.time, h.cams, xy, h.sigma, h.com))
    return out


@pytest.fixture(scope="module")
def lens_scene():
    R, t = rig(8, radius=5.0)
    hyps = hypotheses(R, t, people(150, 7), noise_px=1.0, seed=7)
    R0, t0 = perturbed(R, t, 0.05, 1.0, seed=8)
    return R, t, hyps, R0, t0


def _batch(R0, t0, hyps, lenses: tuple[int, ...]) -> Problem:
    return problem(R0, t0, hyps, std_t=0.25, std_deg=5.0, kind="batch", lenses=lenses,
                   config=OptimizeConfig(max_iterations=100))


def test_lenses_as_good_as_their_files_are_kept(lens_scene):
    R, t, hyps, R0, t0 = lens_scene
    with_lenses = solve(_batch(R0, t0, hyps, tuple(range(8))))
    without = solve(_batch(R0, t0, hyps, ()))
    assert with_lenses.ok and without.ok
    assert with_lenses.lenses is None and with_lenses.lens_std is None  # the estimates scatter by their noise only
    assert np.array_equal(with_lenses.t, without.t) and np.array_equal(with_lenses.R, without.R)


def test_lenses_off_their_files_are_estimated_and_the_poses_fit_them(lens_scene):
    R, t, hyps, R0, t0 = lens_scene
    rng = np.random.default_rng(3)
    off = np.c_[np.repeat(rng.normal(0, 0.02, 8)[:, None], 2, axis=1), rng.normal(0, 0.01, (8, 2))]
    seen = _through_lenses(hyps, off)
    kept = solve(_batch(R0, t0, seen, ()))
    sol = solve(_batch(R0, t0, seen, tuple(range(8))))
    assert kept.ok and sol.ok, (kept.reason, sol.reason)
    assert sol.lens_std is not None and sol.lenses is not None
    assert 0.01 < sol.lens_std[0] < 0.04 and 0.003 < sol.lens_std[2] < 0.03  # the spread drawn: 0.02, 0.01
    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    # the focal lengths trade with each camera's distance, the principal points with its turn: found to a part
    assert rms(sol.lenses[:, :2] - off[:, :2]) < rms(off[:, :2]) / 3  # 0.0077 of 0.028 (focal fraction)
    assert rms(sol.lenses[:, 2:] - off[:, 2:]) < rms(off[:, 2:]) / 2  # 0.0046 of 0.0106 (focal lengths)
    before = evaluate(poses(kept.R, kept.t), poses(R, t)).shape_position.mean
    after = evaluate(poses(sol.R, sol.t), poses(R, t)).shape_position.mean
    assert after < before / 3, (before, after)  # 0.097 -> 0.021 m
    # residuals through the estimated lenses: the 1 px noise (Rayleigh median 1.18)
    assert np.median(sol.residual_px) < np.median(kept.residual_px) and np.median(sol.residual_px) < 1.25
    # only the cameras asked for: the others keep their files' lenses
    part = solve(_batch(R0, t0, seen, (0, 2, 3, 5, 6)))
    assert part.ok and part.lenses is not None
    assert np.isnan(part.lenses[[1, 4, 7]]).all() and np.isfinite(part.lenses[[0, 2, 3, 5, 6]]).all()


def test_the_final_std_carries_the_lenses_accuracy(lens_scene):
    """Lenses 1 % off their files, kept as the files (the solve is asked for no lens): the
    keypoints' noise alone states a std the poses are far outside of; with the files'
    accuracy (``optimize.lens_accuracy_*`` 1 %) the stated std is about their error."""
    R, t, hyps, R0, t0 = lens_scene
    off = np.random.default_rng(11).normal(0, 0.01, (8, 4))
    seen = _through_lenses(hyps, off)
    cfg = OptimizeConfig(max_iterations=100, lens_accuracy_focal=0.01, lens_accuracy_centre=0.01)
    sol = solve(problem(R0, t0, seen, std_t=0.25, std_deg=5.0, kind="batch", config=cfg, lens_accuracy=True))
    assert sol.ok and sol.lenses is None and sol.cov_shape_lenses is not None
    acc = evaluate(poses(sol.R, sol.t), poses(R, t))
    err = np.array([acc.per_camera[n][2] for n in poses(R, t)])
    noise, _ = pose_std(sol.cov_shape)
    both, _ = pose_std(sol.cov_shape_lenses)
    assert np.all(both > 5 * noise)  # 21 mm against 1.0 mm
    # the 3D error against sqrt(3) x the per-axis std: 1 on average when the std is honest
    z_noise, z_both = err / (np.sqrt(3) * noise), err / (np.sqrt(3) * both)
    assert np.sqrt(np.mean(z_noise ** 2)) > 5  # 19.6
    assert 0.5 < np.sqrt(np.mean(z_both ** 2)) < 1.6, (err, both)  # 0.98 (0.93-1.43 for other draws and 0.3 %)
    # focal lengths the data show off (2 %) are estimated, their uncertainty the solve's own;
    # the principal points they show no spread of are held, and their errors considered: the
    # turn of each camera, which a principal point's shift mimics, is the less certain
    far = np.c_[np.repeat(np.random.default_rng(3).normal(0, 0.02, 8)[:, None], 2, axis=1), np.zeros((8, 2))]
    est = solve(problem(R0, t0, _through_lenses(hyps, far), std_t=0.25, std_deg=5.0, kind="batch", config=cfg,
                        lenses=tuple(range(8)), lens_accuracy=True))
    assert est.ok and est.lenses is not None and est.cov_shape_lenses is not None
    assert est.lens_std[0] > 0.01 and est.lens_std[2] < 1e-3, est.lens_std
    turn, turned = pose_std(est.cov_shape)[1], pose_std(est.cov_shape_lenses)[1]
    assert np.all(turned > 2 * turn), (turn, turned)  # 0.07-0.08° -> 0.43-0.56° (1 % of the focal length: 0.57°)
    # not asked (every cycle), or no accuracy stated: nothing added
    assert solve(problem(R0, t0, seen, std_t=0.25, std_deg=5.0, kind="batch", config=cfg)).cov_shape_lenses is None
    none = cfg.model_copy(update={"lens_accuracy_focal": 0.0, "lens_accuracy_centre": 0.0})
    quiet = solve(problem(R0, t0, seen, std_t=0.25, std_deg=5.0, kind="batch", config=none, lens_accuracy=True))
    assert quiet.cov_shape_lenses is None and np.array_equal(quiet.t, sol.t)
