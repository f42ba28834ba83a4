"""`extrcal report`: tolerant session reader and a self-contained HTML with valid inline SVG."""

from __future__ import annotations

import gzip
import json
import re
import shutil
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from backend.cameras import Extrinsics, Pose, load_extrinsics, save_extrinsics
from backend.evaluate import evaluate
from backend.geometry import R_to_quat, pose_local, pose_retract
from backend.perturb import perturb_extrinsics
from backend.report import (JOINT_GROUPS, ReportError, floor_frame, line_chart, load_session,
                            render_html)

N_CYCLES = 30


def _camera_dicts(poses, k):
    return [{"name": n, "translation": p.t.tolist(), "rotation": R_to_quat(p.R).tolist(),
             "std_translation": 0.02 * np.exp(-k / 10) + 0.001 * i, "std_rotation": 0.8 * np.exp(-k / 10),
             "observations": 40 * k, "cycles": k, "converged": k > 20 and i != 3,
             "change_translation": 0.0, "change_rotation": 0.0, "last_seen": 10.0 + k}
            for i, (n, p) in enumerate(poses.items())]


def _cycle_poses(init, ref, k, rng):
    """Poses moving from the initial estimate towards the reference, with a little noise."""
    a = 1 - np.exp(-k / 6)
    out = {}
    for n in ref:
        xi = pose_local(init[n].pose.R, init[n].pose.t, ref[n].pose.R, ref[n].pose.t)
        R, t = pose_retract(init[n].pose.R, init[n].pose.t, a * xi + rng.normal(size=6) * 1e-3)
        out[n] = Pose(R, t)
    return out


@pytest.fixture()
def session(lab_dir: Path, tmp_path: Path):
    """A session directory shaped like the service's: CalibrationState dicts per cycle."""
    d = tmp_path / "session"
    (d / "cameras").mkdir(parents=True)
    ref = load_extrinsics(lab_dir / "reference.yaml")
    init = perturb_extrinsics(ref, 0.25, 10.0, seed=3, keep_first=True)
    shutil.copy(lab_dir / "intrinsics.yaml", d / "cameras" / "intrinsics.yaml")
    shutil.copy(lab_dir / "reference.yaml", d / "cameras" / "reference.yaml")
    shutil.copy(lab_dir / "room.yaml", d / "room.yaml")
    save_extrinsics(d / "cameras" / "initial.yaml", init)
    rng = np.random.default_rng(0)
    lines, all_poses = [], {}
    for k in range(1, N_CYCLES + 1):
        poses = _cycle_poses(init, ref, k, rng)
        all_poses[k] = poses
        state = {"data_time": 10.0 + k, "cycle": k, "converged": False, "cameras": _camera_dicts(poses, k),
                 "counters": {"messages": 100 * k},
                 "last_cycle": {"cycle": k, "data_time": 10.0 + k, "hypotheses": 50, "observations": 1000,
                                "cameras": list(ref), "accepted": True, "reason": "",
                                "max_change_translation": 0.1 * np.exp(-k / 5),
                                "max_change_rotation": 3 * np.exp(-k / 5),
                                "reprojection_px": 2 + 8 * np.exp(-k / 4)}}
        if k == N_CYCLES:
            state["last_cycle"]["reprojection_per_camera"] = {n: 1.5 + 0.1 * i for i, n in enumerate(ref)}
            state["last_cycle"]["reprojection_per_group"] = {g: 2.0 + 0.2 * i for i, g in enumerate(JOINT_GROUPS)}
        lines.append(json.dumps(state))
    lines.insert(5, "{not json")
    lines.insert(9, json.dumps({"no": "cycle"}))
    (d / "history.jsonl").write_text("\n".join(lines) + "\n")
    (d / "session.json").write_text(json.dumps({"id": "s-42", "title": "lab test", "site": "lab"}))
    save_extrinsics(d / "result.yaml", {n: Extrinsics(p, ref[n].resolution, 0.001, 0.05)
                                        for n, p in all_poses[N_CYCLES].items()})
    return d, ref, init, all_poses


