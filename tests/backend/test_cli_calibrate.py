"""`extrcal calibrate` on a small simulated recording."""

from __future__ import annotations

import gzip
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from backend.cameras import Extrinsics, load_extrinsics, save_extrinsics, save_intrinsics
from backend.evaluate import evaluate
from backend.perturb import perturb_extrinsics
from edge_clients.sim import Scene, SimConfig, Simulator

WEST = ("cam_11", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")
ABSENT = "cam_5"  # in the camera files, never in the recording


@pytest.fixture(scope="module")
def cli():
    from backend.cli import _register_all, app

    _register_all()
    return app


@pytest.fixture(scope="module")
def files(lab_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("calibrate")
    full = Scene.load(lab_dir)
    scene = Scene.from_cameras({n: full.intrinsics[n] for n in WEST}, {n: full.poses[n] for n in WEST},
                               lab_dir / "room.yaml")
    rec = d / "rec.jsonl.gz"
    Simulator(scene, SimConfig(persons=2, duration=10.0, seed=2, heights=(1.9, 1.75))).write(rec)
    names = WEST + (ABSENT,)
    save_intrinsics(d / "intrinsics.yaml", {n: full.intrinsics[n] for n in names})
    ref = {n: Extrinsics(full.poses[n], full.intrinsics[n].resolution) for n in names}
    save_extrinsics(d / "reference.yaml", ref)
    save_extrinsics(d / "initial.yaml", perturb_extrinsics(ref, 0.05, 2.0, seed=1))
    # 10 s of data: the first adjustment (which waits up to 20 s) would leave only the final batch
    (d / "engine.toml").write_text("[select]\nscope = 15\nfirst_scope = 0\n\n[refine]\nfinal_batch = true\n")
    return d


def _invoke(cli, *argv):
    return CliRunner().invoke(cli, ["calibrate", *[str(a) for a in argv]])


def _args(d, rec, out, *extra):
    return ("--intrinsics", d / "intrinsics.yaml", "--initial", d / "initial.yaml", "--recording", rec,
            "--output", out, *extra)


CALIBRATE_ARGS = ("--config", "engine.toml", "--set", "select.min_spacing=0.25", "--seed", "1")


def _configured(d):
    return [str(d / a) if a.endswith(".toml") else a for a in CALIBRATE_ARGS]


@pytest.fixture(scope="module")
def calibrated(cli, files):
    """One run on the JSON Lines recording, with a reference and a history."""
    d = files
    out, hist = d / "out.yaml", d / "history.jsonl"
    r = _invoke(cli, *_args(d, d / "rec.jsonl.gz", out, "--reference", d / "reference.yaml",
                            "--history", hist, *_configured(d)))
    return r, out, hist


def test_calibrate_writes_extrinsics_history_and_names_uncalibrated_cameras(files, calibrated):
    d = files
    r, out, hist = calibrated
    assert r.exit_code == 0, r.output
    assert f"wrote {out}" in r.output
    assert "vs reference: position" in r.output
    # bootstrap.with_initial = auto: 10 s of data are too few to compare the initial
    # estimate with the data's shape; it is said, and the initial estimate used as it is
    assert "bootstrap not possible" in r.output and "the initial estimate is used as it is" in r.output
    assert re.search(rf"not calibrated.*{ABSENT}", r.output)

    result = load_extrinsics(out)
    assert set(result) == set(WEST) | {ABSENT}
    for n, e in result.items():
        assert e.std_translation is not None and e.std_rotation is not None
        assert np.isfinite(e.std_translation) and e.std_translation > 0
    text = out.read_text()
    assert text.startswith("# extrcal calibrate of ")
    assert re.search(r"^# bootstrap not possible .*: the initial estimate is used as it is$", text, re.M)  # and the file
    named = re.search(r"# not calibrated \(kept initial pose\): (.*)", text).group(1).split(", ")
    assert ABSENT in named
    # what the stated std holds (optimize.lens_accuracy_*, 0.3 % by default)
    assert "# stated std: the keypoints' noise and the calibration files' lens accuracy, 0.3 % in focal length" in text
    cycles = int(re.search(r"(\d+) cycles", text).group(1))
    assert cycles >= 3
    doc = yaml.safe_load(text)
    assert {n for n, e in doc.items() if not e["calibrated"]} == set(named)
    assert len(set(WEST) - set(named)) >= 4, r.output  # the cameras with data were calibrated
    # the simulated lenses are 0.2 % off their files: less than 10 s of data can tell
    assert "lenses off" not in text and not Path(f"{out}.intrinsics.yaml").exists()

    lines = [json.loads(x) for x in hist.read_text().splitlines()]
    assert len(lines) == cycles
    assert [x["cycle"] for x in lines] == list(range(1, cycles + 1))
    for x in lines:
        assert {c["name"] for c in x["cameras"]} == set(WEST) | {ABSENT}
        assert {"std_translation", "std_rotation", "translation", "rotation"} <= set(x["cameras"][0])
        assert x["report"]["solve_seconds"] > 0 and "error" in x
    # the result is better than the start, in the history and in the file
    ref = {n: e.pose for n, e in load_extrinsics(d / "reference.yaml").items()}
    init = {n: e.pose for n, e in load_extrinsics(d / "initial.yaml").items()}
    west = list(WEST)
    assert evaluate({n: e.pose for n, e in result.items()}, ref, west).orientation.mean < \
        evaluate(init, ref, west).orientation.mean / 2
    assert lines[-1]["error"]["orientation"] < lines[0]["error"]["orientation"] + 1e-9


def test_a_msgpack_recording_gives_the_same_result(cli, files, calibrated):
    from proto import read_recording, write_recording

    d = files
    rec = d / "rec.msgpack"
    write_recording(rec, read_recording(d / "rec.jsonl.gz"))
    out = d / "out_msgpack.yaml"
    r = _invoke(cli, *_args(d, rec, out, "--quiet", *_configured(d)))
    assert r.exit_code == 0, r.output
    a, b = load_extrinsics(calibrated[1]), load_extrinsics(out)
    assert set(a) == set(b)
    for n in a:  # the same messages, the same seed: the same numbers
        np.testing.assert_array_equal(a[n].pose.t, b[n].pose.t)
        np.testing.assert_array_equal(a[n].pose.R, b[n].pose.R)


def test_a_reference_without_enough_common_cameras_is_a_clear_error(cli, files, tmp_path):
    d = files
    ref = load_extrinsics(d / "reference.yaml")
    two = tmp_path / "one.yaml"
    save_extrinsics(two, {n: ref[n] for n in WEST[:1]})
    r = _invoke(cli, *_args(d, d / "rec.jsonl.gz", tmp_path / "o.yaml", "--quiet", "--reference", two,
                            "--set", "select.scope=15"))
    # a clear message (or a note), not a traceback after the whole run
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    assert "2 cameras" in r.output


def test_a_broken_recording_is_reported_at_its_line(cli, files):
    d = files
    lines = gzip.open(d / "rec.jsonl.gz", "rt").read().splitlines()
    bad = d / "broken.jsonl"
    lines[6] = lines[6][: len(lines[6]) // 2]  # a line cut in half
    bad.write_text("\n".join(lines) + "\n")
    out = d / "never.yaml"
    r = _invoke(cli, *_args(d, bad, out, "--quiet"))
    assert r.exit_code == 2
    assert f"{bad}:7" in r.output and "not JSON" in r.output
    assert not out.exists()

    # a well-formed line with a bad field names the line and the field
    rec = json.loads(lines[3])
    rec["size"] = [-1, 480]
    lines[6] = json.dumps(rec)
    bad.write_text("\n".join(lines) + "\n")
    r = _invoke(cli, *_args(d, bad, out, "--quiet"))
    assert r.exit_code == 2 and f"{bad}:7" in r.output and "size" in r.output
    # --skip-bad goes on and counts it
    r = _invoke(cli, *_args(d, bad, out, "--quiet", "--skip-bad", "--set", "select.scope=15"))
    assert r.exit_code == 0, r.output
    assert "1 bad records skipped" in r.output and out.exists()


def test_messages_of_sensors_the_camera_files_do_not_name_are_counted_and_named(cli, files, tmp_path):
    d = files
    lines = gzip.open(d / "rec.jsonl.gz", "rt").read().splitlines()
    typo = []
    for ln in lines[:40]:
        rec = json.loads(ln)
        if rec["sensor"] == WEST[0]:
            rec["sensor"] = "cam11"  # a sensor whose id is not its camera's key
            typo.append(json.dumps(rec))
    rec_path = tmp_path / "typo.jsonl"
    rec_path.write_text("\n".join(lines + typo) + "\n")
    r = _invoke(cli, *_args(d, rec_path, tmp_path / "o.yaml", "--quiet", *_configured(d)))
    assert r.exit_code == 0, r.output
    flat = " ".join(r.output.split())
    assert typo and f"messages rejected: unknown_sensor {len(typo)} (cam11 {len(typo)})" in flat
    assert "unknown sensors are ids not in" in flat


def test_bad_inputs_give_one_clear_error(cli, files, tmp_path):
    d = files
    out = tmp_path / "o.yaml"
    r = _invoke(cli, *_args(d, tmp_path / "missing.jsonl", out))
    assert r.exit_code == 2 and "does not exist" in r.output
    r = _invoke(cli, *_args(d, d / "rec.jsonl.gz", out, "--set", "select.scoop=3"))
    assert r.exit_code == 2 and "select.scoop" in r.output
    broken = tmp_path / "initial.yaml"
    broken.write_text("cam_11:\n  translation: [0, 0]\n  rotation: [0, 0, 0, 1]\n")
    r = CliRunner().invoke(cli, ["calibrate", "--intrinsics", str(d / "intrinsics.yaml"), "--initial", str(broken),
                                 "--recording", str(d / "rec.jsonl.gz"), "--output", str(out)])
    assert r.exit_code == 2 and f"{broken}:2" in r.output and "translation" in r.output
    assert not out.exists()


def test_without_an_initial_estimate_too_little_data_is_a_clear_error(cli, files, tmp_path):
    d = files
    out = tmp_path / "o.yaml"
    args = ["calibrate", "--intrinsics", str(d / "intrinsics.yaml"), "--recording", str(d / "rec.jsonl.gz"),
            "--output", str(out)]
    # 2 s of data cannot hold the frames a camera pair needs: one clear error, no file
    r = CliRunner().invoke(cli, [*args, "--set", "bootstrap.max_seconds=2"])
    assert r.exit_code == 2, r.output
    assert "bootstrap failed" in r.output and "too few" in r.output
    assert "in the first 2 s of data" in r.output and "bootstrap.max_seconds=0" in r.output  # what to try next
    assert not out.exists()
    # --distrust-initial takes the same path
    r = CliRunner().invoke(cli, [*args, "--initial", str(d / "initial.yaml"), "--distrust-initial", "--quiet",
                                 "--set", "bootstrap.max_seconds=2"])
    assert r.exit_code == 2 and "bootstrap failed" in r.output
    for bad in ("tall", "0.2", "1.85,3.5", ","):
        r = CliRunner().invoke(cli, [*args, "--person-height", bad])
        assert r.exit_code == 2 and "--person-height" in r.output, (bad, r.output)


@pytest.mark.parametrize("mode", ["people", "keep"])
def test_a_floor_plan_6_percent_too_large_is_put_right_by_walkers_of_known_height(cli, files, tmp_path, mode):
    d = files
    init = load_extrinsics(d / "initial.yaml")
    c = np.mean([e.pose.t for e in init.values()], axis=0)
    big = {n: Extrinsics(type(e.pose)(e.pose.R, c + 1.06 * (e.pose.t - c)), e.resolution) for n, e in init.items()}
    save_extrinsics(tmp_path / "big.yaml", big)
    out = tmp_path / "out.yaml"
    r = _invoke(cli, "--intrinsics", d / "intrinsics.yaml", "--initial", tmp_path / "big.yaml", "--recording",
                d / "rec.jsonl.gz", "--output", out, "--person-height", "1.9,1.75", *_configured(d),
                "--set", f"bootstrap.initial_scale={mode}")
    assert r.exit_code == 0, r.output
    ref = load_extrinsics(d / "reference.yaml")
    got = load_extrinsics(out)
    names = [n for n in WEST if n in got]
    scale = evaluate({n: got[n].pose for n in names}, {n: ref[n].pose for n in names}).scale
    head = out.read_text().split("\ncam_")[0]
    assert "scale check" in head and "known height" in head
    if mode == "people":
        # the result's scale is the people's (10 s of two walkers: a few % off), within its reported std
        std = float(re.search(r"± ([0-9.]+) % now", head).group(1)) / 100
        assert abs(np.log(scale)) < 2 * std, (scale, head)
        assert abs(scale - 1) < 0.6 * abs(1 / 1.06 - 1), (scale, head)
    else:
        assert "scale kept" in head
        assert abs(scale - 1 / 1.06) < 0.01, scale  # the floor plan's


def test_lenses_3_percent_off_their_files_are_estimated_and_the_poses_fit_them(cli, files, lab_dir, tmp_path):
    """The same cameras, their lenses 3 % (focal) and ~6 px off the calibration files
    (simulated), 60 s: the result states the lenses' spread, writes the lenses it found,
    and its poses are nearer the truth than those that fit the files' lenses. (In 30 s six
    cameras do not show the spread at 5 %: the files' lenses are kept.)"""
    from backend.cameras import load_intrinsics

    d = files
    full = Scene.load(lab_dir)
    scene = Scene.from_cameras({n: full.intrinsics[n] for n in WEST}, {n: full.poses[n] for n in WEST},
                               lab_dir / "room.yaml")
    rec = tmp_path / "lenses.jsonl.gz"
    Simulator(scene, SimConfig(persons=2, duration=60.0, seed=2, heights=(1.9, 1.75), intrinsics_error=0.03)).write(rec)
    ref = {n: e.pose for n, e in load_extrinsics(d / "reference.yaml").items()}
    shape = {}
    for profiles in (False, True):
        for mode in ("auto", "off"):
            out = tmp_path / f"{mode}-{profiles}.yaml"
            r = _invoke(cli, *_args(d, rec, out, "--seed", "1", "--quiet", "--set", f"optimize.lenses={mode}",
                                      "--set", "refine.split_check=false",
                                      "--set", f"preprocess.partial_torso={str(profiles).lower()}"))
            assert r.exit_code == 0, r.output
            got = load_extrinsics(out)
            shape[mode, profiles] = evaluate({n: got[n].pose for n in WEST}, ref, list(WEST)).shape_position.mean
            lens_file = Path(f"{out}.intrinsics.yaml")
            assert ("lenses off their calibration files" in out.read_text()) == (mode == "auto")
            assert lens_file.exists() == (mode == "auto")
    lenses = load_intrinsics(tmp_path / "auto-False.yaml.intrinsics.yaml")
    files_ = load_intrinsics(d / "intrinsics.yaml")
    assert set(lenses) >= set(WEST)
    assert any(abs(lenses[n].fx / files_[n].fx - 1) > 0.01 for n in WEST)  # not the files' again
    # the paper's preprocessing: 0.069 against 0.105 m. With the profile views (the
    # default) 0.083 against 0.098 m on this seed; over seeds 2-6 both reach the same mean
    # with the lenses estimated (bench/lenses.py; docs/bootstrap.md, Session 50)
    assert shape["auto", False] < 0.85 * shape["off", False], shape
    assert shape["auto", True] < shape["off", True], shape
