"""Generated scenes: the corridor's overlap property, the room's coverage, their files, the CLI option."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from edge_clients.sim import Scene, SimConfig, Simulator
from edge_clients.sim.scenes import _walled, corridor, floor_views, grid, make, room, studio, tworooms, write_scene

# a standing person's torso as the association needs it (both hips and both shoulders),
# for statures 1.55-2.0 m: hips 0.53 H, shoulders 0.818 H
TORSOS = ((0.82, 1.27), (0.95, 1.47), (1.06, 1.64))


def test_corridor_cameras_overlap_only_their_neighbours():
    scene = corridor()
    C = len(scene.names)
    assert C == 6
    for torso in TORSOS:
        _, seen = floor_views(scene, torso)
        # no floor point where a torso is in three views
        assert seen.sum(0).max() == 2, torso
        for a in range(C):
            for b in range(a + 1, C):
                shared = int((seen[a] & seen[b]).sum())
                if b == a + 1:
                    assert shared >= 50, (torso, a, b, shared)  # >= 0.5 m² of floor (0.1 m cells)
                else:
                    assert shared == 0, (torso, a, b, shared)
    # the simulator's own coverage (torso and head) agrees: walkers' targets are the overlaps
    _, seen = floor_views(scene)
    assert seen.sum(0).max() == 2


def test_corridor_geometry_and_errors():
    s = corridor(4, spacing=3.0)
    c = s.centres()
    assert np.allclose(np.diff(c[:, 0]), 3.0) and np.allclose(c[:, 2], 2.6)
    for n in s.names:  # rotations are proper, cameras look forward and down
        R = s.poses[n].R
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert R[0, 2] > 0.5 and R[2, 2] < -0.3
    with pytest.raises(ValueError, match="at least 2"):
        corridor(1)
    with pytest.raises(ValueError, match="unknown scene"):
        make("cathedral")


@pytest.mark.parametrize("n", [4, 8])
def test_room_cameras_look_at_the_room_and_most_of_it_is_seen_by_three(n):
    s = room(n)
    c = s.centres()
    assert len(s.names) == n and np.allclose(c[:, 2], 2.5)
    assert (c[:, 0] > 0).all() and (c[:, 0] < 7).all() and (c[:, 1] > 0).all() and (c[:, 1] < 5).all()
    for name in s.names:  # proper rotations, looking down into the room
        R = s.poses[name].R
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0) and R[2, 2] < -0.2
        i = s.intrinsics[name]
        assert i.resolution == (640, 480) and i.dist[0] < 0  # wide and barrel-distorted
    _, seen = floor_views(s)
    k = seen.sum(0)
    assert (k >= 2).mean() > 0.95 and (k >= 3).mean() > 0.8
    with pytest.raises(ValueError, match="2 to 8"):
        room(9)
    assert make("room", cameras=4).names == s.names[:4]


def test_a_rolled_camera_turns_about_its_optical_axis_only():
    flat, rolled = room(4), room(4, roll=(0.0, 90.0, 180.0))
    for k, name in enumerate(flat.names):
        a, b = flat.poses[name], rolled.poses[name]
        assert np.allclose(a.t, b.t) and np.allclose(a.R[:, 2], b.R[:, 2])  # same place, same view
        turn = np.degrees(np.arctan2(a.R[:, 1] @ b.R[:, 0], a.R[:, 0] @ b.R[:, 0]))
        assert np.isclose(turn, (0.0, 90.0, 180.0, 0.0)[k]) or np.isclose(abs(turn), 180.0) and k == 2


def test_a_grid_hall_has_many_cameras_half_the_pairs_sharing_no_floor():
    s = grid(30, seed=3)
    c = s.centres()
    assert len(s.names) == 30 and c[:, 2].min() >= 2.6 and c[:, 2].max() <= 2.9
    # a grid 3 m apart: 7 columns for 30 cameras, camera 0 above the floor's origin
    assert np.allclose(c[:7, 1], 0.0) and np.allclose(np.diff(c[:7, 0]), 3.0) and np.allclose(c[0, :2], 0.0)
    pitch = [np.degrees(np.arcsin(-s.poses[n].R[2, 2])) for n in s.names]
    assert min(pitch) >= 25.0 and max(pitch) <= 45.0
    for n in s.names:  # proper rotations, image rows horizontal
        R = s.poses[n].R
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0) and abs(R[2, 0]) < 1e-12
    yaws = np.degrees(np.arctan2([s.poses[n].R[1, 2] for n in s.names], [s.poses[n].R[0, 2] for n in s.names]))
    assert np.ptp(yaws) > 270  # every way
    _, seen = floor_views(s)
    shared = seen.astype(np.int32) @ seen.T.astype(np.int32) >= 100  # >= 1 m² of floor (0.1 m cells)
    pairs = shared[np.triu_indices(30, 1)]
    assert 0.25 < pairs.mean() < 0.65, pairs.mean()  # unlike a room's, where every pair shares most of it
    assert (shared.sum(1) >= 3).all()  # itself and two others at least
    assert grid(30, seed=3).poses["cam_7"] == s.poses["cam_7"] and grid(30, seed=4).poses["cam_7"] != s.poses["cam_7"]
    assert make("grid", cameras=5).names == grid(5).names
    with pytest.raises(ValueError, match="at least 2"):
        grid(1)


def test_a_studio_rings_its_floor_at_two_heights_and_looks_down_on_it_from_above():
    s = studio()
    c = s.centres()
    assert s.names == tuple(f"cam_{i}" for i in range(9))
    assert np.allclose(np.hypot(c[:8, 0], c[:8, 1]), 3.5) and np.allclose(c[:8, 2], [1.3, 3.0] * 4)
    for n in s.names:
        R = s.poses[n].R
        assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    up = s.poses["cam_8"].R
    assert np.allclose(up[:, 2], [0, 0, -1]) and np.allclose(c[8], [0, 0, 3.4])  # straight down
    assert {s.intrinsics[n].resolution for n in s.names} == {(1280, 720), (848, 480), (1024, 1024)}
    _, seen = floor_views(s)
    k = seen.sum(0)
    assert (k >= 3).mean() > 0.95 and seen[8].sum() > 500  # the ceiling camera sees whole walkers too
    # its images have no up: a walker circling under it is seen upright, sideways and upside down
    sim = Simulator(s, SimConfig(persons=1, duration=30.0, seed=2, heights=(1.8,)))
    heads = []
    for _, msg in sim.messages(["cam_8"]):
        for person in msg.persons:
            kp = person.kp
            if (kp[[0, 11, 12], 2] > 0.5).all():
                v = kp[0, :2] - kp[11:13, :2].mean(0)  # hips to nose
                heads.append(np.degrees(np.arctan2(v[0], -v[1])))
    assert len(heads) > 50 and np.ptp(heads) > 180
    assert make("studio", cameras=4, overhead=None).names == ("cam_0", "cam_1", "cam_2", "cam_3")
    with pytest.raises(ValueError, match="at least 2"):
        studio(1)


def test_two_rooms_see_each_other_only_through_their_door():
    s = tworooms()
    c = s.centres()
    assert len(s.names) == 8 and (c[:4, 0] < 5).all() and (c[4:, 0] > 5).all()
    plan = s.floorplan
    wall = np.array([[5.0, 0.5], [5.0, 3.5]])
    assert plan.occupied_at(wall).all() and not plan.occupied_at(np.array([[5.0, 2.0]])).any()  # the door
    xy, seen = floor_views(s)
    # cam_2 sits by the wall between the rooms, looking away from the door: only its own room
    assert seen[2].sum() > 1000 and (xy[seen[2], 0] < 5).all()
    for k in (3, 7):  # the cameras facing the door see into the other room
        other = xy[seen[k], 0] > 5 if k == 3 else xy[seen[k], 0] < 5
        assert 300 < other.sum() < 0.5 * seen[k].sum()
    # walkers go from room to room
    sim = Simulator(s, SimConfig(persons=1, duration=120.0, seed=0, heights=(1.8,)))
    side = sim.truth.joints[0, :, 0, 0] > 5.0
    assert 0.2 < side.mean() < 0.8 and (np.diff(side.astype(int)) != 0).sum() >= 4
    with pytest.raises(ValueError, match="door"):
        tworooms(door=0.3)
    # an inner wall lies where it is said to, also off the middle
    lopsided = _walled(s.names, s.intrinsics, s.poses, (0.0, 0.0), (10.0, 4.0), ((5.0, 0.0, 5.2, 1.0),))
    occ = lopsided.floorplan.occupied_at(np.array([[5.1, 0.5], [5.1, 3.5], [4.8, 0.5], [5.1, 1.2]]))
    assert occ.tolist() == [True, False, False, False]


def test_written_scene_loads_and_simulates(tmp_path):
    scene = corridor()
    d = write_scene(scene, tmp_path / "corridor")
    loaded = Scene.load(d)
    assert loaded.names == scene.names
    for n in scene.names:
        assert loaded.poses[n] == scene.poses[n] and loaded.intrinsics[n] == scene.intrinsics[n]
    assert np.allclose(loaded.floor.up, [0, 0, 1]) and loaded.floorplan is not None
    assert np.array_equal(loaded.floorplan.occupied, scene.floorplan.occupied)
    # a walker stays inside the corridor and is seen by two cameras most of the time
    sim = Simulator(loaded, SimConfig(persons=1, duration=20.0, seed=1, heights=(1.8,)))
    truth = sim.truth
    xy = truth.joints[0, :, 0, :2]  # nose, floor frame = world frame here
    assert xy[:, 1].min() > -1.25 and xy[:, 1].max() < 1.25


def test_cli_simulate_corridor(tmp_path):
    from backend.cli import _register_all, app

    _register_all()
    out = tmp_path / "c.jsonl"
    r = CliRunner().invoke(app, ["simulate", "--scene", "corridor", "--persons", "1", "--duration", "4",
                                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "c.jsonl.cameras" / "reference.yaml").is_file() and out.is_file()
    assert "6 cameras" in r.output
    r = CliRunner().invoke(app, ["simulate", "--scene", "atrium", "--out", str(tmp_path / "d.jsonl")])
    assert r.exit_code != 0 and "unknown scene" in r.output
