"""Calibration sessions: lifecycle, persistence in the state directory, resume.

A session is one calibration run: a camera set (intrinsics + initial estimate, and an
optional reference to measure against), an engine config and stop criteria. Its life:

    waiting_for_data ─► calibrating ⇄ converged ─► stopped | failed

- ``waiting_for_data``: created; no cycle has been solved yet (no sensors, too few
  framesets or hypotheses so far; ``reason`` says which).
- ``calibrating``: cycles run; not every calibrated camera is converged.
- ``converged``: every camera that took part in a cycle is converged (see
  ``converged_description``). The session keeps refining (a camera may fall back to
  calibrating if new data moves it) unless its stop criteria include ``converged``.
- ``stopped``: ended by a request or a stop criterion (``reason``); the result is final.
- ``failed``: could not go on (``reason``); the last good result is kept.

On disk, one directory per session under ``<state_dir>/sessions/<id>/``::

    session.json    the record below (state, reason, stop criteria, progress)
    config.json     the effective EngineConfig
    intrinsics.yaml initial.yaml [reference.yaml]   the camera files as given
    result.yaml     the current calibration, FORMATS.md extrinsics with std
    state.json      the current CalibrationState (per-camera detail, counters)
    snapshot.json   the pipeline snapshot to resume from
    history.jsonl   one line per cycle

Every file but the history is replaced atomically (``write_atomic``). The history is
append-only, one ``write`` per line; a line torn by a crash is dropped when read, and
on resume the lines after the snapshot's cycle are cut so history and estimate agree.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

import numpy as np

from .cameras import (
    CameraFileError, CameraSet, Extrinsics, Pose, natural_key, parse_extrinsics, parse_intrinsics, write_atomic,
)
from .config import EngineConfig

# 20261121T181223.123-ab12; ids of older versions have no milliseconds and still sort first
SESSION_ID = re.compile(r"^[0-9]{8}T[0-9]{6}(?:\.[0-9]{3})?-[0-9a-f]{4}$")


class SessionState(str, Enum):
    waiting_for_data = "waiting_for_data"
    calibrating = "calibrating"
    converged = "converged"
    stopped = "stopped"
    failed = "failed"

    @property
    def active(self) -> bool:
        return self in (SessionState.waiting_for_data, SessionState.calibrating, SessionState.converged)


# ------------------------------------------------------------------ domain errors


class SessionError(Exception):
    """Base of the errors the API maps to 4xx (backend/api/errors.py)."""


class SessionConflict(SessionError):
    """Another session is running (409)."""


class SessionNotFound(SessionError):
    """No session with that id (404)."""


class SessionInputError(SessionError):
    """The request cannot make a session: camera files, config, names (422)."""


class NotAvailable(SessionError):
    """The thing exists but has nothing to show yet, e.g. no calibration (404)."""


# ------------------------------------------------------------------ criteria and record


class StopCriteria(BaseModel):
    """When a session ends by itself; any criterion that is met ends it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    duration: float | None = Field(
        None, gt=0, description="s on the service clock since the session's first accepted message")
    converged: bool = Field(False, description="stop as soon as the session is converged")
    max_cycles: int | None = Field(None, ge=1, description="stop after this many optimisation cycles")


@dataclass
class SessionRecord:
    """What session.json holds. Times: ``*_wall`` host epoch seconds, ``*_data`` service clock."""

    id: str
    name: str | None
    state: SessionState
    reason: str
    stop: StopCriteria
    config_overrides: dict[str, Any]
    sources: dict[str, str]  # intrinsics/initial/reference → "upload" or "file:<name>"
    seed: int = 0
    created_wall: float = field(default_factory=time.time)
    ended_wall: float | None = None
    first_data: float | None = None  # service clock at the first accepted message
    cycles: int = 0
    converged_cycle: int | None = None  # first cycle at which the session was converged
    stopped_by: str | None = None  # request | duration | converged | max_cycles
    resumed: int = 0  # times it was resumed after a restart
    accuracy: dict[str, Any] | None = None  # latest figures against the reference
    final_batch: dict[str, Any] | None = None  # what the final batch adjustment did
    # a session that bootstraps its start from the people (backend/live_bootstrap.py): its
    # options, phase and, once done, the bootstrap's metadata (frame, scale, cameras placed)
    bootstrap: dict[str, Any] | None = None
    # a session with an initial estimate: the walkers' heights if known, and at the end the
    # check of the initial estimate's scale against the people's (backend/scale_check.py)
    scale: dict[str, Any] | None = None
    # a session with an initial estimate: the live check of it against the data's shape
    # (bootstrap.live_check): phase, data_seconds, used, the reconciliation, a note
    initial_check: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id, "name": self.name, "state": self.state.value, "reason": self.reason,
            "stop": self.stop.model_dump(), "config_overrides": self.config_overrides,
            "sources": self.sources, "seed": self.seed, "created_wall": self.created_wall,
            "ended_wall": self.ended_wall, "first_data": self.first_data, "cycles": self.cycles,
            "converged_cycle": self.converged_cycle, "stopped_by": self.stopped_by,
            "resumed": self.resumed, "accuracy": self.accuracy, "final_batch": self.final_batch,
            "bootstrap": self.bootstrap, "scale": self.scale, "initial_check": self.initial_check,
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "SessionRecord":
        return SessionRecord(
            id=d["id"], name=d.get("name"), state=SessionState(d["state"]), reason=d.get("reason", ""),
            stop=StopCriteria.model_validate(d.get("stop") or {}),
            config_overrides=d.get("config_overrides") or {}, sources=d.get("sources") or {},
            seed=int(d.get("seed", 0)), created_wall=float(d.get("created_wall", 0.0)),
            ended_wall=d.get("ended_wall"), first_data=d.get("first_data"), cycles=int(d.get("cycles", 0)),
            converged_cycle=d.get("converged_cycle"), stopped_by=d.get("stopped_by"),
            resumed=int(d.get("resumed", 0)), accuracy=d.get("accuracy"), final_batch=d.get("final_batch"),
            bootstrap=d.get("bootstrap"), scale=d.get("scale"), initial_check=d.get("initial_check"),
        )


