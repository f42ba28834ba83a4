"""Rotations, SE(3) in GTSAM's conventions, Umeyama alignment, triangulation, segments."""

from __future__ import annotations

import numpy as np
import pytest

from backend.geometry import (
    R_to_quat,
    _least_median_start,
    align_poses,
    closest_points_segments,
    from_prior,
    pose_compose,
    pose_inverse,
    pose_local,
    pose_retract,
    quat_to_R,
    rotation_angle_deg,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    triangulate_batch,
    triangulate_dlt,
    trimmed_similarity,
    umeyama,
)


def _random_rotations(n, rng):
    out = [np.eye(3), so3_exp([np.pi, 0, 0]), so3_exp([0, np.pi - 1e-6, 0]), so3_exp([1e-9, 0, 0])]
    for _ in range(n):
        out.append(so3_exp(rng.normal(size=3) * rng.uniform(0, 3)))
    return out


def test_quaternion_round_trip_and_convention():
    rng = np.random.default_rng(0)
    for R in _random_rotations(50, rng):
        q = R_to_quat(R)
        assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1)
        np.testing.assert_allclose(quat_to_R(q), R, atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1) and np.allclose(R.T @ R, np.eye(3))
    # (x, y, z, w): 90° about z maps x to y
    R = quat_to_R([0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # not normalised on input: normalised here
    np.testing.assert_allclose(quat_to_R([0, 0, 2, 2]), R, atol=1e-12)


def test_so3_exp_log_inverse_including_near_pi():
    rng = np.random.default_rng(1)
    for R in _random_rotations(100, rng):
        np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-9)
    w = np.array([0.3, -0.4, 1.2])
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-12)
    assert rotation_angle_deg(np.eye(3), so3_exp([0, 0, np.radians(33)])) == pytest.approx(33)
    assert rotation_angle_deg(np.eye(3), so3_exp([np.pi, 0, 0])) == pytest.approx(180)


