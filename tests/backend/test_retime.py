"""Archived views timed again with a sensor's final clock offset (backend/retime.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
from backend.config import EngineConfig, SyncConfig
from backend.pipeline import Pipeline
from backend.retime import RawArchive
from backend.sync import Synchronizer
from proto import KeypointMessage
from test_clock_offsets import _msg, six_cameras  # _msg: one person, 17 joints on a line moving with x

LAB = Path(__file__).resolve().parents[2] / "edge_clients" / "data" / "ais_lab20"


def test_raw_archive_keeps_its_seconds_sorted_and_ignores_duplicates_and_strangers():
    raw = RawArchive(["a"], seconds=1.0)
    for k in (3, 1, 2, 0, 2):  # out of order, one twice
        raw.push(_msg("a", k, 1000.0 + 0.1 * k, 0))
    raw.push(_msg("nope", 0, 1000.0, 0))
    assert len(raw) == 4 and raw.span("a") == (1000.0, pytest.approx(1000.3))
    raw.push(_msg("a", 20, 1002.0, 0))  # 2 s later: the older ones go
    assert len(raw) == 1 and raw.span("a") == (1002.0, 1002.0)
    assert raw.span("nope") is None
    assert raw.keep(["a", "b"]).span("a") == (1002.0, 1002.0) and raw.keep(["b"]).span("b") is None


def test_views_at_an_offset_are_those_the_synchroniser_makes_with_it():
    cfg = SyncConfig(wait=0.1)
    sync, raw = Synchronizer(cfg, ["a", "b"]), RawArchive(["b"], 60.0)
    sync.set_offset("b", 0.12)
    views = {}
    for k in range(60):
        t = 1000.0 + k / 20
        sync.push(_msg("a", k, t, x=100 * t))
        m = _msg("b", k, t + 0.12 + 0.013 * (k % 3), x=100 * t)  # late and jittered
        sync.push(m)
        raw.push(m)
        for fs in sync.pop_ready(t - 0.1):
            views.update({fs.time: v for v in fs.views if v.sensor == "b"})
    assert len(views) > 20  # 10 framesets a second over 3 s
    again = raw.views("b", 0.12, list(views), cfg)
    for v, w in zip(views.values(), again):
        assert w is not None and w.interpolated == v.interpolated and w.stamp == pytest.approx(v.stamp)
        assert np.array_equal(w.kp, v.kp)


@pytest.fixture(scope="module")
def scene():
    return six_cameras(20.0, 5, {"cam_9": 0.12})


def _run(cams: CameraSet, msgs: list[KeypointMessage], offset: float | None) -> Pipeline:
    cfg = EngineConfig.from_dict({"clock": {"estimate": True}, "refine": {"final_batch": False},
                                  "associate": {"relocalize": False}})
    p = Pipeline(cams, cfg)
    p._calibrated = lambda: False  # no estimate: the offset is what the test sets
    if offset is not None:
        p.sync.set_offset("cam_9", offset)
    for m in msgs:
        p.push(m)
        if p.clock is not None:
            p.advance(p.clock)
    return p


def test_an_offset_found_late_times_the_whole_archive_again(scene):
    """The sensor's offset applied after 20 s of data: its archived views, left out of the
    batch before, are then those of a run that knew the offset from the start."""
    cams, msgs = scene
    late, known = _run(cams, msgs, None), _run(cams, msgs, 0.12)
    c = late.names.index("cam_9")
    views = lambda p: {T: [v for v in vs if v[0].cam == c] for T, vs in p._timed_frames()}  # noqa: E731
    late.clocks.applied[c] = 0.12
    late._retime(["cam_9"])
    assert not any(views(late).values())  # timed 120 ms off: out of the batch
    others = {T: [v for v in vs if v[0].cam != c] for T, vs in late.frames}

    accepted = late.preprocess.accepted
    n = late.retime_archive()["cam_9"]
    assert late.retimed == {"cam_9": n} and n > 100
    got, want = views(late), views(known)
    common = [T for T in got if T in want and T > late.frames[0][0] + 1.0]
    assert len(common) > 0.8 * len(want)
    for T in common:
        assert len(got[T]) == len(want[T])
        for a, b in zip(got[T], want[T]):
            assert len(a) == len(b)
            for d, e in zip(a, b):
                np.testing.assert_array_equal(d.xy, e.xy)
    assert {T: [v for v in vs if v[0].cam != c] for T, vs in late.frames} == others  # the others untouched
    assert late.retime_archive() == {}  # nothing left to time again
    assert late.preprocess.accepted == accepted  # what the session counted stays the live data's


def test_without_estimation_no_raw_messages_are_kept():
    intr = load_intrinsics(LAB / "intrinsics.yaml")
    ref = load_extrinsics(LAB / "reference.yaml")
    cams = CameraSet.combine({"cam_1": intr["cam_1"], "cam_2": intr["cam_2"]},
                             {"cam_1": ref["cam_1"], "cam_2": ref["cam_2"]})
    assert Pipeline(cams, EngineConfig()).raw is None
    cfg = EngineConfig.from_dict({"clock": {"estimate": True, "retime_seconds": 0}})
    assert Pipeline(cams, cfg).raw is None
