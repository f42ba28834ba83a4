"""The simulator: parseable, deterministic, per-sensor consistent, exact without noise,
plausible figures in the 20-camera lab, and its parts (floor, walls, occlusion, body)."""

from __future__ import annotations

import itertools
import math
import struct
import zlib

import numpy as np
import pytest

from backend.cameras import project
from edge_clients.sim import Scene, SimConfig, Simulator, Truth
from edge_clients.sim.area import build_area, fov_limit, in_fov, wall_map
from edge_clients.sim.body import HIPS_W, SHOULDERS_W, Body, pose_joints
from edge_clients.sim.scene import read_gray_image
from edge_clients.sim.sensors import FLAG_DUPLICATE, SensorSim
from proto import read_recording, to_dict


DURATION = 8.0


@pytest.fixture(scope="module")
def scene(lab_dir) -> Scene:
    return Scene.load(lab_dir)


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    """A noisy 8 s run of two people in the lab, written as JSON Lines + gzip."""
    out = tmp_path_factory.mktemp("sim") / "rec.jsonl.gz"
    sim = Simulator(scene, SimConfig(persons=2, duration=DURATION, seed=0, heights=(1.96, 1.70)))
    stats = sim.write(out)
    return sim, stats, out


def test_recording_parses_and_matches_the_truth(run, scene):
    sim, stats, out = run
    msgs = list(read_recording(out))
    truth = Truth.load(Truth.sidecar_path(out))
    assert len(msgs) == stats.total_messages == len(truth.msg_seq) > 1500
    last_seq: dict[str, int] = {}
    for i, m in enumerate(msgs):
        assert truth.sensors[truth.msg_sensor[i]] == m.sensor and truth.msg_seq[i] == m.seq
        assert m.seq > last_seq.get(m.sensor, -1)
        last_seq[m.sensor] = m.seq
        assert m.size == scene.intrinsics[m.sensor].resolution
        assert len(m.persons) == int(np.sum(truth.det_msg == i))
    assert set(last_seq) == set(scene.names)
    assert np.all(np.diff(truth.msg_arrival) >= 0)  # arrival order
    delay = truth.msg_arrival - truth.msg_capture
    assert delay.min() >= 0.02 and delay.max() < 0.2
    clock = truth.msg_stamp - truth.msg_capture
    assert np.abs(clock).max() < 0.02 and np.abs(clock).max() > 0  # NTP errors of a few ms
    assert np.all(np.diff(truth.times) > 0)
    cap = truth.msg_capture
    assert truth.times[0] <= cap.min() and cap.max() <= truth.times[-1]


def test_same_seed_gives_identical_bytes(scene, tmp_path):
    cfg = SimConfig(persons=2, duration=2.0, seed=11)
    Simulator(scene, cfg).write(tmp_path / "a.jsonl.gz")
    Simulator(scene, cfg).write(tmp_path / "b.jsonl.gz")
    Simulator(scene, SimConfig(persons=2, duration=2.0, seed=12)).write(tmp_path / "c.jsonl.gz")
    a, b, c = ((tmp_path / f"{x}.jsonl.gz").read_bytes() for x in "abc")
    assert a == b and a != c
    ta, tb = Truth.load(tmp_path / "a.jsonl.gz.truth.npz"), Truth.load(tmp_path / "b.jsonl.gz.truth.npz")
    np.testing.assert_array_equal(ta.joints, tb.joints)
    np.testing.assert_array_equal(ta.det_person, tb.det_person)


def test_sensor_subsets_give_the_all_sensor_messages(scene):
    sim = Simulator(scene, SimConfig(persons=2, duration=3.0, seed=3))
    full = [(a, to_dict(m)) for a, m in sim.messages()]
    for subset in (["cam_3", "cam_12"], ["cam_15"]):
        part = [(a, to_dict(m)) for a, m in sim.messages(subset)]
        want = [x for x in full if x[1]["sensor"] in subset]
        assert len(part) == len(want) > 40
        assert repr(part) == repr(want)  # floats bit for bit
    assert any(p["persons"] for _, p in full)


