"""Calibration without an initial estimate (backend/bootstrap.py) and metric scale from
people (backend/people.py): the pieces on synthetic data, and the whole bootstrap on a
short seeded simulation of the lab's west room.

Whole run (7 cameras, 2 walkers of 1.96 m / 1.70 m, 60 s, seed 0), measured when the bars
were set (similarity-aligned "shape" error over the cameras; scale error vs the truth):

                         placed  shape mean  orientation mean / max  scale (known heights)
    bootstrap            7/7     0.0121 m    0.126° / 0.211°         -0.45 % (reported ± 1.4 %)
    + online pipeline    7/7     0.0121 m    0.132° / 0.217°

The bars are the issue's targets (every camera within 0.05 m / 0.5°, scale within 1 %);
they fail when, e.g., a wrong pair is chained into the view graph (a camera tens of
degrees off) or the scale loses a segment.
"""

from __future__ import annotations

import numpy as np
import pytest

from backend.bootstrap import (
    BootstrapError, PairPose, average_rotations, bootstrap, camera_set, collect_frames, handover, pair_bones,
    pair_scales, relative_pose, single_views, split_cameras, triangle_check,
)
from backend.cameras import CameraSet, Extrinsics
from backend.config import BootstrapConfig, EngineConfig
from backend.evaluate import evaluate
from backend.geometry import rotation_angle_deg, so3_exp
from backend.optimize import BONE_NAMES, BONES
from backend.perturb import perturb_extrinsics
from backend.reconcile import reconcile_cameras
from backend.people import Person, chain_ratio, estimate_scale, persons, segments, tracks
from backend.preprocess import Detection

RNG = np.random.default_rng


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_R_cam of a camera at centre looking at target, image x horizontal."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _project(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = (X - t) @ R
    return Xc[:, :2] / Xc[:, 2:3]


def _walker(rng, frames: int, height: float = 1.8) -> np.ndarray:
    """(F, 17, 3) a crude person: 17 points spread over a body-sized box, walking."""
    body = np.c_[rng.uniform(-0.2, 0.2, 17), rng.uniform(-0.15, 0.15, 17), rng.uniform(0.05, height, 17)]
    path = np.c_[np.linspace(-2, 2, frames), 1.5 * np.sin(np.linspace(0, 3, frames)), np.zeros(frames)]
    return path[:, None, :] + body[None]


# ------------------------------------------------------------------ pieces


