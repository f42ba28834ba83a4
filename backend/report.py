"""A self-contained HTML record of a calibration session (`extrcal report`).

One file, no scripts, no network: inline CSS and SVG plots generated here (hover a point
or a camera for its numbers, through SVG <title>). Sections: summary, camera plot (top
view of initial, result and reference cameras with their viewing wedges), convergence
over cycles (pose change, std, error vs reference, reprojection error), per-camera table,
per-joint-group reprojection errors, accuracy vs reference (FORMATS.md figures).

Input (``load_session``), read tolerantly; what it did not understand becomes a warning:

- a session directory: camera files ``intrinsics.yaml``, ``initial.yaml``, ``result.yaml``,
  ``reference.yaml``, optional ``room.yaml`` (floor plane for the top view), either at the
  top level or under ``cameras/``, and ``history.jsonl`` (``.jsonl.gz``) with one JSON object
  per cycle; a ``session.json``/``config.json``/``meta.json`` adds a title and settings
  to the summary, and may name the files (``{"files": {"intrinsics": "..."}}``);
- or a history file alone (``extrcal calibrate --history H.jsonl``), with the camera files
  given as options.

A history line may be a ``CalibrationState.to_dict()`` (``cameras`` list with translation,
rotation, std_*, observations, converged; ``last_cycle`` a ``CycleReport``), a
``CycleReport`` with a ``cameras`` list of camera dicts (the calibrate history), or either
wrapped as ``{"state": ..., "report": ...}``; ``cameras`` may also be a name → dict map.
Optional per line: ``error`` / ``accuracy`` vs reference (an ``Accuracy.to_dict()`` or
``{"position": m, "orientation": deg}``), ``reprojection_per_camera`` (name → px) and
``reprojection_per_group`` (joint group → px), also inside ``last_cycle``/``report``.
A ``reprojection.json`` in the session directory (``{"per_camera": {...},
"per_group": {...}}``) overrides the last cycle's. Where a line has poses and a reference
is known, the error vs reference is computed here with backend.evaluate.
"""

from __future__ import annotations

import gzip
import html
import json
import math
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import yaml

from .cameras import (CameraFileError, Extrinsics, Intrinsics, Pose, load_extrinsics, load_intrinsics,
                      natural_key)
from .evaluate import MIN_CAMERAS, align_poses, evaluate
from .geometry import quat_to_R, rotation_angle_deg
from .session import SessionStore

# COCO-17 joint groups, in the order of the paper's tables.
JOINT_GROUPS: dict[str, tuple[int, ...]] = {
    "head": (0, 1, 2, 3, 4), "shoulders": (5, 6), "elbows": (7, 8), "wrists": (9, 10),
    "hips": (11, 12), "knees": (13, 14), "ankles": (15, 16),
}


class ReportError(ValueError):
    """A session that cannot be reported on; the message says what is missing."""


@dataclass(frozen=True)
class CycleRecord:
    """One history line, normalised. Per-camera maps only hold what the line had."""

    cycle: int
    data_time: float | None
    poses: Mapping[str, Pose]
    std_translation: Mapping[str, float]
    std_rotation: Mapping[str, float]
    converged: Mapping[str, bool]
    observations: Mapping[str, int]
    reprojection_px: float | None = None
    change_translation: float | None = None  # m, max over cameras this cycle
    change_rotation: float | None = None  # deg
    hypotheses: int | None = None
    accepted: bool | None = None
    error_position: float | None = None  # m, rigid alignment, mean over cameras
    error_orientation: float | None = None  # deg
    error_shape_position: float | None = None  # m, similarity alignment
    reprojection_per_camera: Mapping[str, float] = field(default_factory=dict)
    reprojection_per_group: Mapping[str, float] = field(default_factory=dict)


@dataclass
class SessionData:
    source: Path
    title: str
    intrinsics: dict[str, Intrinsics]
    initial: dict[str, Extrinsics] | None
    result: dict[str, Extrinsics] | None
    reference: dict[str, Extrinsics] | None
    cycles: list[CycleRecord]
    meta: dict[str, Any]
    warnings: list[str]
    floor: tuple[np.ndarray, np.ndarray] | None = None  # (up, e1) unit vectors in the world
    reprojection_per_camera: dict[str, float] = field(default_factory=dict)
    reprojection_per_group: dict[str, float] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)  # the engine config of the session
    final_state: CycleRecord | None = None  # state.json: the latest per-camera detail
    reprojection_source: str = ""  # where the per-camera/per-group errors come from

    @property
    def camera_names(self) -> list[str]:
        names: set[str] = set()
        for d in (self.result, self.initial, self.reference):
            if d:
                names |= set(d)
        if self.cycles:
            names |= set(self.cycles[-1].poses)
        return sorted(names, key=natural_key)

    def final_poses(self) -> dict[str, Pose]:
        if self.result:
            return {n: e.pose for n, e in self.result.items()}
        return dict(self.cycles[-1].poses) if self.cycles else {}


# ------------------------------------------------------------------ reading


_CAMERA_FILES = ("intrinsics", "initial", "result", "reference")


def _find(root: Path, names: Sequence[str]) -> Path | None:
    for sub in ("", "cameras"):
        for n in names:
            p = root / sub / n if sub else root / n
            if p.is_file():
                return p
    return None