def test_noise_free_projections_are_exact(scene, tmp_path):
    sim = Simulator(scene, SimConfig(persons=3, duration=2.0, seed=5, noise=False))
    sim.write(tmp_path / "exact.msgpack")
    truth = Truth.load(tmp_path / "exact.msgpack.truth.npz")
    msgs = list(read_recording(tmp_path / "exact.msgpack"))
    assert np.all(truth.det_person >= 0)  # no false detections without noise
    checked = 0
    for d in range(len(truth.det_msg)):
        m = msgs[truth.det_msg[d]]
        kp = m.persons[truth.det_index[d]].kp
        J = truth.joints_at(truth.det_capture[d])[truth.det_person[d]]
        uv, _ = project(J, scene.intrinsics[m.sensor], scene.poses[m.sensor])
        ok = kp[:, 2] > 0
        np.testing.assert_allclose(kp[ok, :2], uv[ok], atol=1e-6, rtol=0)
        checked += int(ok.sum())
    assert checked > 5000


def test_lenses_differ_from_their_calibration_as_the_truth_says(scene):
    """With zero pixel noise and no gross errors, reported joints are the true joints seen
    through the true lenses (which differ slightly from the calibration files)."""
    from dataclasses import replace

    cfg = SimConfig(persons=2, duration=1.0, seed=6, noise_scale=0.0, pixel_decimals=None, swap_prob=0.0,
                    snap_prob=0.0, hidden_drop=1.0, intrinsics_error=0.003)
    sim = Simulator(scene, cfg)
    msgs = [m for _, m in sim.messages()]
    t = sim.truth
    k = t.sensors.index("cam_4")
    assert abs(t.lens_fx[k] / scene.intrinsics["cam_4"].fx - 1) > 1e-5
    worst_file = checked = 0
    for d in np.flatnonzero(t.det_person >= 0):
        m = msgs[t.det_msg[d]]
        s = t.sensors.index(m.sensor)
        kp = m.persons[t.det_index[d]].kp
        ok = kp[:, 2] > 0
        J = t.joints_at(t.det_capture[d])[t.det_person[d]]
        file_intr = scene.intrinsics[m.sensor]
        lens = replace(file_intr, fx=t.lens_fx[s], fy=t.lens_fy[s], cx=t.lens_cx[s], cy=t.lens_cy[s])
        uv, _ = project(J, lens, scene.poses[m.sensor])
        np.testing.assert_allclose(kp[ok, :2], uv[ok], atol=1e-6)
        uv_file, _ = project(J, file_intr, scene.poses[m.sensor])
        worst_file = max(worst_file, float(np.abs(kp[ok, :2] - uv_file[ok]).max()))
        checked += int(ok.sum())
    assert checked > 1000 and 0.1 < worst_file < 10


def test_figures_are_plausible_for_the_lab(run):
    _, st, _ = run
    seen = [n for n, s in st.with_person.items() if s > 0]
    assert len(seen) >= 15  # most cameras see someone
    assert st.seen_by_at_least(2) > 0.9  # each person is seen by >= 2 cameras most of the time
    assert 3 < st.mean_cameras() < 15
    n = st.noise_rms
    assert n["torso"] < n["elbow/knee"] < n["wrist/ankle"] and n["head"] < n["wrist/ankle"]
    assert 1.0 < n["torso"] < 3.0 and 2.5 < n["wrist/ankle"] < 6.0
    assert 9 < st.visible_joints <= 17 and st.confident_joints < st.visible_joints
    assert st.false_detections > 0 and st.missed > 0 and st.detections > 800
    for name, count in st.messages.items():  # every sensor keeps its own rate, minus drops
        assert 0.8 * st.rates[name] * DURATION <= count <= st.rates[name] * DURATION + 1
    assert len({round(r, 3) for r in st.rates.values()}) == len(st.rates)
    text = st.table()
    assert "with person" in text and "injected pixel noise" in text and "cam_19" in text


