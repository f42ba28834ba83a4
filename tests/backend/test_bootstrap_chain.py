"""A camera chain without three-way overlap (``edge_clients.sim.scenes.corridor``: six
cameras down a corridor, each seeing the walker only with its neighbours): no two camera
pairs triangulate one instant, so only the walker's bones relate their scales
(``bootstrap.bone_scales``). Without them the bootstrap placed 2 of the 6 cameras, and a
rough initial estimate could not be reconciled with so few; its centres, nearly on one
line, leave the turn about the corridor to the orientations (``geometry.align_poses``).

Measured when the bars were set (seeded, one walker of 1.80 m, the first 90 s): 6/6
placed, shape 0.051 m / 1.44° (worst 0.078 m / 1.86°), scale 1.048 (the population
prior's 1.72 m for the walker); without the bones 2 placed. Since the bones place only
what the geometry and the resection leave (session 38): shape 0.037 m (worst 0.052 m),
orientations within 1.12° after the best turn of the world (1.35° before).
"""

from __future__ import annotations

import numpy as np
import pytest

from backend.bootstrap import _place_by_bones, bootstrap, collect_frames
from backend.cameras import CameraSet, Extrinsics, Pose
from backend.config import EngineConfig
from backend.evaluate import evaluate
from backend.geometry import project_so3, rotation_angle_deg, so3_exp
from backend.perturb import perturb_extrinsics
from backend.reconcile import reconcile_cameras
from edge_clients.sim import SimConfig, Simulator
from edge_clients.sim.scenes import corridor


@pytest.fixture(scope="module")
def chain():
    scene = corridor()
    sim = Simulator(scene, SimConfig(persons=1, duration=90.0, seed=0, heights=(1.8,)))
    cfg = EngineConfig().for_images(i.resolution for i in scene.intrinsics.values())
    frames = collect_frames(scene.names, scene.intrinsics, cfg, (m for _, m in sim.messages(scene.names)))
    focal = np.array([0.5 * (scene.intrinsics[n].fx + scene.intrinsics[n].fy) for n in scene.names])
    return scene, frames, focal, cfg, bootstrap(frames, scene.names, focal, cfg)


def test_a_corridor_is_placed_whole_by_the_walkers_bones(chain):
    scene, frames, focal, cfg, boot = chain
    assert boot.located.all()
    acc = evaluate(boot.poses(), scene.poses)
    assert acc.shape_position.max < 0.15
    # the orientations up to one turn of the world: the centres, nearly on one line, leave
    # the evaluation's turn about the corridor free (the same result 2.0-3.3° through it)
    got = boot.poses()
    Rw = project_so3(sum(scene.poses[n].R @ got[n].R.T for n in scene.names))
    assert max(rotation_angle_deg(Rw @ got[n].R, scene.poses[n].R) for n in scene.names) < 1.5
    assert 0.85 < acc.scale < 1.15  # the population prior's scale, for one walker of 1.80 m
    # without the bones' relations only the best-related pair is placed
    off = cfg.model_copy(update={"bootstrap": cfg.bootstrap.model_copy(update={"bone_scales": False})})
    assert bootstrap(frames, scene.names, focal, off).located.sum() == 2


def test_rough_estimates_of_a_corridor_are_reconciled_in_their_own_frame(chain):
    """Five 1.5 m / 45° starts: every camera starts from the data's shape, turned from the
    truth by 4-19° (the start's frame: nothing in the data says more). With the centres
    alone the same starts ended 5-45° off, and seed 1's alignment refused 4 cameras."""
    scene, _frames, _focal, cfg, boot = chain
    truth = {n: Extrinsics(p, scene.intrinsics[n].resolution) for n, p in scene.poses.items()}
    for seed in range(5):
        cams = CameraSet(scene.names, scene.intrinsics, perturb_extrinsics(truth, 1.5, 45.0, seed=seed))
        rec, _, note = reconcile_cameras(boot, cams, cfg)
        assert rec is not None and rec.from_bootstrap.all(), note
        got = {n: Pose(rec.R[c], rec.t[c]) for c, n in enumerate(scene.names)}
        assert evaluate(got, scene.poses).shape_position.max < 0.15
        assert max(rotation_angle_deg(got[n].R, scene.poses[n].R) for n in scene.names) < 20.0, seed


def test_two_walkers_down_a_corridor_keep_the_chain_at_one_scale():
    """The bootstrap's adjustments hold the walkers' bones from their first solve. Their
    priors are a gauge (1 m), so in a chain nothing else holds a link's scale: solved first
    without bones, the 180 s of two walkers below shrank cam_2-cam_5 to 0.39x (the world
    2.6x too small after the people's scale, shape 1.9 m)."""
    scene = corridor()
    sim = Simulator(scene, SimConfig(persons=2, duration=180.0, seed=0, heights=(1.80, 1.65)))
    cfg = EngineConfig().for_images(i.resolution for i in scene.intrinsics.values())
    frames = collect_frames(scene.names, scene.intrinsics, cfg, (m for _, m in sim.messages(scene.names)))
    focal = np.array([0.5 * (scene.intrinsics[n].fx + scene.intrinsics[n].fy) for n in scene.names])
    boot = bootstrap(frames, scene.names, focal, cfg)
    assert boot.located.sum() >= 4
    placed = {n: p for n, p in boot.poses().items() if boot.located[scene.names.index(n)]}
    acc = evaluate(placed, {n: scene.poses[n] for n in placed})
    assert acc.shape_position.max < 0.15
    assert 0.9 < acc.scale < 1.12  # the population prior's 1.72 m against walkers of 1.80 and 1.65 m


def test_the_bones_placement_is_moved_onto_the_network_by_two_cameras():
    """``_place_by_bones``: the cameras only the bones placed, moved onto the adjusted
    network by the similarity of two cameras both placed (its turn from their orientations:
    two centres leave the turn about their line free)."""
    rng = np.random.default_rng(4)
    C = 6
    R = np.stack([so3_exp(rng.normal(0, 0.5, 3)) for _ in range(C)])
    t = np.c_[np.arange(C) * 3.5, rng.normal(0, 0.2, C), np.full(C, 2.6)]
    Rw, s, tw = so3_exp([0.1, -0.3, 1.2]), 0.29, np.array([1.0, -2.0, 0.3])
    R_b = np.einsum("ij,cjk->cik", Rw.T, R)  # the bones' frame: turned, scaled, moved
    t_b = ((t - tw) @ Rw) / s
    located = np.array([False, False, True, True, False, False])
    got_R, got_t, added = _place_by_bones(R, np.where(located[:, None], t, 0.0), located, R_b, t_b, np.ones(C, bool))
    assert added.tolist() == [True, True, False, False, True, True]
    assert np.allclose(got_R, R, atol=1e-9) and np.allclose(got_t, t, atol=1e-9)
    # one camera in common places nothing
    one = np.array([False, False, True, False, False, False])
    assert not _place_by_bones(R, t, one, R_b, t_b, np.ones(C, bool))[2].any()
