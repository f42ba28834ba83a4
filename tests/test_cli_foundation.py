"""The foundation's commands: perturb, evaluate, simulate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from backend.cameras import load_extrinsics
from backend.geometry import rotation_angle_deg


@pytest.fixture(scope="module")
def cli():
    from backend.cli import _register_all, app

    _register_all()
    return app


def _run(cli, *argv, code=0):
    r = CliRunner().invoke(cli, [str(a) for a in argv])
    assert r.exit_code == code, r.output
    return r.output


def test_help_lists_the_commands(cli):
    out = _run(cli, "--help")
    for cmd in ("simulate", "perturb", "evaluate"):
        assert cmd in out
    assert "--translation" in _run(cli, "perturb", "--help")
    assert "--heights" in _run(cli, "simulate", "--help")


def test_perturb_then_evaluate(cli, lab_dir, tmp_path):
    ref = lab_dir / "reference.yaml"
    init = tmp_path / "init.yaml"
    out = _run(cli, "perturb", "--reference", ref, "--translation", 0.25, "--rotation", 10, "--seed", 0, "--out", init)
    assert "20 cameras" in out
    a, b = load_extrinsics(init), load_extrinsics(ref)
    assert a["cam_0"] == b["cam_0"]
    for n in list(b)[1:]:
        assert np.linalg.norm(a[n].pose.t - b[n].pose.t) == pytest.approx(0.25)
        assert rotation_angle_deg(a[n].pose.R, b[n].pose.R) == pytest.approx(10.0)
    assert init.read_text().startswith("# extrcal perturb --translation 0.25 --rotation 10.0 --seed 0")

    figures = json.loads(_run(cli, "evaluate", "--result", init, "--reference", ref, "--json"))
    assert 0.1 < figures["position"]["mean"] < 0.3 and figures["position"]["max"] < 0.4
    assert 5 < figures["orientation"]["mean"] < 11
    assert len(figures["per_camera"]) == 20
    table = _run(cli, "evaluate", "--result", init, "--reference", ref)
    assert "cam_19" in table and table.strip().splitlines()[-1].startswith("position ")


def test_evaluate_reference_against_itself(cli, lab_dir):
    ref = lab_dir / "reference.yaml"
    d = json.loads(_run(cli, "evaluate", "--result", ref, "--reference", ref, "--json"))
    assert d["position"]["max"] < 1e-9 and d["orientation"]["max"] < 1e-9 and d["scale"] == pytest.approx(1.0)


def test_broken_files_are_one_clear_error(cli, lab_dir, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("cam_0:\n  translation: [0, 0]\n  rotation: [0, 0, 0, 1]\n")
    out = _run(cli, "evaluate", "--result", bad, "--reference", lab_dir / "reference.yaml", code=2)
    assert f"error: {bad}:2: cam_0.translation: expected 3 numbers, got 2 values" in out
    out = _run(cli, "perturb", "--reference", bad, "--out", tmp_path / "x.yaml", code=2)
    assert "cam_0.translation" in out and not (tmp_path / "x.yaml").exists()


def test_simulate_writes_recording_and_truth_and_prints_figures(cli, lab_dir, tmp_path):
    out = tmp_path / "rec.jsonl.gz"
    text = _run(cli, "simulate", "--cameras", lab_dir, "--persons", 2, "--duration", 2, "--seed", 0,
                "--heights", "1.96,1.70", "--noise-scale", 1.5, "--set", "miss_prob=0.05", "--out", out)
    assert out.is_file() and (tmp_path / "rec.jsonl.gz.truth.npz").is_file()
    for words in ("with person", "mean joints per detection", "cameras detecting a person", "injected pixel noise",
                  "cam_19", "heights 1.96, 1.70 m"):
        assert words in text
    from edge_clients.sim import Truth

    t = Truth.load(tmp_path / "rec.jsonl.gz.truth.npz")
    assert t.config["noise_scale"] == 1.5 and t.config["miss_prob"] == 0.05 and t.config["duration"] == 2.0
    _run(cli, "simulate", "--cameras", lab_dir, "--duration", 1, "--out", tmp_path / "c.msgpack",
         "--set", "clock_offsets=cam_2:-0.2,cam_17:0.12")
    c = Truth.load(tmp_path / "c.msgpack.truth.npz")
    offsets = dict(zip(c.sensors, c.clock_offset.tolist()))
    assert offsets["cam_2"] == pytest.approx(-0.2) and offsets["cam_17"] == pytest.approx(0.12)
    d = json.loads(_run(cli, "simulate", "--cameras", lab_dir, "--duration", 1, "--out", tmp_path / "b.msgpack",
                        "--no-noise", "--json"))
    assert d["false_detections"] == 0 and sum(d["messages"].values()) > 100


def test_simulate_bad_options(cli, tmp_path, lab_dir):
    out = _run(cli, "simulate", "--out", tmp_path / "r.jsonl", "--set", "bogus=1", code=2)
    assert "unknown simulator setting" in out
    out = _run(cli, "simulate", "--out", tmp_path / "r.jsonl", "--set", "clock_offsets=cam_2:-0.2,cam_5", code=2)
    assert "expected sensor:number pairs separated by commas, got 'cam_5'" in " ".join(out.replace("│", " ").split())
    out = _run(cli, "simulate", "--cameras", lab_dir, "--out", tmp_path / "r.jsonl", "--heights", "1.8", code=2)
    assert "heights: 1 heights for 2 persons" in out
    out = _run(cli, "simulate", "--cameras", tmp_path, "--out", tmp_path / "r.jsonl", code=2)
    assert "intrinsics file does not exist" in out