def test_truth_sidecar_and_the_bodies(run):
    sim, _, out = run
    t = Truth.load(Truth.sidecar_path(out))
    mem = sim.truth
    for name in ("joints", "times", "msg_capture", "det_person", "det_flags", "states", "clock_offset"):
        np.testing.assert_array_equal(getattr(t, name), getattr(mem, name))
    assert t.sensors == mem.sensors and t.config["seed"] == 0 and t.config["duration"] == DURATION
    np.testing.assert_allclose(t.heights, [1.96, 1.70])
    i = int(np.flatnonzero(t.det_person >= 0)[0])
    sensor, seq = t.sensors[t.det_sensor[i]], int(t.det_seq[i])
    assert t.capture_time(sensor, seq) == t.det_capture[i]
    assert t.det_person[i] in t.persons_of(sensor, seq)
    assert t.joints_at(t.det_capture[i]).shape == (2, 17, 3)
    # anthropometry in the floor frame
    up = t.floor_up
    z = (t.joints - t.floor_origin) @ up  # (P, T, 17) heights above the floor
    for p, H in enumerate(t.heights):
        standing = t.states[p, :, 7] < 0.05  # not bending
        shoulders = np.linalg.norm(t.joints[p, :, 5] - t.joints[p, :, 6], axis=-1)
        hips = np.linalg.norm(t.joints[p, :, 11] - t.joints[p, :, 12], axis=-1)
        assert np.median(shoulders) / H == pytest.approx(SHOULDERS_W, rel=0.1)
        assert np.median(hips) / H == pytest.approx(HIPS_W, rel=0.1)
        assert np.median(z[p, standing, 0]) / H == pytest.approx(0.92, abs=0.04)  # nose
        assert z[p, :, 15:17].min() > 0.0 and np.median(z[p, :, 15:17]) < 0.12  # ankles near the floor
    speed = t.states[:, :, 5]
    assert speed.max() < 1.7 and np.mean(speed > 0.5) > 0.5 and np.mean(speed < 0.05) > 0.02  # walking, with stops
    gap = np.linalg.norm(t.states[0, :, :2] - t.states[1, :, :2], axis=-1)
    assert gap.min() >= 0.5 - 1e-9


@pytest.mark.parametrize("seed", [3, 5])
def test_walkers_keep_going(scene, seed):
    """Nobody gets stuck at a wall corner or in front of someone: within any 20 s a
    walker gets somewhere (pauses last 2-6 s)."""
    from edge_clients.sim.world import World

    cfg = SimConfig(persons=3, seed=seed)
    world = World(scene, cfg, build_area(scene, cfg.coverage_range))
    _, states = world.advance(int(60 * cfg.world_rate))
    xy = states[:, :, :2]
    for p in range(3):
        walked = np.r_[0, np.cumsum(np.linalg.norm(np.diff(xy[p], axis=0), axis=1))]
        in_20s = walked[2000:] - walked[:-2000]
        assert in_20s.min() > 3.0, (p, float(in_20s.min()))


def test_endless_run_is_produced_lazily(scene):
    sim = Simulator(scene, SimConfig(persons=2, duration=math.inf, seed=1))
    first = list(itertools.islice(sim.messages(["cam_0", "cam_1"]), 100))
    assert len(first) == 100 and all(b[0] >= a[0] for a, b in zip(first, first[1:]))
    with pytest.raises(ValueError, match="endless"):
        _ = sim.truth


