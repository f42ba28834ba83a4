"""People keep their size: bone-length factors carry scale along a camera chain."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from backend.cameras import CameraSet, Extrinsics, Pose
from backend.config import EngineConfig
from backend.evaluate import evaluate
from backend.optimize import BONE_NAMES, Problem, hypotheses_and_persons, solve
from backend.people import label_persons, segments
from backend.perturb import perturb_extrinsics
from backend.pipeline import Pipeline
from backend.refine import Refiner
from edge_clients.sim import Scene, SimConfig, Simulator
from edge_clients.sim.scenes import corridor

HEIGHT = 1.80


@pytest.fixture(scope="module")
def chain():
    """A 3-camera corridor (each camera overlaps only its neighbours), 1 walker for 90 s,
    the initial estimate 0.25 m / 10° off; the pipeline's front end (no cycles) archives
    the frames and a batch problem over them is built as the final batch would be."""
    scene = corridor(3)
    sim = Simulator(scene, SimConfig(persons=1, duration=90.0, seed=3, heights=(HEIGHT,)))
    ref = {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}
    init = perturb_extrinsics(ref, 0.25, 10.0, seed=1)
    cams = CameraSet.combine(dict(scene.intrinsics), init)
    p = Pipeline(cams, EngineConfig())
    for _, msg in sim.messages():
        p.push(msg)
        p.advance(p.clock)
    p.advance(p.clock + 1.0)
    assert len(p.frames) > 100
    prob = p._batch_problem(1000, 0.1, final=True)
    return prob, {n: e.pose for n, e in ref.items()}, list(scene.names), p


def _solved(prob: Problem, bones: str, names, cfg):
    sol = solve(replace(prob, config=prob.config.model_copy(update={"bones": bones})))
    assert sol.ok, sol.reason
    rf = Refiner(cfg.refine, prob.prior_R, prob.prior_t)
    rf.update(sol.active, sol.R, sol.t, sol.cov, posterior=True)  # the pipeline's batch path: scale kept
    return sol, {n: Pose(rf.R[c], rf.t[c]) for c, n in enumerate(names)}


def test_every_hypothesis_of_the_chain_has_two_views(chain):
    prob, _, _, _ = chain
    hyps, person = hypotheses_and_persons(replace(prob, config=prob.config.model_copy(update={"bones": "batch"})))
    assert hyps and {len(h.cams) for h in hyps} == {2}
    # one walker: every hypothesis with a measured chain is the same person
    assert set(person[person >= 0].tolist()) == {0} and (person >= 0).mean() > 0.3


def test_bone_lengths_carry_scale_along_the_chain(chain):
    prob, ref, names, p = chain
    before = evaluate({n: Pose(prob.R[c], prob.t[c]) for c, n in enumerate(names)}, ref)
    off, poses_off = _solved(prob, "off", names, p.cfg)
    on, poses_on = _solved(prob, "batch", names, p.cfg)
    e_off, e_on = evaluate(poses_off, ref), evaluate(poses_on, ref)
    # without them each link keeps the scale its priors give it; with them the chain is one shape
    assert e_on.shape_position.mean < 0.5 * e_off.shape_position.mean, (e_off.summary(), e_on.summary())
    assert e_on.position.mean < 0.08 < before.position.mean, (before.summary(), e_on.summary())
    assert off.bone_lengths is None
    # one person, lengths like a 1.80 m person's (in the estimate's units: scale within ~5 %)
    L = on.bone_lengths
    assert L.shape == (1, len(BONE_NAMES)) and np.all(np.isfinite(L))
    thigh, shank = L[0, BONE_NAMES.index("thigh")], L[0, BONE_NAMES.index("shank")]
    assert thigh == pytest.approx(0.245 * HEIGHT, rel=0.1) and shank == pytest.approx(0.246 * HEIGHT, rel=0.1)
    # without outlier rounds the one solve has the bones, and its error is compared with its own start
    one = solve(replace(prob, config=prob.config.model_copy(update={"bones": "batch", "outlier_rounds": 0})))
    assert one.ok and one.final_error < one.initial_error and one.bone_lengths is not None


def _giant(h, R, t, k: float):
    """The two-view phantom of hypothesis h: its body blown up k times about its first
    camera, which therefore sees it unchanged, and projected anew into the second: one
    walker in front of each of two cameras whose rays meet beyond the far one."""
    from backend.associate import Hypothesis, triangulate_hypotheses

    a, b = int(h.cams[0]), int(h.cams[1])
    X = t[a] + k * (triangulate_hypotheses([h], R, t)[0] - t[a])  # (17, 3), NaN = not triangulated
    Xc = (X - t[b]) @ R[b]
    xy = np.stack([h.xy[0], Xc[:, :2] / Xc[:, 2:]])
    xy[:, ~np.isfinite(X).all(axis=1)] = np.nan
    return Hypothesis(h.time, h.cams[:2].copy(), xy, h.sigma[:2].copy(), t[a] + k * (h.com - t[a]))


def test_phantoms_far_larger_than_anyone_are_dropped_before_the_bones(chain):
    """docs/bones.md, Session 33: in a corridor two cameras that share no floor, each with
    a walker in front of it, triangulate a giant; a few such pairs bent a two-walker
    corridor 0.2 m. Giants 1.6-2.2x the walker are dropped, the walker's own hypotheses kept."""
    from backend.people import oversized

    prob, _, _, _ = chain
    cfg = prob.config.model_copy(update={"bones": "batch"})
    real, person = hypotheses_and_persons(replace(prob, config=cfg, max_hypotheses=0, spacing=0.0))
    rng = np.random.default_rng(0)
    # of hypotheses measured whole (labelled): one measured in part is judged by fewer bones
    giants = [_giant(real[i], prob.R, prob.t, k) for i, k in
              zip(rng.choice(np.flatnonzero(person >= 0), 40, replace=False), rng.uniform(1.6, 2.2, 40))]
    given = replace(prob, frames=(), hypotheses=tuple(real + giants), config=cfg)
    kept, person = hypotheses_and_persons(given)
    ids = {id(h) for h in kept}
    assert not any(id(g) in ids for g in giants)
    assert sum(id(h) in ids for h in real) >= 0.97 * len(real) and len(person) == len(kept)
    # off: nothing dropped; without bones nothing is measured, so nothing either
    off = replace(given, config=cfg.model_copy(update={"max_size_ratio": 0.0}))
    assert len(hypotheses_and_persons(off)[0]) == len(real) + len(giants)
    assert len(hypotheses_and_persons(replace(given, config=cfg.model_copy(update={"bones": "off"})))[0]) == len(
        real) + len(giants)
    seg = segments(real + giants, prob.R, prob.t)
    assert not oversized(seg, np.full(len(real) + len(giants), -1), 1.3).any()  # no person to compare with
    # the solve counts them (the final batch's report and `extrcal calibrate`'s header say it)
    sol = solve(given)
    assert sol.ok and sol.phantoms == len(real) + len(giants) - len(kept)


