"""Association: depth intervals from the torso, greedy matching, the reprojection gate."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from backend.associate import (Associator, depth_interval, epipolar_miss, intersect_rays, torso_centre,
                               triangulate_torso)
from backend.config import AssociateConfig
from backend.preprocess import TORSO, Detection

F = 450.0  # px focal length of the rig's cameras (640x480)
SIZE = np.array([640.0, 480.0])


def look_at(centre, target) -> np.ndarray:
    """world_R_cam of a camera at ``centre`` looking at ``target`` (world z up, no roll)."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def rig(n: int = 4, half: float = 4.0, height: float = 2.6):
    """n cameras on a circle of radius ``half`` around the origin, looking at (0, 0, 1)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3
    t = np.c_[half * np.cos(a), half * np.sin(a), np.full(n, height)]
    R = np.array([look_at(c, [0.0, 0.0, 1.0]) for c in t])
    return R, t


def body(pos, heading=0.0, height=1.8) -> np.ndarray:
    """(17, 3) joints of a standing person at floor point pos (x, y), world z up."""
    h = height
    # lateral (left +), height fractions; the face a little forward
    lat = {0: 0, 1: 0.03, 2: -0.03, 3: 0.07, 4: -0.07, 5: 0.0877, 6: -0.0877, 7: 0.12, 8: -0.12, 9: 0.13,
           10: -0.13, 11: 0.0763, 12: -0.0763, 13: 0.08, 14: -0.08, 15: 0.08, 16: -0.08}
    up = {0: 0.93, 1: 0.95, 2: 0.95, 3: 0.94, 4: 0.94, 5: 0.818, 6: 0.818, 7: 0.63, 8: 0.63, 9: 0.47,
          10: 0.47, 11: 0.526, 12: 0.526, 13: 0.28, 14: 0.28, 15: 0.04, 16: 0.04}
    fwd = {0: 0.06, 1: 0.05, 2: 0.05}
    f = np.array([np.cos(heading), np.sin(heading), 0.0])
    left = np.array([-np.sin(heading), np.cos(heading), 0.0])
    return np.array([[pos[0], pos[1], 0.0] + h * (lat[j] * left + fwd.get(j, 0.0) * f + [0, 0, up[j]])
                     for j in range(17)])


def observe(R, t, c, J) -> np.ndarray:
    """Normalised image coordinates (17, 2) of joints J in camera c; NaN outside the image."""
    Xc = (J - t[c]) @ R[c]
    xy = Xc[:, :2] / Xc[:, 2:]
    uv = xy * F + SIZE / 2
    out = (Xc[:, 2] <= 0.1) | np.any((uv < 0) | (uv > SIZE), axis=1)
    xy[out] = np.nan
    return xy


def detection(R, t, c, J, index=-1) -> Detection:
    xy = observe(R, t, c, J)
    assert np.all(np.isfinite(xy[list(TORSO)])), "the torso must be in view"
    return Detection(c, xy, np.where(np.isfinite(xy[:, 0]), 2.0, np.nan), F, 0, index)


# ------------------------------------------------------------------ depth interval


def _sample_depths(seed, n, *, max_radius, tilt_deg=15.0, fx=426.0, size=(848, 480), hidden=()):
    """n random persons (1.70-2.00 m, random yaw, tilted by N(0, tilt_deg) about each
    axis) whose torso is inside a wide-lens image (the lab's 848x480, fx 426: ~90°
    across), seen by a camera pitched down 20-45°, with the torso centre's ray within
    ``max_radius`` (normalised) of the optical axis: rows (true depth, lo, hi, |centre|)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    W, H = size
    m = 4 * n
    h = rng.uniform(1.70, 2.00, m)
    body = np.zeros((m, 4, 3))  # body frame: x forward, y left, z up; shoulders, hips
    body[:, 0] = np.c_[0 * h, 0.1753 * h / 2, 0.2924 * h / 2]
    body[:, 1] = np.c_[0 * h, -0.1753 * h / 2, 0.2924 * h / 2]
    body[:, 2] = np.c_[0 * h, 0.1526 * h / 2, -0.2924 * h / 2]
    body[:, 3] = np.c_[0 * h, -0.1526 * h / 2, -0.2924 * h / 2]
    yaw = Rotation.from_rotvec(np.c_[np.zeros((m, 2)), rng.uniform(0, 2 * np.pi, m)])
    tilt = Rotation.from_rotvec(rng.normal(size=(m, 3)) * np.radians(tilt_deg))
    p = np.radians(rng.uniform(20, 45, m))
    # camera axes in the body's world frame (x right, y down, z forward)
    zc = np.c_[np.cos(p), 0 * p, -np.sin(p)]
    xc = np.tile([0.0, -1.0, 0.0], (m, 1))
    yc = np.cross(zc, xc)
    Rwc = np.stack([xc, yc, zc], axis=2)
    Jw = np.einsum("mij,mkj->mki", (tilt * yaw).as_matrix(), body)
    Jc = np.einsum("mji,mkj->mki", Rwc, Jw)
    d = rng.uniform(1.5, 9.0, m)
    if np.isfinite(max_radius):  # uniform in the disc
        a, rr = rng.uniform(0, 2 * np.pi, m), max_radius * np.sqrt(rng.uniform(size=m))
        c = rr[:, None] * np.c_[np.cos(a), np.sin(a)]
    else:
        c = np.c_[rng.uniform(-W / 2, W / 2, m), rng.uniform(-H / 2, H / 2, m)] / fx
    Xc = Jc + d[:, None, None] * np.c_[c, np.ones(m)][:, None, :]
    ok = np.all(Xc[..., 2] > 0.2, axis=1)
    xy4 = Xc[..., :2] / np.where(ok[:, None], Xc[..., 2], 1.0)[..., None]
    uv = xy4 * fx + [W / 2, H / 2]
    ok &= np.all((uv >= 0) & (uv <= [W, H]), axis=(1, 2))
    out = []
    for k in np.flatnonzero(ok)[:n]:
        xy = np.full((17, 2), np.nan)
        xy[list(TORSO)] = xy4[k]
        xy[[TORSO[i] for i in hidden]] = np.nan
        lo, hi = depth_interval(xy, AssociateConfig())
        out.append((Xc[k, :, 2].mean(), lo, hi, np.linalg.norm(c[k])))
    assert len(out) == n
    return np.array(out)


