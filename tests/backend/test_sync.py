"""Synchronisation: framesets on a regular grid from free-running sensors.

Interpolation is checked against the exact projection of a person whose image motion is
linear (motion parallel to both image planes, no distortion), so any error is the
synchroniser's, not the test's approximation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from backend.cameras import Intrinsics, Pose, project
from backend.config import SyncConfig
from backend.sync import Synchronizer, interpolate
from proto import KeypointMessage, Person

SIZE = (640, 480)
INTR = Intrinsics("x", 450.0, 450.0, 320.0, 240.0, np.zeros(0), SIZE)
T0 = 1000.0  # small stamps keep float64 interpolation exact to ~1e-12 s


def _camera(pitch_deg: float, centre) -> Pose:
    """A camera whose x axis is the world x axis, looking along +y pitched down."""
    p = np.radians(pitch_deg)
    z = np.array([0.0, np.cos(p), -np.sin(p)])
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z], axis=1), np.asarray(centre, dtype=np.float64))


CAMS = {"a": _camera(0.0, [0.0, -4.0, 1.2]), "b": _camera(30.0, [0.5, -3.0, 3.0])}
# A rigid 17-joint body around (0, 1, 1) (world z up), walking along world x.
_RNG = np.random.default_rng(4)
BODY = np.array([0.0, 1.0, 1.0]) + _RNG.uniform(-0.3, 0.3, (17, 3)) * [1, 0.5, 3]
VELOCITY = np.array([0.8, 0.0, 0.0])


def _joints(t: float) -> np.ndarray:
    return BODY + VELOCITY * (t - T0)


def _pixels(sensor: str, t: float) -> np.ndarray:
    uv, z = project(_joints(t), INTR, CAMS.get(sensor, CAMS["a"]))
    assert np.all(z > 0)
    return uv


def _person(uv: np.ndarray, conf: float = 0.9) -> Person:
    kp = np.c_[uv, np.full(len(uv), conf)].astype(np.float64)
    return Person(kp, bbox=np.array([*uv.min(0), *uv.max(0)]))


def _msg(sensor: str, seq: int, stamp: float, persons=None, size=SIZE) -> KeypointMessage:
    if persons is None:
        persons = (_person(_pixels(sensor, stamp)),)
    return KeypointMessage(sensor, seq, stamp, size, tuple(persons))


def _stream(sensor: str, rate: float, phase: float, duration: float) -> list[KeypointMessage]:
    n = int(duration * rate)
    return [_msg(sensor, k, T0 + phase + k / rate) for k in range(n)]


def test_interpolated_keypoints_are_the_true_projection_at_the_frameset_time():
    msgs = _stream("a", 13.0, 0.013, 3.0) + _stream("b", 29.0, 0.021, 3.0)
    msgs.sort(key=lambda m: m.stamp)
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    for m in msgs:
        assert sync.push(m) is None
    fss = sync.pop_ready(T0 + 10.0)
    # the grid starts one step after the first stamp and ends where the brackets end
    assert 25 <= len(fss) <= 30
    assert np.allclose(np.diff([f.time for f in fss]), 0.1)
    worst = 0.0
    for fs in fss:
        assert [v.sensor for v in fs.views] == ["a", "b"]
        for v in fs.views:
            assert v.stamp == fs.time and v.offset == 0.0
            assert v.kp.shape == (1, 17, 3)
            err = np.abs(v.kp[0, :, :2] - _pixels(v.sensor, fs.time)).max()
            worst = max(worst, err)
            assert np.all(v.kp[0, :, 2] == pytest.approx(0.9))
    assert worst < 1e-6
    # the image really moves: nearest-message keypoints would be off by pixels
    assert np.abs(_pixels("a", T0 + 1.0) - _pixels("a", T0 + 1.0 + 0.5 / 13)).max() > 2
    assert sync.framesets == len(fss)
    # past the data the grid finds nobody: only empty framesets are dropped
    assert set(sync.framesets_rejected) <= {"too_few_views"}


def test_interpolate_function_speed_and_provenance():
    m0, m1 = _msg("a", 7, T0 + 0.10), _msg("a", 8, T0 + 0.15)
    v = interpolate(m0, m1, T0 + 0.13)
    assert v.interpolated and v.seq == 7 and v.index.tolist() == [0]
    assert np.abs(v.kp[0, :, :2] - _pixels("a", T0 + 0.13)).max() < 1e-6
    expected = np.linalg.norm(_pixels("a", T0 + 0.15) - _pixels("a", T0 + 0.10), axis=1) / 0.05
    assert np.allclose(v.speed[0], expected)
    # a joint missing in either message is missing in the interpolation
    kp = m1.persons[0].kp.copy()
    kp[3, 2] = 0.0
    v = interpolate(m0, KeypointMessage("a", 8, T0 + 0.15, SIZE, (Person(kp),)), T0 + 0.13)
    assert v.kp[0, 3, 2] == 0.0 and v.speed[0, 3] == 0.0 and v.kp[0, 4, 2] > 0


def test_nearest_message_within_max_offset_else_the_sensor_sits_out():
    """Sensor c sends rarely (no bracketing pair closer than max_gap): it joins a
    frameset with its nearest message if that is within max_offset, else sits out."""
    cfg = SyncConfig(max_offset=0.05)
    msgs = _stream("a", 20.0, 0.01, 2.0) + _stream("b", 20.0, 0.03, 2.0)
    msgs += [_msg("c", 0, T0 + 0.52), _msg("c", 1, T0 + 1.28)]
    msgs.sort(key=lambda m: m.stamp)
    sync = Synchronizer(cfg, ["a", "b", "c"])
    for m in msgs:
        assert sync.push(m) is None
    fss = {round(f.time - T0, 3): f for f in sync.pop_ready(T0 + 10.0)}
    with_c = {t: next(v for v in f.views if v.sensor == "c") for t, f in fss.items()
              if any(v.sensor == "c" for v in f.views)}
    assert sorted(with_c) == [0.5, 1.3]
    assert with_c[0.5].offset == pytest.approx(0.02) and with_c[0.5].stamp == T0 + 0.52
    assert with_c[1.3].offset == pytest.approx(-0.02) and with_c[1.3].stamp == T0 + 1.28
    assert not with_c[0.5].interpolated and with_c[0.5].seq == 0
    # 0.4, 0.6, 1.2, 1.4 are 0.08-0.12 s from c's messages: c sits out, a and b still make them
    for t in (0.4, 0.6, 1.2, 1.4):
        assert [v.sensor for v in fss[t].views] == ["a", "b"]


def test_a_slow_sensor_is_interpolated_at_every_frameset_up_to_max_gap():
    """A 2.2 Hz sensor (a pose detector on a small board) joins every frameset,
    interpolated; a stall longer than ``max_gap`` is a gap, not interpolated across.
    With the rule of before (only brackets within 2 x max_offset, 0.1 s) it joined
    about one frameset in five."""
    msgs = _stream("a", 2.2, 0.01, 5.0) + _stream("b", 20.0, 0.03, 5.0) + _stream("c", 15.0, 0.02, 5.0)
    msgs = [m for m in msgs if not (m.sensor == "a" and 2.0 < m.stamp - T0 < 2.8)]  # a stall of a
    msgs.sort(key=lambda m: m.stamp)
    sync = Synchronizer(SyncConfig(), ["a", "b", "c"])
    for m in msgs:
        sync.push(m)
    a_stamps = [m.stamp - T0 for m in msgs if m.sensor == "a"]
    before, after = max(t for t in a_stamps if t < 2.0), min(t for t in a_stamps if t > 2.8)
    fss = [f for f in sync.pop_ready(T0 + 10.0) if f.time <= T0 + max(a_stamps)]
    a = {round(f.time - T0, 3): next((v for v in f.views if v.sensor == "a"), None) for f in fss}
    for t, v in a.items():
        if before + 0.05 < t < after - 0.05:
            assert v is None, t  # a sits out: b and c make the frameset
        else:
            assert v is not None and v.interpolated, t
            assert np.abs(v.kp[0, :, :2] - _pixels("a", T0 + t)).max() < 1e-6
    assert sum(v is not None for v in a.values()) >= 30
    assert sum(v is None for v in a.values()) >= 8
    old = Synchronizer(SyncConfig(max_gap=0.1), ["a", "b", "c"])
    for m in msgs:
        old.push(m)
    joined = sum(any(v.sensor == "a" for v in f.views) for f in old.pop_ready(T0 + 10.0) if f.time <= T0 + max(a_stamps))
    assert joined < 0.3 * sum(v is not None for v in a.values())


def test_without_interpolation_the_nearest_message_is_used():
    msgs = _stream("a", 20.0, 0.01, 1.0) + _stream("b", 20.0, 0.03, 1.0)
    msgs.sort(key=lambda m: m.stamp)
    sync = Synchronizer(SyncConfig(interpolate=False), ["a", "b"])
    for m in msgs:
        sync.push(m)
    fss = [f for f in sync.pop_ready(T0 + 10.0) if f.time < T0 + 0.9]  # inside both streams
    assert len(fss) >= 7
    for fs in fss:
        for v in fs.views:
            assert not v.interpolated
            assert abs(v.offset) <= 0.025 + 1e-9 and v.stamp == pytest.approx(fs.time + v.offset)
            assert np.allclose(v.kp[0, :, :2], _pixels(v.sensor, v.stamp))


def test_stamp_span_and_std_limits_reject_and_count():
    # c's single message at +0.64 is used (max_offset 0.2) by framesets 0.5, 0.6, 0.7, 0.8
    # with offsets 0.14, 0.04, 0.06, 0.16; a and b are interpolated (offset 0).
    base = _stream("a", 20.0, 0.01, 1.5) + _stream("b", 20.0, 0.03, 1.5)
    c = _msg("c", 0, T0 + 0.64)

    def run(cfg: SyncConfig) -> tuple[Synchronizer, dict]:
        sync = Synchronizer(cfg, ["a", "b", "c"])
        for m in sorted(base + [c], key=lambda m: m.stamp):
            assert sync.push(m) is None
        return sync, {round(f.time - T0, 3): f for f in sync.pop_ready(T0 + 10.0)}

    sync, fss = run(SyncConfig(max_offset=0.2, max_span=0.05, max_std=1.0))
    assert sync.framesets_rejected["stamp_span"] == 3
    assert set(sync.framesets_rejected) == {"stamp_span", "too_few_views"}  # the latter after the data
    assert 0.6 in fss and not {0.5, 0.7, 0.8} & set(fss)
    assert [v.sensor for v in fss[0.6].views] == ["a", "b", "c"]

    # span 0.06 allowed, but std of (0, 0, 0.06) = 0.028 > 0.025; (0, 0, 0.04): 0.019
    sync, fss = run(SyncConfig(max_offset=0.2, max_span=1.0, max_std=0.025))
    assert sync.framesets_rejected["stamp_std"] == 3 and "stamp_span" not in sync.framesets_rejected
    assert 0.6 in fss and 0.7 not in fss
    assert sync.framesets == len(fss)


def test_bad_messages_are_rejected_with_their_reason():
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    now = T0 + 100.0
    m = _msg("a", 1, now - 0.1)
    assert sync.push(m, now) is None
    assert sync.push(m, now) == "duplicate"
    assert sync.push(_msg("a", 2, now - 0.1), now) == "duplicate"  # same instant, other seq
    assert sync.push(_msg("zz", 1, now), now) == "unknown_sensor"
    assert sync.push(_msg("b", 1, now + 6.0), now) == "stamp_in_future"
    assert sync.push(_msg("b", 2, now - 31.0), now) == "stamp_too_old"
    assert sync.push(_msg("b", 3, now + 4.0), now) is None  # within the limits
    fresh = Synchronizer(SyncConfig(), ["a", "b"])
    assert fresh.push(_msg("b", 4, now - 29.0), now) is None
    # framesets already closed: a message for their time is late
    sync.pop_ready(now + 5.0)
    assert sync.push(_msg("a", 9, now + 2.0), now + 5.0) == "late"
    assert dict(sync.rejected) == {"duplicate": 2, "unknown_sensor": 1, "stamp_in_future": 1,
                                   "stamp_too_old": 1, "late": 1}
    assert sync.rejected_sensors == {"duplicate": {"a": 2}, "unknown_sensor": {"zz": 1}, "stamp_in_future": {"b": 1},
                                     "stamp_too_old": {"b": 1}, "late": {"a": 1}}
    # unknown sensors are named, the first 32 names (random ids must not grow it)
    for k in range(100):
        assert sync.push(_msg(f"x{k % 50}", k, now + 4.5), now + 5.0) == "unknown_sensor"
    unknown = sync.rejected_sensors["unknown_sensor"]
    assert unknown["zz"] == 1 and unknown["x0"] == 2 and "x40" not in unknown
    assert len(unknown) == 32 and sync.rejected["unknown_sensor"] == 101


def test_out_of_order_arrivals_give_the_in_order_framesets():
    msgs = _stream("a", 20.0, 0.01, 4.0) + _stream("b", 15.0, 0.03, 4.0)
    rng = np.random.default_rng(1)
    # arrival = stamp + a random delay below wait - one message period: every bracket is
    # in before its frameset closes, though messages overtake each other
    arrivals = [m.stamp + rng.uniform(0.0, 0.15) for m in msgs]
    order = np.argsort(arrivals)
    assert np.any(np.diff([msgs[i].stamp for i in order]) < 0)  # really out of order

    def framesets(seq):
        sync = Synchronizer(SyncConfig(), ["a", "b"])
        out = []
        for i in seq:
            assert sync.push(msgs[i]) is None
            out += sync.pop_ready(arrivals[i])
        out += sync.pop_ready(T0 + 100.0)
        return out

    ordered = framesets(sorted(range(len(msgs)), key=lambda i: msgs[i].stamp))
    shuffled = framesets(order)
    assert len(ordered) == len(shuffled) >= 35
    for f, g in zip(ordered, shuffled):
        assert f.time == g.time and len(f.views) == len(g.views) == 2
        for v, w in zip(f.views, g.views):
            assert v.sensor == w.sensor and np.array_equal(v.kp, w.kp)
            # past a sensor's last message (the end of the data) its nearest one stands in
            assert v.interpolated or f.time > msgs[-1].stamp - 0.1
            if v.interpolated:
                assert np.abs(v.kp[0, :, :2] - _pixels(v.sensor, f.time)).max() < 1e-6


def test_buffers_stay_bounded_over_a_long_stream():
    rate_a, rate_b, duration = 20.0, 25.0, 300.0
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    pa = _person(_pixels("a", T0))  # fixed pixels: the bookkeeping is under test here
    pb = _person(_pixels("b", T0))
    msgs = sorted(
        [KeypointMessage("a", k, T0 + 0.01 + k / rate_a, SIZE, (pa,)) for k in range(int(duration * rate_a))]
        + [KeypointMessage("b", k, T0 + 0.02 + k / rate_b, SIZE, (pb,)) for k in range(int(duration * rate_b))],
        key=lambda m: m.stamp)
    most = {"a": 0, "b": 0}
    emitted = 0
    for i, m in enumerate(msgs):
        assert sync.push(m, m.stamp) is None
        emitted += len(sync.pop_ready(m.stamp))
        if i % 50 == 0:
            for s in most:
                assert len(sync._stamps[s]) == len(sync._msgs[s])
                most[s] = max(most[s], len(sync._stamps[s]))
            assert len(sync._pairs) <= 4097
    # the buffer holds ~2 s behind the grid plus the wait
    hold = 2.0 + sync.cfg.wait + 0.25
    assert most["a"] <= hold * rate_a + 2 and most["b"] <= hold * rate_b + 2
    assert emitted == sync.framesets >= (duration - sync.cfg.wait) * 10 - 5
    assert not sync.framesets_rejected and not sync.rejected


def test_a_long_silence_does_not_emit_a_backlog():
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    for m in sorted(_stream("a", 20.0, 0.01, 1.0) + _stream("b", 20.0, 0.03, 1.0), key=lambda m: m.stamp):
        sync.push(m)
    assert len(sync.pop_ready(T0 + 1.0 + sync.cfg.wait - 0.25)) >= 5
    before = sum(sync.framesets_rejected.values())
    sync.pop_ready(T0 + 3600.0)  # an hour without data
    assert sum(sync.framesets_rejected.values()) - before < 200
    assert sync.next_time > T0 + 3599.0


def test_the_framesets_before_a_silence_come_out_before_the_jump():
    """The last second's framesets were waiting for later messages when the sensors went
    silent; the jump over the silence emits them first (it used to skip them)."""
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    for m in sorted(_stream("a", 20.0, 0.01, 1.0) + _stream("b", 20.0, 0.03, 1.0), key=lambda m: m.stamp):
        sync.push(m)
    out = sync.pop_ready(T0 + 3600.0)
    assert len(out) >= 9 and all(len(f.views) == 2 for f in out)
    assert sync.next_time > T0 + 3599.0


@pytest.mark.parametrize("now", [math.inf, math.nan])
def test_a_clock_that_is_not_a_finite_time_is_refused_and_nothing_is_lost(now):
    msgs = _stream("a", 13.0, 0.013, 3.0) + _stream("b", 29.0, 0.021, 3.0)
    msgs.sort(key=lambda m: m.stamp)
    sync = Synchronizer(SyncConfig(), ["a", "b"])
    for m in msgs:
        sync.push(m)
    with pytest.raises(ValueError, match="finite time"):
        sync.pop_ready(now)
    assert 25 <= len(sync.pop_ready(T0 + 10.0)) <= 30  # the refused call took nothing