def test_load_session_dir(session):
    d, ref, init, all_poses = session
    data = load_session(d)
    assert data.title == "lab test" and data.meta["site"] == "lab"
    assert [c.cycle for c in data.cycles] == list(range(1, N_CYCLES + 1))
    assert len(data.warnings) == 1 and "skipped 2 unreadable lines" in data.warnings[0]
    assert "line 6" in data.warnings[0] and "line 10: no integer 'cycle'" in data.warnings[0]
    assert data.intrinsics and data.initial and data.reference and data.result and data.floor is not None
    assert data.camera_names[:3] == ["cam_0", "cam_1", "cam_2"] and len(data.camera_names) == 20
    c5 = data.cycles[4]
    assert c5.poses["cam_7"] == all_poses[5]["cam_7"]
    assert c5.reprojection_px == pytest.approx(2 + 8 * np.exp(-5 / 4))
    assert c5.change_translation == pytest.approx(0.1 * np.exp(-1))
    assert c5.converged["cam_3"] is False and c5.observations["cam_0"] == 200
    # error vs reference is computed from each line's poses, with FORMATS.md's alignment
    want = evaluate(all_poses[5], {n: e.pose for n, e in ref.items()})
    assert c5.error_position == pytest.approx(want.position.mean)
    assert c5.error_shape_position == pytest.approx(want.shape_position.mean)
    errs = [c.error_position for c in data.cycles]
    assert errs[-1] < 0.1 * errs[0]
    assert data.reprojection_per_group["wrists"] == pytest.approx(2.6)
    assert data.reprojection_per_camera["cam_2"] == pytest.approx(1.7)
    # The lab's floor: up is the room's normal, so camera heights read as "up" coordinates.
    up = data.floor[0]
    assert up == pytest.approx([-0.00602624711885269, 0.8301635613450286, -0.5574873503144275])


class _Checker(HTMLParser):
    VOID = {"meta", "br", "img", "input", "link", "hr"}

    def __init__(self):
        super().__init__()
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}> with open {self.stack[-3:]}")
        else:
            self.stack.pop()


def test_render_html_self_contained(session):
    d, ref, init, _ = session
    html = render_html(load_session(d))
    p = _Checker()
    p.feed(html)
    assert not p.errors and not p.stack
    # nothing loaded from anywhere: no scripts, stylesheets, images or fonts by URL
    assert not [t for t, a in p.tags if t in ("script", "link", "img", "iframe")]
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", html)
    assert "url(" not in html and "@import" not in html
    # every inline SVG is well-formed XML
    svgs = re.findall(r"<svg\b.*?</svg>", html, flags=re.S)
    assert len(svgs) >= 7
    for s in svgs:
        ET.fromstring(s)
    # the camera plot holds every camera of the three sets
    cam_plot = next(s for s in svgs if 'id="camera-plot"' in s)
    root = ET.fromstring(cam_plot)
    sets = {g.get("data-set"): [c.get("data-camera") for c in g] for g in root.iter("{http://www.w3.org/2000/svg}g")
            if g.get("data-set")}
    assert set(sets) == {"reference (aligned)", "initial", "result"}
    assert all(sorted(v) == sorted(ref) for v in sets.values())
    # the table has every camera, the charts and sections are there
    table = re.search(r'<table id="cameras">.*?</table>', html, flags=re.S).group(0)
    assert all(f"<td>{n}</td>" in table for n in ref)
    for title in ("Pose change per cycle", "Error vs reference", "Reprojection error per cycle",
                  "per joint group", "Std of the camera positions"):
        assert title in html
    assert "skipped 2 unreadable lines" in html
    assert "20/20" not in html and "19/20" in html  # cam_3 never converged


def test_history_file_alone_calibrate_format(lab_dir, tmp_path):
    """`extrcal calibrate --history` lines: a CycleReport with camera dicts, errors inline."""
    ref = load_extrinsics(lab_dir / "reference.yaml")
    init = perturb_extrinsics(ref, 0.25, 10.0, seed=4, keep_first=True)
    rng = np.random.default_rng(1)
    path = tmp_path / "h.jsonl.gz"
    with gzip.open(path, "wt") as f:
        for k in (1, 2, 3, 2):  # a resumed run repeats cycle 2; the later line wins
            poses = _cycle_poses(init, ref, k, rng)
            rec = {"cycle": k, "data_time": 1.0 * k, "hypotheses": 50, "reprojection_px": 3.0,
                   "cameras": {n: {"translation": p.t.tolist(), "rotation": R_to_quat(p.R).tolist(),
                                   "std_translation": 0.01, "std_rotation": 0.3} for n, p in poses.items()},
                   "error": {"position": {"mean": 0.1 / k, "std": 0.0, "min": 0.0, "max": 0.0},
                             "orientation": 1.0 / k}}
            f.write(json.dumps(rec) + "\n")
    data = load_session(path, reference=lab_dir / "reference.yaml", intrinsics=lab_dir / "intrinsics.yaml")
    assert [c.cycle for c in data.cycles] == [1, 2, 3]
    assert data.cycles[1].error_position == pytest.approx(0.05)  # from the line, not recomputed
    assert data.cycles[2].error_orientation == pytest.approx(1 / 3)
    assert data.result is None and data.final_poses() == dict(data.cycles[-1].poses)
    html = render_html(data)
    assert "Error vs reference" in html and 'id="camera-plot"' in html