def test_se3_exp_log_retract_local():
    rng = np.random.default_rng(2)
    for _ in range(50):
        axis = rng.normal(size=3)
        w = axis / np.linalg.norm(axis) * rng.uniform(0, 3.0)  # |ω| < π: log is unique
        xi = np.concatenate([w, rng.normal(size=3) * 3])
        R, t = se3_exp(xi)
        np.testing.assert_allclose(se3_log(R, t), xi, atol=1e-9)
        Ra, ta = so3_exp(rng.normal(size=3)), rng.normal(size=3)
        Rb, tb = pose_retract(Ra, ta, xi)
        np.testing.assert_allclose(pose_local(Ra, ta, Rb, tb), xi, atol=1e-9)
    Ri, ti = pose_inverse(Ra, ta)
    Rc, tc = pose_compose(Ra, ta, Ri, ti)
    np.testing.assert_allclose(Rc, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(tc, 0, atol=1e-12)


def test_se3_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(3)
    for _ in range(20):
        xi = np.concatenate([rng.normal(size=3), rng.normal(size=3) * 2])
        R, t = se3_exp(xi)
        P = gtsam.Pose3.Expmap(xi)
        np.testing.assert_allclose(R, P.rotation().matrix(), atol=1e-12)
        np.testing.assert_allclose(t, P.translation(), atol=1e-12)
        A = gtsam.Pose3(gtsam.Rot3(so3_exp(rng.normal(size=3))), rng.normal(size=3))
        B = A.retract(xi)
        Rb, tb = pose_retract(A.rotation().matrix(), A.translation(), xi)
        np.testing.assert_allclose(Rb, B.rotation().matrix(), atol=1e-9)
        np.testing.assert_allclose(tb, B.translation(), atol=1e-9)
        np.testing.assert_allclose(pose_local(A.rotation().matrix(), A.translation(), Rb, tb),
                                   A.localCoordinates(B), atol=1e-7)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_a_known_transform(with_scale):
    rng = np.random.default_rng(4)
    src = rng.normal(size=(20, 3)) * [5, 4, 1]
    R = so3_exp([0.4, -1.1, 2.0])
    s = 1.37 if with_scale else 1.0
    t = np.array([3.0, -2.0, 0.5])
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst, with_scale=with_scale)
    assert s2 == pytest.approx(s, abs=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_a_trimmed_similarity_keeps_the_majority_where_a_block_of_points_is_metres_off():
    """Twenty camera centres over a 30 x 10 m lab 0.75 m off each, the five at one end (a
    room the bootstrap chained through a wrong pair) turned 65° about the middle as a block.
    Without the least median start the fit of all of them is turned 22° and, trimmed at 3x
    its median residual, keeps the block; with it the fit is the majority's. A sound start
    stands as it was."""
    rng = np.random.default_rng(0)
    dst = np.c_[rng.uniform(0, 30, 20), rng.uniform(0, 10, 20), rng.uniform(2.4, 2.8, 20)]
    Rw, s, tw = so3_exp([0.1, -0.3, 2.0]), 0.4, np.array([1.0, -2.0, 0.5])
    src = ((dst + rng.normal(0, 0.75 / np.sqrt(3), dst.shape)) - tw) @ Rw / s  # dst ≈ s·Rw·src + tw
    block = np.argsort(dst[:, 0]) < 5
    calm = src.copy()
    middle = src.mean(0)
    src[block] = (src[block] - middle) @ so3_exp([0.0, 0.0, np.radians(65)]).T + middle
    sf, Rf, tf, keep = trimmed_similarity(src, dst)
    assert keep.tolist() == (~block).tolist()
    assert rotation_angle_deg(Rf, Rw) < 3.0 and abs(sf / s - 1) < 0.03
    res = np.linalg.norm(sf * src @ Rf.T + tf - dst, axis=1)
    assert np.median(res[~block]) < 1.0 and res[block].min() > 3.0
    assert _least_median_start(calm, dst, s, Rw, tw, 0.2) == (s, Rw, tw)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    src = rng.normal(size=(10, 3))
    dst = src * [1, 1, -1]  # a mirror image
    _, R, _ = umeyama(src, dst, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_is_least_squares():
    """Against a numerical minimiser of the same cost."""
    scipy_opt = pytest.importorskip("scipy.optimize")
    rng = np.random.default_rng(6)
    src = rng.normal(size=(12, 3)) * 3
    dst = src @ so3_exp([0.2, 0.1, -0.3]).T + [1, 2, 3] + rng.normal(size=(12, 3)) * 0.2

    def cost(x):
        return np.sum((src @ so3_exp(x[:3]).T + x[3:] - dst) ** 2)

    best = scipy_opt.minimize(cost, np.zeros(6), method="BFGS", options={"gtol": 1e-10})
    s, R, t = umeyama(src, dst, with_scale=False)
    assert s == 1.0
    assert np.sum((src @ R.T + t - dst) ** 2) <= best.fun + 1e-9
    np.testing.assert_allclose(R, so3_exp(best.x[:3]), atol=1e-5)


def test_triangulate_dlt_exact():
    rng = np.random.default_rng(7)
    X = np.array([0.5, -0.3, 4.0])
    P, xy = [], []
    for _ in range(4):
        R = so3_exp(rng.normal(size=3) * 0.2)  # world_R_cam
        c = rng.normal(size=3)
        Rt = R.T
        P.append(np.concatenate([Rt, (-Rt @ c)[:, None]], axis=1))
        Xc = Rt @ (X - c)
        xy.append(Xc[:2] / Xc[2])
    np.testing.assert_allclose(triangulate_dlt(np.array(P), np.array(xy)), X, atol=1e-9)


def test_triangulate_batch_exact_in_chunks_and_nan_where_underdetermined(monkeypatch):
    """Points seen by 1-6 of 8 cameras (missing views NaN): exact where >= 2 views, NaN
    else; the same points in many small chunks give the same result to the bit."""
    import backend.geometry as geometry

    rng = np.random.default_rng(3)
    C, N, V = 8, 500, 6
    R = np.array([so3_exp(rng.normal(size=3) * 0.15) for _ in range(C)])  # roughly looking along +z
    t = np.c_[rng.uniform(-2, 2, (C, 2)), np.full(C, -6.0)]
    X = rng.uniform(-1, 1, (N, 3))
    cams = np.array([rng.permutation(C)[:V] for _ in range(N)])
    Xc = np.einsum("nvji,nvj->nvi", R[cams], X[:, None] - t[cams])
    xy = Xc[..., :2] / Xc[..., 2:]
    seen = rng.integers(1, V + 1, N)
    xy[np.arange(V)[None] >= seen[:, None]] = np.nan
    got = triangulate_batch(R, t, cams, xy)
    np.testing.assert_allclose(got[seen >= 2], X[seen >= 2], atol=1e-9)
    assert np.isnan(got[seen < 2]).all()
    monkeypatch.setattr(geometry, "_TRIANGULATE_CHUNK", 37)
    assert np.array_equal(triangulate_batch(R, t, cams, xy), got, equal_nan=True)
    assert np.isnan(triangulate_batch(R, t, cams[:5, :1], xy[:5, :1])).all()  # one view: 2 rows, thin SVD


def _brute_force(p0, p1, q0, q1, n=301):
    s = np.linspace(0, 1, n)
    a = p0 + s[:, None] * (p1 - p0)
    b = q0 + s[:, None] * (q1 - q0)
    return np.min(np.linalg.norm(a[:, None] - b[None], axis=-1))


def test_closest_points_segments_against_brute_force():
    rng = np.random.default_rng(8)
    cases = [rng.normal(size=(4, 3)) for _ in range(30)]
    cases.append(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float))  # parallel
    cases.append(np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0]], float))  # parallel, disjoint
    cases.append(np.array([[0, 0, 0], [0, 0, 0], [1, 1, 0], [1, -1, 0]], float))  # a point
    cases.append(np.array([[0, 0, 0], [1, 0, 0], [2, 2, 2], [2, 2, 2]], float))  # a point
    p0, p1, q0, q1 = (np.array([c[i] for c in cases]) for i in range(4))
    d, cp, cq = closest_points_segments(p0, p1, q0, q1)
    np.testing.assert_allclose(d, np.linalg.norm(cp - cq, axis=1), atol=1e-12)
    for i, c in enumerate(cases):
        bf = _brute_force(*c)
        assert bf - 3e-2 <= d[i] <= bf + 1e-9, (i, d[i], bf)
    # broadcasting over leading axes
    d2, _, _ = closest_points_segments(p0[:, None], p1[:, None], q0[None, :3], q1[None, :3])
    assert d2.shape == (len(cases), 3)


