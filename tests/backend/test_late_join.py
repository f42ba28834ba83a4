"""Cameras the bootstrap did not place join later (backend/late_join.py): a seeded
simulation of the lab's west room with two walkers, 90 s, in which cam_17 sees nobody in
the first 45 s (a corner people reach later). The bootstrap takes the first 40 s and
cannot place it; `extrcal calibrate` resects it at the end against the online estimate
and its final batch adjusts it: it ends within the bars with the others. A run in which
no camera joins ends exactly as without the second front end.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from backend.cameras import CameraSet, Extrinsics, load_extrinsics, save_intrinsics
from backend.config import EngineConfig
from backend.evaluate import evaluate, up_tilt
from backend.late_join import JoiningPipeline
from backend.pipeline import run_offline

WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")
LATE = "cam_17"
QUIET = 45.0  # s in which LATE sees nobody
BOOT = ["bootstrap.max_seconds=40", "bootstrap.min_pair_frames=20",
        "refine.split_check=false"]  # the split-half check is tested elsewhere and costs another final batch
SMALL_FINAL = ["refine.batch_size=300"]  # for the tests of "unchanged": the final batch runs, smaller


@pytest.fixture(scope="module")
def west(lab_dir, tmp_path_factory):
    """(directory with intrinsics.yaml, rec.msgpack (LATE quiet at first),
    seen.msgpack (the first 50 s, LATE seen throughout), intrinsics, true poses, the quiet messages)."""
    from edge_clients.sim import Scene, SimConfig, Simulator
    from proto import write_recording

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    seen = [m for _, m in Simulator(scene, SimConfig(persons=2, duration=90.0, seed=5, heights=(1.85, 1.70))).messages()]
    t0 = seen[0].stamp
    msgs = [dataclasses.replace(m, persons=()) if m.sensor == LATE and m.stamp - t0 < QUIET else m for m in seen]
    d = tmp_path_factory.mktemp("late")
    write_recording(d / "rec.msgpack", msgs)
    write_recording(d / "seen.msgpack", [m for m in seen if m.stamp - t0 < QUIET + 5.0])
    save_intrinsics(d / "intrinsics.yaml", intr)
    return d, intr, {n: full.poses[n] for n in WEST}, msgs


def _calibrate(d, out, overrides, recording="rec.msgpack", history=None):
    from backend.cli_engine import calibrate

    calibrate(intrinsics=d / "intrinsics.yaml", recording=d / recording, output=out, initial=None,
              distrust_initial=False, person_height=None, reference=None, config=None, set_=overrides, seed=0,
              history=history, skip_bad=False, quiet=True)


def test_a_camera_the_bootstrap_left_out_is_placed_later_within_the_bars(west, tmp_path):
    import json

    d, _, truth, _ = west
    out = tmp_path / "out.yaml"
    _calibrate(d, out, BOOT)
    meta = json.loads((tmp_path / "out.yaml.bootstrap.json").read_text())
    assert LATE in meta["not_located"]  # the bootstrap could not place it ...
    assert [j["name"] for j in meta["placed_later"]] == [LATE], meta["late_resections"]  # ... the end of the run did
    res = load_extrinsics(out)
    assert set(res) == set(WEST) and f"{LATE}:" in out.read_text()
    assert "calibrated: true" in out.read_text().split(f"{LATE}:")[1].split("cam_")[0]
    ev = evaluate({n: e.pose for n, e in res.items()}, truth)
    for n, (_, _, pos, ori) in ev.per_camera.items():
        assert pos < 0.05 and ori < 0.5, (n, ev.per_camera)
    assert f"# {LATE} placed after the bootstrap: resected against the online estimate over" in out.read_text()
    # its std is the final batch's marginal, not the prior it entered with
    assert res[LATE].std_translation < meta["placed_later"][0]["std_translation"]


def test_a_camera_placed_while_the_run_goes_on_joins_its_cycles(west, tmp_path):
    """A resection every 10 s of data (``bootstrap.late_join_interval``): LATE, seen from
    45 s on, joins the running pipeline; its cycles calibrate it before the final batch
    does, and it ends within the bars with the others."""
    import json

    d, _, truth, _ = west
    out, hist = tmp_path / "out.yaml", tmp_path / "history.jsonl"
    _calibrate(d, out, BOOT + ["bootstrap.late_join_interval=10"], history=hist)
    meta = json.loads((tmp_path / "out.yaml.bootstrap.json").read_text())
    assert [(j["name"], j["live"], j["adjusted"]) for j in meta["placed_later"]] == [(LATE, True, True)]
    cycles = [json.loads(line) for line in hist.read_text().splitlines()]
    online = [c for c in cycles[:-1] if any(cam["name"] == LATE for cam in c["cameras"])]
    assert online
    assert max(cam["cycles"] for c in online for cam in c["cameras"] if cam["name"] == LATE) >= 2  # its own cycles
    assert len(online[0]["cameras"]) == len(WEST)  # from then on every camera is in the estimate
    res = load_extrinsics(out)
    ev = evaluate({n: e.pose for n, e in res.items()}, truth)
    for n, (_, _, pos, ori) in ev.per_camera.items():
        assert pos < 0.05 and ori < 0.5, (n, ev.per_camera)
    assert "joined the running calibration" in out.read_text()


def _run(cams, cfg, msgs, pipeline=None):
    return run_offline(cams, cfg, msgs, seed=3, pipeline=pipeline)


def test_a_run_in_which_no_camera_joins_is_unchanged(west):
    """The second front end and a resection that places nothing leave the result as the
    plain pipeline's, to the bit (the same frames, the same seeds)."""
    _, intr, truth, msgs = west
    placed = [n for n in WEST if n != LATE]
    cams = CameraSet.combine({n: intr[n] for n in placed},
                             {n: Extrinsics(truth[n], intr[n].resolution) for n in placed})
    cfg = EngineConfig.load(None, ["bootstrap.resect_min_frames=100000", "bootstrap.late_pairs=false",
                                   "refine.final_batch_from_start=true", *SMALL_FINAL])
    plain = _run(cams, cfg, msgs).state()
    joining = JoiningPipeline(cams, cfg, intrinsics=intr, names=WEST, seed=3)
    state = _run(cams, cfg, msgs, joining).state()
    assert len(joining.late_frames) > 50 and joining.joined is None and joining.late == []
    assert joining.late_notes and joining.late_notes[0].startswith(f"{LATE} not resected")
    assert [c.name for c in state.cameras] == placed
    for a, b in zip(plain.cameras, state.cameras):
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t) and np.array_equal(a.cov, b.cov)
    assert state.cycle == plain.cycle


