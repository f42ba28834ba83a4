"""Accuracy bar of the whole engine on the paper's protocol, shortened (bench/accuracy.py
has the full evaluation and the limit).

Two walkers (1.96 m, 1.70 m) for 40 s in the lab's west room (seven cameras), every
camera perturbed by exactly 0.25 m / 10° (cam_11 kept), the full online pipeline with
its default config and the final batch. Everything is seeded, so the figures are the
same on every run; the bars are about 1.5-2x what the engine reached when they were
set, so they fail on a regression, not on noise.

Figures (mean over cameras; the limit is a batch adjustment with the simulator's true
associations, same data and scale rule, as in bench/accuracy.py):

                    rigid       shape       orientation   worst camera
    initial         0.196 m     0.180 m     8.73°
    7d3cf9b         0.0627 m    0.0164 m    0.175°        0.31°
    29dbd85         0.0466 m    0.0164 m    0.178°        0.32°
    limit 29dbd85   0.0457 m    0.0147 m    0.176°        0.27°
    first adj.      0.0445 m    0.0196 m    0.228°        0.60°
    + LS scale      0.0647 m    0.0196 m    0.227°        0.61°

The rigid figure is mostly the initial estimate's scale (about 1 % off in this small
room), which the method keeps by design (its estimate changed between the two engine
versions); shape and orientation are what the data decide. The bars catch, e.g., the
paper's filter settings (0.41°, worst camera 1.26°) and a run without the final batch
(0.535°, worst camera 1.22°, measured with the first adjustment). The first adjustment (select.first_scope,
two passes over the first 20 s) costs this short run cycles: its worst camera went from
0.44° to 0.60° (the 20-camera lab gained: no camera dragged off, docs/accuracy.md); the
least-squares scale (refine.keep_scale) moved the rigid figure, which is the scale's.
"""

from __future__ import annotations

import pytest

from backend.cameras import CameraSet, Extrinsics
from backend.config import EngineConfig
from backend.evaluate import evaluate
from backend.perturb import perturb_extrinsics
from backend.pipeline import run_offline
from edge_clients.sim import Scene, SimConfig, Simulator

WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")
DURATION = 40.0
SEED = 0

# bars (see the module doc for the figures they were set from)
RIGID_POSITION = 0.090  # m (its floor is the kept scale)
SHAPE_POSITION = 0.030  # m
ORIENTATION = 0.35  # deg
WORST_ORIENTATION = 0.80  # deg, any one camera


@pytest.fixture(scope="module")
def calibrated(lab_dir):
    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    sim = Simulator(scene, SimConfig(persons=2, duration=DURATION, seed=SEED, heights=(1.96, 1.70)))
    msgs = [m for _, m in sim.messages()]
    ref = {n: Extrinsics(full.poses[n], intr[n].resolution) for n in WEST}
    cams = CameraSet.combine(intr, perturb_extrinsics(ref, 0.25, 10.0, seed=SEED))
    p = run_offline(cams, EngineConfig(), msgs, seed=SEED)
    truth = {n: full.poses[n] for n in WEST}
    return evaluate(cams.poses(), truth), evaluate(p.state().poses(), truth), p.state()


def test_the_start_is_the_papers_protocol(calibrated):
    before, _, _ = calibrated
    # exactly 0.25 m / 10° per camera (one camera kept): after alignment most of it remains
    assert 0.15 < before.position.mean < 0.25 and 7.5 < before.orientation.mean < 10.0, before.summary()


def test_every_camera_is_calibrated(calibrated):
    _, _, state = calibrated
    assert [c.name for c in state.cameras if c.cycles == 0] == []


def test_accuracy_after_calibration_is_within_the_bars(calibrated):
    _, after, _ = calibrated
    assert after.position.mean < RIGID_POSITION, after.summary()
    assert after.shape_position.mean < SHAPE_POSITION, after.summary()
    assert after.orientation.mean < ORIENTATION, after.summary()
    assert after.orientation.max < WORST_ORIENTATION, after.summary()


def test_calibration_beats_the_initial_estimate_by_a_large_factor(calibrated):
    before, after, _ = calibrated
    assert after.orientation.mean < before.orientation.mean / 25, (before.summary(), after.summary())
    assert after.shape_position.mean < before.shape_position.mean / 6, (before.summary(), after.summary())
    # the rigid figure keeps the initial estimate's scale error (about 1 % here)
    assert after.position.mean < before.position.mean / 2.5, (before.summary(), after.summary())
