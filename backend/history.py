"""Versioned calibrations: every accepted calibration is kept, one can be made active.

Layout under ``<state_dir>/calibrations/``::

    <v>.yaml             the FORMATS.md extrinsics (with std), as the session wrote them
    <v>.intrinsics.yaml  the intrinsics it was made with (for the export formats)
    <v>.json             metadata (version, created, by, session, reason, accuracy, ...)
                         and the calibration document of GET /calibration
    active.json          {"version": v}: the active version, survives restarts

A version is immutable. Rolling back records a *new* version, a copy of the old one
(``source_version``), so the history says who changed the active calibration, when and why.
Every file is written atomically; ``<v>.json`` is written last and makes the version exist.
"""

from __future__ import annotations

import json
import logging
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from .cameras import write_atomic
from .session import NotAvailable, clean_json

log = logging.getLogger(__name__)


class VersionNotFound(NotAvailable):
    """No calibration version with that number (404)."""


class CalibrationHistory:
    """The versions on disk, with the index and the active document kept in memory.

    Thread-safe: the service writes versions in threads and reads them on its loop."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self._lock = threading.Lock()
        self._meta: dict[int, dict[str, Any]] = {}
        self._active: int | None = None
        self._active_doc: dict[str, Any] | None = None
        self._load()

    def _load(self) -> None:
        if not self.root.is_dir():
            return
        for p in self.root.glob("*.json"):
            if not p.stem.isdigit():
                continue
            try:
                d = json.loads(p.read_text())
                meta = {k: v for k, v in d.items() if k != "calibration"}
                if int(meta["version"]) != int(p.stem) or not isinstance(d.get("calibration"), dict):
                    raise ValueError("version number or calibration missing")
            except (OSError, ValueError, KeyError, TypeError) as e:  # a broken file must not stop the service
                log.error("calibration version %s is unreadable and skipped: %s", p, e)
                continue
            self._meta[int(p.stem)] = meta
        try:
            active = json.loads((self.root / "active.json").read_text())["version"]
        except FileNotFoundError:
            active = None
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("%s is unreadable: %s; no calibration version is active", self.root / "active.json", e)
            active = None
        if active is not None and int(active) in self._meta:
            self._active = int(active)
            self._active_doc = self._doc(self._active)
        elif active is not None:
            log.error("the active calibration version %s does not exist; none is active", active)

    # ------------------------------------------------------------ reads

    @property
    def active(self) -> int | None:
        return self._active

    def active_doc(self) -> dict[str, Any] | None:
        """The active version's calibration document (cached), or None."""
        return self._active_doc

    def list(self) -> list[dict[str, Any]]:
        """Metadata of every version, newest first, with ``active``."""
        with self._lock:
            return [{**m, "active": v == self._active} for v, m in sorted(self._meta.items(), reverse=True)]

    def meta(self, v: int) -> dict[str, Any]:
        with self._lock:
            if v not in self._meta:
                raise VersionNotFound(f"no calibration version {v}" + (
                    f" (there are 1..{max(self._meta)})" if self._meta else " (none recorded yet)"))
            return {**self._meta[v], "active": v == self._active}

    def doc(self, v: int) -> dict[str, Any]:
        """The calibration document of version ``v`` (the JSON of GET /calibration, with ``version``)."""
        self.meta(v)
        return self._doc(v)

    def _doc(self, v: int) -> dict[str, Any]:
        d = json.loads((self.root / f"{v}.json").read_text())
        m = self._meta[v]
        return {**d["calibration"], "version": v, "source_version": m.get("source_version")}

    def yaml(self, v: int) -> str:
        self.meta(v)
        return (self.root / f"{v}.yaml").read_text()

    def intrinsics(self, v: int) -> str:
        self.meta(v)
        return (self.root / f"{v}.intrinsics.yaml").read_text()

    # ------------------------------------------------------------ writes

    def record(self, doc: dict[str, Any], yaml_text: str, intrinsics_text: str, *, by: str, reason: str,
               activate: bool, source_version: int | None = None) -> dict[str, Any]:
        """A new version from a calibration document and its files; returns its metadata."""
        doc = {k: v for k, v in doc.items() if k not in ("version", "source_version")}
        with self._lock:
            v = max(self._meta, default=0) + 1
            meta = clean_json({
                "version": v,
                "created": datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
                "by": by, "reason": reason, "session": doc.get("session"), "source_version": source_version,
                "cycle": doc.get("cycle"), "converged": doc.get("converged"), "accuracy": doc.get("accuracy"),
                "cameras": len(doc.get("cameras", {})),
            })
            write_atomic(self.root / f"{v}.yaml", yaml_text)
            write_atomic(self.root / f"{v}.intrinsics.yaml", intrinsics_text)
            write_atomic(self.root / f"{v}.json", json.dumps({**meta, "calibration": doc}, indent=1))
            self._meta[v] = meta
            if activate:
                write_atomic(self.root / "active.json", json.dumps({"version": v}))
                self._active = v
                self._active_doc = self._doc(v)
            return {**meta, "active": activate}

    def activate(self, v: int, *, reason: str | None) -> dict[str, Any]:
        """Make version ``v`` active again: recorded as a new version, a copy of ``v``."""
        self.meta(v)  # 404
        with self._lock:
            doc = json.loads((self.root / f"{v}.json").read_text())["calibration"]
            current = self._active
        by = "rollback" if current is not None and v < current else "api"
        why = reason or (f"rollback from version {current} to version {v}" if by == "rollback"
                         else f"version {v} activated")
        return self.record(doc, self.yaml(v), self.intrinsics(v), by=by, reason=why, activate=True,
                           source_version=v)