def test_two_walkers_in_a_corridor_the_final_batch_drops_and_counts_their_phantoms():
    """4 cameras in a row, 2 walkers for 90 s, from 0.25 m / 10°: cameras 0 and 2 (or 1
    and 3), which share no floor, each see one walker. Measured on seeds 0-2 (/tmp script):
    shape 0.136 / 0.112 / 0.027 m with the phantoms dropped, 0.151 / 0.305 / 0.149 m
    without."""
    from backend.pipeline import run_offline

    scene = corridor(4)
    sim = Simulator(scene, SimConfig(persons=2, duration=90.0, seed=2, heights=(1.80, 1.65)))
    ref = {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}
    cams = CameraSet.combine(dict(scene.intrinsics), perturb_extrinsics(ref, 0.25, 10.0, seed=2))
    p = run_offline(cams, EngineConfig(), (m for _, m in sim.messages()), seed=2)
    got = evaluate({n: Pose(p.refiner.R[c], p.refiner.t[c]) for c, n in enumerate(p.names)},
                   {n: e.pose for n, e in ref.items()})
    assert p.last_report.accepted and p.last_report.phantoms > 0
    assert p.last_report.to_dict()["phantoms"] == p.last_report.phantoms
    # the walkers' lower ankles were held to the floor (backend/floor.py), and it says so
    assert p.last_report.floor_points >= 30 and 0.0 < p.last_report.to_dict()["floor_spread"] < 0.2
    assert got.shape_position.mean < 0.06, got.summary()