def test_depth_interval_contains_the_true_depth_near_the_optical_axis():
    s = _sample_depths(0, 2000, max_radius=0.3)  # within ~17° of the axis
    z, lo, hi = s[:, 0], s[:, 1], s[:, 2]
    inside = (lo <= z) & (z <= hi)
    assert inside.all(), f"{(~inside).sum()} of {len(z)} outside, worst z/hi {np.max(z / hi):.3f}"
    # not absurdly wide: the worst-case orientation costs at most a factor ~2.5
    assert np.median(hi / lo) < 2.2 and np.max(hi / lo) < 2.6


def test_depth_interval_contains_the_true_depth_anywhere_in_a_wide_lens_image():
    """The lab's 848x480 cameras see ~90° across: off the axis a segment's image is longer
    than L/z (x = X/Z stretches by up to sqrt(1 + |x|²)), so the interval must allow for it."""
    s = _sample_depths(1, 2000, max_radius=np.inf)
    z, lo, hi, r = s.T
    inside = (lo <= z) & (z <= hi)
    worst = int(np.argmax(z / hi))
    assert inside.all(), (f"{(~inside).sum()} of {len(z)} persons outside their depth interval; worst: "
                          f"true depth {z[worst]:.2f} m > upper bound {hi[worst]:.2f} m "
                          f"at |xy| = {r[worst]:.2f} off the axis")


def test_depth_interval_with_one_side_of_the_torso_hidden_still_contains_the_true_depth():
    """A profile view's far shoulder and hip are hidden (preprocess.partial_torso): no
    width bounds the depth, the torso alone must, loosely."""
    s = _sample_depths(2, 2000, max_radius=np.inf, hidden=(1, 3))
    z, lo, hi = s[:, 0], s[:, 1], s[:, 2]
    inside = (lo <= z) & (z <= hi)
    assert inside.all(), f"{(~inside).sum()} of {len(z)} outside"
    full = _sample_depths(2, 2000, max_radius=np.inf)
    assert np.all(lo <= full[:, 1])  # looser than with both widths ...
    assert np.median(hi / z) < 1.25 * np.median(full[:, 2] / full[:, 0])  # ... but bounded above as well


def test_depth_interval_scales_with_the_person():
    J = body([0.0, 0.0], heading=-np.pi / 2, height=1.85)  # facing the camera
    Rc = look_at([0.0, -4.0, 1.0], [0.0, 0.0, 1.0])[None]
    tc = np.array([[0.0, -4.0, 1.0]])
    xy = observe(Rc, tc, 0, J)
    lo, hi = depth_interval(xy, AssociateConfig())
    assert lo < 4.0 < hi and hi - lo < 4.0
    far = observe(Rc, tc - [0.0, 4.0, 0.0], 0, J)  # twice as far
    lo2, hi2 = depth_interval(far, AssociateConfig())
    assert lo2 == pytest.approx(2 * lo, rel=0.05) and hi2 == pytest.approx(2 * hi, rel=0.05)


