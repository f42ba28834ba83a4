"""Sensor clock offsets: the estimator's pieces, the synchroniser applying offsets, and
a short simulated run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
from backend.clock_offsets import (BODY, ClockOffsetEstimator, Samples, fit_pose, interpolate_track,
                                   _row_nanmedian, jackknife_minimum, parabola_minimum, profile)
from backend.geometry import so3_exp
from backend.config import EngineConfig, SyncConfig
from backend.pipeline import Pipeline
from backend.sync import Synchronizer
from proto import KeypointMessage, Person

LAB = Path(__file__).resolve().parents[2] / "edge_clients" / "data" / "ais_lab20"


def test_interpolate_track_brackets_and_gaps():
    stamps = np.array([0.0, 0.1, 0.2, 0.6])
    xy = np.arange(4, dtype=float)[:, None, None] * np.ones((4, 2, 2))
    ok = np.ones((4, 2), bool)
    ok[1, 1] = False
    pos, good = interpolate_track(stamps, xy, ok, np.array([0.05, 0.15, 0.4, 0.6, 0.7]), max_gap=0.3)
    assert pos[0, 0, 0] == pytest.approx(0.5) and good[0, 0] and not good[0, 1]  # joint 1 missing at 0.1
    assert pos[1, 0, 0] == pytest.approx(1.5)
    assert not good[2].any()  # the 0.4 s gap is too wide
    assert good[3].all() and pos[3, 0, 0] == pytest.approx(3.0)  # exactly the last stamp
    assert not good[4].any()  # after the track


def test_parabola_minimum_is_sub_grid_and_refuses_edges():
    grid = np.arange(-0.05, 0.0501, 0.01)
    assert parabola_minimum((grid - 0.013) ** 2, grid) == pytest.approx(0.013, abs=1e-9)
    assert parabola_minimum((grid - 0.2) ** 2, grid) is None
    assert parabola_minimum((grid - 0.045) ** 2, grid) is None  # too close to the edge for 5 points


def test_jackknife_minimum_and_its_spread():
    rng = np.random.default_rng(1)
    grid = np.arange(-0.02, 0.0201, 0.004)
    blocks = np.stack([(grid - 0.003 - rng.normal(0, 0.002)) ** 2 * 1e4 for _ in range(8)])
    x, s = jackknife_minimum(blocks, grid)
    assert abs(x - 0.003) < 0.003 and 0.0002 < s < 0.003
    assert jackknife_minimum(blocks[:2], grid) is None


def _camera(rng) -> tuple[np.ndarray, np.ndarray]:
    """A camera 6 m from the origin looking at it (world_R_cam, centre)."""
    c = np.array([6.0, 0.5, 2.5])
    z = -c / np.linalg.norm(c)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1), c


def test_fit_pose_recovers_a_pose_3_degrees_and_20_cm_off():
    rng = np.random.default_rng(2)
    R, t = _camera(rng)
    X = rng.uniform(-1.5, 1.5, (300, 3)) + [0, 0, 1.0]
    Xc = (X - t) @ R
    x = Xc[:, :2] / Xc[:, 2:] + rng.normal(0, 1 / 500, (300, 2))
    x[:20] += 0.3  # outliers
    R0, t0 = R @ so3_exp(np.radians([2.0, -2.0, 1.0])), t + [0.15, -0.1, 0.08]
    Rf, tf, d = fit_pose(X, x, R0, t0, 5 / 500, 10)
    assert np.degrees(np.arccos(np.clip((np.trace(Rf.T @ R) - 1) / 2, -1, 1))) < 0.1
    assert np.linalg.norm(tf - t) < 0.01
    assert np.median(d[20:]) * 500 < 1.5


def _walking(rng, R, t, body, duration: float, delay: float) -> Samples:
    """One person (body (J, 3)) on a Lissajous path at about 1 m/s (every direction
    within 40 s), 3D with 1 cm noise at 10 Hz framesets; the sensor (R, t) sees it
    ``delay`` s late at 30 Hz with 2 px noise."""
    def walk(T):
        return np.stack([2.5 * np.sin(0.45 * T), 2 * np.cos(0.37 * T), np.zeros_like(T)], axis=1)

    times = np.arange(0.0, duration, 0.1)
    fine_t = np.arange(-1.0, duration + 1.0, 1 / 30)
    X = walk(times)[:, None, :] + body  # (N, J, 3) at the frameset times
    Xc = (walk(fine_t - delay)[:, None, :] + body - t) @ R  # what the sensor saw at its raw stamps
    xy = Xc[..., :2] / Xc[..., 2:] + rng.normal(0, 2 / 500, Xc[..., :2].shape)
    track = (fine_t, xy, np.ones(xy.shape[:2], bool))
    return Samples(X + rng.normal(0, 0.01, X.shape), times, tuple(track for _ in times))


def test_profile_finds_a_delay_with_the_pose_off():
    """Persons walking in every direction; the sensor sees them 80 ms late, its pose is
    2° / 10 cm off: the profile over the offset (pose fitted at each) finds 80 ms."""
    rng = np.random.default_rng(3)
    R, t = _camera(rng)
    body = rng.normal(0, 0.25, (len(BODY), 3)) + [0, 0, 1.0]
    delay = 0.08
    smp = _walking(rng, R, t, body, 40.0, delay)
    grid = np.arange(-0.2, 0.2001, 0.01)
    R0, t0 = R @ so3_exp(np.radians([1.5, -1.0, 0.8])), t + [0.08, -0.05, 0.03]
    res = profile(smp, grid, R0, t0, 0.3, 5.0, 500.0, 0.5)
    assert grid[np.argmin(res[0].sum(0))] == pytest.approx(delay, abs=0.011)
    fine = delay + np.arange(-0.02, 0.0201, 0.004)
    x, s = jackknife_minimum(profile(smp, fine, R0, t0, 0.3, 5.0, 500.0, 0.5)[0], fine)
    assert abs(x - delay) < 0.003 and s < 0.003


def test_coarse_profile_with_the_pose_held_finds_a_large_offset():
    """The search over the whole range holds the pose (fitted at the centre, then once
    at the best candidate) instead of fitting it at every candidate: a sensor 200 ms
    early with its pose 1.5° / 8 cm off is found within one grid step; so is a
    synchronised one."""
    rng = np.random.default_rng(4)
    R, t = _camera(rng)
    body = rng.normal(0, 0.25, (len(BODY), 3)) + [0, 0, 1.0]
    grid = np.arange(-0.25, 0.2501, 0.01)
    R0, t0 = R @ so3_exp(np.radians([1.5, -1.0, 0.8])), t + [0.08, -0.05, 0.03]
    for delay in (-0.2, 0.0):
        smp = _walking(rng, R, t, body, 60.0, delay)
        res = profile(smp, grid, R0, t0, 0.3, 5.0, 500.0, 0.5, nuisance="fixed")
        assert res[1] == 12 and res[2] < 4.0  # 60 s in 5 s blocks; residuals near the noise at the minimum
        assert grid[np.argmin(res[0].sum(0))] == pytest.approx(delay, abs=0.011)


def test_identification_gate_grows_with_the_pose_covariance():
    """A sensor's gate for its free tracks is clock.match_px with a certain pose, wider
    with an uncertain one (3 stds of the projection), at most clock.match_max_px."""
    cfg = EngineConfig().clock
    intr = load_intrinsics(LAB / "intrinsics.yaml")["cam_0"]
    est = ClockOffsetEstimator(cfg, ("a",), {"a": intr}, 0.6)
    f = float(est.focal[0])
    R, t = _camera(np.random.default_rng(5))
    X = (np.random.default_rng(6).normal(0, 0.25, (3, len(BODY), 3)) + [0, 0, 1.0])
    Xc = (X - t) @ R
    proj = Xc[..., :2] / Xc[..., 2:]
    proj[2] = np.nan  # a person behind the camera: the plain gate
    assert est._gates(0, proj, R, t, X) * f == pytest.approx([cfg.match_px] * 3)  # no covariance given
    est.pose_cov = np.zeros((1, 6, 6))
    assert est._gates(0, proj, R, t, X) * f == pytest.approx([cfg.match_px] * 3)
    est.pose_cov[0] = np.diag([np.radians(1.0) ** 2] * 3 + [0.02**2] * 3)  # 1°, 2 cm
    g = est._gates(0, proj, R, t, X) * f
    sig = np.radians(1.0) * f  # a rotation of 1° moves the image by about f rad
    assert cfg.match_px + 5 < g[0] < cfg.match_max_px and g[0] >= np.hypot(cfg.match_px, 0.9 * 3 * sig)
    assert g[2] == pytest.approx(cfg.match_px)
    est.pose_cov[0] = np.diag([np.radians(10.0) ** 2] * 3 + [0.25**2] * 3)  # the initial 10° / 0.25 m
    assert est._gates(0, proj, R, t, X)[:2] * f == pytest.approx([cfg.match_max_px] * 2)


def test_relocation_when_a_first_offset_is_applied():
    """The pose the estimate fitted with a sensor's offset replaces its camera's when that
    was never calibrated (a mistimed sensor's views join no hypothesis) or lies beyond
    the 3-sigma tail of its covariance; not when they agree."""
    intr = load_intrinsics(LAB / "intrinsics.yaml")["cam_0"]
    est = ClockOffsetEstimator(EngineConfig().clock, ("a",), {"a": intr}, 0.6)
    R, t = _camera(np.random.default_rng(7))
    P = np.diag([np.radians(0.3) ** 2] * 3 + [0.02**2] * 3)
    assert est.relocation(0, R, t, P, calibrated=False) is None  # nothing fitted yet
    est.pose[0] = (R @ so3_exp(np.radians([0.0, 0.5, 0.0])), t + [0.01, 0.0, 0.0])
    assert est.relocation(0, R, t, P, calibrated=True) is None  # 0.5°, 1 cm: within 3 sigma
    assert est.relocation(0, R, t, P, calibrated=False) is est.pose[0]
    est.pose[0] = (R @ so3_exp(np.radians([0.0, 3.0, 0.0])), t + [0.3, 0.0, 0.0])
    assert est.relocation(0, R, t, P, calibrated=True) is est.pose[0]  # calibrated to mistimed data


def _msg(sensor: str, seq: int, stamp: float, x: float) -> KeypointMessage:
    kp = np.zeros((17, 3))
    kp[:, 0] = x + np.arange(17)
    kp[:, 1] = 200 + 5 * np.arange(17)
    kp[:, 2] = 0.9
    return KeypointMessage(sensor, seq, stamp, (848, 480), (Person(kp),))


def test_applied_offsets_change_framing():
    """A sensor stamped 120 ms late: its keypoints at a frameset instant come from the
    wrong capture until its offset is applied; then they are those of the right one."""
    cfg = SyncConfig(wait=0.1)

    def framesets(offset: float | None) -> dict[float, float]:
        sync = Synchronizer(cfg, ["a", "b"])
        if offset is not None:
            sync.set_offset("b", offset)
        out = {}
        for k in range(60):
            t = 1000.0 + k / 20
            for s, late in (("a", 0.0), ("b", 0.12)):
                sync.push(_msg(s, k, t + late, x=100 * t))  # x moves 100 px/s with true time
            for fs in sync.pop_ready(t + 0.12):
                v = {v.sensor: v for v in fs.views}
                if "a" in v and "b" in v and len(v["b"].kp):
                    out[round(fs.time, 3)] = float(v["b"].kp[0, 0, 0] - v["a"].kp[0, 0, 0])
        return out

    plain, fixed = framesets(None), framesets(0.12)
    assert plain and fixed
    assert np.median(list(plain.values())) == pytest.approx(-12.0, abs=0.5)  # 120 ms of motion
    assert max(abs(x) for x in fixed.values()) < 1e-6


def test_set_offset_restamps_buffered_messages_and_keeps_raw_duplicates():
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    assert sync.push(_msg("b", 1, 1000.0, 0)) is None
    sync.set_offset("b", 0.05)
    assert sync._stamps["b"] == [pytest.approx(999.95)]
    assert sync.push(_msg("b", 1, 1000.0, 0)) == "duplicate"  # the same raw message again
    with pytest.raises(KeyError):
        sync.set_offset("nope", 0.1)


SIX = tuple(f"cam_{i}" for i in (1, 2, 8, 9, 10, 14))


def six_cameras(duration: float, seed: int, offsets: dict[str, float]):
    """6 cameras of the lab at their reference poses and what they publish: 2 persons,
    no detector noise, ``offsets`` (sensor -> s) on their clocks. Returns (cameras,
    messages)."""
    from edge_clients.sim import Scene, SimConfig, Simulator

    sim = Simulator(Scene.load(LAB), SimConfig(persons=2, duration=duration, seed=seed, noise=False,
                                               heights=(1.96, 1.70), clock_offsets=offsets))
    intr = load_intrinsics(LAB / "intrinsics.yaml")
    ref = load_extrinsics(LAB / "reference.yaml")
    return CameraSet.combine({n: intr[n] for n in SIX}, {n: ref[n] for n in SIX}), [m for _, m in sim.messages(SIX)]


def estimator_alone(cams: CameraSet, cfg: EngineConfig, msgs) -> Pipeline:
    """A pipeline fed ``msgs`` whose poses stay the reference (no adjustment): the clock
    estimator alone, finished."""
    p = Pipeline(cams, cfg)
    p._calibrated = lambda: True  # the poses are the reference: no adjustment to wait for
    for msg in msgs:
        p.push(msg)
        if p.clock is not None:
            p.advance(p.clock)
    p.finish()
    return p


@pytest.fixture(scope="module")
def short_run():
    """6 cameras of the lab, 2 persons, 40 s, no detector noise, two sensors 150 ms
    early / 90 ms late; the estimator fed with the reference poses."""
    names = list(SIX)
    offsets = {"cam_2": -0.15, "cam_9": 0.09}
    cams, msgs = six_cameras(40.0, 3, offsets)
    cfg = EngineConfig.from_dict({"clock": {"estimate": True}, "refine": {"final_batch": False},
                                  "associate": {"relocalize": False}})
    return estimator_alone(cams, cfg, msgs), offsets, names


@pytest.mark.xfail(strict=True, reason="the bar is not met on this small scene (docs/clock_offsets.md): with 2 "
                   "of 6 sensors off nearly every person's 3D from the others has a mistimed view, and 40 s "
                   "do not let the estimates untangle that")
def test_short_run_estimates_offsets_within_a_few_ms(short_run):
    p, offsets, names = short_run
    clocks = {c.sensor: c for c in p.state().clocks}
    true = np.array([offsets.get(n, 0.0) for n in names])
    true = true - np.median(true)
    for n, tr in zip(names, true):
        c = clocks[n]
        assert c.offset is not None, n
        assert abs(c.offset - tr) < 0.004, (n, c.offset, tr)
        assert 0 < c.std < 0.01
    for n in offsets:  # the big ones are applied
        assert abs(clocks[n].applied - true[names.index(n)]) < 0.005
    assert p.sync.offset("cam_2") == pytest.approx(clocks["cam_2"].applied)


def test_state_and_snapshot_carry_applied_offsets(short_run):
    p, _, _ = short_run
    d = p.state().to_dict()
    assert set(d["clocks"]) == set(p.names)
    # a sensor without an estimate says why (this scene: too little data in the last update)
    clocks = p.state().clocks
    for c in clocks:
        assert c.offset is not None or c.note, c.sensor
        assert d["clocks"][c.sensor]["note"] == c.note
    for n, c in d["clocks"].items():
        assert c["applied"] == pytest.approx(p.sync.offset(n))
    # an applied offset survives a restart: the data stay timed as before
    p.clocks.applied[p.names.index("cam_2")] = -0.15
    p._retime(["cam_2"])
    assert p.sync.offset("cam_2") == -0.15
    q = Pipeline.restore(p.cameras, p.cfg, p.snapshot())
    assert q.sync.offset("cam_2") == -0.15 and q.clocks.applied[q.names.index("cam_2")] == -0.15


def test_reestimate_after_the_final_adjustment_reports_and_applies_nothing(short_run):
    """The estimate at the end of a run, with the final poses: the offsets reported are
    those the given poses see (the same as a flush update with them), nothing applied
    changes."""
    import copy

    p, _, _ = short_run
    R, t = p.refiner.R.copy(), p.refiner.t.copy()
    flush = copy.deepcopy(p.clocks)
    flush.update(p.clock, R, t, flush=True)
    again = copy.deepcopy(p.clocks)
    applied = again.applied.copy()
    again.reestimate(p.clock, R, t)
    assert np.array_equal(again.applied, applied) and again._job is None
    assert np.allclose(again.raw, flush.raw, equal_nan=True) and np.isfinite(again.raw).sum() >= 3
    assert np.allclose(again.offset, flush.offset, equal_nan=True)
    assert again.note == flush.note


def test_a_drift_is_warned_of_when_two_fresh_estimates_agree_on_it():
    """One estimate 40 ms from the anchor is noise until the next fresh one says the same
    (a noisy detector made 11 such single jumps on synchronised sensors); a stale estimate
    (the update left the sensor as it was) confirms nothing."""
    est = _estimator_with([0.0, 0.0, 0.0], 1.0)

    def update(ms: float, now: float, fresh: bool = True) -> int:
        est.raw[0] = ms / 1000
        est.note[0] = None if fresh else "no clear minimum (jackknife)"
        est._apply(now)
        return int(est.drift_warnings[0])

    assert update(0.0, 10) == 0  # the anchor
    assert update(40.0, 20) == 0 and update(0.0, 30) == 0  # a single jump, gone again
    assert update(40.0, 40) == 0 and update(40.0, 50, fresh=False) == 0  # not confirmed by a stale one
    assert update(41.0, 60) == 1  # confirmed
    assert update(41.0, 70) == 1 and update(40.5, 80) == 1  # the new anchor: nothing more


def test_an_estimate_back_within_ntp_spread_is_no_drift():
    """A synchronised sensor whose first estimates were 22 ms off (the poses still rough)
    and now say 3 ms: that clock did not move, the estimate was wrong; no warning. One
    that leaves NTP's spread from there is warned of."""
    est = _estimator_with([0.0, 0.0, 0.0], 2.0)
    est.nblocks[:] = 8  # 22 - 4.5 x 2 ms: within min_apply, not applied

    def update(ms: float, now: float) -> int:
        est.raw[0] = ms / 1000
        est._apply(now)
        return int(est.drift_warnings[0])

    assert update(-22.0, 10) == 0 and update(-21.0, 20) == 0 and est.applied[0] == 0.0
    est.std[:] = 0.001
    assert update(3.0, 30) == 0 and update(3.5, 40) == 0  # re-anchored, silently
    assert update(30.0, 50) == 0 and update(31.0, 60) == 1


def test_a_less_certain_reestimate_does_not_replace_an_estimate(monkeypatch):
    """The re-estimate after the final batch replaces a sensor's estimate only when it is
    at least as certain (seed 5 of the bench: +123.7 +- 2.7 ms would have become +132.8 +-
    9.2); a sensor without an estimate before takes it, one the re-estimate lost keeps its."""
    from types import SimpleNamespace

    from backend.clock_offsets import ClockResult

    est = _estimator_with([123.7, -50.0, 5.0, 0.0], 2.7)
    est.raw[3] = est.std[3] = np.nan
    S = 4
    res = ClockResult(np.array([0.1328, -0.0510, np.nan, 0.0021]), np.array([0.0092, 0.0011, np.nan, 0.004]),
                      np.ones(S), np.full(S, 8), np.full(S, np.nan), (None,) * S,
                      (None, None, "no clear minimum (jackknife)", None))
    monkeypatch.setattr(est, "begin", lambda *a, **k: SimpleNamespace(run=lambda: res))
    applied = est.applied.copy()
    est.reestimate(1000.0, np.repeat(np.eye(3)[None], S, 0), np.zeros((S, 3)))
    assert est.raw[0] == pytest.approx(0.1237) and est.std[0] == pytest.approx(0.0027)  # kept
    assert est.raw[1] == pytest.approx(-0.0510) and est.std[1] == pytest.approx(0.0011)  # more certain: taken
    assert est.raw[2] == pytest.approx(0.005) and est.note[2] is None  # lost by the re-estimate: kept
    assert est.raw[3] == pytest.approx(0.0021)  # none before: taken
    assert np.array_equal(est.applied, applied)


def test_retime_leaves_archived_views_timed_otherwise_out_until_taken_back(short_run):
    p, _, _ = short_run
    c = p.names.index("cam_8")
    views = lambda: sum(1 for _, vs in p._timed_frames() for v in vs if v[0].cam == c)  # noqa: E731
    before, others = views(), sum(len(vs) for _, vs in p._timed_frames())
    assert before > 0
    old = p.sync.offset("cam_8")
    p.clocks.applied[c] = old + 0.05
    p._retime(["cam_8"])
    assert views() == 0  # timed 50 ms off: not for the batch
    assert sum(len(vs) for _, vs in p._timed_frames()) == others - before  # the other cameras' views stay
    p.clocks.applied[c] = old  # taken back: they are timed right again
    p._retime(["cam_8"])
    assert views() == before


def test_estimation_off_applies_nothing():
    assert EngineConfig().clock.estimate == "auto"  # started by stamps that run apart (its CPU: docs/clock_offsets.md)
    cfg = EngineConfig.from_dict({"clock": {"estimate": False}})
    est = ClockOffsetEstimator(cfg.clock, ("a",), {"a": load_intrinsics(LAB / "intrinsics.yaml")["cam_0"]}, 0.6)
    assert not est.due(1000.0)


def _estimator_with(raw_ms: list[float], std_ms: float) -> ClockOffsetEstimator:
    intr = load_intrinsics(LAB / "intrinsics.yaml")["cam_0"]
    names = tuple(f"s{i}" for i in range(len(raw_ms)))
    est = ClockOffsetEstimator(EngineConfig().clock, names, {n: intr for n in names}, 0.6)
    est.raw[:] = np.array(raw_ms) / 1000
    est.std[:] = std_ms / 1000
    est.nblocks[:] = 24
    est.note = [None] * len(names)  # as after an update that estimated every sensor
    return est


def _fake_profile(true: float, coarse: float):
    """A profile whose fine cost has its minimum at ``true`` and whose coarse search
    (the pose held) finds ``coarse`` instead: a pose fitted to mistimed views."""
    def fake(samples, grid, R, t, *a, nuisance="pose", **k):
        at = coarse if nuisance == "fixed" else true
        rng = np.random.default_rng(0)
        cost = (grid[None, :] - at) ** 2 * 1e4 + 1.0 + 0.01 * rng.random((8, len(grid)))
        return cost, 8, 2.0, 500, (R, t)
    return fake


@pytest.mark.parametrize("true, coarse, found", [(0.119, 0.050, True), (0.119, 0.119, True), (0.30, 0.100, False)])
def test_the_fine_search_walks_to_a_minimum_the_coarse_search_missed(monkeypatch, true, coarse, found):
    """Seed 3's cam_13 (+119 ms): the coarse search with its pose held found +70 ms, the
    fine one walked +90, +110, +126 and was cut off after three grids on every update for
    90 s. It walks as far as it needs within the searched range."""
    import backend.clock_offsets as co

    est = _estimator_with([0.0], 1.0)
    est.raw[:] = est.std[:] = np.nan
    monkeypatch.setattr(co, "profile", _fake_profile(true, coarse))
    monkeypatch.setattr(est, "_samples", lambda *a, **k: object())
    why = est._estimate_sensor_why(0, [], [], np.eye(3)[None], np.zeros((1, 3)))
    if found:
        assert why is None and est.raw[0] == pytest.approx(true, abs=0.002)
    else:  # the minimum lies beyond clock.max_offset: no estimate, the next update searches the range again
        assert why is not None and "beyond" in why and np.isnan(est.center[0]) and np.isnan(est.raw[0])


def test_offsets_within_ntp_spread_are_not_applied():
    """An estimate below clock.min_apply (what NTP keeps clocks within) changes nothing,
    however confident: applying it would drop the sensor's archived views for a timing
    error worth a centimetre. A real offset is applied, followed by changes beyond
    clock.min_change and 2.5 std, and taken back below half of min_apply."""
    cfg = EngineConfig().clock
    assert 0.01 <= cfg.min_apply <= 0.02 and cfg.min_change < cfg.min_apply
    est = _estimator_with([0.0, 9.0, -6.0, 2.0, -11.0, 200.0], 0.5)  # median 1.0 ms
    assert est._apply(-10.0) == []  # a first estimate is a candidate: applied when the next one agrees
    assert est._apply(0.0) == ["s5"]
    assert est.applied == pytest.approx([0, 0, 0, 0, 0, 0.199])
    est.raw[5] += 0.002  # within min_change
    assert est._apply(10.0) == []
    est.raw[5] += 0.004
    assert est._apply(20.0) == ["s5"] and est.applied[5] == pytest.approx(0.205)
    est.std[5] = 0.004  # a move of 8 ms is within 2.5 std of this estimate
    est.raw[5] += 0.008
    assert est._apply(30.0) == []
    est.std[:] = 0.0005
    est.raw[5] = 0.010  # 9 ms from the median: kept (hysteresis) ...
    assert est._apply(40.0) == ["s5"] and est.applied[5] == pytest.approx(0.009)
    est.raw[5] = 0.006  # ... until below half of min_apply
    assert est._apply(50.0) == ["s5"] and est.applied[5] == 0.0
    # the offset must be beyond min_apply by its tail, with the std from few blocks
    # itself uncertain (Student's t): 29 ms from the median with std 4 ms is 29 - 4.5 * 4 =
    # 11 ms beyond zero from 8 blocks (not enough), 29 - 3.4 * 4 = 15.4 ms from 30
    est.raw[5], est.std[5], est.nblocks[5] = 0.030, 0.004, 8
    assert est._apply(60.0) == [] and est._apply(70.0) == []
    est.nblocks[5] = 30
    assert est._apply(80.0) == [] and est._apply(90.0) == ["s5"]


def test_a_first_offset_needs_two_agreeing_fresh_estimates():
    """A synchronised sensor estimated once at +16.5 ms from few blocks (what the
    jackknife passed on seed 2) is not applied: the offset must be beyond clock.min_apply
    by its tail and found again, within the combined std, by the next fresh estimate;
    an update that left the sensor's estimate as it was does not count."""
    est = _estimator_with([0.0, 1.0, -1.0, 16.5], 1.0)
    est.nblocks[:] = 11
    assert est._apply(0.0) == [] and est._apply(10.0) == []  # 16 ms - 3.9 std: within NTP's spread
    est.raw[3], est.std[3] = 0.060, 0.002
    assert est._apply(20.0) == []  # beyond it, a first time: a candidate
    est.note[3] = "no clear minimum (jackknife)"  # the next update did not re-estimate it: stale
    assert est._apply(30.0) == []
    est.note[3] = None
    est.raw[3] = 0.080  # fresh, but 20 ms from the candidate (3.9 x 2.8 ms): not confirmed
    assert est._apply(40.0) == []
    est.raw[3] = 0.082  # fresh and agreeing with the last one
    assert est._apply(50.0) == ["s3"] and est.applied[3] == pytest.approx(0.0815)  # median 0.5 ms


def test_clock_job_runs_in_a_thread_on_a_snapshot():
    """The estimate's heavy part (ClockJob.run) runs in another thread while messages and
    framesets go on: it computes from the snapshot taken by clock_job, exactly what the
    same update gives on a copy of the pipeline made at that moment, and only
    apply_clock changes the estimator's state."""
    import pickle
    import threading

    cams, msgs = six_cameras(36.0, 4, {"cam_9": 0.09})
    cfg = EngineConfig.from_dict({"clock": {"estimate": True}, "refine": {"final_batch": False},
                                  "associate": {"relocalize": False}})
    p = Pipeline(cams, cfg)
    p.cycle, p.first_passes = 1, cfg.select.first_passes  # "calibrated": the poses are the reference
    k = 0
    while p.clock is None or p.clock < msgs[0].stamp + 30.0:
        p.push(msgs[k])
        k += 1
        if p.clock is not None:
            p.advance(p.clock, clock_offsets=False)
    assert not np.isfinite(p.clocks.raw).any()  # deferred: advance did not estimate
    copy_ = pickle.loads(pickle.dumps(p))
    job = p.clock_job(p.clock)
    assert job is not None and p.clock_job(p.clock) is None  # one in flight at a time
    out: list = []
    th = threading.Thread(target=lambda: out.append(job.run()))
    th.start()
    for m in msgs[k:]:  # the front end goes on meanwhile
        p.push(m)
        p.advance(p.clock, clock_offsets=False)
    th.join()
    assert not np.isfinite(p.clocks.raw).any()  # nothing changed before apply_clock
    p.apply_clock(job, out[0])
    copy_.clocks.update(job.now, job.R, job.t, P=copy_.refiner.S)  # as Pipeline.clock_job begins it
    assert np.isfinite(p.clocks.raw).sum() >= 2 and np.isfinite(p.clocks.raw[SIX.index("cam_9")])
    np.testing.assert_array_equal(p.clocks.raw, copy_.clocks.raw)
    np.testing.assert_array_equal(p.clocks.std, copy_.clocks.std)
    np.testing.assert_array_equal(p.clocks.applied, copy_.clocks.applied)
    assert p.clocks.due(p.clock + cfg.clock.interval)
    # a cancelled job changes nothing
    job = p.clock_job(p.clock + cfg.clock.interval)
    p.cancel_clock()
    before = p.clocks.raw.copy()
    assert job.run() is None and p.apply_clock(job, None) == []
    np.testing.assert_array_equal(p.clocks.raw, before)


def test_a_sensor_without_data_says_why_it_has_no_offset():
    intr = load_intrinsics(LAB / "intrinsics.yaml")["cam_0"]
    names = ("a", "b", "c")
    est = ClockOffsetEstimator(EngineConfig().clock, names, {n: intr for n in names}, 0.6)
    assert [c.note for c in est.clocks()] == ["no update yet"] * 3
    R, t = np.repeat(np.eye(3)[None], 3, axis=0), np.zeros((3, 3))
    est.update(100.0, R, t, flush=True)
    for c in est.clocks():
        assert c.offset is None and c.note is not None and "no samples" in c.note


def test_a_sensor_whose_estimates_agree_is_estimated_less_often(monkeypatch):
    """A synchronised sensor's fresh estimate that agrees with its last one doubles its
    interval up to clock.settled_interval; one that moved sets it back, and a sensor
    with an offset is estimated at every update. An update skips the sensors not due
    (they say why, and count as stale), a flush estimates every sensor."""
    from backend.clock_offsets import _Record

    est = _estimator_with([0.0, 2.0, 0.0], 1.0)
    cfg = est.cfg
    assert cfg.settled_interval > 2 * cfg.interval
    est._settle(0.0)  # first fresh estimates: nothing to agree with yet
    assert np.all(est.every == cfg.interval)
    for k in range(1, 6):  # agreeing estimates, one interval apart
        est.raw += 0.0005
        est._settle(k * cfg.interval)
    assert np.all(est.every == cfg.settled_interval)
    est.raw[1] += 0.030  # the second sensor's clock jumped
    est._settle(6 * cfg.interval)
    assert est.every[0] == cfg.settled_interval and est.every[1] == cfg.interval
    assert est.next_due[1] < 7 * cfg.interval < est.next_due[0]
    for k in range(7, 12):  # now 30 ms off: estimated at every update, steady or not
        est._settle(k * cfg.interval)
        assert est.every[1] == cfg.interval

    done = []
    monkeypatch.setattr(ClockOffsetEstimator, "_attach_tracks",
                        lambda self, recs, now, flush: [setattr(r, "tracks", [None] * len(r.cams)) for r in recs])
    monkeypatch.setattr(ClockOffsetEstimator, "_estimate_sensor", lambda self, s, *a: done.append(s))
    est.next_due[1] = 7 * cfg.interval
    est.records.append(_Record(7 * cfg.interval, np.array([0, 1]), np.zeros((2, len(BODY), 2)), np.zeros(3)))
    R, t = np.repeat(np.eye(3)[None], 3, axis=0), np.zeros((3, 3))
    job = est.begin(7 * cfg.interval, R, t)
    result = job.run()
    assert done == [1] and result.note[0].startswith("settled") and result.note[1] is None
    assert result.note[2].startswith("settled")
    est.finish(job, result)
    assert est.every[0] == cfg.settled_interval  # a skipped sensor keeps its interval
    done.clear()
    job = est.begin(7 * cfg.interval + 1, R, t, flush=True)
    job.run()
    assert sorted(done) == [0, 1, 2]


def test_views_within_ntp_spread_of_their_estimate_are_trusted():
    """A view made with nothing applied is left out of the others' 3D only when its
    sensor's estimate is one that would be applied (beyond clock.min_apply): with every
    sensor's clock a little off (detector latencies differ per board), the old 5 ms rule
    left no sensor two others timed right. A view made with an offset applied is left out
    when the estimate moved from it by more than clock.retime_tolerance."""
    from backend.clock_offsets import _Record

    est = _estimator_with([0.0, 0.0, 0.0, 0.0, 0.0, 10.0, 30.0, 33.0, 40.0], 1.0)  # median 0
    cfg = est.cfg
    assert cfg.retime_tolerance < 0.010 < cfg.min_apply < 0.030
    applied = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.030, 0.030])
    rec = _Record(0.0, np.arange(9), np.zeros((9, len(BODY), 2)), applied)
    ok, _ = est._trusted([rec])
    assert ok[0].tolist() == [True] * 6 + [False, True, False]