def test_wrapped_records_and_cycle_reports_only(tmp_path, lab_dir):
    ref = load_extrinsics(lab_dir / "reference.yaml")
    d = tmp_path / "s"
    d.mkdir()
    save_extrinsics(d / "result.yaml", ref)
    lines = [json.dumps({"report": {"cycle": k, "data_time": float(k), "cameras": ["cam_0", "cam_1"],
                                    "reprojection_px": 4.0 - k, "max_change_translation": 0.1 / k},
                         "state": {"cycle": k, "cameras": [{"name": "cam_0", "std_translation": 0.1 / k}]}})
             for k in (1, 2, 3)]
    (d / "history.jsonl").write_text("\n".join(lines))
    data = load_session(d)
    assert [c.reprojection_px for c in data.cycles] == [3.0, 2.0, 1.0]
    assert data.cycles[2].std_translation == {"cam_0": pytest.approx(0.1 / 3)}
    assert data.cycles[0].poses == {}  # a CycleReport's camera list holds names only
    render_html(data)


def test_no_history_result_only(tmp_path, lab_dir):
    d = tmp_path / "s"
    d.mkdir()
    shutil.copy(lab_dir / "reference.yaml", d / "result.yaml")
    data = load_session(d)
    assert data.cycles == [] and len(data.camera_names) == 20
    html = render_html(data)
    assert 'id="camera-plot"' in html and "Convergence" not in html


def test_errors(tmp_path):
    with pytest.raises(ReportError, match="no such session"):
        load_session(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReportError, match="nothing to report"):
        load_session(tmp_path / "empty")
    gz = tmp_path / "bad.jsonl.gz"
    gz.write_bytes(b"not gzip at all")
    with pytest.raises(ReportError, match="cannot read the history"):
        load_session(gz)


def test_floor_frame_without_room():
    # cameras mounted upright in a z-up world, looking horizontally
    R = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # cam x→world x, cam y (down)→-z, cam z→y
    B = floor_frame([Pose(R, np.zeros(3))])
    assert np.allclose(np.cross(B[0], B[1]), [0, 0, 1])


def test_line_chart_log_and_gaps():
    svg = line_chart([_series([1, 2, 3, 4], [1.0, None, 0.01, 0.001])], title="t", xlabel="x", ylabel="y", log=True)
    root = ET.fromstring(svg)
    ns = "{http://www.w3.org/2000/svg}"
    assert len(root.findall(f"{ns}circle")) == 1 and len(root.findall(f"{ns}polyline")) == 1
    ticks = [t.text for t in root.iter(f"{ns}text") if t.get("class") == "tick"]
    assert "1e-3" in ticks and "0.01" in ticks and "1" in ticks
    empty = line_chart([_series([1], [None])], title="nothing", xlabel="x", ylabel="y")
    assert "no data" in empty


def _series(x, y):
    from backend.report import Series

    return Series("s", x, y)


def test_cli_report(session, tmp_path):
    from backend.cli_tools import register

    d = session[0]
    app = typer.Typer()
    register(app)
    out = tmp_path / "r" / "report.html"
    r = CliRunner().invoke(app, ["report", str(d), "--out", str(out), "--title", "Lab <run>"])
    assert r.exit_code == 0, r.output
    assert "warning:" in r.output and f"wrote {out} ({N_CYCLES} cycles, 20 cameras)" in r.output
    text = out.read_text()
    assert "<title>Lab &lt;run&gt;</title>" in text
    (d / "cameras" / "intrinsics.yaml").write_text("cam_0: [1, 2\n")
    r = CliRunner().invoke(app, ["report", str(d), "--out", str(out)])
    assert r.exit_code == 2 and "intrinsics.yaml" in r.output and "not valid YAML" in r.output