# ------------------------------------------------------------------ association


def _cams_of(h):
    return sorted(int(c) for c in h.cams)


def test_two_persons_far_apart_in_three_cameras():
    R, t = rig(3)
    A = body([-1.2, 0.4], heading=0.3)
    B = body([1.3, -0.6], heading=2.0)
    # camera 2 does not see B (say, occluded)
    views = [[detection(R, t, 0, A), detection(R, t, 0, B)],
             [detection(R, t, 1, B), detection(R, t, 1, A)],
             [detection(R, t, 2, A)]]
    assoc = Associator(AssociateConfig())
    hyps = assoc(5.0, views, R, t)
    assert len(hyps) == 2 and assoc.created == 2
    by_cams = {tuple(_cams_of(h)): h for h in hyps}
    assert set(by_cams) == {(0, 1, 2), (0, 1)}
    com_a = A[list(TORSO)].mean(0)
    com_b = B[list(TORSO)].mean(0)
    assert np.linalg.norm(by_cams[(0, 1, 2)].com - com_a) < 0.05
    assert np.linalg.norm(by_cams[(0, 1)].com - com_b) < 0.05
    h = by_cams[(0, 1, 2)]
    assert h.time == 5.0 and h.xy.shape == (3, 17, 2) and h.sigma.shape == (3, 17)
    k = list(h.cams).index(2)
    assert np.allclose(h.sigma[k][np.isfinite(h.sigma[k])], 2.0 / F)


def _two_persons_one_camera_in_profile(R, t):
    """Two persons seen whole by cameras 0 and 1, each with its far shoulder and hip
    hidden from camera 2 (preprocess.partial_torso): (A, B) joints, views."""
    A = body([-1.2, 0.4], heading=0.3)
    B = body([1.3, -0.6], heading=2.0)

    def profile(c, J, hide):
        d = detection(R, t, c, J)
        xy = d.xy.copy()
        xy[hide] = np.nan
        return Detection(c, xy, np.where(np.isfinite(xy[:, 0]), 2.0, np.nan), F, 0, -1)

    return A, B, [[detection(R, t, 0, A), detection(R, t, 0, B)],
                  [detection(R, t, 1, B), detection(R, t, 1, A)],
                  [profile(2, A, [6, 8, 10, 12]), profile(2, B, [5, 7, 9, 11])]]


def test_a_person_seen_in_profile_follows_the_other_views_of_that_person():
    """A view with one side hidden joins the hypothesis of its person's whole views
    where its camera's pose is known (follow_px finite)."""
    R, t = rig(3)
    A, B, views = _two_persons_one_camera_in_profile(R, t)
    assoc = Associator(AssociateConfig())
    hyps = assoc(0.0, views, R, t, follow_px=np.full(3, 25.0))
    assert len(hyps) == 2 and assoc.followed == 2
    for h in hyps:
        assert _cams_of(h) == [0, 1, 2]
        J = A if np.linalg.norm(h.com - A[list(TORSO)].mean(0)) < 0.3 else B
        k = list(h.cams).index(2)
        seen = np.isfinite(h.xy[k, :, 0])
        assert np.allclose(h.xy[k, seen], observe(R, t, 2, J)[seen])  # camera 2's view of this person


def test_a_view_in_profile_is_dropped_where_its_camera_is_not_known():
    """Without a follow gate for its camera, or with its camera at a wrong pose, a view
    with one side hidden joins nobody (its depth is unbounded from below: its segment
    would meet anyone along its ray) and is counted."""
    R, t = rig(3)
    _, _, views = _two_persons_one_camera_in_profile(R, t)
    for follow in (None, np.array([25.0, 25.0, np.inf])):
        assoc = Associator(AssociateConfig())
        hyps = assoc(0.0, views, R, t, follow_px=follow)
        assert len(hyps) == 2 and all(_cams_of(h) == [0, 1] for h in hyps)
        assert assoc.rejected["side_view_unmatched"] == 2
    wrong_R, wrong_t = R.copy(), t.copy()  # camera 2 turned 10° about its vertical and 1 m aside
    wrong_R[2] = wrong_R[2] @ Rotation.from_euler("y", 10, degrees=True).as_matrix()
    wrong_t[2] += [1.0, 0.0, 0.0]
    assoc = Associator(AssociateConfig())
    hyps = assoc(0.0, views, wrong_R, wrong_t, follow_px=np.full(3, 25.0))
    assert len(hyps) == 2 and all(_cams_of(h) == [0, 1] for h in hyps)
    assert assoc.followed == 0 and assoc.rejected["side_view_unmatched"] == 2