def test_oversized_judges_missing_bones_by_those_measured():
    from backend.people import Segments, oversized

    N = 6
    size = np.array([1.80, 1.65, 1.80, 2.70, 2.70, 1.90])
    shank, thigh, torso = 0.246 * size, 0.245 * size, 0.2924 * size
    shank[4] = thigh[4] = np.nan  # a giant seen only from the hips up
    shank[5] = np.nan  # a real person's leg missing
    torso[2] = np.nan
    seg = Segments(np.arange(N) * 0.1, np.zeros((N, 3)), shank, thigh, torso, np.zeros((N, 2, 3)), np.zeros((N, 3)))
    person = np.array([0, 1, -1, -1, -1, -1])
    assert oversized(seg, person, 1.3).tolist() == [False, False, False, True, True, False]
    assert not oversized(seg, person, 0.0).any()
    allnan = replace(seg, shank=np.full(N, np.nan), thigh=np.full(N, np.nan), torso=np.full(N, np.nan))
    assert not oversized(allnan, person, 1.3).any()


@pytest.fixture(scope="module")
def lab_room(lab_dir):
    """15 s of two walkers in the 20-camera lab, its true poses: (cameras, messages)."""
    scene = Scene.load(lab_dir)
    sim = Simulator(scene, SimConfig(persons=2, duration=15.0, seed=0, heights=(1.96, 1.70)))
    ref = {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}
    return CameraSet.combine(dict(scene.intrinsics), ref), [m for _, m in sim.messages()]


def test_bones_are_for_chains_and_batch_means_first_and_final_adjustments(chain, lab_room):
    from backend.optimize import bones_wanted

    cfg = EngineConfig().optimize
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    t = np.zeros((2, 3))
    P = np.repeat(np.eye(6)[None], 2, axis=0)
    prob = Problem(cycle=1, R=R, t=t, prior_R=R, prior_t=t, prior_cov=P, focal=np.ones(2), config=cfg)
    # "auto" (the default) is decided by the pipeline when it builds the final adjustment:
    # "batch" where some camera saw people only in pairs (the corridor) ...
    assert cfg.bones == "auto" and not bones_wanted(replace(prob, kind="batch"))
    assert chain[0].config.bones == "batch" and chain[3]._pairwise_only().any()
    assert chain[3]._batch_problem(100, 0.1).config.bones == "off"  # the first adjustment's: not yet
    # ... and off where people are seen by three cameras and more (the lab)
    cams, msgs = lab_room
    p = Pipeline(cams, EngineConfig())
    for msg in msgs:
        p.push(msg)
        p.advance(p.clock)
    assert len(p.frames) > 50 and not p._pairwise_only().any()
    assert p._batch_problem(100, 0.1, final=True).config.bones == "off"
    cfg = cfg.model_copy(update={"bones": "batch"})
    prob = replace(prob, config=cfg)
    assert not bones_wanted(prob) and bones_wanted(replace(prob, kind="batch")) and bones_wanted(replace(prob, kind="first"))
    assert bones_wanted(replace(prob, config=cfg.model_copy(update={"bones": "all"})))
    assert not bones_wanted(replace(prob, kind="batch", config=cfg.model_copy(update={"bones": "off"})))