def test_rotation_angle_is_precise_near_zero_and_pi():
    rng = np.random.default_rng(9)
    for R in _random_rotations(20, rng):
        assert rotation_angle_deg(R, R) < 1e-12
        tiny = so3_exp(rng.normal(size=3) * 1e-3)
        axis = so3_log(tiny)
        assert rotation_angle_deg(R, R @ tiny) == pytest.approx(np.degrees(np.linalg.norm(axis)), rel=1e-9)
    assert rotation_angle_deg(np.eye(3), so3_exp([0, 0, np.pi - 1e-9])) == pytest.approx(180.0)


def _rough(rng, R, t, d, deg):
    """Poses each moved by exactly d m and turned by exactly deg (as bench's starts are)."""
    u = rng.normal(size=t.shape)
    w = rng.normal(size=t.shape)
    t2 = t + d * u / np.linalg.norm(u, axis=1, keepdims=True)
    R2 = np.array([so3_exp(np.radians(deg) * wi / np.linalg.norm(wi)) @ Ri for wi, Ri in zip(w, R)])
    return R2, t2


@pytest.mark.parametrize("layout", ["corridor", "room"])
def test_the_turn_about_a_corridor_comes_from_the_orientations_where_the_centres_leave_it(layout):
    """Six cameras along a corridor, 0.5 m left and right of its axis, estimated 1.5 m / 45°
    off each: their centres leave the turn about the axis to noise (the reconciliation of
    such an estimate turned the data's shape 75° about it); the orientations hold it. In a
    room the centres hold every axis and the fit is the centres' alone, to the bit."""
    rng = np.random.default_rng(3)
    C = 6
    if layout == "corridor":
        t = np.c_[3.5 * np.arange(C), 0.5 * (-1.0) ** np.arange(C), np.full(C, 2.6)]
    else:
        a = np.linspace(0, 2 * np.pi, C, endpoint=False)
        t = np.c_[4 * np.cos(a), 3 * np.sin(a), rng.uniform(2.4, 3.0, C)]
    Rw_true = so3_exp([0.4, -0.2, 1.1])
    errors = {False: [], True: []}
    for trial in range(20):
        R = np.array([so3_exp(rng.normal(size=3)) for _ in range(C)])
        R0, t0 = _rough(rng, R, t, 1.5, 45.0)  # the initial estimate, in the true frame
        Rs = np.einsum("ij,cjk->cik", Rw_true.T, R)  # the data's shape: another frame and scale
        ts = 0.3 * (t - 5.0) @ Rw_true
        for joint in (False, True):
            al = align_poses(Rs, ts, R0, t0, orientations=joint)
            errors[joint].append(rotation_angle_deg(al.Rw, Rw_true))
    centres, both = np.array(errors[False]), np.array(errors[True])
    if layout == "corridor":
        assert np.median(centres) > 20 and np.median(both) < 0.5 * np.median(centres)
        assert np.max(both) < 30
    else:
        assert np.array_equal(centres, both)


def test_from_prior_measures_a_move_in_metres_degrees_and_its_chi2():
    """A pose moved by a known tangent step from its prior: the centre's distance, the
    turn, and the Mahalanobis χ² under the prior's covariance; NaN χ² for a singular one."""
    R0, t0 = quat_to_R(np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9])), np.array([1.0, 2.0, 2.5])
    xi = np.array([0.0, 0.0, np.radians(2.0), 0.03, 0.0, 0.0])  # 2° about the camera's z, 3 cm along its x
    R, t = pose_retract(R0, t0, xi)
    P = np.diag([np.radians(1.0) ** 2] * 3 + [0.01 ** 2] * 3)
    m, deg, chi2 = from_prior(R0, t0, P, R, t)
    assert m == pytest.approx(np.linalg.norm(t - t0)) and deg == pytest.approx(2.0, abs=1e-9)
    local = pose_local(R0, t0, R, t)
    assert chi2 == pytest.approx(float(local @ np.linalg.solve(P, local)))
    assert chi2 > 4.0  # 2 std in turn alone
    assert np.isnan(from_prior(R0, t0, np.zeros((6, 6)), R, t)[2])

