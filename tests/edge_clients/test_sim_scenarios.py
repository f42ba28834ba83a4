"""Simulator scenarios: a camera bumped mid-run, sensors with offset and drifting clocks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from backend.cameras import Pose, project
from edge_clients.sim import Scene, SimConfig, Simulator, Truth
from edge_clients.sim.sensors import rotation
from proto import read_recording

BUMPS = ((1.0, "cam_3", 0.05, 2.0), (1.6, "cam_3", 0.03, 3.0), (0.7, "cam_7", 0.1, 0.0))


@pytest.fixture(scope="module")
def scene(lab_dir) -> Scene:
    return Scene.load(lab_dir)


@pytest.fixture(scope="module")
def bumped(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("bump") / "bump.msgpack"
    sim = Simulator(scene, SimConfig(persons=3, duration=3.0, seed=5, noise=False, bumps=BUMPS))
    sim.write(out)
    return Truth.load(Truth.sidecar_path(out)), list(read_recording(out)), sim


def test_the_truth_records_each_bump(scene, bumped):
    t, _, _ = bumped
    assert [t.sensors[i] for i in t.bump_sensor] == ["cam_7", "cam_3", "cam_3"]
    np.testing.assert_allclose(t.bump_time - t.start_time, [0.7, 1.0, 1.6], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(t.bump_translation, axis=1), [0.1, 0.05, 0.03], atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.linalg.norm(t.bump_rotation, axis=1)), [0.0, 2.0, 3.0], atol=1e-9)
    # the bumps of cam_3 add up: each moves and turns the pose before it
    R, c = scene.poses["cam_3"].R, scene.poses["cam_3"].t
    for k in (1, 2):
        R, c = rotation(t.bump_rotation[k]) @ R, c + t.bump_translation[k]
        np.testing.assert_allclose(t.bump_R[k], R, atol=1e-12)
        np.testing.assert_allclose(t.bump_t[k], c, atol=1e-12)
        angle = math.degrees(math.acos(np.clip((np.trace(t.bump_R[k].T @ (
            scene.poses["cam_3"].R if k == 1 else t.bump_R[1])) - 1) / 2, -1, 1)))
        assert abs(angle - (2.0, 3.0)[k - 1]) < 1e-6
    assert np.linalg.norm(t.bump_translation[1] / 0.05 - t.bump_translation[2] / 0.03) > 1e-3  # own directions


def test_noise_free_projections_follow_the_bumped_pose(scene, bumped):
    t, msgs, _ = bumped
    checked = {"before": 0, "after": 0}
    moved = 0.0
    for d in range(len(t.det_msg)):
        m = msgs[t.det_msg[d]]
        kp = m.persons[t.det_index[d]].kp
        ok = kp[:, 2] > 0
        cap = t.det_capture[d]
        J = t.joints_at(cap)[t.det_person[d]]
        p0 = scene.poses[m.sensor]
        R, c = t.pose_at(m.sensor, cap, p0.R, p0.t)
        uv, _ = project(J, scene.intrinsics[m.sensor], Pose(R, c))
        np.testing.assert_allclose(kp[ok, :2], uv[ok], atol=1e-6, rtol=0)
        if m.sensor in ("cam_3", "cam_7"):
            after = cap >= t.bump_time[t.bump_sensor == t.sensors.index(m.sensor)].min()
            checked["after" if after else "before"] += int(ok.sum())
            if after:
                uv0, _ = project(J, scene.intrinsics[m.sensor], p0)
                moved = max(moved, float(np.abs(kp[ok, :2] - uv0[ok]).max(initial=0.0)))
            else:
                assert R is p0.R
    assert checked["before"] > 100 and checked["after"] > 100, checked
    assert moved > 5.0  # a few cm and degrees move the image points by pixels


def test_bumps_keep_determinism_and_per_sensor_consistency(scene, bumped):
    _, _, sim = bumped
    cfg = sim.config
    full = [(a, m) for a, m in Simulator(scene, cfg).messages()]
    part = list(Simulator(scene, cfg).messages(["cam_3", "cam_5"]))
    want = [x for x in full if x[1].sensor in ("cam_3", "cam_5")]
    assert len(part) == len(want) > 40 and repr(part) == repr(want)
    # cameras that are not bumped see exactly what they see without bumps
    plain = [x for _, x in Simulator(scene, SimConfig(persons=3, duration=3.0, seed=5, noise=False)).messages(["cam_5"])]
    assert repr(plain) == repr([m for _, m in part if m.sensor == "cam_5"])


def test_configured_clock_offsets_and_drifts_are_in_the_stamps(scene, tmp_path):
    offsets = {"cam_1": 0.15, "cam_2": -0.2, "cam_4": 0.0}
    drifts = {"cam_2": 5e-5}
    cfg = SimConfig(persons=1, duration=4.0, seed=2, clock_offsets=offsets, clock_drifts=drifts)
    sim = Simulator(scene, cfg)
    sim.write(tmp_path / "clk.msgpack")
    t = Truth.load(tmp_path / "clk.msgpack.truth.npz")
    msgs = list(read_recording(tmp_path / "clk.msgpack"))
    for name, off in offsets.items():
        k = t.sensors.index(name)
        assert t.clock_offset[k] == off
        sel = t.msg_sensor == k
        assert sel.sum() > 20
        drift = drifts.get(name, t.clock_drift[k])
        assert t.clock_drift[k] == drift
        want = t.msg_capture[sel] + off + drift * (t.msg_capture[sel] - t.start_time)
        np.testing.assert_allclose(t.msg_stamp[sel], want, atol=1e-9, rtol=0)
        np.testing.assert_array_equal([m.stamp for m in np.array(msgs, dtype=object)[sel]], t.msg_stamp[sel])
    k2 = t.sensors.index("cam_2")
    lag = t.msg_stamp[t.msg_sensor == k2] - t.msg_capture[t.msg_sensor == k2]
    assert lag[-1] - lag[0] > 5e-5 * 3  # the drift shows over the run
    # other sensors keep their drawn NTP errors, and their messages
    plain = Simulator(scene, SimConfig(persons=1, duration=4.0, seed=2))
    assert repr(list(plain.messages(["cam_9"]))) == repr(list(sim.messages(["cam_9"])))
    assert plain.truth.clock_offset[t.sensors.index("cam_9")] == t.clock_offset[t.sensors.index("cam_9")]


@pytest.mark.parametrize("kw, needle", [
    ({"bumps": ((1.0, "cam_99", 0.05, 2.0),)}, "unknown sensors cam_99"),
    ({"clock_offsets": {"nope": 0.1}}, "unknown sensors nope"),
])
def test_unknown_sensors_in_scenarios_are_errors(scene, kw, needle):
    with pytest.raises(ValueError, match=needle):
        Simulator(scene, SimConfig(**kw))


@pytest.mark.parametrize("kw, needle", [
    ({"bumps": ((-1.0, "cam_1", 0.05, 2.0),)}, "bumps"),
    ({"bumps": ((1.0, "cam_1", 0.05),)}, "bumps"),
    ({"clock_offsets": {"cam_1": float("nan")}}, "clock_offsets"),
    ({"clock_drifts": 5}, "clock_drifts"),
])
def test_bad_scenarios_are_config_errors(kw, needle):
    with pytest.raises(ValueError, match=needle):
        SimConfig(**kw)
