"""Joining a group of cameras no pair links to the placed ones (backend/groups.py): two
rooms joined by a door (``scenes.tworooms``), four walkers, a short seeded simulation. The
placed room keeps its true poses; the other room's are given in a frame of their own (a
known similarity away), as its own bootstrap would give them: the join must find that
similarity from the persons each room sees of the other's, and must refuse when those
sightings are of other instants (nobody seen by both). The whole bootstrap places both
rooms (it placed one), and a camera its group misplaced is contradicted by the persons in
its view."""

from __future__ import annotations

import numpy as np
import pytest

from backend.bootstrap import bootstrap, collect_frames, view_box
from backend.config import EngineConfig
from backend.evaluate import evaluate
from backend.geometry import rotation_angle_deg, so3_exp
from backend.groups import contradicted, join


@pytest.fixture(scope="module")
def two_rooms():
    from edge_clients.sim import SimConfig, Simulator
    from edge_clients.sim.scenes import tworooms

    scene = tworooms()
    names = scene.names
    sim = Simulator(scene, SimConfig(persons=4, duration=90.0, seed=0))
    msgs = [m for _, m in sim.messages()]
    cfg = EngineConfig().for_images(i.resolution for i in scene.intrinsics.values())
    frames = collect_frames(names, scene.intrinsics, cfg, msgs)
    R = np.array([scene.poses[n].R for n in names])
    t = np.array([scene.poses[n].t for n in names])
    focal = np.array([0.5 * (scene.intrinsics[n].fx + scene.intrinsics[n].fy) for n in names])
    return scene, frames, R, t, focal, cfg


# the second room's own frame: X_own = s Q X_world + d (turned about z, as two floor frames are)
S, Q, D = 0.94, so3_exp(np.array([0.0, 0.0, 1.9])), np.array([-3.0, 7.5, 0.02])


def _own_frame(R, t):
    return np.einsum("ij,cjk->cik", Q, R), S * t @ Q.T + D


def test_a_room_in_its_own_frame_is_joined_by_what_each_room_sees_of_the_other(two_rooms):
    _, frames, R, t, focal, cfg = two_rooms
    first = np.arange(len(R)) < 4
    Rb, tb = _own_frame(R, t)
    j = join(frames, (R, t, first), (Rb, tb, ~first), focal, view_box(frames, len(R)), cfg.associate, cfg.bootstrap)
    print(j.summary())
    assert j.accepted, j.summary()
    assert j.cameras >= 4 and j.frames >= 2 * cfg.bootstrap.resect_min_frames
    # the join undoes the own frame: X_world = (1/S) Q^T (X_own - D)
    assert j.s == pytest.approx(1 / S, rel=0.01)
    assert rotation_angle_deg(j.Q, Q.T) < 0.5
    back = j.s * tb[~first] @ j.Q.T + j.d
    assert np.abs(back - t[~first]).max() < 0.05


def test_sightings_of_other_instants_join_nothing(two_rooms):
    _, frames, R, t, focal, cfg = two_rooms
    first = np.arange(len(R)) < 4
    # the second room's detections 20 s late: each room still sees people, never the other's
    # at the instant it triangulates them
    times = np.array([f[0] for f in frames])
    late = []
    for k, (time_, views) in enumerate(frames):
        j = int(np.searchsorted(times, time_ - 20.0))
        own = tuple(v for v in views if first[v[0].cam])
        other = tuple(v for v in frames[j][1] if not first[v[0].cam]) if time_ - 20.0 >= times[0] else ()
        if len(own) + len(other) >= 2:
            late.append((time_, tuple(sorted(own + other, key=lambda v: v[0].cam))))
    Rb, tb = _own_frame(R, t)
    res = join(late, (R, t, first), (Rb, tb, ~first), focal, view_box(late, len(R)), cfg.associate, cfg.bootstrap)
    print(res.summary())
    assert not res.accepted


def test_the_bootstrap_places_both_rooms(two_rooms):
    scene, frames, _, _, focal, cfg = two_rooms
    names = scene.names
    res = bootstrap(frames, names, focal, cfg, seed=0)
    print(res.to_dict()["joined_groups"])
    # no pair links the rooms: without the join one room is placed (tested on this
    # simulation: cam_4-cam_7 not placed with bootstrap.join_groups off)
    assert res.located.all(), res.to_dict()["not_located"]
    assert len(res.joins) == 1 and "joined" in res.joins[0] and "not joined" not in res.joins[0]
    acc = evaluate(res.poses(), {n: scene.poses[n] for n in names})
    # measured 0.030 m / 0.59° at most; adjusted together over both rooms 0.42 m / 3.7° (see _join_groups)
    assert acc.shape_position.max < 0.06 and acc.shape_orientation.max < 1.0, acc.per_camera


def test_a_camera_its_group_misplaced_is_contradicted_by_the_persons_in_its_view(two_rooms):
    _, frames, R, t, focal, cfg = two_rooms
    second = np.arange(len(R)) >= 4
    R, t = R.copy(), t.copy()
    # 20° and 1.1 m off, looking where people walk (measured: 0 of 136 frames with a person
    # in view agree; at the true pose 181 of 248). Turned further, to where nobody walks, it
    # sees nobody to be contradicted by, and is kept: the resection's gap too.
    R[5] = so3_exp(np.array([0.0, 0.0, 0.35])) @ R[5]
    t[5] += np.array([1.0, -0.5, 0.0])
    bad = contradicted(frames, R, t, np.ones(len(R), bool), second, focal, view_box(frames, len(R)), cfg.associate,
                       cfg.bootstrap)
    print(bad)
    assert list(bad) == [5]
    n, seen = bad[5]
    assert seen >= cfg.bootstrap.resect_min_frames and n < cfg.bootstrap.resect_min_share * seen