def test_the_row_median_is_numpys_nanmedian():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a = rng.normal(size=(int(rng.integers(1, 40)), 13))
        a[rng.random(a.shape) < 0.5] = np.nan
        a[:, 3] = rng.normal(size=len(a))  # every row has a value
        np.testing.assert_array_equal(_row_nanmedian(a), np.nanmedian(a, axis=1))


@pytest.mark.parametrize("offsets, starts", [({"cam_9": 0.09}, True), ({"cam_9": -0.15}, True), ({}, False)])
def test_auto_starts_the_estimate_when_a_sensor_s_stamps_run_apart(offsets, starts):
    """clock.estimate = "auto" (the default): a sensor 90 ms late or 150 ms early shows in
    its stamps as they arrive, and the estimate starts within 20 s of data (a warning
    names the sensor); with every clock synchronised it never starts, and nothing of it
    runs (no records, no raw archive, no clocks in the state). The sensor is one whose
    timing is undecided (the check of the initial estimate waits for it) until an offset
    is applied to it."""
    cams, msgs = six_cameras(30.0, 4, offsets)
    cfg = EngineConfig.from_dict({"refine": {"final_batch": False}})
    assert cfg.clock.estimate == "auto"
    p = Pipeline(cams, cfg)
    started = undecided = None
    for msg in msgs:
        p.push(msg)
        if p.clock is not None:
            p.advance(p.clock)
            if started is None and p.estimating:
                started, undecided = p.clock - msgs[0].stamp, p.timing_undecided()
    assert (started is not None) == starts, started
    if starts:
        assert started < 20.0 and p.raw is not None and p.clocks.records
        assert undecided == list(offsets)
        late = p.names.index(undecided[0])
        p.clocks.applied[late] = offsets[undecided[0]]
        assert p.timing_undecided() == []
        # a sensor with an estimate beyond NTP's spread, not applied yet, is undecided too,
        # unless its std says it cannot be applied (it would hold the check for nothing)
        other = (late + 1) % len(p.names)
        p.clocks.offset[other], p.clocks.std[other] = 2 * cfg.clock.min_apply, cfg.clock.max_std
        assert p.timing_undecided() == [p.names[other]]
        p.clocks.std[other] = 2 * cfg.clock.max_std
        assert p.timing_undecided() == []
        q = Pipeline.restore(cams, cfg, p.snapshot())
        assert q.estimating  # a restarted session goes on estimating
    else:
        assert p.raw is None and not p.clocks.records and p.state().clocks == () and p.timing_undecided() == []
        off = Pipeline.restore(cams, cfg, p.snapshot())
        assert not off.estimating