def load_session(path: str | os.PathLike, *, intrinsics: str | os.PathLike | None = None,
                 initial: str | os.PathLike | None = None, result: str | os.PathLike | None = None,
                 reference: str | os.PathLike | None = None, room: str | os.PathLike | None = None,
                 recording: str | os.PathLike | None = None, max_points: int = 4000) -> SessionData:
    """Read a session directory or a history file; explicit files win over found ones.

    ``recording``: keypoint recording of the session; per-camera and per-joint-group
    reprojection errors of the result are then computed on it (``reprojection_errors``).
    ``max_points``: longer histories are thinned evenly (the last cycle always kept) so
    that the report stays small; the thinning is said in the warnings.
    """
    path = Path(path)
    warnings: list[str] = []
    sessions = path / "sessions"
    if path.is_dir() and sessions.is_dir() and not (path / "history.jsonl").exists():
        # the service's state directory: report its newest session (ids sort by creation)
        ids = SessionStore(sessions).ids()
        if not ids:
            raise ReportError(f"{path}: a state directory without sessions")
        path = sessions / ids[-1]
    meta: dict[str, Any] = {}
    config: dict[str, Any] = {}
    final_state: dict[str, Any] = {}
    files: dict[str, Path | None] = {k: None for k in (*_CAMERA_FILES, "history", "room", "reprojection")}
    if path.is_dir():
        for mname, target in (("session.json", meta), ("meta.json", meta), ("config.json", config),
                              ("state.json", final_state)):
            p = path / mname
            if p.is_file():
                try:
                    m = json.loads(p.read_text())
                    if isinstance(m, dict):
                        target.update(m)
                except (OSError, json.JSONDecodeError) as e:
                    warnings.append(f"{p}: ignored, not valid JSON ({e})")
        named = meta.get("files") if isinstance(meta.get("files"), dict) else {}
        for k in files:
            if isinstance(named.get(k), str) and (path / named[k]).is_file():
                files[k] = path / named[k]
        for k, cands in {
            "intrinsics": ("intrinsics.yaml", "intrinsics.yml"),
            "initial": ("initial.yaml", "initial_extrinsics.yaml", "extrinsics_initial.yaml"),
            "result": ("result.yaml", "extrinsics.yaml", "calibration.yaml"),
            "reference": ("reference.yaml", "extrinsics_reference.yaml"),
            "room": ("room.yaml",),
            "history": ("history.jsonl", "history.jsonl.gz", "cycles.jsonl"),
            "reprojection": ("reprojection.json",),
        }.items():
            files[k] = files[k] or _find(path, cands)
    elif path.is_file():
        files["history"] = path
    else:
        raise ReportError(f"{path}: no such session directory or history file")
    for k, v in (("intrinsics", intrinsics), ("initial", initial), ("result", result),
                 ("reference", reference), ("room", room)):
        if v is not None:
            files[k] = Path(v)

    intr = load_intrinsics(files["intrinsics"]) if files["intrinsics"] else {}
    cams = {k: (load_extrinsics(files[k]) if files[k] else None) for k in ("initial", "result", "reference")}
    cycles = _read_history(files["history"], warnings) if files["history"] else []
    if not cycles and not cams["result"]:
        raise ReportError(f"{path}: found neither a history ({', '.join(('history.jsonl',))}) "
                          "nor a result.yaml: nothing to report")
    if cams["reference"] is not None:
        cycles = [_with_reference_error(c, cams["reference"]) for c in cycles]
    if len(cycles) > max_points:
        keep = np.unique(np.r_[np.linspace(0, len(cycles) - 1, max_points).round().astype(int), len(cycles) - 1])
        warnings.append(f"history thinned from {len(cycles)} to {len(keep)} cycles for the plots")
        cycles = [cycles[i] for i in keep]
    floor = _read_room(files["room"], warnings) if files["room"] else None

    rep_cam: dict[str, float] = {}
    rep_grp: dict[str, float] = {}
    for c in reversed(cycles):  # the latest cycle that has them
        if c.reprojection_per_camera and not rep_cam:
            rep_cam = dict(c.reprojection_per_camera)
        if c.reprojection_per_group and not rep_grp:
            rep_grp = dict(c.reprojection_per_group)
    if files["reprojection"]:
        try:
            r = json.loads(files["reprojection"].read_text())
            rep_cam = _float_map(r.get("per_camera")) or rep_cam
            rep_grp = _float_map(r.get("per_group")) or rep_grp
        except (OSError, json.JSONDecodeError, AttributeError) as e:
            warnings.append(f"{files['reprojection']}: ignored ({e})")

    rep_source = "the session's history" if (rep_cam or rep_grp) else ""
    if recording is not None:
        final_ext = cams["result"]
        if final_ext is None and cycles and cycles[-1].poses:
            final_ext = {n: Extrinsics(p, (0, 0)) for n, p in cycles[-1].poses.items()}
        if not intr or not final_ext:
            raise ReportError(f"{recording}: reprojection errors need the intrinsics and a result")
        try:
            rep_cam, rep_grp, n = reprojection_errors(intr, final_ext, recording)
        except CameraFileError as e:
            raise ReportError(f"{recording}: {e}") from None
        rep_source = f"{Path(recording).name}, {n} keypoints reprojected with the result's poses"
    final = None
    if final_state:
        try:
            final = _parse_record({"cycle": 0, **final_state})
        except (ValueError, TypeError, KeyError) as e:
            warnings.append(f"state.json: ignored ({e})")
    title = str(meta.get("title") or meta.get("name") or meta.get("id") or path.stem)
    return SessionData(path, title, intr, cams["initial"], cams["result"], cams["reference"], cycles,
                       meta, warnings, floor, rep_cam, rep_grp, config, final, rep_source)


def _open_text(path: Path):
    if path.suffix == ".gz":
        return gzip.open(path, "rt", encoding="utf-8")
    return open(path, encoding="utf-8")


def _read_history(path: Path, warnings: list[str]) -> list[CycleRecord]:
    out: list[CycleRecord] = []
    bad: list[str] = []
    try:
        with _open_text(path) as f:
            for lineno, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    rec = _parse_record(json.loads(line))
                except (json.JSONDecodeError, ValueError, TypeError, KeyError) as e:
                    bad.append(f"line {lineno}: {e}")
                    continue
                if rec is not None:
                    out.append(rec)
    except (OSError, EOFError, gzip.BadGzipFile) as e:
        raise ReportError(f"{path}: cannot read the history: {e}") from None
    if bad:
        warnings.append(f"{path}: skipped {len(bad)} unreadable lines ({'; '.join(bad[:3])}"
                        f"{'; ...' if len(bad) > 3 else ''})")
    # A resumed session may repeat cycles: keep the last record of each, in cycle order.
    by_cycle = {r.cycle: r for r in out}
    return [by_cycle[k] for k in sorted(by_cycle)]


