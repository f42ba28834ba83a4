"""Replay: schedule (pure), bad recordings, and the replay → record round trip over real Zenoh."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

import numpy as np
import pytest
from typer.testing import CliRunner

from edge_clients.publisher import SensorPublisher
from edge_clients.record import Recorder
from edge_clients.replay import Schedule, planned, run_replay
from proto import KeypointMessage, Person, read_recording, write_recording
from proto.transport import ZenohSettings, free_port, open_session


def f32(a) -> np.ndarray:
    """Values that survive the wire's packed float32 exactly."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def make_msg(rng, sensor: str, seq: int, stamp: float, persons: int) -> KeypointMessage:
    ps = []
    for i in range(persons):
        kp = np.column_stack([rng.uniform(0, 848, 17), rng.uniform(0, 480, 17), rng.uniform(0, 1, 17)])
        kp[3, 2] = 0.0  # a joint that was not detected
        cov = f32(np.column_stack([rng.uniform(1, 9, 17), rng.uniform(-1, 1, 17), rng.uniform(1, 9, 17)])) if i else None
        ps.append(Person(kp=f32(kp), bbox=np.array([10.5, 20.25, 300.0, 470.125]), score=float(rng.uniform(0.5, 1)),
                         cov=cov, track=i if i else None))
    return KeypointMessage(sensor=sensor, seq=seq, stamp=stamp, size=(848, 480), persons=tuple(ps))


def make_recording(seed: int = 0, seconds: float = 1.5) -> list[KeypointMessage]:
    """Three free-running sensors in arrival order: own rates, clock offsets, latencies;
    cam_2's clock is an hour ahead (a broken NTP), some messages arrive out of stamp order."""
    rng = np.random.default_rng(seed)
    sensors = {"cam_0": (30.0, 0.000, 0.030), "cam_1": (25.0, 0.012, 0.050), "cam_2": (15.0, 3600.0, 0.040)}
    t_start = 1.7e9 + 100.0
    items = []
    for name, (rate, clock_err, latency) in sensors.items():
        n = int(seconds * rate)
        for k in range(n):
            capture = t_start + k / rate + rng.normal(0, 0.001)
            arrival = capture + latency + rng.exponential(0.01)
            items.append((arrival, make_msg(rng, name, 5 + k, capture + clock_err, int(rng.integers(0, 3)))))
    items.sort(key=lambda x: x[0])
    return [m for _, m in items]