def test_relative_pose_recovers_the_pose_and_drops_frames_of_another_person():
    rng = RNG(1)
    Ra, ta = _look_at(np.array([-4.0, -4.0, 2.6]), np.zeros(3)), np.array([-4.0, -4.0, 2.6])
    Rb, tb = _look_at(np.array([4.0, -3.0, 2.5]), np.zeros(3)), np.array([4.0, -3.0, 2.5])
    F = 60
    P = _walker(rng, F)
    Q = _walker(rng, F)[:, :, :] + np.array([1.0, 2.5, 0.0])  # another person elsewhere
    f = 600.0
    xa, xb, fid = [], [], []
    for k in range(F):
        other = k % 4 == 0  # every 4th frame camera b sees the other person: no correspondence
        xa.append(_project(Ra, ta, P[k]) + rng.normal(0, 1.0 / f, (17, 2)))
        xb.append(_project(Rb, tb, Q[k] if other else P[k]) + rng.normal(0, 1.0 / f, (17, 2)))
        fid.append(np.full(17, k))
    xa, xb, fid = np.concatenate(xa), np.concatenate(xb), np.concatenate(fid)
    out = relative_pose(xa, xb, fid, f, EngineConfig().bootstrap, seed=0)
    assert out is not None
    R, t, good, inl = out
    R_true = Rb.T @ Ra
    t_true = Rb.T @ (ta - tb)
    t_true /= np.linalg.norm(t_true)
    assert rotation_angle_deg(R, R_true) < 0.3
    assert np.degrees(np.arccos(np.clip(t @ t_true, -1, 1))) < 0.5
    assert not np.isin(np.arange(0, F, 4), good).any(), "frames of another person must not agree"
    assert len(good) >= 0.9 * (F - F // 4)


def test_pairs_from_scratch_take_single_views_with_the_whole_torso():
    """A profile view (one side of the torso hidden) is not looked at."""
    def det(cam, hide=()):
        xy = np.zeros((17, 2))
        xy[list(hide)] = np.nan
        return Detection(cam, xy, np.full(17, 2.0), 500.0)

    frames = [(0.0, ((det(0),), (det(1, hide=(6, 12)),), (det(2), det(2, hide=(5,))), (det(3, hide=(9,)),)))]
    [single] = single_views(frames)
    assert sorted(single) == [0, 2, 3]  # a hidden wrist is no matter; cam_1 in profile
    assert np.isfinite(single[2].xy[5, 0])  # cam_2's whole person


@pytest.mark.parametrize("still", [False, True])
def test_a_person_standing_still_is_one_frame_to_a_pair(still):
    """Two cameras see one person for 60 frames. Walking, the pair is found; standing
    still, its 17 joints are the same few points in every frame: no pair, though every
    frame agrees (two people each standing still in one of two cameras that share no
    view agreed with a pose 161° off in a slow corridor; ``bootstrap.pair_min_moving``)."""
    from backend.bootstrap import pair_poses

    rng = RNG(4)
    Ra, ta = _look_at(np.array([-4.0, -4.0, 2.6]), np.zeros(3)), np.array([-4.0, -4.0, 2.6])
    Rb, tb = _look_at(np.array([4.0, -3.0, 2.5]), np.zeros(3)), np.array([4.0, -3.0, 2.5])
    F, f = 60, 600.0
    P = _walker(rng, F)
    if still:  # the first frame's pose, breathing a little
        P = P[:1] + rng.normal(0.0, 0.002, P.shape)
    frames = []
    for k in range(F):
        dets = tuple((Detection(c, _project(R, t, P[k]) + rng.normal(0, 1.0 / f, (17, 2)), np.full(17, 2.0), f),)
                     for c, (R, t) in enumerate(((Ra, ta), (Rb, tb))))
        frames.append((0.1 * k, dets))
    cfg = EngineConfig().bootstrap
    found, tried = pair_poses(frames, 2, np.full(2, f), cfg)
    assert tried == 1
    if not still:
        assert len(found) == 1 and rotation_angle_deg(found[0].R, Rb.T @ Ra) < 1.0
        return
    assert found == []
    anyway, _ = pair_poses(frames, 2, np.full(2, f), cfg.model_copy(update={"pair_min_moving": 0}))
    assert len(anyway) == 1 and len(anyway[0].frames) >= 50  # every frame agreed: only the guard refused it


def _pair(a, b, R, inliers=500) -> PairPose:
    return PairPose(a, b, R, np.array([1.0, 0, 0]), np.arange(10), 10, inliers, 1.0, 30.0, np.zeros(0, np.int64),
                    {a: np.zeros(0), b: np.zeros(0)})


def test_rotation_averaging_and_the_triangle_check_find_a_wrong_pair():
    rng = RNG(2)
    C = 6
    Rw = np.array([so3_exp(rng.normal(0, 1.0, 3)) for _ in range(C)])
    pairs = []
    for a in range(C):
        for b in range(a + 1, C):
            Rab = Rw[b].T @ Rw[a] @ so3_exp(rng.normal(0, np.radians(0.3), 3))
            pairs.append(_pair(a, b, Rab))
    wrong = next(k for k, p in enumerate(pairs) if (p.a, p.b) == (1, 4))
    pairs[wrong] = _pair(1, 4, so3_exp([0.0, 0.0, np.radians(40)]) @ pairs[wrong].R, inliers=5000)
    good, bad = triangle_check(pairs, 10.0)
    assert good[wrong] == 0 and bad[wrong] > 0
    assert all(good[k] > 0 for k in range(len(pairs)) if k != wrong)
    # without it, the averaged rotations agree with the truth up to the gauge
    R, known, _ = average_rotations(C, [p for k, p in enumerate(pairs) if k != wrong], sigma_deg=2.5)
    assert known.all()
    for a in range(C):
        for b in range(C):
            assert rotation_angle_deg(R[b].T @ R[a], Rw[b].T @ Rw[a]) < 0.5
    # a wrong pair the spanning tree does not take is outweighed by the reweighting
    pairs[wrong] = _pair(1, 4, pairs[wrong].R, inliers=100)
    R, known, res = average_rotations(C, pairs, sigma_deg=2.5)
    assert res[wrong] > 30
    for a in range(C):
        for b in range(C):
            assert rotation_angle_deg(R[b].T @ R[a], Rw[b].T @ Rw[a]) < 0.5


def test_a_camera_whose_pairs_split_between_two_turns_is_left_to_the_resection():
    """Camera 5 has right pairs with cameras 0 and 1, and wrong ones, all consistent with
    one pose turned 100 degrees, with 2, 3 and 4 (it saw the other walker while they saw
    this one): whichever side the averaging takes, the camera is split. Camera 1's one
    small wrong pair (40 degrees off) does not split it."""
    rng = RNG(4)
    C = 6
    Rw = np.array([so3_exp(rng.normal(0, 1.0, 3)) for _ in range(C)])
    turned = so3_exp([0.0, np.radians(100), 0.0]) @ Rw[5]

    def pair(a, b, Rb_w, frames):
        Rab = Rb_w.T @ Rw[a] @ so3_exp(rng.normal(0, np.radians(0.3), 3))
        return PairPose(a, b, Rab, np.array([1.0, 0, 0]), np.arange(frames), frames, 17 * frames, 1.0, 30.0,
                        np.zeros(0, np.int64), {a: np.zeros(0), b: np.zeros(0)})

    pairs = [pair(a, b, Rw[b], 80) for a in range(5) for b in range(a + 1, 5) if (a, b) != (1, 4)]
    pairs.append(pair(1, 4, so3_exp([0.0, 0.0, np.radians(40)]) @ Rw[4], 30))
    pairs += [pair(0, 5, Rw[5], 50), pair(1, 5, Rw[5], 45)]
    pairs += [pair(a, 5, turned, 40) for a in (2, 3, 4)]
    _, _, res = average_rotations(C, pairs, sigma_deg=2.5)
    kept = res <= 5.0
    assert kept[-5:-3].all() != kept[-3:].all()  # one side of camera 5 kept, the other dropped
    assert not kept[-6]  # camera 1's wrong pair
    split = split_cameras(C, pairs, kept, 0.5)
    assert split.tolist() == [False, False, False, False, False, True]
    assert not split_cameras(C, pairs, kept, 0.0).any()  # off
    # with its right side far stronger the wrong pairs are dropped, and it is not split either
    pairs[-5:-3] = [pair(0, 5, Rw[5], 200), pair(1, 5, Rw[5], 200)]
    _, _, res = average_rotations(C, pairs, sigma_deg=2.5)
    assert (res[-3:] > 5.0).all() and not split_cameras(C, pairs, res <= 5.0, 0.5).any()


def test_bones_relate_the_scales_of_a_chain_without_shared_joints():
    """A corridor: each pair sees the walker where no third camera does, so no two pairs
    triangulate one instant, and only the people's bones say how their unit baselines
    compare. Joints of one walker triangulated by each pair in its own unit (the true
    baseline s), with pixel-like noise and a few stray joints."""
    rng = RNG(5)
    walker = _walker(rng, 60)  # (F, 17, 3)
    s_true = np.array([3.5, 2.8, 4.1, 3.0])  # baselines (m) of the pairs 0-1, 1-2, 2-3, 3-4
    pairs = []
    for k, s in enumerate(s_true):
        frames = np.arange(60 * k, 60 * k + 60)  # each pair its own frames: no shared keys
        X = (walker / s + rng.normal(0, 0.004, walker.shape)).reshape(-1, 3)
        X[rng.choice(len(X), 40, replace=False)] *= 1.5  # stray joints
        keys = (frames[:, None] * 17 + np.arange(17)).ravel()
        b = pair_bones(keys, X)
        pairs.append(PairPose(k, k + 1, np.eye(3), np.array([1.0, 0, 0]), frames, 60, 1000 - k, 1.0, 30.0, keys,
                              {k: X[:, 2], k + 1: X[:, 2]}, b))
    assert np.isfinite(pairs[0].bones).all()
    for k, a, b_ in BONES[:2]:  # shoulder and hip width (the crude walker's left and right differ)
        assert pairs[0].bones[k] == pytest.approx(np.linalg.norm(walker[0, a] - walker[0, b_]) / s_true[0], rel=0.05)
    logs, known, used = pair_scales(pairs, BootstrapConfig())
    assert known.all() and used == 3
    np.testing.assert_allclose(logs - logs[0], np.log(s_true / s_true[0]), atol=0.01)
    # without bones only the anchor pair has a scale: the chain cannot be placed
    logs, known, used = pair_scales(pairs, BootstrapConfig(bone_scales=False))
    assert known.sum() == 1 and used == 0
    # a pair whose bones do not scale alike (its geometry is wrong) is not related
    bad = pairs[2].bones * np.exp(rng.uniform(-0.6, 0.6, len(BONE_NAMES)))
    pairs[2] = PairPose(2, 3, np.eye(3), np.array([1.0, 0, 0]), pairs[2].frames, 60, 998, 1.0, 30.0, pairs[2].keys,
                        pairs[2].depths, bad)
    logs, known, used = pair_scales(pairs, BootstrapConfig())
    assert not known[2] and known.sum() == 2 and used == 1


def test_a_pair_that_saw_two_people_changes_their_size_and_as_a_bridge_is_dropped():
    """docs/bones.md, Session 33: in a corridor with three walkers, cameras 0 and 3 (no
    floor in common) each saw one of two people often enough for an essential matrix, and
    that pair bridged two halves of the chain 1.7 m off. One person keeps its size from
    frame to frame; the joints of two people, one triangulated at the other's depth, do not."""
    from backend.bootstrap import _without_phantom_bridges, pair_size_spread

    rng = RNG(7)
    walker = _walker(rng, 60)  # (F, 17, 3)
    keys = (np.arange(60)[:, None] * 17 + np.arange(17)).ravel()
    one = (walker + rng.normal(0, 0.01, walker.shape)).reshape(-1, 3)
    # a phantom: each frame the second person's rays meet the first's at another depth
    two = (walker * rng.uniform(0.6, 1.5, (60, 1, 1)) + rng.normal(0, 0.01, walker.shape)).reshape(-1, 3)
    s_one, s_two = pair_size_spread(keys, one, pair_bones(keys, one)), pair_size_spread(keys, two, pair_bones(keys, two))
    assert s_one < 0.05 < 0.15 < s_two
    assert np.isnan(pair_size_spread(keys[:0], one[:0], pair_bones(keys[:0], one[:0])))

    def pair(a, b, spread):
        return PairPose(a, b, np.eye(3), np.array([1.0, 0, 0]), np.arange(40), 40, 600, 1.0, 30.0,
                        np.zeros(0, np.int64), {a: np.zeros(0), b: np.zeros(0)}, size_spread=spread)

    # the chain 0-1-2 and 3-4-5, joined by the phantom 0-3; a triangle 5-6-7 on the side
    chain = [pair(0, 1, s_one), pair(1, 2, 0.05), pair(0, 3, s_two), pair(3, 4, 0.06), pair(4, 5, 0.04),
             pair(5, 6, 0.05), pair(6, 7, 0.05), pair(5, 7, 0.05)]
    kept, dropped = _without_phantom_bridges(8, chain, 2.0)
    assert [(p.a, p.b) for p in dropped] == [(0, 3)] and len(kept) == len(chain) - 1
    # in a cycle of pairs the same spread is left to the cycle's checks; off: nothing dropped
    cycled = chain + [pair(2, 4, 0.05)]
    assert not _without_phantom_bridges(8, cycled, 2.0)[1]
    assert not _without_phantom_bridges(8, chain, 0.0)[1]
    # a tight network (median 0.03) keeps a bridge at 0.11: under 13 % is noise, not two people
    tight = [pair(0, 1, 0.03), pair(1, 2, 0.03), pair(2, 3, 0.11), pair(3, 4, 0.03)]
    assert not _without_phantom_bridges(5, tight, 2.0)[1]


def test_scale_from_a_known_height_and_from_the_prior():
    unit = 0.25  # metres per pose unit: the poses are 4x too large
    H = 1.85
    p = Person(chain=chain_ratio() * H / unit, chain_rel_std=0.002, hypotheses=400, tracks=3)
    known = estimate_scale([p], heights=[H])
    assert known.method == "known height"
    assert known.factor == pytest.approx(unit, rel=1e-9)
    assert known.heights == pytest.approx((H,))
    assert known.rel_std == pytest.approx(np.hypot(0.02, 0.002))
    prior = estimate_scale([p], height_mean=1.72, height_std=0.10)
    assert prior.factor == pytest.approx(unit * 1.72 / H)
    assert prior.rel_std == pytest.approx(np.sqrt((0.10 / 1.72) ** 2 + 0.02**2 + 0.002**2))
    # two persons: known heights are matched by rank; the prior's std shrinks by sqrt(2)
    q = Person(chain=chain_ratio() * 1.70 / unit, chain_rel_std=0.002, hypotheses=400, tracks=2)
    both = estimate_scale([p, q], heights=[1.70, 1.85])
    assert both.factor == pytest.approx(unit) and both.heights == pytest.approx((1.85, 1.70))
    assert estimate_scale([p, q]).rel_std == pytest.approx(prior.rel_std / np.sqrt(2))
    # fewer heights than persons: the means are matched, and the persons' spread counts
    one = estimate_scale([p, q], heights=[1.775])
    assert "mean" in one.note and one.rel_std > both.rel_std and one.note in one.summary()
    assert not both.note and not estimate_scale([p, q]).note
    # persons 2x apart (2.43 and 1.22 m in a corridor whose links were scaled wrongly) are
    # not two adults: the result says the geometry disagrees with itself
    tall = Person(chain=chain_ratio() * 2 * 1.70 / unit, chain_rel_std=0.002, hypotheses=400, tracks=2)
    odd = estimate_scale([tall, q])
    assert "disagrees with itself" in odd.note and "2.00 times" in odd.summary()
    with pytest.raises(ValueError):
        estimate_scale([])


def _walkers(walkers, rng) -> tuple[list, np.ndarray, np.ndarray]:
    """Hypotheses of persons (height m, y m, instants) walking along x, seen by two cameras
    at 10 Hz; returns (hypotheses, R, t)."""
    from backend.associate import Hypothesis

    Rc = [_look_at(np.array([-5.0, -5.0, 2.6]), np.zeros(3)), _look_at(np.array([5.0, -5.0, 2.6]), np.zeros(3))]
    tc = [np.array([-5.0, -5.0, 2.6]), np.array([5.0, -5.0, 2.6])]
    R, t = np.array(Rc), np.array(tc)
    hyps = []
    for k in range(max(max(ks) for _, _, ks in walkers) + 1):
        for H, y0, ks in walkers:
            if k not in ks:
                continue
            x = -3 + 0.02 * k
            X = np.zeros((17, 3))
            # ankle, knee, hip, shoulder heights of Drillis & Contini, at the person's place
            for side, dy in ((0, 0.1), (1, -0.1)):
                X[15 + side] = [x, y0 + dy, 0.039 * H]
                X[13 + side] = [x, y0 + dy, 0.285 * H]
                X[11 + side] = [x, y0 + dy, 0.285 * H + 0.245 * H]
                X[5 + side] = [x, y0 + dy * 1.1, 0.285 * H + 0.245 * H + 0.2924 * H]
            X[:5] = [x, y0, 0.93 * H]
            xy = np.stack([_project(R[c], t[c], X) for c in range(2)]) + rng.normal(0, 0.5 / 600, (2, 17, 2))
            hyps.append(Hypothesis(0.1 * k, np.array([0, 1]), xy, np.full((2, 17), 1 / 600), X[11:13].mean(0)))
    return hyps, R, t


def test_tracks_and_persons_tell_two_walkers_apart():
    # two persons of 1.96 m and 1.70 m walking 3 m apart, seen by two cameras, 10 Hz, 30 s
    hyps, R, t = _walkers(((1.96, 0.0, range(300)), (1.70, 3.0, range(300))), RNG(3))
    seg = segments(hyps, R, t)
    ids = tracks(seg.time, seg.com)
    assert len(np.unique(ids)) == 2
    ppl = persons(seg)
    assert len(ppl) == 2
    assert ppl[0].chain / chain_ratio() == pytest.approx(1.96, rel=0.01)
    assert ppl[1].chain / chain_ratio() == pytest.approx(1.70, rel=0.01)
    assert estimate_scale(ppl, heights=[1.96, 1.70]).factor == pytest.approx(1.0, rel=0.005)


def test_a_few_hypotheses_of_nobody_do_not_merge_two_walkers():
    # two walkers of 1.80 and 1.65 m, and 2 s of a "person" of 2.23 m (hypotheses that
    # joined two persons' views): k-means into two groups put it apart and merged the walkers
    hyps, R, t = _walkers(((1.80, 0.0, range(200)), (1.65, 3.0, range(200)), (2.23, 6.0, range(100, 120))), RNG(4))
    ppl = persons(segments(hyps, R, t))
    assert [round(p.chain / chain_ratio(), 2) for p in ppl] == pytest.approx([1.80, 1.65], abs=0.01)
    assert estimate_scale(ppl, heights=[1.80, 1.65]).factor == pytest.approx(1.0, rel=0.005)


def test_bootstrap_refuses_too_little_data():
    d = Detection(0, np.zeros((17, 2)), np.ones(17), 600.0)
    e = Detection(1, np.zeros((17, 2)), np.ones(17), 600.0)
    with pytest.raises(BootstrapError, match="too few"):
        bootstrap([(0.0, ((d,), (e,)))], ("cam_0", "cam_1"), np.array([600.0, 600.0]), EngineConfig())


def test_a_camera_s_views_retimed_are_its_views_that_much_later():
    """``retimed``: camera 1's single-person views interpolated ``delta`` s later (a view
    of two persons is no end of it: which is which?); none across a gap of over 0.25 s."""
    from backend.bootstrap import retimed

    def det(c, x):
        xy = np.full((17, 2), float(x))
        xy[3] = np.nan  # a joint it missed
        sigma = np.ones(17)
        sigma[3] = np.nan
        return Detection(c, xy, sigma, 600.0)

    frames = [(0.1 * k, ((det(0, 0.0),), (det(1, k),))) for k in range(10)]
    frames[4] = (0.4, ((det(0, 0.0),), (det(1, 4), det(1, 40))))  # two persons: not one to time
    frames += [(2.0, ((det(0, 0.0),), (det(1, 20),)))]  # after a gap of 1.1 s
    out = retimed(frames, 1, 0.15)
    got = {round(T, 2): v[1][0].xy[0, 0] for T, v in out if len(v) == 2}
    # 0.2 -> 0.35 and 0.3 -> 0.45 lie between 0.3 and 0.5 (0.4 had two persons); 0.8 and 0.9 face the gap
    assert got == pytest.approx({0.0: 1.5, 0.1: 2.5, 0.2: 3.5, 0.3: 4.5, 0.4: 5.5, 0.5: 6.5, 0.6: 7.5, 0.7: 8.5})
    assert {round(T, 2) for T, v in out} == set(got)  # frames left with camera 0 alone are dropped
    assert all(np.isnan(v[1][0].xy[3]).all() and np.isnan(v[1][0].sigma[3]) for _, v in out)
    same = {round(T, 2): v[1] for T, v in retimed(frames, 1, 0.0)}
    assert same[0.3][0].xy[0, 0] == 3.0  # at its own instants: as it was
    assert len(same[0.4]) == 1 and same[0.4][0].xy[0, 0] == pytest.approx(4.0)  # the two persons: one, between


def test_a_sensor_whose_stamps_ran_apart_with_no_pair_either_way_is_not_judged():
    """A camera that saw nobody with the others yet (placed later, if at all) has no pair
    to time it by: left as stamped and out of the shifts, so that no header calls its
    lead a delay (backend/late_join.py times it when it is placed)."""
    from backend.bootstrap import _timed

    frames = [(0.1 * k, ((Detection(0, np.full((17, 2), 0.01 * k), np.ones(17), 600.0),),
                         (Detection(1, np.full((17, 2), 0.02 * k), np.ones(17), 600.0),))) for k in range(30)]
    out, shifts = _timed(frames, ("cam_0", "cam_1", "cam_2"), np.full(3, 600.0), BootstrapConfig(),
                         {"cam_2": 0.2}, seed=0)
    assert shifts == {} and out == frames


# ------------------------------------------------------------------ whole bootstrap, simulated

WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")
DURATION = 60.0
SEED = 0


# for the runs that test no stated std: the split-half check (tested elsewhere) costs another final batch
NO_SPLIT_CHECK = EngineConfig().merged({"refine": {"split_check": False}})


@pytest.fixture(scope="module")
def booted(lab_dir):
    from edge_clients.sim import Scene, SimConfig, Simulator

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    sim = Simulator(scene, SimConfig(persons=2, duration=DURATION, seed=SEED, heights=(1.96, 1.70)))
    msgs = [m for _, m in sim.messages()]
    cfg = EngineConfig()
    frames = collect_frames(WEST, intr, cfg, msgs)
    focal = np.array([0.5 * (intr[n].fx + intr[n].fy) for n in WEST])
    res = bootstrap(frames, WEST, focal, cfg, heights=(1.96, 1.70), seed=SEED)
    truth = {n: full.poses[n] for n in WEST}
    return res, truth, intr, msgs, frames


def test_bootstrap_places_the_cameras_without_an_initial_estimate(booted):
    res, truth, _, _, _ = booted
    print(res.to_dict())
    acc = evaluate(res.poses(), truth)
    print(acc.summary())
    assert res.located.sum() >= 6
    assert acc.shape_position.max < 0.05
    assert acc.shape_orientation.max < 0.5
    # metric scale from the known heights: within 1 % of the truth, its std covers the error
    assert res.scale is not None and res.scale.method == "known height"
    assert abs(1 / acc.scale - 1) < 0.01
    assert abs(np.log(acc.scale)) < 3 * res.scale.rel_std
    # how firmly the last adjustment holds each camera (the reconciliation's evidence)
    placed = res.located
    assert np.all(res.observations[placed] > 100) and np.all(res.observations[~placed] == 0)
    assert np.all(res.residual_px[placed] < 5.0) and np.all(np.isnan(res.residual_px[~placed]))


def test_bootstrap_frame_is_the_floor(booted, lab_dir):
    res, truth, _, _, _ = booted
    import yaml

    floor = yaml.safe_load((lab_dir / "room.yaml").read_text())["floor"]
    up = np.array(floor["normal_up"])
    # the floor frame's z (world) in the truth's frame, through the similarity alignment
    from backend.geometry import umeyama

    names = [n for c, n in enumerate(res.names) if res.located[c]]
    s, Ra, _ = umeyama(np.array([res.poses()[n].t for n in names]), np.array([truth[n].t for n in names]),
                       with_scale=True)
    z = Ra @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(z @ up, -1, 1))) < 1.5
    # cameras hang about 2.6 m above the floor
    heights = np.array([res.poses()[n].t[2] for n in names])
    assert np.all((heights > 2.0) & (heights < 3.2))
    assert "floor" in res.frame and res.poses()[names[0]].t[:2] == pytest.approx([0, 0], abs=1e-9)