def test_label_persons_splits_two_sizes_and_skips_short_tracks():
    from backend.people import Segments

    rng = np.random.default_rng(0)
    T = np.repeat(np.arange(100) * 0.1, 2)
    com = np.zeros((200, 3))
    com[0::2, 0] = np.arange(100) * 0.1
    com[1::2, 0] = 5.0 - np.arange(100) * 0.1
    com[1::2, 1] = 3.0
    size = np.where(np.arange(200) % 2 == 0, 1.96, 1.70)
    n = lambda: rng.normal(0, 0.01, 200)  # noqa: E731
    seg = Segments(T, com, 0.246 * size + n(), 0.245 * size + n(), 0.2924 * size + n(), np.zeros((200, 2, 3)),
                   np.zeros((200, 3)))
    lab = label_persons(seg)
    assert len(set(lab[0::2])) == 1 and len(set(lab[1::2])) == 1 and lab[0] != lab[1]
    # a hypothesis alone in its track (fewer than min_track) gets no person
    com2 = com.copy()
    com2[50, 0] = 100.0
    assert label_persons(replace(seg, com=com2))[50] == -1
    assert segments([], np.zeros((0, 3, 3)), np.zeros((0, 3))).time.shape == (0,)


def test_label_persons_of_a_chain_whose_links_are_scaled_apart():
    """Two walkers of 1.80 and 1.65 m pass four links of a corridor in turn, and the
    estimate has the links' scales 1.0, 1.04, 0.97 and 1.5 (a two-walker corridor's online
    estimate had its link 3-4 1.5x too large). Grouped by size alone, link 3-4's walkers are
    one "person" and everyone else the other; told which link each hypothesis is in, the
    grouping fits the links' scales too and finds the walkers. In one network scale the
    links change nothing."""
    from backend.people import Segments

    rng = np.random.default_rng(1)
    scale = [1.0, 1.04, 0.97, 1.5]
    T, com, size, link, who = [], [], [], [], []
    for visit in range(16):  # each walker walks through each link twice, 3 s apart
        lk, person = visit % 4, (visit // 4) % 2
        t0 = 5.0 * visit
        for k in range(20):
            T.append(t0 + 0.1 * k)
            com.append([3.5 * lk + 0.05 * k, 3.0 * person, 1.0])
            size.append((1.80, 1.65)[person] * scale[lk])
            link.append(lk)
            who.append(person)
    T, com, size, link, who = map(np.array, (T, com, size, link, who))
    n = lambda: rng.normal(0, 0.01, len(T))  # noqa: E731

    def seg_of(sz):
        return Segments(T, com, 0.246 * sz + n(), 0.245 * sz + n(), 0.2924 * sz + n(), np.zeros((len(T), 2, 3)),
                        np.zeros((len(T), 3)))

    def agrees(lab):
        return max(np.mean(lab == who), np.mean(lab == 1 - who))

    seg = seg_of(size)
    assert agrees(label_persons(seg, count=2)) < 0.8
    assert agrees(label_persons(seg, count=2, links=link)) == 1.0
    one = seg_of(np.where(who == 0, 1.80, 1.65))
    assert np.array_equal(label_persons(one, count=2, links=link), label_persons(one, count=2))


def test_pipeline_cycles_run_on_a_chain_without_three_view_hypotheses():
    """Cycles wait for hypotheses of >= 3 views while a camera is unsettled; in a corridor
    there are none, and the cameras that only ever share people pairwise take part anyway."""
    from backend.pipeline import run_offline

    scene = corridor(3)
    sim = Simulator(scene, SimConfig(persons=1, duration=60.0, seed=3, heights=(HEIGHT,)))
    ref = {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}
    cams = CameraSet.combine(dict(scene.intrinsics), perturb_extrinsics(ref, 0.25, 10.0, seed=1))
    reports = []
    p = run_offline(cams, EngineConfig(), (m for _, m in sim.messages()), progress=lambda s, r: reports.append(r),
                    finish=False)
    pairwise = p._pairwise_only()
    assert pairwise.sum() >= 2 and np.array_equal(pairwise, p.associated_total >= 30)
    accepted = [r for r in reports if r.accepted and r.hypotheses > 0]
    assert accepted and {c for r in accepted for c in r.cameras} >= {n for n, w in zip(scene.names, pairwise) if w}