def test_a_run_with_every_camera_placed_is_unchanged(west, tmp_path):
    """LATE seen from the start: the bootstrap places every camera, and `bootstrap.late`
    changes nothing."""
    d = west[0]
    outs = []
    for late in ("true", "false"):
        out = tmp_path / f"out_{late}.yaml"
        _calibrate(d, out, BOOT + SMALL_FINAL + [f"bootstrap.late={late}"], "seen.msgpack")
        outs.append(out.read_text())
    assert set(load_extrinsics(tmp_path / "out_true.yaml")) == set(WEST)
    assert "placed after the bootstrap" not in outs[0] and outs[0] == outs[1]


def test_a_late_camera_whose_clock_runs_ahead_is_resected_and_adjusted_timed_by_its_lead(lab_dir):
    """LATE quiet for 45 s of 75 and its clock 0.2 s ahead; the others at their true
    poses. Its stamps run ~0.2 s ahead of the others' as they arrive, and nobody
    estimates its offset (it has no pose to associate with). On its views as stamped
    its resection agrees in fewer framesets, less those it disagrees in, than on them
    its lead later: it joins timed by its lead, the final batch has its archived views
    so timed, and it ends within the bars (0.031 m / 0.16°; as stamped, with
    ``clock.estimate = false``, its pair placed it and it ended 0.20 m / 2.4° off). Its
    views timed right, with a lead of a delay's (its stamps right): kept as stamped."""
    from edge_clients.sim import Scene, SimConfig, Simulator

    full = Scene.load(lab_dir)
    intr = {n: full.intrinsics[n] for n in WEST}
    scene = Scene.from_cameras(intr, {n: full.poses[n] for n in WEST}, lab_dir / "room.yaml")
    sim = Simulator(scene, SimConfig(persons=2, duration=75.0, seed=5, heights=(1.85, 1.70), clock_offsets={LATE: 0.2}))
    seen = [m for _, m in sim.messages()]
    t0 = min(m.stamp for m in seen if m.sensor != LATE)
    msgs = [dataclasses.replace(m, persons=()) if m.sensor == LATE and m.stamp - 0.2 - t0 < QUIET else m for m in seen]
    placed = [n for n in WEST if n != LATE]
    truth = {n: full.poses[n] for n in WEST}
    cams = CameraSet.combine({n: intr[n] for n in placed}, {n: Extrinsics(truth[n], intr[n].resolution) for n in placed})
    cfg = EngineConfig.load(None, ["refine.split_check=false", *SMALL_FINAL])
    p = _run(cams, cfg, msgs, JoiningPipeline(cams, cfg, intrinsics=intr, names=WEST, seed=3))
    [j] = p.late
    assert j.name == LATE and j.adjusted and j.timed == pytest.approx(0.2, abs=0.04), p.late_notes
    assert "timed by its stamps' lead (+" in j.summary()
    assert [n for n in p.late_notes if n.startswith(f"{LATE}: its stamps ran +")][0].endswith("timed by it (its clock's offset)")
    ev = evaluate(p.state().poses(), truth)
    assert ev.per_camera[LATE][2] < 0.05 and ev.per_camera[LATE][3] < 0.5, ev.per_camera
    assert ev.orientation.max < 0.5, ev.per_camera
    # its archived views are timed by the lead now: as they would be stamped if the lead
    # were a delay's (the stamps right), the opposite lead is not taken
    job = p._late_job()
    c = WEST.index(LATE)
    assert job.leads.keys() == {c}
    found = dataclasses.replace(job, leads={c: -j.timed}).run()
    assert found.timed == {} and [r.accepted for r in found.resections] == [True]
    assert found.timing[c].endswith("as stamped"), found.timing