def test_handover_to_the_online_pipeline(booted):
    res, truth, intr, msgs, _ = booted
    from backend.pipeline import run_offline

    cfg = handover(NO_SPLIT_CHECK, res)
    assert cfg.refine.initial_std_translation >= EngineConfig().bootstrap.handover_std_translation
    cams = camera_set(intr, res)
    assert set(cams.names) == {n for c, n in enumerate(res.names) if res.located[c]}
    p = run_offline(cams, cfg, msgs, seed=SEED)
    acc = evaluate(p.state().poses(), {n: truth[n] for n in cams.names})
    print(acc.summary())
    assert acc.shape_position.max < 0.05
    assert acc.shape_orientation.max < 0.5


def test_the_handover_holds_the_data_shape_against_wrong_associations():
    """Two rooms joined by a door, four walkers, 60 s, no initial estimate: a walker each
    camera alone sees pairs up with one in the other room, and the first adjustment follows
    such views as far as the hand-over's prior lets it. Measured (seed 0): the bootstrap's
    shape 0.016 m; online from it 0.047 m / 0.87° with the default floor (0.03 m / 0.5°),
    0.265 m / 2.98° with the 0.10 m / 2° it had until session 56."""
    from backend.bootstrap import bootstrap_messages
    from backend.pipeline import run_offline
    from edge_clients.sim import SimConfig, Simulator
    from edge_clients.sim.scenes import tworooms

    scene = tworooms()
    msgs = [m for _, m in Simulator(scene, SimConfig(persons=4, duration=60.0, seed=0)).messages()]
    cfg = EngineConfig().for_images(i.resolution for i in scene.intrinsics.values())
    res = bootstrap_messages(scene.intrinsics, cfg, msgs, seed=0)
    assert res.located.all()
    p = run_offline(camera_set(scene.intrinsics, res), handover(cfg, res), iter(msgs), seed=0, finish=False)
    acc = evaluate(p.state().poses(), scene.poses)
    print(acc.summary())
    assert acc.shape_position.mean < 0.10 and acc.shape_orientation.mean < 2.0