def test_a_pair_that_a_profile_view_rivals_is_not_made():
    """Camera 0 sees A whole and B in profile, camera 1 only B. Among whole views alone
    the two cameras each see one person, and their segments pair A with B; camera 0's
    profile of B meets camera 1's B closer, so the pair is dropped (and counted). The
    same whole views without the profile make the pair: the profile is the evidence."""
    R, t = rig(2)
    A = body([0.2, -0.3], heading=1.0)
    B = body([0.5, 0.1], heading=2.5, height=1.7)
    b0 = detection(R, t, 0, B)
    xy = b0.xy.copy()
    xy[[6, 8, 10, 12]] = np.nan  # B's right side hidden from camera 0
    profile = Detection(0, xy, np.where(np.isfinite(xy[:, 0]), 2.0, np.nan), F, 0, -1)
    whole = [[detection(R, t, 0, A)], [detection(R, t, 1, B)]]
    cfg = AssociateConfig()
    assert len(Associator(cfg)(0.0, whole, R, t)) == 1  # segments alone pair A with B
    assoc = Associator(cfg)
    assert assoc(0.0, [[detection(R, t, 0, A), profile], [detection(R, t, 1, B)]], R, t) == []
    assert assoc.rejected["pair_rivalled_by_side_view"] == 2
    # a profile of someone else, off to the side, rivals nothing: A's pair with A stays
    C = body([-2.5, 2.0], heading=0.0)
    c0 = detection(R, t, 0, C)
    xy = c0.xy.copy()
    xy[[5, 7, 9, 11]] = np.nan
    other = Detection(0, xy, np.where(np.isfinite(xy[:, 0]), 2.0, np.nan), F, 0, -1)
    assoc = Associator(cfg)
    [h] = assoc(0.0, [[detection(R, t, 0, A), other], [detection(R, t, 1, A)]], R, t)
    assert _cams_of(h) == [0, 1] and assoc.rejected["pair_rivalled_by_side_view"] == 0


def test_a_detection_is_never_used_twice_and_cameras_are_distinct():
    """Crowded scenes (persons 0.6-1.5 m apart, closer than the 1 m segment threshold):
    whatever the grouping, one detection goes to one hypothesis, one view per camera."""
    rng = np.random.default_rng(3)
    R, t = rig(5)
    assoc = Associator(AssociateConfig())
    total = 0
    for trial in range(30):
        n = rng.integers(2, 5)
        pos = []
        while len(pos) < n:
            p = rng.uniform(-1.5, 1.5, 2)
            if all(np.linalg.norm(p - q) > 0.6 for q in pos):
                pos.append(p)
        people = [body(p, rng.uniform(0, 2 * np.pi), rng.uniform(1.7, 1.95)) for p in pos]
        views, ids = [], {}
        for c in range(len(R)):
            v = []
            for i, J in enumerate(people):
                xy = observe(R, t, c, J)
                if np.all(np.isfinite(xy[list(TORSO)])):
                    d = Detection(c, xy, np.full(17, 2.0), F)
                    ids[(c, xy.tobytes())] = i
                    v.append(d)
            if v:
                views.append(v[::-1] if trial % 2 else v)
        hyps = assoc(float(trial), views, R, t)
        used = []
        for h in hyps:
            assert len(set(h.cams.tolist())) == len(h.cams) >= 2
            used += [(int(c), h.xy[k].tobytes()) for k, c in enumerate(h.cams)]
        assert len(used) == len(set(used))
        total += len(hyps)
    assert total >= 40  # the scenes did produce hypotheses