def new_session_id() -> str:
    """Sortable by creation time, readable, unique enough for one host.

    Milliseconds, because two sessions made in one second (a stop and a start from a
    script) must still sort in the order they were made: the list and the reports read
    "newest" from it.
    """
    ns = time.time_ns()
    sec, ms = divmod(ns // 1_000_000, 1000)
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime(sec)) + f".{ms:03d}-" + secrets.token_hex(2)


# ------------------------------------------------------------------ the camera files of a session


@dataclass(frozen=True)
class SessionInputs:
    """Validated inputs of a session: texts as given and what they parse to.

    Without an initial estimate (``initial_yaml`` None: the session bootstraps, see
    backend/live_bootstrap.py) ``cameras`` holds the intrinsics with placeholder poses
    (identity, no std) that nothing may use as an estimate."""

    intrinsics_yaml: str
    initial_yaml: str | None
    reference_yaml: str | None
    cameras: CameraSet
    reference: dict[str, Pose] | None
    config: EngineConfig

    @staticmethod
    def parse(intrinsics_yaml: str, initial_yaml: str | None, reference_yaml: str | None, config: EngineConfig,
              sources: dict[str, str] | None = None, *, subset: bool = False) -> "SessionInputs":
        """Raises SessionInputError naming the file (as given), line and field. ``subset``:
        the initial estimate may hold fewer cameras than the intrinsics (a bootstrap's,
        which left some out): the session's cameras are its."""
        src = sources or {}
        try:
            intr = parse_intrinsics(intrinsics_yaml, _label(src, "intrinsics"))
            init = parse_extrinsics(initial_yaml, _label(src, "initial")) if initial_yaml is not None else {
                n: Extrinsics(Pose(np.eye(3), np.zeros(3)), i.resolution) for n, i in intr.items()}
            if subset:
                intr = {n: i for n, i in intr.items() if n in init}
            cams = CameraSet.combine(intr, init, _label(src, "intrinsics"), _label(src, "initial"))
            config = config.for_images(cams.sizes)
            ref = None
            if reference_yaml is not None:
                ref_e = parse_extrinsics(reference_yaml, _label(src, "reference"))
                ref = {k: v.pose for k, v in ref_e.items()}
                unknown = sorted(set(ref) - set(cams.names), key=natural_key)
                if unknown:
                    raise SessionInputError(
                        f"{_label(src, 'reference')}: cameras not in the camera set: {', '.join(unknown)}")
                if len(set(ref) & set(cams.names)) < 3:
                    raise SessionInputError(
                        f"{_label(src, 'reference')}: needs at least 3 of the session's cameras to compare")
        except CameraFileError as e:
            raise SessionInputError(str(e)) from None
        if len(cams.names) < 2:
            raise SessionInputError(f"{_label(src, 'initial')}: a calibration needs at least 2 cameras, got {len(cams.names)}")
        return SessionInputs(intrinsics_yaml, initial_yaml, reference_yaml, cams, ref, config)


def _label(sources: dict[str, str], what: str) -> str:
    s = sources.get(what, "upload")
    return f"{what}_yaml" if s == "upload" else s.removeprefix("file:")


# ------------------------------------------------------------------ the state directory