def test_extrinsics_of_a_result_roundtrip(booted):
    res, _, intr, _, _ = booted
    ext = res.extrinsics({n: intr[n].resolution for n in res.names})
    assert isinstance(ext[res.names[0]], Extrinsics)
    assert all(ext[n].std_translation is not None for c, n in enumerate(res.names) if res.located[c])


# ------------------------------------------------------------------ with an initial estimate (backend/reconcile.py)


def test_pipeline_from_a_rough_start_takes_the_data_shape(booted):
    """0.75 m / 20° off per camera; the online pipeline from the bootstrap's shape aligned
    onto it: every camera's shape within the bootstrap's bars, the initial estimate's
    frame and scale kept (the rigid error is what 7 cameras 0.75 m off leave of a frame)."""
    res, truth, intr, msgs, _ = booted
    from backend.pipeline import run_offline

    ref = {n: Extrinsics(p, intr[n].resolution) for n, p in truth.items()}
    init = perturb_extrinsics(ref, 0.75, 20.0, seed=4)
    cams = CameraSet.combine(intr, init)
    cfg = NO_SPLIT_CHECK
    rec, _, note = reconcile_cameras(res, cams, cfg)
    print(note)
    assert rec is not None and rec.used and not rec.refused.any()
    before = evaluate(cams.poses(), truth)
    # the initial estimate says 0.25 m / 10° by default; the data show it is further off
    run_cfg = rec.config(cfg)
    assert run_cfg.refine.initial_std_translation > 0.5 and run_cfg.refine.initial_std_rotation > 15
    p = run_offline(cams, run_cfg, msgs, seed=SEED, start=rec.start(run_cfg))
    acc = evaluate(p.state().poses(), truth)
    print(before.summary(), "->", acc.summary())
    assert acc.shape_position.max < 0.05 and acc.shape_orientation.max < 0.5
    # measured 0.54 m -> 0.061 m rigid, 0.0125 m shape (the rigid rest: the frame that 7
    # cameras 0.75 m off define)
    assert before.position.mean > 0.4 and acc.position.mean < 0.15
    # the prior is the initial estimate: R0/t0 unchanged, its scale kept
    assert np.allclose(p.refiner.t0, np.array([init[n].pose.t for n in cams.names]))