def test_a_detector_that_detects_people_twice(scene, tmp_path):
    cfg = SimConfig(persons=2, duration=4.0, seed=5)
    plain = [to_dict(m) for _, m in Simulator(scene, cfg).messages(["cam_3", "cam_9"])]
    sim = Simulator(scene, SimConfig(**{**cfg.to_dict(), "duplicate_prob": 0.3}))
    st = sim.write(tmp_path / "dup.jsonl")
    t = Truth.load(tmp_path / "dup.jsonl.truth.npz")
    dup = (t.det_flags & FLAG_DUPLICATE) > 0
    assert st.duplicates == dup.sum() and 0.2 < dup.sum() / (t.det_person >= 0).sum() < 0.3
    assert (t.det_person[dup] >= 0).all()  # a duplicate is of a real person
    # every other detection is as without duplicates: their own random stream
    msgs = list(read_recording(tmp_path / "dup.jsonl"))  # in the truth's msg order
    at = {(m.sensor, m.seq): k for k, m in enumerate(msgs)}
    for want in plain:
        k = at[(want["sensor"], want["seq"])]
        got = to_dict(msgs[k])["persons"]
        kept = [got[i] for i in t.det_index[(t.det_msg == k) & ~dup]]
        assert sorted(map(repr, kept)) == sorted(map(repr, want["persons"]))
    # a duplicate lies on its person's other detection in the same frame, with fewer joints
    pairs = 0
    for d in np.flatnonzero(dup):
        twin = np.flatnonzero((t.det_msg == t.det_msg[d]) & (t.det_person == t.det_person[d]) & ~dup)
        assert len(twin) == 1
        first, second = (msgs[t.det_msg[d]].persons[t.det_index[i]].kp for i in (twin[0], d))
        both = (first[:, 2] > 0) & (second[:, 2] > 0)
        if both.sum() >= 5:
            h = np.ptp(first[first[:, 2] > 0, 1])
            assert np.median(np.linalg.norm(first[both, :2] - second[both, :2], axis=1)) < 0.05 * h
            pairs += 1
        assert (second[:, 2] > 0).sum() <= (first[:, 2] > 0).sum()
    assert pairs > 50


def test_a_sensor_that_stamps_late_by_a_varying_time(scene, tmp_path):
    cfg = SimConfig(persons=2, duration=6.0, seed=2)
    Simulator(scene, cfg).write(tmp_path / "a.jsonl")
    Simulator(scene, SimConfig(**{**cfg.to_dict(), "stamp_jitter": 0.02})).write(tmp_path / "b.jsonl")
    a, b = (Truth.load(tmp_path / f"{x}.jsonl.truth.npz") for x in "ab")
    # the same frames and detections; only the stamps moved, by 20 ms (std), at most 3 std
    assert np.array_equal(a.msg_capture, b.msg_capture) and np.array_equal(a.det_person, b.det_person)
    late = b.msg_stamp - a.msg_stamp
    assert 0.018 < late.std() < 0.022 and np.abs(late).max() <= 0.06 + 1e-9 and abs(late.mean()) < 0.002
    ma, mb = read_recording(tmp_path / "a.jsonl"), read_recording(tmp_path / "b.jsonl")
    assert all(x.persons == y.persons for x, y in zip(ma, mb))


def test_no_persons_only_false_detections(scene, tmp_path):
    st = Simulator(scene, SimConfig(persons=0, duration=1.0, seed=2, false_rate=0.5)).write(tmp_path / "empty.jsonl")
    t = Truth.load(tmp_path / "empty.jsonl.truth.npz")
    assert st.detections == 0 and st.false_detections > 0 and np.all(t.det_person == -1)
    assert all(s.score < 0.6 for m in read_recording(tmp_path / "empty.jsonl") for s in m.persons)


def test_bad_arguments(scene):
    with pytest.raises(ValueError, match="unknown sensors cam_77"):
        list(Simulator(scene, SimConfig(duration=1.0)).messages(["cam_1", "cam_77"]))
    with pytest.raises(ValueError, match="heights: 1 heights for 2 persons"):
        SimConfig(persons=2, heights=(1.8,))
    with pytest.raises(ValueError, match="SimConfig.drop_prob"):
        SimConfig(drop_prob=1.5)
    with pytest.raises(ValueError, match="SimConfig.rates"):
        SimConfig(rates=(30.0, 10.0))


# ---------------------------------------------------------------- the parts


def test_a_subset_of_the_cameras_keeps_the_room(scene, lab_dir):
    west = ("cam_14", "cam_11", "cam_12")
    part = scene.subset(west)
    again = Scene.from_cameras({n: scene.intrinsics[n] for n in west}, {n: scene.poses[n] for n in west},
                               lab_dir / "room.yaml")
    assert part.names == again.names == ("cam_11", "cam_12", "cam_14")
    assert all(part.poses[n] is scene.poses[n] and part.intrinsics[n] is scene.intrinsics[n] for n in west)
    assert np.allclose(part.floor.up, again.floor.up) and np.allclose(part.floor.origin, again.floor.origin)
    assert part.floorplan is scene.floorplan is not None
    with pytest.raises(ValueError, match="cam_99"):
        scene.subset(("cam_11", "cam_99"))