def test_service_session_layout(tmp_path, lab_dir):
    """The service's session directory (backend/session.py): history lines are a flattened
    CycleReport with `accuracy` and `per_camera`; state.json holds the latest detail."""
    d = tmp_path / "20260101T000000-abcd"
    d.mkdir()
    for f in ("intrinsics.yaml", "reference.yaml"):
        shutil.copy(lab_dir / f, d / f)
    shutil.copy(lab_dir / "reference.yaml", d / "initial.yaml")
    shutil.copy(lab_dir / "reference.yaml", d / "result.yaml")
    ref = load_extrinsics(lab_dir / "reference.yaml")
    lines = []
    for k in (1, 2):
        lines.append({"cycle": k, "data_time": 5.0 + k, "hypotheses": 50, "observations": 900, "cameras": list(ref)[:4],
                      "initial_error": 2.0, "final_error": 1.0, "iterations": 4, "solve_seconds": 0.1, "moved": True,
                      "accepted": True, "reason": "", "max_change_translation": 0.01 / k, "max_change_rotation": 0.5 / k,
                      "reprojection_px": 3.0 / k, "wall": 1.7e9, "state": "calibrating", "converged": False,
                      "cameras_converged": 0, "cameras_calibrated": 4, "max_std_translation": 0.02,
                      "max_std_rotation": 0.5,
                      "accuracy": {"position_mean": 0.2 / k, "position_max": 0.3, "orientation_mean": 2.0 / k,
                                   "orientation_max": 3.0, "shape_position_mean": 0.1 / k, "shape_orientation_mean": 1.0,
                                   "scale": 1.0},
                      "per_camera": {n: [0.02 / k, 0.4 / k, None, None, k == 2 and n != "cam_1"] for n in ref}})
    (d / "history.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    (d / "session.json").write_text(json.dumps({"id": d.name, "name": "morning run", "state": "stopped",
                                                "reason": "stopped by request", "stop": {"converged": True},
                                                "created_wall": 1.7e9, "cycles": 2,
                                                "scale": {"person_height": None, "check": {"factor": 1.0},
                                                          "summary": "scale check: 0.4 sigma apart; kept"}}))
    (d / "config.json").write_text(json.dumps({"select": {"scope": 50}, "sync": {"rate": 15.0}}))
    (d / "state.json").write_text(json.dumps({"cycle": 2, "data_time": 7.0, "converged": False, "cameras": [
        {"name": n, "observations": 100 + i, "converged": n != "cam_1", "std_translation": 0.01,
         "std_rotation": 0.2} for i, n in enumerate(ref)]}))
    data = load_session(d)
    assert data.title == "morning run" and data.config["select"]["scope"] == 50
    c1, c2 = data.cycles
    assert c2.error_position == pytest.approx(0.1) and c2.error_shape_position == pytest.approx(0.05)
    assert c1.std_translation["cam_5"] == pytest.approx(0.02) and c2.converged["cam_1"] is False
    assert data.final_state.observations["cam_3"] == 103
    html = render_html(data)
    assert "19/20" in html and "morning run" in html and "select.scope" in html
    assert "stopped by request" in html and "2023-11-14 22:13:20 UTC" in html
    assert "scale check: 0.4 sigma apart; kept" in html


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory, lab_dir):
    """8 s of the simulated lab, exact projections (no detector noise)."""
    from backend.cli import _register_all, app

    _register_all()
    out = tmp_path_factory.mktemp("sim") / "rec.jsonl.gz"
    r = CliRunner().invoke(app, ["simulate", "--cameras", str(lab_dir), "--out", str(out), "--duration", "8",
                                 "--persons", "2", "--seed", "5", "--no-noise"])
    assert r.exit_code == 0, r.output
    return out


def test_reprojection_errors_from_a_recording(sim_recording, lab_dir, tmp_path):
    from backend.cameras import load_intrinsics
    from backend.report import reprojection_errors

    intr = load_intrinsics(lab_dir / "intrinsics.yaml")
    ref = load_extrinsics(lab_dir / "reference.yaml")
    cam, grp, n = reprojection_errors(intr, ref, sim_recording)
    assert n > 1000 and set(grp) == set(JOINT_GROUPS)
    assert len(cam) >= 15
    # the true poses and exact projections: only the sync's interpolation is left
    assert max(grp.values()) < 1.0 and np.median(list(cam.values())) < 1.0
    bad = perturb_extrinsics(ref, 0.05, 2.0, seed=1, keep_first=True)
    cam_b, grp_b, _ = reprojection_errors(intr, bad, sim_recording)
    assert min(grp_b.values()) > 10 * max(grp.values()) and min(grp_b.values()) > 3.0

    # through the CLI, into the report's tables
    from backend.cli_tools import register

    d = tmp_path / "s"
    d.mkdir()
    shutil.copy(lab_dir / "intrinsics.yaml", d / "intrinsics.yaml")
    save_extrinsics(d / "result.yaml", bad)
    app = typer.Typer()
    register(app)
    out = tmp_path / "r.html"
    r = CliRunner().invoke(app, ["report", str(d), "--recording", str(sim_recording), "--out", str(out)])
    assert r.exit_code == 0, r.output
    html = out.read_text()
    table = re.search(r'<table id="joint-groups">.*?</table>', html, flags=re.S).group(0)
    shown = dict(re.findall(r"<tr><td>(\w+)</td><td>([0-9.]+)</td></tr>", table))
    assert set(shown) == set(JOINT_GROUPS)
    assert float(shown["hips"]) == pytest.approx(grp_b["hips"], abs=0.01)
    assert "keypoints reprojected with the result" in html
    r = CliRunner().invoke(app, ["report", str(tmp_path / "s"), "--recording", str(lab_dir / "room.yaml"),
                                 "--out", str(out)])
    assert r.exit_code == 2 and "room.yaml" in r.output