class SessionStore:
    """Sessions on disk. Blocking file I/O: the service calls it through a writer thread."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def dir(self, sid: str) -> Path:
        if not SESSION_ID.match(sid):
            raise SessionNotFound(f"no session {sid!r}")
        return self.root / sid

    def ids(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir() if SESSION_ID.match(p.name) and (p / "session.json").is_file())

    # -- writing
    def create(self, rec: SessionRecord, inputs: SessionInputs) -> None:
        d = self.dir(rec.id)
        d.mkdir(parents=True, exist_ok=False)
        write_atomic(d / "intrinsics.yaml", inputs.intrinsics_yaml)
        if inputs.initial_yaml is not None:
            write_atomic(d / "initial.yaml", inputs.initial_yaml)
        if inputs.reference_yaml is not None:
            write_atomic(d / "reference.yaml", inputs.reference_yaml)
        write_atomic(d / "config.json", json.dumps(inputs.config.model_dump(mode="json"), indent=1))
        self.save_record(rec)

    def save_record(self, rec: SessionRecord) -> None:
        write_atomic(self.dir(rec.id) / "session.json", _dumps(rec.to_dict(), indent=1))

    def save_result(self, sid: str, result_yaml: str, state: dict[str, Any]) -> None:
        d = self.dir(sid)
        write_atomic(d / "state.json", _dumps(state))
        write_atomic(d / "result.yaml", result_yaml)

    def save_start(self, sid: str, initial_yaml: str | None, config: EngineConfig) -> None:
        """The start a session's pipeline runs from once it was bootstrapped live: the
        effective config and (without an initial estimate) the bootstrap's cameras as the
        initial estimate: what a resume reads."""
        d = self.dir(sid)
        write_atomic(d / "config.json", json.dumps(config.model_dump(mode="json"), indent=1))
        if initial_yaml is not None:
            write_atomic(d / "initial.yaml", initial_yaml)

    def save_snapshot(self, sid: str, snapshot: dict[str, Any]) -> None:
        write_atomic(self.dir(sid) / "snapshot.json", _dumps(snapshot))

    def append_history(self, sid: str, lines: list[dict[str, Any]]) -> None:
        if not lines:
            return
        data = "".join(_dumps(x) + "\n" for x in lines).encode()
        fd = os.open(self.dir(sid) / "history.jsonl", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)

    def cut_history(self, sid: str, max_cycle: int) -> int:
        """Keep the lines up to ``max_cycle`` (and drop a torn tail); returns lines kept."""
        path = self.dir(sid) / "history.jsonl"
        lines = self.history(sid)
        keep = [x for x in lines if int(x.get("cycle", 0)) <= max_cycle]
        if len(keep) != len(lines) or (path.exists() and _has_torn_tail(path)):
            write_atomic(path, "".join(_dumps(x) + "\n" for x in keep))
        return len(keep)

    # -- reading
    def load_record(self, sid: str) -> SessionRecord:
        path = self.dir(sid) / "session.json"
        if not path.is_file():
            raise SessionNotFound(f"no session {sid!r}")
        try:
            return SessionRecord.from_dict(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError) as e:
            raise SessionInputError(f"{path}: unreadable session record: {e}") from None

    def load_inputs(self, rec: SessionRecord, base: EngineConfig | None = None) -> SessionInputs:
        d = self.dir(rec.id)
        try:
            cfg = EngineConfig.from_dict(json.loads((d / "config.json").read_text()), str(d / "config.json"))
        except (OSError, ValueError) as e:
            raise SessionInputError(f"{d / 'config.json'}: {e}") from None
        ref, init = d / "reference.yaml", d / "initial.yaml"
        try:  # no initial.yaml: a session bootstrapping without one (written when it is done)
            texts = [(d / "intrinsics.yaml").read_text(), init.read_text() if init.is_file() else None,
                     ref.read_text() if ref.is_file() else None]
        except OSError as e:
            raise SessionInputError(f"{d}: {e}") from None
        # a session bootstrapped live saved the cameras its bootstrap placed (and those that
        # joined later) as its start; the intrinsics keep every camera
        done = rec.bootstrap is not None and rec.bootstrap.get("phase") == "done"
        return SessionInputs.parse(*texts, cfg, {k: f"file:{d / (k + '.yaml')}" for k in ("intrinsics", "initial", "reference")},
                                   subset=done)

    def load_snapshot(self, sid: str) -> dict[str, Any] | None:
        path = self.dir(sid) / "snapshot.json"
        if not path.is_file():
            return None
        return json.loads(path.read_text())

    def load_state(self, sid: str) -> dict[str, Any] | None:
        path = self.dir(sid) / "state.json"
        if not path.is_file():
            return None
        try:
            return json.loads(path.read_text())
        except ValueError:
            return None

    def result_yaml(self, sid: str) -> str | None:
        path = self.dir(sid) / "result.yaml"
        return path.read_text() if path.is_file() else None

    def history(self, sid: str, since: int = 0) -> list[dict[str, Any]]:
        path = self.dir(sid) / "history.jsonl"
        if not path.is_file():
            return []
        out = []
        with open(path, "rb") as f:
            for raw in f:
                try:
                    x = json.loads(raw)
                except ValueError:
                    continue  # a line torn by a crash
                if isinstance(x, dict) and int(x.get("cycle", 0)) > since:
                    out.append(x)
        return out


def _has_torn_tail(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        if f.tell() == 0:
            return False
        f.seek(-1, os.SEEK_END)
        return f.read(1) != b"\n"


def _clean(x: Any) -> Any:
    """JSON has no NaN/inf: they become null."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def _dumps(x: Any, indent: int | None = None) -> str:
    return json.dumps(_clean(x), indent=indent, allow_nan=False)


dumps_json = _dumps
clean_json = _clean
