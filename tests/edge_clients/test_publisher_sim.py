"""`extrcal sensor sim` over real Zenoh publishes exactly what the simulator yields, per sensor."""

from __future__ import annotations

import queue
import time
from collections import defaultdict

import numpy as np
import pytest
from typer.testing import CliRunner

from proto import decode, keys
from proto.transport import ZenohSettings, free_port, open_session

sim = pytest.importorskip("edge_clients.sim")


def run_cli(args: list[str]):
    from backend.cli import _register_all, app

    _register_all()
    return CliRunner().invoke(app, args)


def same_message(got, want) -> None:
    assert (got.sensor, got.seq, got.stamp, got.size, got.layout) == (want.sensor, want.seq, want.stamp, want.size, want.layout)
    assert len(got.persons) == len(want.persons)
    for g, w in zip(got.persons, want.persons):
        # The wire packs keypoints as float32: < 1e-4 px at these image sizes.
        np.testing.assert_allclose(g.kp, w.kp, atol=2e-4, rtol=0)
        assert (g.bbox is None) == (w.bbox is None)
        if g.bbox is not None:
            np.testing.assert_array_equal(g.bbox, w.bbox)
        assert g.score == w.score and g.track == w.track


@pytest.mark.serial  # the publisher's pace is measured on the wall clock, from a start 3 s ahead
def test_sensor_sim_publishes_what_the_simulator_yields(lab_dir):
    """A process running two of the lab's 20 sensors sends exactly their messages of the
    all-sensor run (one process per sensor is the same with one; see test_publisher_backend)."""
    sensors = ["cam_0", "cam_7"]
    ep = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ZenohSettings(listen=(ep,)))
    got: queue.Queue = queue.Queue()
    sub = session.declare_subscriber(keys.all_keypoints("simsite"),
                                     lambda s: got.put((time.monotonic(), s.payload.to_bytes())))
    start_at = time.time() + 3.0  # the CLI starts, loads the scene and warms the simulator up
    duration, speed = 1.0, 2.0
    try:
        args = ["sensor", "sim", "--cameras", str(lab_dir), "--persons", "2", "--seed", "4",
                "--duration", str(duration), "--speed", str(speed), "--start-at", repr(start_at),
                "--site", "simsite", "--zenoh-connect", ep, "--wait-subscriber", "10", "-q"]
        for s in sensors:
            args += ["--sensor", s]
        res = run_cli(args)
        assert res.exit_code == 0, res.output
        # The all-sensor run of the same world, filtered: what each process must send.
        scene = sim.Scene.load(lab_dir)
        config = sim.SimConfig(persons=2, seed=4, duration=duration, start_time=start_at)
        want = [(a, m) for a, m in sim.Simulator(scene, config).messages() if m.sensor in sensors]
        arrivals, msgs = [], []
        deadline = time.monotonic() + 10
        while len(msgs) < len(want) and time.monotonic() < deadline:
            try:
                t, payload = got.get(timeout=0.2)
            except queue.Empty:
                continue
            arrivals.append(t)
            msgs.append(decode(payload))
        time.sleep(0.1)
        assert got.empty(), "nothing more than the simulator's messages"
    finally:
        sub.undeclare()
        session.close()
    assert len(want) > 10 * len(sensors)
    assert f"sent {len(want)} messages from {len(sensors)} sensors" in res.output
    by = defaultdict(list)
    for m in msgs:
        by[m.sensor].append(m)
    for name in sensors:
        w = [m for _, m in want if m.sensor == name]
        assert len(by[name]) == len(w)
        for g, x in zip(by[name], w):
            same_message(g, x)
    # Paced: arrivals spread over the simulated arrival span divided by --speed.
    span_sim = (want[-1][0] - want[0][0]) / speed
    span_got = arrivals[-1] - arrivals[0]
    assert span_sim * 0.8 - 0.05 < span_got < span_sim + 1.5