def test_cameras_swapped_in_the_initial_estimate_are_calibrated_where_the_data_hold_them(booted):
    """A label mix-up: two cameras' poses exchanged in a good initial estimate. Left to the
    pipeline they were never calibrated (their views join nobody; re-localisation refuses
    poses that far from the initial estimate); the bootstrap holds them firmly, so they
    start from the data's pose and the run's frame and scale forget their wrong ones."""
    res, truth, intr, msgs, _ = booted
    from dataclasses import replace

    from backend.pipeline import run_offline

    ref = {n: Extrinsics(p, intr[n].resolution) for n, p in truth.items()}
    init = perturb_extrinsics(ref, 0.10, 3.0, seed=5)
    init["cam_12"], init["cam_16"] = (replace(init["cam_12"], pose=init["cam_16"].pose),
                                      replace(init["cam_16"], pose=init["cam_12"].pose))
    cams = CameraSet.combine(intr, init)
    cfg = NO_SPLIT_CHECK
    rec, _, note = reconcile_cameras(res, cams, cfg)
    print(note)
    assert rec is not None and [n for n, o in zip(rec.names, rec.overruled) if o] == ["cam_12", "cam_16"]
    assert "swapped or moved" in note
    run_cfg = rec.config(cfg)
    p = run_offline(rec.cameras(cams), run_cfg, msgs, seed=SEED, start=rec.start(run_cfg))
    acc = evaluate(p.state().poses(), truth)
    print(acc.summary())
    assert acc.shape_position.max < 0.05 and acc.shape_orientation.max < 0.5
    assert acc.position.mean < 0.06 and acc.orientation.max < 0.5