def test_floor_from_camera_geometry_matches_the_room(scene):
    guessed = Scene.from_cameras(scene.intrinsics, scene.poses)
    assert guessed.floorplan is None
    angle = math.degrees(math.acos(min(1.0, float(guessed.floor.up @ scene.floor.up))))
    assert angle < 3.0
    assert abs(float((guessed.floor.origin - scene.floor.origin) @ scene.floor.up)) < 0.15
    # and people walk there
    st = Simulator(guessed, SimConfig(persons=1, duration=1.0, seed=4)).stats
    assert st.detections > 25


def test_walls_hide_like_a_brute_force_ray_cast(scene):
    walls = wall_map(scene)
    plan = scene.floorplan
    rng = np.random.default_rng(0)
    area = build_area(scene, 12.0)
    lo, hi = plan.extent()
    agree = total = 0
    for k in (0, 5, 13):
        c = walls.xy[k]
        pts = rng.uniform(lo, hi, (300, 2))
        pts = pts[np.linalg.norm(pts - c, axis=1) < 15]
        got = walls.blocked(k, pts)
        for p, g in zip(pts, got):
            s = np.linspace(0, 1, 2000)[:, None]
            ray = c + s * (p - c)
            along = s[:, 0] * np.linalg.norm(p - c)
            ray = ray[(along > 0.35) & (along < np.linalg.norm(p - c) - 0.15)]
            want = bool(np.any(plan.occupied_at(ray))) if len(ray) else False
            agree += g == want
            total += 1
    assert agree / total > 0.93
    # walkers stay in the walkable area, which is free space seen by >= 2 cameras mostly
    assert area.targets.sum() > 0.6 * area.walk.sum()
    assert np.all(area.coverage[area.targets] >= 2)


def _looking_along(scene, name: str):
    """A camera's lens and pose, the floor, the camera's floor point and the unit floor
    direction (2,) it looks along."""
    intr, pose = scene.intrinsics[name], scene.poses[name]
    floor = scene.floor
    cam = floor.to_floor(pose.t)
    view = floor.to_floor(pose.t + pose.R[:, 2]) - cam
    return intr, pose, floor, cam, view[:2] / np.linalg.norm(view[:2])


def test_a_person_behind_another_is_occluded(scene):
    """Two people in a line from a camera: the rear one's hips and knees are hidden (its
    shoulders show beside the front one's head: the camera hangs at 2.5 m), the front
    one's are not."""
    name = "cam_9"
    intr, pose, floor, cam, d = _looking_along(scene, name)
    body = Body(height=1.8, hips_w=0.27, shoulders_w=0.32, arm_swing=0.3, lean=0.05, foot_w=0.1, bob=0.02)
    z1 = np.zeros(1)
    Js = []
    for dist in (2.5, 3.1):
        pos = (cam[:2] + dist * d)[None]
        Jf = pose_joints(body, pos, z1 + math.atan2(-d[1], -d[0]), z1, z1, z1, z1, z1, z1, z1 + 1, z1, z1)
        Js.append(floor.to_world(Jf)[0])
    J = np.stack(Js)[None]  # (1, 2, 17, 3)
    s = SensorSim(name, scene.names.index(name), intr, pose, SimConfig(noise=False), None, floor.R, floor.origin)
    uv, depth = project(J.reshape(-1, 3), intr, pose)
    occ = s._occluded(J, uv.reshape(1, 2, 17, 2), depth.reshape(1, 2, 17), np.ones((1, 2, 17), bool))
    assert not occ[0, 0, [5, 6, 11, 12, 13, 14]].any()  # front person
    assert occ[0, 1, [11, 12, 13, 14]].all()  # rear person