def test_a_camera_placed_by_its_pair_says_so_and_what_scaled_it():
    from backend.late_join import later_summary

    j = {"name": "cam_5", "data_seconds": 142.0, "frames": 54, "seen": 56, "spread": None, "residual_px": 1.5,
         "std_translation": 0.1, "std_rotation": 2.0, "adjusted": True, "live": False, "paired_with": "cam_4",
         "scaled_by": "floor"}
    line = later_summary(j)
    assert line.startswith("cam_5 placed after the bootstrap by its pair with cam_4 over 142 s of data")
    assert "floor" in line and "spread" not in line
    j.update(paired_with="", spread=0.8)
    assert later_summary(j).startswith("cam_5 placed after the bootstrap: resected against the online estimate")


def test_the_end_of_a_corridor_joins_by_its_pair(tmp_path):
    """Two walkers down the corridor (6 cameras, each overlapping its neighbours only),
    180 s, no initial estimate: the bootstrap's 120 s leave cam_5 out (it sees people with
    cam_4 alone, too rarely then), no resection can place it, and its pair with cam_4 does
    while the run goes on. Before the pairs it was left out of the result."""
    import json

    from edge_clients.sim import SimConfig, Simulator
    from edge_clients.sim.scenes import corridor
    from proto import write_recording

    scene = corridor()
    sim = Simulator(scene, SimConfig(persons=2, duration=180.0, seed=0, heights=(1.80, 1.65)))
    write_recording(tmp_path / "rec.msgpack", [m for _, m in sim.messages(scene.names)])
    save_intrinsics(tmp_path / "intrinsics.yaml", scene.intrinsics)
    out = tmp_path / "out.yaml"
    _calibrate(tmp_path, out, ["refine.split_check=false"])
    meta = json.loads((tmp_path / "out.yaml.bootstrap.json").read_text())
    assert "cam_5" in meta["not_located"]
    later = {j["name"]: j for j in meta["placed_later"]}
    assert later["cam_5"]["paired_with"] == "cam_4" and later["cam_5"]["scaled_by"] == "floor"
    assert "# cam_5 placed after the bootstrap by its pair with cam_4" in out.read_text()
    res = load_extrinsics(out)
    assert set(res) == set(scene.names)
    ev = evaluate({n: e.pose for n, e in res.items()}, scene.poses)
    assert ev.shape_position.max < 0.15 and ev.orientation.max < 2.0, ev.per_camera
    # the world's z is the floor's up: levelled on the final batch's floor, of every camera's people
    assert "# world frame levelled again on the final batch adjustment's floor" in out.read_text()
    assert up_tilt({n: e.pose for n, e in res.items()}, scene.poses, scene.floor.up) < 0.5