def test_the_final_batch_from_the_bootstrap_is_kept_when_the_online_estimate_was_dragged(booted):
    """The online cycles can drag a camera the bootstrap placed well (seed 2's cam_13 of the
    lab, docs/bootstrap.md), and the final batch, a local optimisation that re-associates
    from where it starts, may not bring it back. With the hand-over's config the final batch
    also runs from the bootstrap and is kept when it explains the data better. The drag here
    is exaggerated (2 m / 30°) so that the batch from the dragged estimate surely fails."""
    import copy

    from backend.geometry import so3_exp
    from backend.pipeline import run_offline

    res, truth, intr, msgs, _ = booted
    cfg = handover(NO_SPLIT_CHECK, res)
    assert cfg.refine.final_batch_from_start
    cams = camera_set(intr, res)
    p = run_offline(cams, cfg, msgs, seed=SEED, finish=False)
    c = cams.names.index("cam_14")
    rf = p.refiner
    rf.R[c] = so3_exp(np.radians([0.0, 0.0, 30.0])) @ rf.R[c]  # dragged: 30° about the vertical, 2 m aside
    rf.t[c] = rf.t[c] + np.array([2.0, 0.0, 0.0])

    def error(pipe) -> tuple[float, float]:
        per = evaluate(pipe.state().poses(), {n: truth[n] for n in cams.names}).per_camera["cam_14"]
        return per[2], per[3]

    off = copy.deepcopy(p)
    off.cfg = off.cfg.model_copy(update={"refine": off.cfg.refine.model_copy(update={"final_batch_from_start": False})})
    off.finish()
    p.finish()
    print(error(off), error(p), p.final_batch_start)
    assert off.final_batch_start is None
    pos_off, ori_off = error(off)
    assert pos_off > 0.05 or ori_off > 0.5  # from the dragged estimate the batch does not bring it back
    assert p.final_batch_start == "start"
    pos, ori = error(p)
    assert pos < 0.05 and ori < 0.5