@pytest.fixture
def zenoh_pair():
    """Two real sessions on loopback: one listens on a free port, the other connects."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    a = open_session(ZenohSettings(listen=(ep,)))
    b = open_session(ZenohSettings(connect=(ep,)))
    yield a, b, ep
    b.close()
    a.close()


# ---------------------------------------------------------------- schedule


def test_schedule_keeps_each_sensors_timing_and_the_arrival_order():
    msgs = make_recording()
    t0 = float(np.median([m.stamp for m in msgs[:64]]))
    sched = Schedule(t0=t0)
    dues = [sched.place(m) for m in msgs]
    assert all(b >= a for a, b in zip(dues, dues[1:])), "file (arrival) order must be kept"
    assert dues[-1] < 2.0, "an hour-off clock must not stall the replay"
    assert sched.reanchors == 0
    by = defaultdict(list)
    for d, m in zip(dues, msgs):
        by[m.sensor].append((d, m.stamp))
    for name, pairs in by.items():
        d, s = np.array(pairs).T
        # Paced by its own stamps: due - stamp is constant per sensor, except where the
        # file order forces a message to wait behind an earlier one (jitter, < 40 ms).
        lag = (d - d[0]) - (s - s[0])
        assert np.percentile(np.abs(lag), 50) < 0.005, name
        assert np.max(np.abs(lag)) < 0.04, name


def test_schedule_shortens_clock_steps_beyond_max_gap():
    rng = np.random.default_rng(1)
    msgs = [make_msg(rng, "cam_0", k, 1.7e9 + k * 0.1, 0) for k in range(10)]
    msgs += [make_msg(rng, "cam_0", 10 + k, 1.7e9 + 500 + k * 0.1, 0) for k in range(10)]  # a 500 s step
    sched = Schedule(t0=msgs[0].stamp, max_gap=5.0)
    dues = [sched.place(m) for m in msgs]
    assert sched.reanchors == 1
    assert dues[-1] == pytest.approx(1.8, abs=1e-6)


def test_planned_loops_shift_stamps_once_per_loop_and_continue_seq(tmp_path):
    msgs = make_recording(seconds=0.5)
    path = tmp_path / "r.jsonl"
    write_recording(path, msgs)
    origin = 2.0e9
    out = list(planned(path, origin=origin, loop=3))
    assert len(out) == 3 * len(msgs)
    t0 = float(np.median([m.stamp for m in msgs[:64]]))
    # Loop 0: one shift for all sensors, clock offsets kept.
    for (_, n, m), orig in zip(out[: len(msgs)], msgs):
        assert n == 0 and m.seq == orig.seq
        assert m.stamp - orig.stamp == pytest.approx(origin - t0, abs=1e-6)
    per_sensor = defaultdict(list)
    for due, n, m in out:
        per_sensor[m.sensor].append((due, m.seq, m.stamp))
    for name, rows in per_sensor.items():
        due, seq, stamp = np.array(rows).T
        assert np.all(np.diff(seq) > 0), f"{name}: seq must keep increasing across loops"
        assert np.all(np.diff(stamp) > 0), f"{name}: stamps must keep increasing across loops"
    dues = [d for d, _, _ in out]
    assert all(b >= a for a, b in zip(dues, dues[1:]))
    # Later loops are the first one shifted by one loop length, identically for all messages.
    shifts = {round(out[len(msgs) + i][2].stamp - out[i][2].stamp, 6) for i in range(len(msgs))}
    assert len(shifts) == 1


def test_planned_filters_sensors_but_keeps_the_common_shift(tmp_path):
    msgs = make_recording(seconds=0.5)
    path = tmp_path / "r.msgpack"
    write_recording(path, msgs)
    all_out = [m for _, _, m in planned(path, origin=2e9)]
    one = [m for _, _, m in planned(path, origin=2e9, sensors=["cam_1"])]
    assert [m.seq for m in one] == [m.seq for m in all_out if m.sensor == "cam_1"]
    assert [m.stamp for m in one] == [m.stamp for m in all_out if m.sensor == "cam_1"]


# ---------------------------------------------------------------- bad recordings


def test_replay_refuses_a_bad_recording_naming_file_line_and_field(tmp_path):
    from backend.cli import _register_all, app

    _register_all()
    good = make_recording(seconds=0.2)
    path = tmp_path / "bad.jsonl"
    write_recording(path, good[:3])
    lines = path.read_text().splitlines()
    lines.insert(1, lines[0].replace('"seq":', '"seq":-'))
    lines.append('{"v": 1, "sensor": "cam_0", "seq": 99, "stamp": 1.7e9, "size": [848, 480], "persons": [{"kp": [[1, 2, 1.5]]}]}')
    lines.append("not json")
    path.write_text("\n".join(lines) + "\n")
    runner = CliRunner()
    res = runner.invoke(app, ["replay", str(path), "-q", "--zenoh-connect", "tcp/127.0.0.1:1"])
    assert res.exit_code == 2
    assert f"{path}:2: seq: must be >= 0" in res.output
    # --skip-bad gets past the check and names what it skipped; --speed 0 and a dead
    # endpoint: the peer session opens anyway and the messages go nowhere.
    res = runner.invoke(app, ["replay", str(path), "--skip-bad", "--speed", "0", "-q",
                              "--zenoh-connect", f"tcp/127.0.0.1:{free_port()}"])
    assert res.exit_code == 0, res.output
    assert "sent 3 messages" in res.output
    assert "skipped 3 bad records" in res.output
    assert f"{path}:2: seq: must be >= 0" in res.output


def test_replay_of_a_missing_or_empty_file_is_a_clear_error(tmp_path):
    from backend.cli import _register_all, app

    _register_all()
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    res = CliRunner().invoke(app, ["replay", str(empty), "-q"])
    assert res.exit_code == 2 and "no valid messages" in res.output
    res = CliRunner().invoke(app, ["replay", str(tmp_path / "nope.jsonl"), "-q"])
    assert res.exit_code == 2 and "does not exist" in res.output


# ---------------------------------------------------------------- round trip


@pytest.mark.serial  # the replay's pace is measured on the wall clock
def test_replay_record_round_trip_changes_nothing_but_the_time_shift(tmp_path, zenoh_pair):
    rec_session, pub_session, _ = zenoh_pair
    original = make_recording()
    src = tmp_path / "src.jsonl.gz"
    write_recording(src, original)
    out = tmp_path / "out.msgpack"
    stop = threading.Event()
    recorder = Recorder(rec_session, out, flush_every=0.2)
    result = {}
    th = threading.Thread(target=lambda: result.setdefault("report", recorder.run(stop)))
    th.start()
    try:
        assert recorder.started.wait(10)
        with SensorPublisher(pub_session, block=True) as pub:
            assert pub.wait_matched(["cam_0", "cam_1", "cam_2"], 10)
            t = time.time()
            report = run_replay(pub, src, speed=5.0)
        deadline = time.monotonic() + 10
        while recorder.report.total < len(original) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        stop.set()
        th.join(10)
    assert report.sent == {"cam_0": 45, "cam_1": 37, "cam_2": 22}
    assert 1.5 / 5 * 0.8 < report.seconds < 1.5 / 5 + 1.0, "paced at 5× the recording's 1.5 s"
    assert abs(report.shift - (t - np.median([m.stamp for m in original[:64]]))) < 0.5
    rec = result["report"]
    assert rec.total == len(original) and not rec.rejected and not rec.dropped
    got = list(read_recording(out))
    by_sensor = defaultdict(list)
    for m in got:
        by_sensor[m.sensor].append(m)
    shifts = []
    for name in ("cam_0", "cam_1", "cam_2"):
        want = [m for m in original if m.sensor == name]
        have = by_sensor[name]
        assert len(have) == len(want)
        for w, h in zip(want, have):
            shifts.append(h.stamp - w.stamp)
            assert (h.seq, h.size, h.layout, h.persons) == (w.seq, w.size, w.layout, w.persons)
    assert np.ptp(shifts) < 1e-6, "one stamp shift for all sensors and messages"
    assert shifts[0] == pytest.approx(report.shift, abs=1e-6)


def test_loops_replay_a_clock_step_the_same_way_each_time(tmp_path):
    rng = np.random.default_rng(2)
    msgs = [make_msg(rng, "cam_0", k, 1.7e9 + k * 0.1, 0) for k in range(5)]
    msgs += [make_msg(rng, "cam_0", 5 + k, 1.7e9 + 500 + k * 0.1, 0) for k in range(5)]
    path = tmp_path / "step.jsonl"
    write_recording(path, msgs)
    out = list(planned(path, origin=2e9, loop=2, max_gap=5.0))
    dues = np.array([d for d, _, _ in out])
    first, second = dues[:10], dues[10:]
    np.testing.assert_allclose(second - second[0], first - first[0], atol=1e-9)