def test_auto_is_not_started_by_a_sensor_that_paused():
    """A sensor silent for a minute (a reboot) and back, its clock synchronised: its frame
    period is the steps between its stamps with the gap left out, so its stamps do not
    look ahead of the others' when it is back (a period over its whole span did: 0.1 s
    instead of 0.033, half of it added to its newest stamp)."""
    cams, msgs = six_cameras(90.0, 4, {})
    t0 = msgs[0].stamp
    quiet = SIX[2]
    msgs = [m for m in msgs if not (m.sensor == quiet and 5.0 < m.stamp - t0 < 65.0)]
    p = Pipeline(cams, EngineConfig.from_dict({"refine": {"final_batch": False}}))
    for msg in msgs:
        p.push(msg)
        if p.clock is not None:
            p._watch_stamps(p.clock)
    assert not p.estimating
    assert p.stamps.period(quiet) == pytest.approx(np.median(np.diff([m.stamp for m in msgs if m.sensor == quiet])),
                                                 rel=0.2)


WEST = tuple(f"cam_{i}" for i in range(11, 18))


@pytest.fixture(scope="module")
def west_mistimed():
    """The lab's west room (7 cameras at their reference poses), 2 persons, 120 s, the
    detector's noise, no NTP error but cam_14 30 ms late, which is left alone
    (``clock.min_apply`` 50 ms): its views keep placing persons for the others a little
    off in time. The estimator fed with the reference poses; the clocks of the last live
    update, then of the estimate at the end of the run (``reestimate``)."""
    from edge_clients.sim import Scene, SimConfig, Simulator

    sim = Simulator(Scene.load(LAB), SimConfig(persons=2, duration=120.0, seed=3, heights=(1.96, 1.70),
                                               clock_std=0.0, clock_offsets={"cam_14": 0.03}))
    intr, ref = load_intrinsics(LAB / "intrinsics.yaml"), load_extrinsics(LAB / "reference.yaml")
    cams = CameraSet.combine({n: intr[n] for n in WEST}, {n: ref[n] for n in WEST})
    cfg = EngineConfig.from_dict({"clock": {"estimate": True, "min_apply": 0.05}, "refine": {"final_batch": False},
                                  "associate": {"relocalize": False}})
    p = estimator_alone(cams, cfg, (msg for _, msg in sim.messages(WEST)))
    live = {c.sensor: c for c in p.clocks.clocks()}
    p.clocks.reestimate(p.clock, p.refiner.R, p.refiner.t)
    return live, {c.sensor: c for c in p.clocks.clocks()}


def test_the_std_at_the_end_covers_an_error_the_reference_cameras_share(west_mistimed):
    """A reference camera mistimed within what is left alone moves the offsets of the
    sensors it places persons for, alike in every block of data: the blocks' jackknife
    does not see it, the spread over the reference cameras (each left out in turn) does."""
    live, final = west_mistimed
    assert all(c.std_references is None for c in live.values())  # measured only at the end
    true = {n: 0.03 if n == "cam_14" else 0.0 for n in WEST}
    med = np.median(list(true.values()))
    measured = [c for c in final.values() if c.std_references is not None]
    assert len(measured) >= 3
    for c in final.values():
        if c.offset is not None:
            assert c.std == max(c.std_blocks, c.std_references or 0.0)
    hidden = 0
    for c in measured:
        err = abs(c.offset - (true[c.sensor] - med))
        assert err <= 2.0 * c.std, (c.sensor, err, c.std)
        hidden += err > 2.0 * c.std_blocks
    assert hidden >= 1  # the case the spread is for: an error beyond the blocks' own std
    d = final["cam_11"].to_dict()
    assert d["std"] == final["cam_11"].std and d["std_references"] == final["cam_11"].std_references