def _num(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _float_map(d: Any) -> dict[str, float]:
    if not isinstance(d, dict):
        return {}
    return {str(k): v for k, v in ((k, _num(v)) for k, v in d.items()) if v is not None}


def _stat(x: Any) -> float | None:
    """A number, or the mean of an evaluate.Stats dict."""
    return _num(x["mean"]) if isinstance(x, dict) and "mean" in x else _num(x)


def _parse_record(d: Any) -> CycleRecord | None:
    if not isinstance(d, dict):
        raise ValueError("not a JSON object")
    # Unwrap {"state": ..., "report": ...} records; the outer keys win.
    state = d.get("state") if isinstance(d.get("state"), dict) else {}
    report = next((d[k] for k in ("report", "cycle_report", "last_cycle") if isinstance(d.get(k), dict)), None)
    report = report or (state.get("last_cycle") if isinstance(state.get("last_cycle"), dict) else {})
    merged = {**report, **state, **{k: v for k, v in d.items() if k not in ("state", "report", "cycle_report")}}
    cycle = merged.get("cycle", report.get("cycle"))
    if isinstance(cycle, bool) or not isinstance(cycle, int):
        raise ValueError("no integer 'cycle'")
    cams = merged.get("cameras")
    if isinstance(cams, dict):
        cams = [{"name": k, **v} for k, v in cams.items() if isinstance(v, dict)]
    poses, std_t, std_r, conv, obs = {}, {}, {}, {}, {}
    if isinstance(cams, list):
        for c in cams:
            if not isinstance(c, dict) or "name" not in c:
                continue  # a CycleReport's `cameras` is a list of names: no poses there
            n = str(c["name"])
            t, q = c.get("translation"), c.get("rotation")
            if isinstance(t, list) and len(t) == 3 and isinstance(q, list) and len(q) == 4:
                tv, qv = np.array(t, dtype=float), np.array(q, dtype=float)
                if np.all(np.isfinite(tv)) and np.all(np.isfinite(qv)) and np.linalg.norm(qv) > 0.5:
                    poses[n] = Pose(quat_to_R(qv), tv)
            if (v := _num(c.get("std_translation"))) is not None:
                std_t[n] = v
            if (v := _num(c.get("std_rotation"))) is not None:
                std_r[n] = v
            if isinstance(c.get("converged"), bool):
                conv[n] = c["converged"]
            if (v := _num(c.get("observations"))) is not None:
                obs[n] = int(v)
    pc = merged.get("per_camera")
    if isinstance(pc, dict):  # the service's history: name → [std_t, std_r, change_t, change_r, converged]
        for n, v in pc.items():
            if isinstance(v, list) and len(v) >= 2:
                if (x := _num(v[0])) is not None:
                    std_t.setdefault(str(n), x)
                if (x := _num(v[1])) is not None:
                    std_r.setdefault(str(n), x)
                if len(v) >= 5 and isinstance(v[4], bool):
                    conv.setdefault(str(n), v[4])
    err = next((merged[k] for k in ("error", "accuracy", "reference_error") if isinstance(merged.get(k), dict)), {})

    def pick(*keys: str) -> float | None:
        for k in keys:
            for src in (merged, report):
                if (v := _num(src.get(k))) is not None:
                    return v
        return None

    accepted = merged.get("accepted", report.get("accepted"))
    return CycleRecord(
        cycle=cycle,
        data_time=pick("data_time"),
        poses=poses, std_translation=std_t, std_rotation=std_r, converged=conv, observations=obs,
        reprojection_px=pick("reprojection_px", "reprojection"),
        change_translation=pick("max_change_translation", "change_translation"),
        change_rotation=pick("max_change_rotation", "change_rotation"),
        hypotheses=(int(h) if (h := pick("hypotheses")) is not None else None),
        accepted=accepted if isinstance(accepted, bool) else None,
        error_position=_stat(err.get("position", err.get("position_mean"))),
        error_orientation=_stat(err.get("orientation", err.get("orientation_mean"))),
        error_shape_position=_stat(err.get("shape_position", err.get("shape_position_mean"))),
        reprojection_per_camera=_float_map(merged.get("reprojection_per_camera") or report.get("reprojection_per_camera")),
        reprojection_per_group=_float_map(merged.get("reprojection_per_group") or report.get("reprojection_per_group")),
    )


def _with_reference_error(c: CycleRecord, reference: Mapping[str, Extrinsics]) -> CycleRecord:
    from dataclasses import replace

    if c.error_position is not None or len(set(c.poses) & set(reference)) < MIN_CAMERAS:
        return c
    try:
        acc = evaluate(c.poses, {n: e.pose for n, e in reference.items()})
    except (ValueError, np.linalg.LinAlgError):
        return c
    return replace(c, error_position=acc.position.mean, error_orientation=acc.orientation.mean,
                   error_shape_position=acc.shape_position.mean)


def _read_room(path: Path, warnings: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        d = yaml.safe_load(path.read_text())
        up = np.array(d["floor"]["normal_up"], dtype=float)
        e1 = np.array(d["floor"]["e1"], dtype=float)
        assert up.shape == (3,) and e1.shape == (3,)
        up /= np.linalg.norm(up)
        e1 = e1 - up * (e1 @ up)
        return up, e1 / np.linalg.norm(e1)
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError, AssertionError, ZeroDivisionError) as e:
        warnings.append(f"{path}: floor plane not used ({type(e).__name__}: {e})")
        return None


# ------------------------------------------------------------------ reprojection from a recording


def reprojection_errors(intrinsics: Mapping[str, Intrinsics], extrinsics: Mapping[str, Extrinsics],
                        recording: str | os.PathLike, *, config: Any = None,
                        skip_bad: bool = True) -> tuple[dict[str, float], dict[str, float], int]:
    """Median reprojection error (px) per camera and per joint group of a calibration on a
    recording, the way the engine sees the data: framesets, preprocessing and association
    with the engine's components and these poses; each person's joints triangulated (DLT)
    from all its views and reprojected into each. Pixels are undistorted normalised
    coordinates times the focal length. Returns (per camera, per joint group, residuals).
    """
    from proto import ReadStats, read_recording

    from .associate import Associator
    from .cameras import CameraSet
    from .config import EngineConfig
    from .geometry import triangulate_views
    from .preprocess import Preprocessor
    from .sync import Synchronizer

    cams = CameraSet.combine(intrinsics, extrinsics)
    cfg = (config or EngineConfig()).for_images(cams.sizes)
    names = cams.names
    R = np.array([cams.extrinsics[n].pose.R for n in names])
    t = np.array([cams.extrinsics[n].pose.t for n in names])
    focal = np.array([0.5 * (cams.intrinsics[n].fx + cams.intrinsics[n].fy) for n in names])
    sync = Synchronizer(cfg.sync, names)
    pre = Preprocessor(cfg.preprocess, names, cams.intrinsics)
    assoc = Associator(cfg.associate)
    per_cam: list[list[np.ndarray]] = [[] for _ in names]
    per_joint: list[list[np.ndarray]] = [[] for _ in range(17)]

    def consume(framesets) -> None:
        for fs in framesets:
            dets = pre(fs)
            if len(dets) < 2:
                continue
            for h in assoc(fs.time, dets, R, t, None):
                X, _ = triangulate_views(R, t, h.cams, h.xy)  # (17, 3), NaN where not triangulated
                for v, c in enumerate(h.cams):
                    Xc = (X - t[c]) @ R[c]  # world → camera c
                    ok = np.all(np.isfinite(h.xy[v]), axis=1) & np.all(np.isfinite(Xc), axis=1)
                    ok[ok] &= Xc[ok, 2] > 1e-6
                    if not ok.any():
                        continue
                    r = np.linalg.norm(Xc[ok, :2] / Xc[ok, 2:3] - h.xy[v][ok], axis=1) * focal[c]
                    per_cam[c].append(r)
                    for j, rj in zip(np.flatnonzero(ok), r):
                        per_joint[j].append(np.array([rj]))

    stats = ReadStats()
    clock: float | None = None
    for msg in read_recording(recording, skip_bad=skip_bad, stats=stats):
        sync.push(msg, clock)
        clock = msg.stamp if clock is None else max(clock, msg.stamp)
        consume(sync.pop_ready(clock))
    if clock is None:
        first = f" (first: {stats.first_errors[0]})" if stats.first_errors else ""
        raise ReportError(f"{recording}: no keypoint messages, {stats.skipped} bad records skipped{first}")
    # close the framesets still waiting for late messages
    consume(sync.pop_ready(clock + cfg.sync.wait + 2.0 / cfg.sync.rate))
    cam_px = {names[c]: float(np.median(np.concatenate(v))) for c, v in enumerate(per_cam) if v}
    grp_px = {}
    for g, joints in JOINT_GROUPS.items():
        vals = [x for j in joints for x in per_joint[j]]
        if vals:
            grp_px[g] = float(np.median(np.concatenate(vals)))
    n = int(sum(len(x) for v in per_cam for x in v))
    return cam_px, grp_px, n


# ------------------------------------------------------------------ geometry for the plot


def floor_frame(poses: Iterable[Pose], floor: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(2, 3) rows = the plot's x and y axes in the world, y the floor's "north".

    From the room's floor plane when given; otherwise "up" is the mean of the cameras'
    up directions (-y of OpenCV's camera axes: cameras are mounted roughly upright),
    falling back to the world z axis when they disagree.
    """
    if floor is not None:
        up, e1 = floor
    else:
        ups = np.array([-p.R[:, 1] for p in poses])
        up = ups.mean(0) if len(ups) else np.zeros(3)
        if np.linalg.norm(up) < 0.5:
            up = np.array([0.0, 0.0, 1.0])
        up = up / np.linalg.norm(up)
        e1 = np.array([1.0, 0.0, 0.0])
        if abs(e1 @ up) > 0.9:
            e1 = np.array([0.0, 1.0, 0.0])
        e1 = e1 - up * (e1 @ up)
        e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return np.stack([e1, e2])


def wedge(pose: Pose, intr: Intrinsics | None, depth: float) -> np.ndarray:
    """(5, 3) world points: the centre and the image corners' rays at ``depth`` m."""
    if intr is not None:
        w, h = intr.resolution
        xs = np.array([-intr.cx / intr.fx, (w - intr.cx) / intr.fx])
        ys = np.array([-intr.cy / intr.fy, (h - intr.cy) / intr.fy])
    else:  # about 90° x 60°
        xs, ys = np.array([-1.0, 1.0]), np.array([-0.58, 0.58])
    corners = np.array([[xs[0], ys[0], 1], [xs[1], ys[0], 1], [xs[1], ys[1], 1], [xs[0], ys[1], 1]]) * depth
    return np.vstack([pose.t, pose.to_world(corners)])


# ------------------------------------------------------------------ SVG


_PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]


def _e(s: Any) -> str:
    return html.escape(str(s), quote=True)


def _fmt(v: float | None, digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    if v != 0 and (abs(v) < 10 ** -(digits) or abs(v) >= 1e6):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}f}"


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    return [start + k * step for k in range(int((hi - start) / step + 1e-9) + 1)]


def _tick_label(v: float, log: bool) -> str:
    if log:
        e = round(math.log10(v))
        return f"1e{e}" if abs(e) >= 3 else f"{10.0 ** e:g}"
    return f"{v:.6g}"


@dataclass
class Series:
    name: str
    x: Sequence[float]
    y: Sequence[float | None]
    color: str = "#1f77b4"
    width: float = 1.6
    dash: str | None = None
    opacity: float = 1.0
    legend: bool = True


def line_chart(series: Sequence[Series], *, title: str, xlabel: str, ylabel: str, log: bool = False,
               width: int = 640, height: int = 270, hline: tuple[float, str] | None = None) -> str:
    """An SVG line chart; None/NaN/non-positive-on-log values break the line."""
    ml, mr, mt, mb = 62, 14, 44, 40
    pts = [(x, y) for s in series for x, y in zip(s.x, s.y)
           if y is not None and math.isfinite(y) and (not log or y > 0) and math.isfinite(x)]
    if hline and (not log or hline[0] > 0):
        pts.append((pts[0][0] if pts else 0.0, hline[0]))
    if not pts:
        return (f'<svg class="chart" viewBox="0 0 {width} {height}" width="{width}" height="{height}">'
                f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle" class="muted">{_e(title)}: '
                "no data</text></svg>")
    xs = [p[0] for p in pts]
    ys = [p[1] for p in pts]
    x0, x1 = min(xs), max(xs)
    if x1 == x0:
        x0, x1 = x0 - 1, x1 + 1
    if log:
        y0, y1 = math.floor(math.log10(min(ys))), math.ceil(math.log10(max(ys)))
        if y1 == y0:
            y1 += 1
        yt = [10.0 ** k for k in range(y0, y1 + 1)]
        fy = lambda v: math.log10(v)  # noqa: E731
        ylo, yhi = float(y0), float(y1)
    else:
        ylo, yhi = min(0.0, min(ys)), max(ys)
        if yhi == ylo:
            yhi = ylo + 1
        yhi += 0.05 * (yhi - ylo)
        yt = _nice_ticks(ylo, yhi)
        fy = lambda v: v  # noqa: E731
    pw, ph = width - ml - mr, height - mt - mb

    def X(v: float) -> float:
        return ml + (v - x0) / (x1 - x0) * pw

    def Y(v: float) -> float:
        return mt + ph - (fy(v) - ylo) / (yhi - ylo) * ph

    o = [f'<svg class="chart" viewBox="0 0 {width} {height}" width="{width}" height="{height}" '
         f'xmlns="http://www.w3.org/2000/svg" role="img" aria-label="{_e(title)}">',
         f'<text x="{ml}" y="16" class="ctitle">{_e(title)}</text>',
         f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" class="plotbg"/>']
    for v in yt:
        y = Y(v)
        o.append(f'<line x1="{ml}" x2="{ml + pw}" y1="{y:.1f}" y2="{y:.1f}" class="grid"/>'
                 f'<text x="{ml - 5}" y="{y + 4:.1f}" text-anchor="end" class="tick">{_tick_label(v, log)}</text>')
    for v in _nice_ticks(x0, x1, 6):
        x = X(v)
        o.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{mt}" y2="{mt + ph}" class="grid"/>'
                 f'<text x="{x:.1f}" y="{mt + ph + 15}" text-anchor="middle" class="tick">{v:g}</text>')
    o.append(f'<text x="{ml + pw / 2}" y="{height - 6}" text-anchor="middle" class="axis">{_e(xlabel)}</text>')
    o.append(f'<text transform="translate(14 {mt + ph / 2}) rotate(-90)" text-anchor="middle" class="axis">{_e(ylabel)}</text>')
    if hline and (not log or hline[0] > 0):
        y = Y(hline[0])
        o.append(f'<line x1="{ml}" x2="{ml + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#555" stroke-dasharray="6 4"/>'
                 f'<text x="{ml + pw - 4}" y="{y - 4:.1f}" text-anchor="end" class="tick">{_e(hline[1])}</text>')
    for s in series:
        runs: list[list[str]] = [[]]
        for x, y in zip(s.x, s.y):
            if y is None or not math.isfinite(y) or (log and y <= 0):
                runs.append([])
                continue
            runs[-1].append(f"{X(x):.1f},{Y(y):.1f}")
        dash = f' stroke-dasharray="{s.dash}"' if s.dash else ""
        for r in runs:
            if len(r) == 1:
                cx, cy = r[0].split(",")
                o.append(f'<circle cx="{cx}" cy="{cy}" r="2" fill="{s.color}" opacity="{s.opacity}"/>')
            elif r:
                o.append(f'<polyline points="{" ".join(r)}" fill="none" stroke="{s.color}" '
                         f'stroke-width="{s.width}" opacity="{s.opacity}"{dash}><title>{_e(s.name)}</title></polyline>')
    lx = ml
    for s in [s for s in series if s.legend]:
        dash = f' stroke-dasharray="{s.dash}"' if s.dash else ""
        o.append(f'<line x1="{lx}" x2="{lx + 16}" y1="30" y2="30" stroke="{s.color}" stroke-width="2.5"{dash}/>'
                 f'<text x="{lx + 20}" y="34" class="legend">{_e(s.name)}</text>')
        lx += 30 + 6.2 * len(s.name)
    o.append("</svg>")
    return "".join(o)


def bar_chart(values: Mapping[str, float], *, title: str, unit: str, width: int = 640,
              color: str = "#1f77b4") -> str:
    """Horizontal bars, one per key, in the given order."""
    items = [(k, v) for k, v in values.items() if v is not None and math.isfinite(v)]
    if not items:
        return ""
    row, ml, mr, mt = 16, 90, 60, 26
    height = mt + row * len(items) + 10
    vmax = max(v for _, v in items) or 1.0
    pw = width - ml - mr
    o = [f'<svg class="chart" viewBox="0 0 {width} {height}" width="{width}" height="{height}" '
         f'xmlns="http://www.w3.org/2000/svg" role="img" aria-label="{_e(title)}">',
         f'<text x="{ml}" y="16" class="ctitle">{_e(title)}</text>']
    for k, (name, v) in enumerate(items):
        y = mt + k * row
        w = max(v / vmax * pw, 0.5)
        o.append(f'<text x="{ml - 6}" y="{y + 11}" text-anchor="end" class="tick">{_e(name)}</text>'
                 f'<rect x="{ml}" y="{y + 2}" width="{w:.1f}" height="{row - 4}" fill="{color}">'
                 f'<title>{_e(name)}: {v:.3f} {_e(unit)}</title></rect>'
                 f'<text x="{ml + w + 4:.1f}" y="{y + 11}" class="tick">{v:.2f} {_e(unit)}</text>')
    o.append("</svg>")
    return "".join(o)


def camera_plot(data: SessionData, *, width: int = 900, height: int = 680) -> str:
    """Top view (onto the floor plane) of the cameras: initial, result, reference."""
    sets: list[tuple[str, Mapping[str, Pose], str, str]] = []
    if data.reference:
        sets.append(("reference", {n: e.pose for n, e in data.reference.items()}, "#2ca02c", "4 3"))
    if data.initial:
        sets.append(("initial", {n: e.pose for n, e in data.initial.items()}, "#999999", "2 2"))
    final = data.final_poses()
    if final:
        sets.append(("result", final, "#1f77b4", ""))
    if not sets:
        return ""
    main = final or sets[0][1]
    # The result's frame decides the floor; the reference is drawn aligned onto it when
    # it lives in another frame (rigid alignment, as the accuracy figures do).
    if data.reference and final and len(set(final) & set(data.reference)) >= MIN_CAMERAS:
        sets[0] = ("reference (aligned)", _align_to(sets[0][1], final), "#2ca02c", "4 3")
    B = floor_frame(main.values(), data.floor)
    allpts = np.array([p.t for _, poses, _, _ in sets for p in poses.values()])
    spread = float(np.ptp(allpts @ B.T, axis=0).max()) if len(allpts) > 1 else 1.0
    depth = min(max(0.035 * spread, 0.15), 1.0)
    wedges = {(label, n): wedge(p, data.intrinsics.get(n), depth) @ B.T
              for label, poses, _, _ in sets for n, p in poses.items()}
    xy = np.vstack(list(wedges.values()))
    lo, hi = xy.min(0), xy.max(0)
    span = max(hi - lo) or 1.0
    pad = 0.06 * span + 0.3
    lo, hi = lo - pad, hi + pad
    s = min((width - 20) / (hi[0] - lo[0]), (height - 50) / (hi[1] - lo[1]))

    def P(v) -> tuple[float, float]:
        return 10 + (v[0] - lo[0]) * s, 30 + (hi[1] - v[1]) * s  # y up

    o = [f'<svg class="chart" id="camera-plot" viewBox="0 0 {width} {height}" width="{width}" height="{height}" '
         'xmlns="http://www.w3.org/2000/svg" role="img" aria-label="camera positions, top view">',
         '<text x="10" y="16" class="ctitle">Cameras, top view onto the floor plane</text>']
    # scale bar
    bar = 10 ** math.floor(math.log10(span / 4))
    x0, y0 = P((lo[0] + pad / 2, lo[1] + pad / 3))
    o.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x0 + bar * s:.1f}" y2="{y0:.1f}" stroke="#333" stroke-width="2"/>'
             f'<text x="{x0 + bar * s / 2:.1f}" y="{y0 - 4:.1f}" text-anchor="middle" class="tick">{bar:g} m</text>')
    if data.initial and final:
        for n, p in final.items():
            if n in data.initial:
                a, b = P(data.initial[n].pose.t @ B.T), P(p.t @ B.T)
                o.append(f'<line x1="{a[0]:.1f}" y1="{a[1]:.1f}" x2="{b[0]:.1f}" y2="{b[1]:.1f}" '
                         'stroke="#bbb" stroke-width="1"/>')
    for label, poses, color, dash in sets:
        o.append(f'<g class="camset" data-set="{_e(label)}">')
        for n, p in sorted(poses.items(), key=lambda kv: natural_key(kv[0])):
            w = wedges[(label, n)]
            c = P(w[0])
            hull = _hull([P(v) for v in w])
            poly = " ".join(f"{x:.1f},{y:.1f}" for x, y in hull)
            axis = P(w[1:].mean(0))
            d = f' stroke-dasharray="{dash}"' if dash else ""
            pos = ", ".join(f"{v:.3f}" for v in p.t)
            o.append(f'<g class="cam" data-camera="{_e(n)}"><title>{_e(n)} ({_e(label)}): centre [{pos}] m</title>'
                     f'<polygon points="{poly}" fill="{color}" fill-opacity="0.10" stroke="{color}" stroke-width="1"{d}/>'
                     f'<line x1="{c[0]:.1f}" y1="{c[1]:.1f}" x2="{axis[0]:.1f}" y2="{axis[1]:.1f}" stroke="{color}" '
                     f'stroke-width="1.2"{d}/>'
                     f'<circle cx="{c[0]:.1f}" cy="{c[1]:.1f}" r="3.2" fill="{color if label == "result" else "white"}" '
                     f'stroke="{color}" stroke-width="1.4"/>')
            if label == "result" or len(sets) == 1:
                o.append(f'<text x="{c[0] + 5:.1f}" y="{c[1] - 5:.1f}" class="label">{_e(n)}</text>')
            o.append("</g>")
        o.append("</g>")
    ly = height - 12
    lx = 10
    for label, _, color, dash in sets:
        d = f' stroke-dasharray="{dash}"' if dash else ""
        o.append(f'<line x1="{lx}" x2="{lx + 18}" y1="{ly - 4}" y2="{ly - 4}" stroke="{color}" stroke-width="2.5"{d}/>'
                 f'<text x="{lx + 22}" y="{ly}" class="legend">{_e(label)}</text>')
        lx += 40 + 7 * len(label)
    o.append("</svg>")
    return "".join(o)