def test_keypoints_lie_on_the_outline_a_camera_sees(scene):
    """surface_offset: seen from the front, a hip's keypoint lies 1.25 x the offset out
    from the joint along the body's left-right axis; seen from the side, far less (only the
    offset's part across the ray shows); the head's keypoints never move."""
    name = "cam_9"
    intr, pose, floor, cam, d = _looking_along(scene, name)
    body = Body(height=1.8, hips_w=0.27, shoulders_w=0.32, arm_swing=0.0, lean=0.0, foot_w=0.1, bob=0.0)
    z1, pos = np.zeros(1), (cam[:2] + 3.0 * d)[None]
    facing = math.atan2(-d[1], -d[0])  # towards the camera
    J = np.stack([floor.to_world(pose_joints(body, pos, z1 + h, z1, z1, z1, z1, z1, z1, z1 + 1, z1, z1))[0]
                  for h in (facing, facing + math.pi / 2)])[:, None]  # (2 headings, 1 person, 17, 3)
    s = SensorSim(name, scene.names.index(name), intr, pose, SimConfig(surface_offset=0.04), None, floor.R, floor.origin)
    moved = np.linalg.norm(s._keypoints_3d(J) - J, axis=-1)[:, 0]  # (2, 17)
    # front: the hips' move is 1.25 x 4 cm less the small part along the slanted ray
    assert 0.045 < moved[0, 11] <= 0.05 and 0.045 < moved[0, 12] <= 0.05
    # side view: what is left is the part across the ray that looks down at the hips
    assert moved[1, 11] < 0.5 * moved[0, 11] and moved[1, 12] < 0.5 * moved[0, 12]
    assert np.all(moved[:, :5] == 0)
    off = SensorSim(name, scene.names.index(name), intr, pose, SimConfig(), None, floor.R, floor.origin)
    assert off._keypoints_3d(J) is J


def test_directions_outside_the_lens_model_are_not_seen(scene):
    intr, pose = scene.intrinsics["cam_4"], scene.poses["cam_4"]
    lim = fov_limit(intr)
    Xc = np.array([[1.8, 0.0, 1.0]])  # 61° off axis, far outside the 640x480 view
    uv, _ = project(pose.to_world(Xc), intr, pose)
    assert 0 <= uv[0, 0] < 640  # OpenCV's polynomial folds it back into the image
    assert not in_fov(Xc, lim)[0]
    assert in_fov(np.array([[0.7, 0.5, 1.0], [0.0, 0.0, 3.0]]), lim).all()  # the image corner is in view


def _png(gray: np.ndarray, filters) -> bytes:
    """A minimal PNG encoder with chosen per-row filter types (to test the decoder)."""
    h, w = gray.shape
    raw = bytearray()
    prev = np.zeros(w, np.int64)
    for r in range(h):
        cur = gray[r].astype(np.int64)
        f = filters[r % len(filters)]
        left = np.concatenate([[0], cur[:-1]])
        upleft = np.concatenate([[0], prev[:-1]])
        if f == 0:
            line = cur
        elif f == 1:
            line = cur - left
        elif f == 2:
            line = cur - prev
        elif f == 3:
            line = cur - (left + prev) // 2
        else:
            pa, pb, pc = np.abs(prev - upleft), np.abs(left - upleft), np.abs(left + prev - 2 * upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, upleft))
            line = cur - pred
        raw += bytes([f]) + bytes((line & 255).astype(np.uint8))
        prev = cur

    def chunk(t, b):
        return struct.pack(">I", len(b)) + t + b + struct.pack(">I", zlib.crc32(t + b) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(bytes(raw))) + chunk(b"IEND", b""))


def test_png_and_pgm_floor_plans(tmp_path, lab_dir):
    img = np.random.default_rng(0).integers(0, 256, (23, 17)).astype(np.uint8)
    p = tmp_path / "plan.png"
    p.write_bytes(_png(img, [0, 1, 2, 3, 4]))
    np.testing.assert_array_equal(read_gray_image(p), img)
    q = tmp_path / "plan.pgm"
    q.write_bytes(b"P5\n# a ROS map\n17 23\n255\n" + img.tobytes())
    np.testing.assert_array_equal(read_gray_image(q), img)
    lab = read_gray_image(lab_dir / "floorplan.png")
    assert lab.shape == (558, 531) and (lab < 100).mean() > 0.01 and (lab > 230).mean() > 0.3