def test_the_gate_drops_a_view_whose_torso_is_inconsistent():
    R, t = rig(4)
    A = body([0.2, -0.3], heading=1.0)
    wrong = A + [0.4, 0.4, 0.0]  # camera 3's view is off by ~0.55 m (tens of px)
    views = [[detection(R, t, c, A)] for c in range(3)] + [[detection(R, t, 3, wrong)]]
    cfg = AssociateConfig()
    # without a gate the segments (within 1 m) join all four views
    [h] = Associator(cfg)(0.0, views, R, t)
    assert _cams_of(h) == [0, 1, 2, 3]
    _, err = triangulate_torso(h, R, t, np.full(4, F))
    assert err[list(h.cams).index(3)] > 25
    assoc = Associator(cfg)
    [h] = assoc(0.0, views, R, t, gate_px=np.full(4, 25.0))
    assert _cams_of(h) == [0, 1, 2]
    assert assoc.rejected["reprojection_gate"] == 1
    assert np.linalg.norm(h.com - A[list(TORSO)].mean(0)) < 0.02
    # cameras that are not gated (inf) keep their view
    [h] = Associator(cfg)(0.0, views, R, t, gate_px=np.array([25.0, 25.0, 25.0, np.inf]))
    assert _cams_of(h) == [0, 1, 2, 3]


def test_two_views_of_two_people_are_not_paired_once_the_poses_can_tell():
    """Camera 0 sees only A, camera 1 only B, close enough for their torso segments to
    meet: two views have no third to show it, their joints' epipolar lines do."""
    R, t = rig(2)
    A = body([0.2, -0.3], heading=1.0)
    B = body([0.5, 0.1], heading=2.5, height=1.7)
    lone = [[detection(R, t, 0, A)], [detection(R, t, 1, B)]]
    cfg = AssociateConfig()
    assert len(Associator(cfg)(0.0, lone, R, t)) == 1  # segments alone pair them
    assoc = Associator(cfg)
    assert assoc(0.0, lone, R, t, pose_px=np.zeros(2)) == []
    assert assoc.rejected["epipolar"] == 1
    # one person in both views stays a hypothesis, and so does the pair while the poses
    # are too uncertain to tell (their test would drop right pairs too)
    [h] = assoc(0.0, [[detection(R, t, 0, A)], [detection(R, t, 1, A)]], R, t, pose_px=np.zeros(2))
    assert _cams_of(h) == [0, 1]
    assert len(assoc(0.0, lone, R, t, pose_px=np.full(2, 100.0))) == 1
    assert len(Associator(cfg.model_copy(update={"epipolar_sigmas": 0.0}))(0.0, lone, R, t,
                                                                             pose_px=np.zeros(2))) == 1


def test_epipolar_miss_is_the_keypoint_noise_for_one_person_and_large_for_two():
    R, t = rig(2)
    A, B = body([0.2, -0.3], heading=1.0), body([0.5, 0.1], heading=2.5, height=1.7)
    rng = np.random.default_rng(0)
    a = detection(R, t, 0, A)
    b = detection(R, t, 1, A)
    b = Detection(1, b.xy + rng.normal(0, 2.0 / F, b.xy.shape), b.sigma, F)
    miss, noise = epipolar_miss(a, b, R, t)
    assert noise == pytest.approx(2.0 * np.sqrt(2))
    assert miss < noise
    miss, _ = epipolar_miss(a, detection(R, t, 1, B), R, t)
    assert miss > 5 * noise
    # scale-free: a camera moved along the baseline (a chain's link at another scale)
    # changes nothing
    t2 = t.copy()
    t2[1] = t[0] + 2 * (t[1] - t[0])
    assert epipolar_miss(a, b, R, t2)[0] == pytest.approx(epipolar_miss(a, b, R, t)[0], rel=1e-9)


def test_segments_too_far_apart_do_not_join():
    R, t = rig(2)
    A = body([-1.5, 0.0])
    B = body([1.5, 0.3])
    assoc = Associator(AssociateConfig(max_distance=0.2))
    # camera 0 sees A, camera 1 sees B only: no common person
    hyps = assoc(0.0, [[detection(R, t, 0, A)], [detection(R, t, 1, B)]], R, t)
    assert hyps == []


def test_intersect_rays_and_triangulate_torso():
    rng = np.random.default_rng(0)
    X = rng.normal(size=3)
    origins = rng.normal(size=(4, 3)) * 3
    dirs = X - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    assert np.allclose(intersect_rays(origins, dirs), X)
    R, t = rig(3)
    A = body([0.3, 0.1])
    [h] = Associator(AssociateConfig())(0.0, [[detection(R, t, c, A)] for c in range(3)], R, t)
    Xt, err = triangulate_torso(h, R, t, np.full(3, F))
    assert np.allclose(Xt, A[list(TORSO)], atol=1e-9) and err.max() < 1e-6
    assert np.allclose(torso_centre(h.xy[0]), h.xy[0][list(TORSO)].mean(0))