def test_a_camera_joined_live_that_no_cycle_adjusted_is_said_unconfirmed():
    """A camera placed by a late pair that then never got a cycle (too few views with the
    others: a wrong pair's camera looks where they see nobody) is not said to be adjusted."""
    from backend.late_join import later_summary

    j = {"name": "cam_22", "paired_with": "cam_2", "data_seconds": 151.0, "frames": 40, "seen": 42,
         "residual_px": 1.9, "spread": 1.33, "scaled_by": "", "std_translation": 0.223, "std_rotation": 2.0, "live": True,
         "adjusted": False}
    line = later_summary(j)
    assert "its pair's pose is its result, unconfirmed" in line and "adjusted it) from" not in line
    assert "its cycles and the final batch adjusted it" in later_summary({**j, "adjusted": True})
    assert "its resection's pose" in later_summary({**j, "paired_with": ""})


def test_a_camera_a_late_pair_placed_that_no_cycle_took_is_taken_back(west):
    """The rule (``unconfirmed``): placed by a pair while the run went on and not adjusted
    by a cycle or the final batch. The plumbing, on a finished pipeline: such a camera is
    not in the state (nor the result), is among the cameras not placed, and the header
    says why."""
    from backend.late_join import Joined, late_comment, unconfirmed
    from backend.resect import Resection

    r = Resection(6, np.eye(3), np.zeros(3), 40, 42, 42, 0.5, 0, 1.9, None, True, "")
    pair = Joined(LATE, r, 150.0, 0.2, 2.0, live=True, paired_with="cam_12")
    assert unconfirmed([pair]) == [pair]
    assert unconfirmed([dataclasses.replace(pair, adjusted=True)]) == []  # its cycles took it
    assert unconfirmed([dataclasses.replace(pair, paired_with="")]) == []  # resected: the persons confirm it
    assert unconfirmed([dataclasses.replace(pair, live=False)]) == []  # joined at the end: no cycle to take it

    _, intr, truth, msgs = west
    cams = CameraSet.combine(intr, {n: Extrinsics(truth[n], intr[n].resolution) for n in WEST})
    cfg = EngineConfig.load(None, ["bootstrap.late_pairs=false", *SMALL_FINAL])
    joining = JoiningPipeline(cams, cfg, intrinsics=intr, names=WEST, seed=3)
    _run(cams, cfg, msgs[: len(msgs) // 3], joining)
    assert LATE in [c.name for c in joining.state().cameras] and joining.not_placed == []
    joining.taken_back = [pair]
    assert [c.name for c in joining.state().cameras] == [n for n in WEST if n != LATE]
    assert joining.not_placed == [LATE]
    lines = late_comment(joining)
    assert any(ln.startswith(f"{LATE} placed by its pair with cam_12 after the bootstrap, then taken back") for ln in lines)
    assert lines[-1] == f"not placed by the bootstrap nor later (not calibrated): {LATE}"
