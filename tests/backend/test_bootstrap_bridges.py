"""Cameras the bootstrap's view graph reaches only over bridge pairs (backend/bootstrap.py,
``check_bridged``): a pair no triangle checks places its camera wherever its frames say;
with two walkers who happen to move alike it placed a camera 160° / 7 m off (seed 1 of the
lab with 60 s of data, docs/bootstrap.md). The check: the persons the core cameras
triangulate without it, in its view, must be what it sees.

The graph here is given (synthetic pairs over a short seeded simulation of the lab's west
room, one walker), so each case is exact: a bridged camera at its true pose is verified,
the same camera 160° off is not (re-localised by PnP near its true pose, or dropped), and a
corridor (every pair a bridge, no core) is left alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from backend.bootstrap import PairPose, bridges, check_bridged, collect_frames, core_cameras
from backend.config import EngineConfig
from backend.geometry import rotation_angle_deg, so3_exp

WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")


def test_bridges_and_the_core_of_a_view_graph():
    # a triangle 0-1-2 with a tail 2-3-4, and an isolated edge 5-6
    edges = [(0, 1), (1, 2), (0, 2), (2, 3), (3, 4), (5, 6)]
    assert bridges(7, edges).tolist() == [False, False, False, True, True, True]
    assert np.flatnonzero(core_cameras(7, edges)).tolist() == [0, 1, 2]
    # a corridor: every pair a bridge, no core
    chain = [(k, k + 1) for k in range(5)]
    assert bridges(6, chain).all() and not core_cameras(6, chain).any()
    assert not core_cameras(3, []).any()


def _pair(a: int, b: int, frames: np.ndarray) -> PairPose:
    """A view-graph edge: check_bridged uses its cameras and its frames only."""
    return PairPose(a, b, np.eye(3), np.array([1.0, 0, 0]), frames, len(frames), 17 * len(frames), 1.0, 30.0,
                    np.zeros(0, np.int64), {a: np.zeros(0), b: np.zeros(0)})


@pytest.fixture(scope="module")
def west(lab_dir):
    from edge_clients.sim import Scene, SimConfig, Simulator

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    sim = Simulator(scene, SimConfig(persons=1, duration=30.0, seed=3, heights=(1.80,)))
    frames = collect_frames(WEST, intr, EngineConfig(), [m for _, m in sim.messages()])
    R = np.array([full.poses[n].R for n in WEST])
    t = np.array([full.poses[n].t for n in WEST])
    focal = np.array([0.5 * (intr[n].fx + intr[n].fy) for n in WEST])
    up = np.array(yaml.safe_load((lab_dir / "room.yaml").read_text())["floor"]["normal_up"], dtype=np.float64)
    return frames, R, t, focal, up / np.linalg.norm(up)


def _wrong(frames, R: np.ndarray, t: np.ndarray, c: int, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera c turned 160° about the vertical through the middle of the persons it sees
    with the others: it looks at them from the wrong side of the room, and where it
    sees people the others' persons fall (in their middle), like the pose of a pair whose
    frames mixed two walkers who moved alike."""
    from backend.relocalize import frame_correspondences

    X = np.concatenate([X for X, _ in frame_correspondences(frames, c, R, t, EngineConfig().associate)])
    mid = np.median(X, axis=0)
    R, t = R.copy(), t.copy()
    turn = so3_exp(np.radians(160.0) * up)
    R[c], t[c] = turn @ R[c], mid + turn @ (t[c] - mid)
    return R, t


def test_a_bridged_camera_is_verified_at_its_pose_and_not_when_a_wrong_pair_placed_it(west):
    frames, R, t, focal, up = west
    located = np.ones(7, bool)
    own = np.arange(0, len(frames), 7)  # the bridge pair's own frames are not its evidence
    ring = [_pair(k, k + 1, np.arange(0)) for k in range(5)] + [_pair(0, 5, np.arange(0)), _pair(1, 4, np.arange(0))]
    pairs = ring + [_pair(2, 6, own)]  # camera 6 hangs on camera 2 by one pair
    cfg = EngineConfig()

    R1, t1, loc1, checks = check_bridged(frames, pairs, R, t, located, focal, cfg)
    print(checks)
    assert [(c.cam, c.outcome) for c in checks] == [(6, "verified")]
    assert checks[0].frames >= cfg.bootstrap.check_min_frames and checks[0].agree >= 0.9 * checks[0].frames
    assert loc1.all() and np.array_equal(R1, R) and np.array_equal(t1, t)

    Rw, tw = _wrong(frames, R, t, 6, up)
    R2, t2, loc2, checks = check_bridged(frames, pairs, Rw, tw, located, focal, cfg)
    print(checks)
    assert len(checks) == 1 and checks[0].cam == 6 and checks[0].outcome in ("re-localised", "dropped")
    assert checks[0].agree < cfg.bootstrap.check_min_agree * checks[0].frames
    if checks[0].outcome == "re-localised":  # one walker: PnP finds it
        assert loc2[6] and np.linalg.norm(t2[6] - t[6]) < 0.1 and rotation_angle_deg(R2[6], R[6]) < 1.0
    else:
        assert not loc2[6]
    assert np.array_equal(R2[:6], Rw[:6]) and np.array_equal(t2[:6], tw[:6])  # the core is not touched



def test_a_corridor_is_not_checked(west):
    """Every pair a bridge: no core triangulates what a camera sees without it, so nothing
    is checked, even a camera that is wrong (the bundle adjustment is the check there)."""
    frames, R, t, focal, up = west
    Rw, tw = _wrong(frames, R, t, 6, up)
    chain = [_pair(k, k + 1, np.arange(0)) for k in range(6)]
    R2, t2, loc2, checks = check_bridged(frames, chain, Rw, tw, np.ones(7, bool), focal, EngineConfig())
    assert checks == [] and loc2.all() and np.array_equal(R2, Rw) and np.array_equal(t2, tw)