def _hull(pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Convex hull, counter-clockwise (Andrew's monotone chain)."""
    pts = sorted(set(pts))
    if len(pts) < 3:
        return pts

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    upper: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _align_to(src: Mapping[str, Pose], dst: Mapping[str, Pose]) -> dict[str, Pose]:
    """src moved rigidly onto dst (aligned on the shared cameras as the accuracy figures are)."""
    names = sorted(set(src) & set(dst), key=natural_key)
    _, R, t = align_poses(src, dst, names, with_scale=False)
    return {n: Pose(R @ p.R, R @ p.t + t) for n, p in src.items()}


# ------------------------------------------------------------------ HTML


_CSS = """
body{font:14px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;color:#222;margin:0;background:#f6f7f9}
main{max-width:1380px;margin:0 auto;padding:18px 24px 40px}
h1{font-size:22px;margin:4px 0 2px}h2{font-size:17px;margin:26px 0 8px;border-bottom:1px solid #ddd;padding-bottom:3px}
.muted{color:#777;fill:#777}.grid2{display:flex;flex-wrap:wrap;gap:14px}
.card{background:#fff;border:1px solid #e2e4e8;border-radius:6px;padding:10px 12px}
.kpis{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}.kpi{background:#fff;border:1px solid #e2e4e8;border-radius:6px;padding:8px 14px;min-width:120px}
.kpi b{display:block;font-size:20px}.kpi span{color:#666;font-size:12px}
.ok{color:#197a35}.bad{color:#b3261e}.warn{background:#fff6e0;border:1px solid #f0d48a;padding:6px 10px;border-radius:6px;margin:6px 0}
table{border-collapse:collapse;background:#fff;font-variant-numeric:tabular-nums}
th,td{border:1px solid #e2e4e8;padding:3px 8px;text-align:right}th{background:#f0f2f5}td:first-child,th:first-child{text-align:left}
svg.chart{background:#fff;border:1px solid #e2e4e8;border-radius:6px}
svg .ctitle{font-weight:600;font-size:13px}svg .tick{font-size:10.5px;fill:#555}svg .axis{font-size:11.5px;fill:#333}
svg .legend{font-size:11.5px;fill:#333}svg .label{font-size:10px;fill:#1f4f7a}svg .plotbg{fill:#fcfcfd;stroke:#ddd}
svg .grid{stroke:#eceef1}code{background:#eef0f3;padding:0 4px;border-radius:3px}
"""


def _kpi(value: str, label: str, cls: str = "") -> str:
    return f'<div class="kpi"><b class="{cls}">{_e(value)}</b><span>{_e(label)}</span></div>'


def render_html(data: SessionData, *, title: str | None = None) -> str:
    """The report as one HTML document (no scripts, no external resources)."""
    title = title or f"Calibration report: {data.title}"
    cyc = data.cycles
    last = cyc[-1] if cyc else None
    final = data.final_poses()
    names = data.camera_names
    acc = None
    if data.reference and final and len(set(final) & set(data.reference)) >= MIN_CAMERAS:
        try:
            acc = evaluate(final, {n: e.pose for n, e in data.reference.items()})
        except ValueError as e:
            data.warnings.append(f"accuracy vs reference not computed: {e}")
    std_t = {n: e.std_translation for n, e in (data.result or {}).items() if e.std_translation is not None}
    std_r = {n: e.std_rotation for n, e in (data.result or {}).items() if e.std_rotation is not None}
    conv: dict[str, bool] = {}
    obs: dict[str, int] = {}
    for rec in (last, data.final_state):  # the later source wins
        if rec is not None:
            std_t = {**rec.std_translation, **std_t} if rec is last else {**std_t, **rec.std_translation}
            std_r = {**rec.std_rotation, **std_r} if rec is last else {**std_r, **rec.std_rotation}
            conv.update(rec.converged)
            obs.update(rec.observations)

    h: list[str] = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>{_e(title)}</h1>",
        f'<div class="muted">source <code>{_e(data.source)}</code> · written '
        f'{datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")} by extrcal report</div>',
    ]
    for w in data.warnings:
        h.append(f'<div class="warn">{_e(w)}</div>')

    # --- summary
    k = [_kpi(str(len(names)), "cameras")]
    if last:
        k.append(_kpi(str(last.cycle), "cycles"))
        if last.data_time is not None and cyc[0].data_time is not None:
            k.append(_kpi(f"{last.data_time - cyc[0].data_time:.0f} s", "data time from first to last cycle"))
    if conv:
        nconv = sum(conv.values())
        k.append(_kpi(f"{nconv}/{len(conv)}", "cameras converged", "ok" if nconv == len(conv) else "bad"))
    if std_t:
        k.append(_kpi(f"{np.mean(list(std_t.values())) * 100:.1f} cm", "mean std translation"))
    if std_r:
        k.append(_kpi(f"{np.mean(list(std_r.values())):.2f}°", "mean std rotation"))
    if acc:
        k.append(_kpi(f"{acc.position.mean * 100:.1f} cm", "position error vs reference (rigid)"))
        k.append(_kpi(f"{acc.orientation.mean:.2f}°", "orientation error vs reference"))
        k.append(_kpi(f"{acc.shape_position.mean * 100:.1f} cm", "shape error (similarity)"))
    if last and last.reprojection_px is not None:
        k.append(_kpi(f"{last.reprojection_px:.2f} px", "reprojection error, last cycle (median)"))
    h.append('<div class="kpis">' + "".join(k) + "</div>")
    settings = {kk: v for kk, v in data.meta.items() if kk not in ("files",) and not isinstance(v, (dict, list))}
    for kk in ("stop", "config_overrides", "sources"):
        if isinstance(data.meta.get(kk), dict) and data.meta[kk]:
            settings[kk] = json.dumps(data.meta[kk])
    scale = data.meta.get("scale")
    if isinstance(scale, dict) and scale.get("summary"):  # the initial estimate's scale against the people's
        settings["scale check"] = scale["summary"]
    for kk in ("created_wall", "ended_wall", "first_data"):
        if isinstance(settings.get(kk), (int, float)):
            settings[kk] = datetime.fromtimestamp(settings[kk], timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    if settings:
        h.append("<details open><summary>session</summary><table id=\"session\">" + "".join(
            f"<tr><td>{_e(kk)}</td><td>{_e(v)}</td></tr>" for kk, v in settings.items()) + "</table></details>")
    if data.config:
        rows = [(f"{sec}.{kk}", v) for sec, vals in data.config.items() if isinstance(vals, dict)
                for kk, v in vals.items()]
        h.append("<details><summary>engine configuration</summary><table>" + "".join(
            f"<tr><td>{_e(kk)}</td><td>{_e(v)}</td></tr>" for kk, v in rows) + "</table></details>")

    # --- camera plot
    h.append("<h2>Cameras</h2>")
    h.append(f'<div class="grid2">{camera_plot(data)}</div>')

    # --- convergence
    if cyc:
        h.append("<h2>Convergence</h2><div class=\"grid2\">")
        x = [c.cycle for c in cyc]
        xl = "cycle"
        ch = [Series("max translation change (m)", x, [c.change_translation for c in cyc], _PALETTE[0]),
              Series("max rotation change (°)", x, [c.change_rotation for c in cyc], _PALETTE[1])]
        if any(v is None for v in ch[0].y) and any(c.poses for c in cyc):
            # No change in the lines: compute it from consecutive poses.
            dt, dr = _pose_changes(cyc)
            ch = [Series("max translation change (m)", x, dt, _PALETTE[0]),
                  Series("max rotation change (°)", x, dr, _PALETTE[1])]
        h.append(line_chart(ch, title="Pose change per cycle", xlabel=xl, ylabel="m / °", log=True))
        cams = sorted({n for c in cyc for n in c.std_translation}, key=natural_key)
        thin = [Series(n, x, [c.std_translation.get(n) for c in cyc], "#9cb8d6", 0.8, legend=False) for n in cams]
        mean = [float(np.mean(list(c.std_translation.values()))) if c.std_translation else None for c in cyc]
        h.append(line_chart(thin + [Series("mean std translation (m)", x, mean, _PALETTE[0], 2.2)],
                            title="Std of the camera positions (each camera, mean bold)", xlabel=xl, ylabel="m", log=True))
        thin = [Series(n, x, [c.std_rotation.get(n) for c in cyc], "#e3a3a3", 0.8, legend=False) for n in cams]
        mean = [float(np.mean(list(c.std_rotation.values()))) if c.std_rotation else None for c in cyc]
        h.append(line_chart(thin + [Series("mean std rotation (°)", x, mean, _PALETTE[1], 2.2)],
                            title="Std of the camera orientations (each camera, mean bold)", xlabel=xl, ylabel="°", log=True))
        if any(c.error_position is not None for c in cyc):
            h.append(line_chart(
                [Series("position error, rigid (m)", x, [c.error_position for c in cyc], _PALETTE[0]),
                 Series("shape error, similarity (m)", x, [c.error_shape_position for c in cyc], _PALETTE[2], dash="5 3"),
                 Series("orientation error (°)", x, [c.error_orientation for c in cyc], _PALETTE[1])],
                title="Error vs reference (mean over cameras)", xlabel=xl, ylabel="m / °", log=True,
                hline=(0.053, "paper: 0.053 m")))
        if any(c.reprojection_px is not None for c in cyc):
            h.append(line_chart([Series("median reprojection error (px)", x, [c.reprojection_px for c in cyc], _PALETTE[3])],
                                title="Reprojection error per cycle", xlabel=xl, ylabel="px"))
        if any(c.hypotheses is not None for c in cyc):
            h.append(line_chart([Series("hypotheses in the cycle", x, [c.hypotheses for c in cyc], _PALETTE[4])],
                                title="Hypotheses per cycle", xlabel=xl, ylabel="count"))
        h.append("</div>")

    # --- per camera
    h.append("<h2>Per camera</h2>")
    cols = ["camera", "x m", "y m", "z m", "std t cm", "std r °"]
    if obs:
        cols.append("observations")
    if conv:
        cols.append("converged")
    if data.initial and final:
        cols += ["moved from initial m", "rotated °"]
    if acc:
        cols += ["position err cm", "orientation err °", "shape err cm"]
    if data.reprojection_per_camera:
        cols.append("reproj px")
    rows = []
    for n in names:
        p = final.get(n)
        r = [_e(n)]
        r += [f"{p.t[i]:.3f}" if p else "–" for i in range(3)]
        r += [_fmt(std_t[n] * 100, 2) if n in std_t else "–", _fmt(std_r.get(n), 3)]
        if obs:
            r.append(str(obs.get(n, "–")))
        if conv:
            r.append('<span class="ok">yes</span>' if conv.get(n) else '<span class="bad">no</span>')
        if data.initial and final:
            if p and n in data.initial:
                ip = data.initial[n].pose
                r += [_fmt(float(np.linalg.norm(p.t - ip.t)), 3), _fmt(rotation_angle_deg(ip.R, p.R), 2)]
            else:
                r += ["–", "–"]
        if acc:
            pc = acc.per_camera.get(n)
            r += [_fmt(pc[0] * 100, 2), _fmt(pc[1], 3), _fmt(pc[2] * 100, 2)] if pc else ["–"] * 3
        if data.reprojection_per_camera:
            r.append(_fmt(data.reprojection_per_camera.get(n), 2))
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>")
    h.append('<table id="cameras"><thead><tr>' + "".join(f"<th>{_e(c)}</th>" for c in cols)
             + "</tr></thead><tbody>" + "".join(rows) + "</tbody></table>")
    if acc:
        h.append(f'<p>Accuracy vs reference over {len(acc.cameras)} cameras: {_e(acc.summary())}. '
                 "Rigid figures align the centres with a rigid transform (the paper's protocol); shape "
                 "figures allow a scale, which the method keeps from the initial estimate.</p>")

    # --- reprojection
    h.append("<h2>Reprojection errors</h2>")
    if data.reprojection_per_camera or data.reprojection_per_group:
        h.append(f'<p class="muted">Median over keypoints, from {_e(data.reprojection_source)}.</p>')
        h.append('<div class="grid2">')
        if data.reprojection_per_camera:
            ordered = {n: data.reprojection_per_camera[n] for n in sorted(data.reprojection_per_camera, key=natural_key)}
            h.append(bar_chart(ordered, title="per camera", unit="px"))
        if data.reprojection_per_group:
            order = [g for g in JOINT_GROUPS if g in data.reprojection_per_group]
            order += sorted(set(data.reprojection_per_group) - set(order))
            h.append(bar_chart({g: data.reprojection_per_group[g] for g in order}, title="per joint group",
                               unit="px", color=_PALETTE[3]))
            h.append('<table id="joint-groups"><thead><tr><th>joint group</th><th>px</th></tr></thead><tbody>'
                     + "".join(f"<tr><td>{_e(g)}</td><td>{_fmt(data.reprojection_per_group[g], 2)}</td></tr>"
                               for g in order) + "</tbody></table>")
        h.append("</div>")
    else:
        h.append('<p class="muted">The session recorded no per-camera or per-joint-group reprojection '
                 "errors; give the session's recording (<code>--recording</code>) to compute them.</p>")
    h.append("</main></body></html>\n")
    return "\n".join(h)


def _pose_changes(cyc: Sequence[CycleRecord]) -> tuple[list[float | None], list[float | None]]:
    dt: list[float | None] = [None]
    dr: list[float | None] = [None]
    for a, b in zip(cyc, cyc[1:]):
        common = set(a.poses) & set(b.poses)
        if not common:
            dt.append(None)
            dr.append(None)
            continue
        dt.append(max(float(np.linalg.norm(a.poses[n].t - b.poses[n].t)) for n in common))
        dr.append(max(rotation_angle_deg(a.poses[n].R, b.poses[n].R) for n in common))
    return dt, dr


__all__ = ["JOINT_GROUPS", "CycleRecord", "ReportError", "SessionData", "bar_chart", "camera_plot",
           "floor_frame", "line_chart", "load_session", "render_html", "wedge", "CameraFileError"]