def test_cameras_with_nine_times_the_pixels_bootstrap_as_well(lab_dir):
    """The west room with 1920x1440 images (the lab's lenses, 3x the pixels each way, so
    the detector's pixel errors are 3x too): the px parameters follow the image size
    (``EngineConfig.for_images``). Taken as they are (stated for VGA), no pair passes
    the RANSAC and frame gates and the bootstrap fails."""
    from edge_clients.sim import Scene, SimConfig, Simulator

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n].scaled_to(tuple(3 * v for v in full.intrinsics[n].resolution)) for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    msgs = [m for _, m in Simulator(scene, SimConfig(persons=2, duration=DURATION, seed=SEED,
                                                     heights=(1.96, 1.70))).messages()]
    focal = np.array([0.5 * (intr[n].fx + intr[n].fy) for n in WEST])
    cfg = EngineConfig().for_images(i.resolution for i in intr.values())
    assert cfg.bootstrap.ransac_px == pytest.approx(9.0)
    res = bootstrap(collect_frames(WEST, intr, cfg, msgs), WEST, focal, cfg, heights=(1.96, 1.70), seed=SEED)
    acc = evaluate(res.poses(), {n: full.poses[n] for n in WEST})
    print(acc.summary())
    assert res.located.sum() >= 6
    assert acc.shape_position.max < 0.05 and acc.shape_orientation.max < 0.5
    as_given = EngineConfig().merged({"preprocess": {"pixel_reference": None}})
    with pytest.raises(BootstrapError, match="no camera pair"):
        bootstrap(collect_frames(WEST, intr, as_given, msgs), WEST, focal, as_given, seed=SEED)


def test_the_floor_frame_is_level_though_wrong_pairs_put_ankles_metres_off():
    """A corridor's walkers along x, ankles 0.07-0.2 m above the floor z = 0, bodies
    upright; a fifth of the hypotheses are two walkers' wrong pairs whose ankles lie
    metres off in height. Every ankle's least-squares plane stood on its side there (the
    corridor with three walkers, session 34: 60-78° from level); the lower ankles' robust
    plane is level."""
    from backend.bootstrap import floor_frame
    from backend.people import Segments

    rng = np.random.default_rng(4)
    N = 400
    x = rng.uniform(0, 17.5, N)
    y = rng.uniform(-0.8, 0.8, N)
    ankles = np.stack([np.stack([x + 0.1, y + 0.1, np.full(N, 0.07)], 1),
                       np.stack([x - 0.1, y - 0.1, 0.07 + rng.uniform(0, 0.15, N)], 1)], 1)
    ankles += rng.normal(0, 0.03, ankles.shape)
    wrong = rng.random(N) < 0.2
    ankles[wrong, :, 2] += rng.uniform(-3.0, 3.0, (wrong.sum(), 1))
    up = np.tile([0.0, 0.0, 0.9], (N, 1)) + rng.normal(0, 0.05, (N, 3))
    seg = Segments(np.arange(N, dtype=float), ankles.mean(1) + [0, 0, 1.0], np.full(N, 0.44), np.full(N, 0.44),
                   np.full(N, 0.52), ankles, up)
    t = np.array([[0.0, 0.5, 2.6], [3.5, -0.5, 2.6], [7.0, 0.5, 2.6]])
    F, o, note, _ = floor_frame(seg, t, np.ones(3, bool), 1.80, ["cam_0", "cam_1", "cam_2"])
    assert np.degrees(np.arccos(F[2] @ [0, 0, 1])) < 1.0, F
    # the floor 0.039 x 1.80 m below the ankles' stance level: the cameras 2.6 m above it
    assert ((t - o) @ F.T)[:, 2] == pytest.approx(2.6, abs=0.03)
    assert "lower ankles" in note
    # least squares over every ankle would not be level
    P = ankles.reshape(-1, 3)
    n = np.linalg.svd(P - P.mean(0))[2][2]
    assert np.degrees(np.arccos(abs(n[2]))) > 30.0


def test_a_clock_that_runs_ahead_is_timed_by_its_lead_and_a_late_detector_as_stamped(lab_dir):
    """The west room, 60 s: cam_13's clock runs 0.2 s ahead (NTP failing), cam_15's
    messages arrive 0.2 s after the others' (a slower detector, its clock right). As they
    arrive, both sensors' stamps run 0.2 s apart from the others'; only their pairs tell
    which views are mistimed: cam_13's are timed by its lead, cam_15's kept as stamped,
    and every camera lands within the bars. Taken as stamped, cam_13's views show the
    walkers a fifth of a second late."""
    from backend.bootstrap import bootstrap_messages, mistimed_summary
    from edge_clients.sim import Scene, SimConfig, Simulator

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    sim = Simulator(scene, SimConfig(persons=2, duration=DURATION, seed=SEED, heights=(1.96, 1.70),
                                     clock_offsets={"cam_13": 0.2}))
    arrivals = sorted(((a + (0.2 if m.sensor == "cam_15" else 0.0), k, m) for k, (a, m) in enumerate(sim.messages())),
                      key=lambda x: x[:2])
    msgs = [m for _, _, m in arrivals]
    truth = {n: full.poses[n] for n in WEST}
    res = bootstrap_messages(intr, EngineConfig(), msgs, heights=(1.96, 1.70), seed=SEED)
    print(res.to_dict()["mistimed"])
    assert set(res.mistimed) == {"cam_13", "cam_15"}
    assert res.mistimed["cam_13"] == pytest.approx(0.2, abs=0.05) and res.mistimed["cam_15"] == 0.0
    line = mistimed_summary(res.mistimed)  # the result's header says so
    assert "cam_13 +2" in line and "ms (its clock), cam_15 as stamped (its delay)" in line
    acc = evaluate(res.poses(), truth)
    print(acc.summary())
    assert res.located.all()
    assert acc.shape_position.max < 0.05 and acc.shape_orientation.max < 0.5
    # the same frames as stamped: cam_13 not placed, or off the bars
    cfg = EngineConfig()
    focal = np.array([0.5 * (intr[n].fx + intr[n].fy) for n in WEST])
    as_stamped = bootstrap(collect_frames(WEST, intr, cfg, msgs), WEST, focal, cfg, heights=(1.96, 1.70), seed=SEED)
    acc = evaluate(as_stamped.poses(), truth)
    print(acc.summary())
    assert as_stamped.mistimed == {}
    off = acc.per_camera.get("cam_13")
    assert off is None or off[2] > 0.05 or off[3] > 0.5


def test_the_rotations_are_rooted_where_the_scales_are():
    """The camera with the most inliers over the pairs a scale relates, not over all."""
    from backend.bootstrap import _busiest

    def pair(a, b, n):
        return PairPose(a, b, np.eye(3), np.array([1.0, 0, 0]), np.arange(n), n, n, 1.0, 10.0,
                        np.zeros(0, np.int64), {})

    pairs = [pair(0, 1, 500), pair(1, 2, 400), pair(3, 4, 60), pair(4, 5, 50)]
    assert _busiest(6, pairs, np.array([True, True, True, True])) == 1
    assert _busiest(6, pairs, np.array([False, False, True, True])) == 4
    assert _busiest(6, pairs, np.zeros(4, bool)) is None
