"""What the REST API asks of the service besides starting and stopping sessions (a part
of ``Service``): a session as JSON (the running one from memory, the others from the
state directory), its history and result in every export format, the calibration
versions (recorded, listed, activated, published on Zenoh), and /status."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .cameras import dump_extrinsics, parse_extrinsics, parse_intrinsics
from .live_bootstrap import result_comment
from .session import NotAvailable, SessionInputError, SessionRecord, clean_json, dumps_json

if TYPE_CHECKING:
    from .service import ActiveSession
    from .state import CalibrationState, CycleReport

log = logging.getLogger("extrcal.service")  # the service's: its messages keep their logger

STATUS_FRESH = 0.5  # s: a snapshot younger than this is served as it is (_status_loop refreshes it)
STATUS_ASKED = 5.0  # s after a /status request during which the snapshot is kept fresh
STATUS_WAIT = 0.03  # s the HTTP thread waits for a fresh status before it serves the snapshot


class UnknownFormat(Exception):
    """A result format nobody can write (400)."""


class ServiceApi:
    """``Service``'s methods behind the API's routers (backend/api/routers)."""

    def active_state(self) -> "CalibrationState | None":
        """The running session's current CalibrationState, or None."""
        return self.active.state if self.active is not None else None

    def session_dict(self, sid: str) -> dict[str, Any]:
        s = self.active
        if s is not None and s.record.id == sid:
            rec, state = s.record, s.state.to_dict()
            live = True
        else:
            rec = self.store.load_record(sid)
            state = self.store.load_state(sid)
            live = False
        d = rec.to_dict()
        d["live"] = live
        d["stopping"] = bool(live and s is not None and s.finishing)
        # the running session's files are not being written: its progress is at risk
        d["storage_error"] = self.writer.error if live else None
        d["solver_fault"] = s.solver_fault if live else None
        d["cameras"] = state["cameras"] if state else []
        d["counters"] = state.get("counters") if state else None
        d["last_cycle"] = state.get("last_cycle") if state else None
        d["data_time"] = state.get("data_time") if state else None
        d["converged"] = bool(state.get("converged")) if state else False
        return clean_json(d)

    async def _settled(self) -> None:
        """A session that has ended but whose files are still being written is awaited:
        whoever reads "stopped" or "failed" may fetch its result at once and must get the
        final one, not the cycle before it."""
        s = self.active
        if s is not None and not s.record.state.active and not s.done.is_set():
            await asyncio.shield(s.done.wait())

    async def session_view(self, sid: str) -> dict[str, Any]:
        """session_dict, with the files of a finished session read in a thread."""
        await self._settled()
        s = self.active
        if s is not None and s.record.id == sid:
            return self.session_dict(sid)
        return await asyncio.to_thread(self.session_dict, sid)

    async def list_sessions(self) -> list[dict[str, Any]]:
        await self._settled()
        s = self.active
        live = copy_record(s.record) if s is not None else None
        return await asyncio.to_thread(self._list_sessions, live)

    def _list_sessions(self, live: SessionRecord | None) -> list[dict[str, Any]]:
        out = []
        for sid in reversed(self.store.ids()):
            rec = live if live is not None and live.id == sid else None
            try:
                rec = rec or self.store.load_record(sid)
            except SessionInputError as e:
                out.append({"id": sid, "state": "failed", "reason": str(e)})
                continue
            out.append(clean_json({k: v for k, v in rec.to_dict().items()
                                   if k in ("id", "name", "state", "reason", "created_wall", "ended_wall", "cycles",
                                            "converged_cycle", "stopped_by", "resumed", "accuracy")}))
        return out

    async def history(self, sid: str, since: int = 0) -> list[dict[str, Any]]:
        def read() -> list[dict[str, Any]]:
            self.store.load_record(sid)  # 404
            return self.store.history(sid, since)

        return await asyncio.to_thread(read)

    def calibration_dict(self, s: ActiveSession) -> dict[str, Any]:
        return self._calibration_doc(s)()

    def _calibration_doc(self, s: ActiveSession) -> Callable[[], dict[str, Any]]:
        """What calibration_dict needs, captured now; the returned function builds the
        document anywhere (the state is frozen), e.g. in the writer thread."""
        state, res, site = s.state, s.resolutions, self.settings.site
        sid, state_name = s.record.id, s.record.state.value
        accuracy = dict(s.record.accuracy) if s.record.accuracy else None

        def build() -> dict[str, Any]:
            cams = {}
            for c in state.cameras:
                d = c.to_dict()
                d.pop("name")
                d["resolution"] = list(res[c.name])
                cams[c.name] = d
            return clean_json({
                "site": site, "session": sid, "state": state_name, "cycle": state.cycle,
                "data_time": state.data_time, "converged": state.converged, "accuracy": accuracy, "cameras": cams,
            })

        return build

    def _latest_finished(self) -> dict[str, Any] | None:
        for sid in reversed(self.store.ids()):
            try:
                return self._stored_calibration(sid)
            except NotAvailable:
                continue
        return None

    def _stored_calibration(self, sid: str) -> dict[str, Any]:
        rec = self.store.load_record(sid)
        state = self.store.load_state(sid)
        result = self.store.result_yaml(sid)
        if state is None or result is None:
            raise NotAvailable(f"session {sid} has no calibration yet")
        ext = parse_extrinsics(result, f"session {sid} result.yaml")
        cams = {}
        for c in state["cameras"]:
            d = dict(c)
            d.pop("name", None)
            d["resolution"] = list(ext[c["name"]].resolution)
            cams[c["name"]] = d
        return clean_json({
            "site": self.settings.site, "session": sid, "state": rec.state.value, "cycle": state.get("cycle"),
            "data_time": state.get("data_time"), "converged": state.get("converged"),
            "accuracy": rec.accuracy, "cameras": cams,
        })

    async def calibration_view(self, sid: str | None, fmt: str) -> tuple[str | bytes | dict, str]:
        """calibration(); a finished session's files are read in a thread."""
        s = self.active
        if s is not None and sid in (None, s.record.id):
            return self.calibration(sid, fmt)
        return await asyncio.to_thread(self.calibration, sid, fmt)

    def calibration(self, sid: str | None, fmt: str) -> tuple[str | bytes | dict, str]:
        """The calibration of session ``sid`` (None: the current or latest) in ``fmt``."""
        s = self.active
        if sid is None and s is None and self.versions.active is not None:
            return self.version_calibration(self.versions.active, fmt)
        if sid is None:
            if s is None:
                ids = self.store.ids()
                sid = next((i for i in reversed(ids) if self.store.result_yaml(i) is not None), None)
                if sid is None:
                    raise NotAvailable("no calibration yet: start a session (POST /sessions)")
            else:
                sid = s.record.id
        live = s is not None and s.record.id == sid
        if not live:
            self.store.load_record(sid)  # 404 for unknown ids
        if fmt == "json":
            return (self.calibration_dict(s) if live else self._stored_calibration(sid)), "application/json"
        if live:
            ext = s.state.extrinsics(s.resolutions)
            text = dump_extrinsics(ext, comment=result_header(s))
            intr_text = s.inputs.intrinsics_yaml
        else:
            text = self.store.result_yaml(sid)
            if text is None:
                raise NotAvailable(f"session {sid} has no calibration yet")
            ext = parse_extrinsics(text, f"session {sid} result.yaml")
            intr_text = (self.store.dir(sid) / "intrinsics.yaml").read_text()
        if fmt == "yaml":
            return text, "application/yaml"
        return _exported(ext, lambda: parse_intrinsics(intr_text, f"session {sid} intrinsics.yaml"), fmt)

    # ------------------------------------------------------------ calibration versions

    async def _record_version(self, s: ActiveSession) -> None:
        """A stopped session's result becomes a version; one that ran cycles becomes the
        active calibration (one stopped before its first cycle only holds the initial
        estimate: recorded, not activated). The publication follows the active version."""
        rec, state = s.record, s.state
        activate = state.cycle > 0
        why = f"session {rec.id} {rec.reason} after {state.cycle} cycles" + (
            "" if activate else " (no cycle ran: recorded, not activated)")
        await self._store_version(s, by=f"session {rec.id}", reason=why, activate=activate)
        active = self.versions.active_doc()
        if active is not None:
            self._publish_doc(active)
        else:
            self._publish_calibration(s)

    async def _store_version(self, s: ActiveSession, *, by: str, reason: str, activate: bool) -> dict[str, Any] | None:
        """The session's calibration as it is now, recorded as a version (its metadata);
        None when the history cannot be written (logged, shown as a storage error)."""
        rec, state = s.record, s.state
        doc = self.calibration_dict(s)
        text = dump_extrinsics(state.extrinsics(s.resolutions), comment=result_header(s))
        try:
            return await asyncio.to_thread(self.versions.record, doc, text, s.inputs.intrinsics_yaml, by=by,
                                           reason=reason, activate=activate)
        except OSError as e:
            log.error("could not record the calibration of session %s as a version: %s", rec.id, e)
            self.writer.error = self.writer.error or f"calibration history: {e}"
            return None

    async def _record_recalibration(self, s: ActiveSession, report: "CycleReport") -> None:
        """Cameras the monitor found moved are calibrated again: the running session's
        network as it is now becomes the active version (by the monitor, saying which
        camera moved and when), so the history has every accepted calibration, not only
        the sessions' ends. The publication keeps showing the session's live estimate."""
        rec = s.record
        flagged = {c.name: c.moved_at for c in s.state.cameras}
        why = "; ".join(f"{n} moved (flagged at {_utc(flagged.get(n))} of data time) and was calibrated again"
                        for n in report.recalibrated) + f" (session {rec.id}, cycle {report.cycle})"
        meta = await self._store_version(s, by="monitor", reason=why, activate=True)
        if meta is None:
            return
        log.info("session %s: %s; version %d", rec.id, why, meta["version"])
        self.events.publish("calibration", {"version": meta["version"], "by": "monitor", "reason": why,
                                            "session": rec.id})

    def _publish_doc(self, doc: dict[str, Any]) -> None:
        pub = self._publisher
        if pub is None:
            return

        def put() -> None:
            with contextlib.suppress(Exception):
                pub.put(dumps_json(doc).encode())

        self.writer.submit(put, storage=False)

    async def list_versions(self) -> list[dict[str, Any]]:
        return self.versions.list()

    async def version_view(self, v: int, fmt: str) -> tuple[str | bytes | dict, str]:
        return await asyncio.to_thread(self.version_calibration, v, fmt)

    def version_calibration(self, v: int, fmt: str) -> tuple[str | bytes | dict, str]:
        """Version ``v`` in ``fmt`` (json, yaml or an export format)."""
        if fmt == "json":
            return self.versions.doc(v), "application/json"
        text = self.versions.yaml(v)
        if fmt == "yaml":
            return text, "application/yaml"
        return _exported(parse_extrinsics(text, f"calibration version {v}"),
                         lambda: parse_intrinsics(self.versions.intrinsics(v), f"calibration version {v} intrinsics"), fmt)

    async def activate_version(self, v: int, reason: str | None) -> dict[str, Any]:
        """Make version ``v`` the active calibration (as a new version, a copy of it) and
        publish it. While a session runs, its live estimate stays what /calibration shows."""
        meta = await asyncio.to_thread(self.versions.activate, v, reason=reason)
        log.info("calibration version %s activated as version %s: %s", v, meta["version"], meta["reason"])
        self.events.publish("calibration", {"version": meta["version"], "source_version": v, "by": meta["by"]})
        doc = self.versions.active_doc()
        if doc is not None and self.active is None:
            self._publish_doc(doc)
        return meta

    def formats(self) -> list[str]:
        out = ["json", "yaml"]
        try:
            from . import export as exporter

            out += [f for f in exporter.FORMATS if f not in out]
        except ModuleNotFoundError:
            pass
        return out

    # ------------------------------------------------------------ status (API)

    def _sensor_limits(self) -> dict[str, float]:
        """The running session's frameset limits, for the per-sensor warnings."""
        s = self.active
        if s is None:
            return {}
        sync = s.pipeline.cfg.sync
        return {"max_offset": sync.max_std, "max_latency": sync.wait}

    def _sensors_with_clocks(self, now_wall: float) -> dict[str, Any]:
        """Per-sensor status plus the running session's clock offset estimate."""
        sensors = self.sensors.to_dict(now_wall, **self._sensor_limits())
        s = self.active
        if s is not None:
            for c in s.state.clocks:
                if c.sensor in sensors:
                    sensors[c.sensor]["time_offset"] = c.to_dict()
            for name, rep in s.pipeline.preprocess.confidence_report().items():  # a Collector's too
                if name in sensors:
                    warn = rep.pop("warning")
                    sensors[name]["keypoints"] = rep
                    if warn:
                        sensors[name]["warnings"] = [*sensors[name].get("warnings", []), warn]
        return sensors

    def status_brief(self) -> dict[str, Any]:
        self._fold_refused()
        s = self.active
        now_wall = time.time()
        sensors = self.sensors.to_dict(now_wall, **self._sensor_limits())
        return clean_json({
            "clock": self.clock.now(),
            "sensors_online": sum(1 for x in sensors.values() if x["online"]),
            "sensors_active": sum(1 for x in sensors.values() if x["rate"] > 0),
            "messages": self.messages,
            "session": None if s is None else {
                "id": s.record.id, "state": s.record.state.value, "reason": s.record.reason,
                "cycle": s.state.cycle, "converged": s.state.converged,
                "cameras_converged": sum(1 for c in s.state.cameras if c.converged),
                "cameras": len(s.state.cameras), "accuracy": s.record.accuracy,
            },
        })

    def status(self) -> dict[str, Any]:
        """The full status, computed now (on the service loop); also published as the
        snapshot that other threads may read."""
        with self.work.measure("status"):
            self._status_stale = False
            d = self._status()
        self._status_snapshot = d  # a new dict every time, never changed after: safe to share
        self._status_pub = d  # ... and the one served as it is while fresh (None after a change)
        return d

    async def status_view(self) -> dict[str, Any]:
        """/status from any loop. On the service loop: ``status()``. From the HTTP thread:
        a fresh status if the service loop computes one within ``STATUS_WAIT``, else the
        last published snapshot (``as_of`` says when it was made): under overload the
        service loop can be busy for longer than a status request may take."""
        loop = self._loop
        if loop is None or asyncio.get_running_loop() is loop:
            return self.status()
        self._status_asked = time.monotonic()
        pub = self._status_pub
        if pub is not None and time.time() - pub["as_of"] < STATUS_FRESH:
            return pub  # fresh enough: waiting for the loop (its GIL) is what makes /status slow
        snap = self._status_snapshot
        # a snapshot from before a session started or ended would contradict what the
        # operator was just told (POST /sessions): then the fresh one is waited for
        stale = self._status_stale
        if snap is not None and not stale and self.lag and self.lag[-1] > STATUS_WAIT:
            return snap  # the loop is busy now: asking it would only add to its work

        async def fresh() -> dict[str, Any]:
            return self.status()

        wrapped = asyncio.wrap_future(asyncio.run_coroutine_threadsafe(fresh(), loop))
        try:
            return await asyncio.wait_for(asyncio.shield(wrapped) if stale else wrapped, STATUS_WAIT)
        except TimeoutError:
            if stale:
                return await wrapped
            snap = self._status_snapshot
            if snap is None:  # none yet (the first second of the service): wait for it
                return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(fresh(), loop))
            return snap

    def _status(self) -> dict[str, Any]:
        self._fold_refused()
        s = self.active
        now_wall = time.time()
        lag = sorted(self.lag)
        counters = s.pipeline.counters() if s is not None else None
        from dataclasses import asdict

        def stats(x: deque) -> dict[str, float] | None:
            if not x:
                return None
            a = np.asarray(x)
            return {"last": float(a[-1]), "mean": float(a.mean()), "p95": float(np.percentile(a, 95)), "max": float(a.max())}

        assert self.handoff is not None
        return clean_json({
            "as_of": now_wall,
            "site": self.settings.site,
            "uptime": now_wall - self.started_wall,
            "clock": self.clock.to_dict(),
            "zenoh": {"mode": self.settings.zenoh.mode, "listen": list(self.settings.zenoh.listen),
                      "connect": list(self.settings.zenoh.connect), **self.links,
                      "last_message_ago": None if self._last_arrival is None else max(now_wall - self._last_arrival, 0.0)},
            "sensors": self._sensors_with_clocks(now_wall),
            "messages": {
                "received": self.messages,
                "rejected": dict(self.rejected),
                "rejected_unattributed": dict(self.sensors.unattributed),
                "ignored": dict(self.ignored),
            },
            "framesets": None if counters is None else {
                "accepted": counters.framesets, "rejected": counters.framesets_rejected,
            },
            "pipeline": None if counters is None else asdict(counters),
            "queues": {
                "ingest": {"length": len(self.handoff), "capacity": self.handoff.capacity,
                           "received": self.handoff.received, "dropped": self.handoff.dropped,
                           "refused_by_key": self.handoff.refused, "wakeups": self.handoff.wakeups},
                "hypotheses": None if counters is None else {"length": counters.queue_length, "dropped": counters.queue_dropped},
                "writer": len(self.writer),
                "event_subscribers": self.events.subscribers,
            },
            "cycles": {
                "count": None if s is None else s.state.cycle,
                "rejected": None if counters is None else counters.cycles_rejected,
                "wall_seconds": stats(self.cycle_wall), "solve_seconds": stats(self.cycle_solve),
                "solver_busy": self.solver.busy, "solver_restarts": self.solver.restarts,
                "solver_faults": self.solver_faults, "solver_fault": None if s is None else s.solver_fault,
            },
            "frameset_delay": stats(self.frameset_delay),
            "loop_lag": {"max": self.lag_max, "p99": lag[int(0.99 * (len(lag) - 1))] if lag else None},
            "loop_work": self.work.to_dict(),
            "storage": {"state_dir": str(self.settings.state_dir), "error": self.writer.error,
                        "errors": self.writer.errors},
            "session": None if s is None else {"id": s.record.id, "state": s.record.state.value,
                                               "reason": s.record.reason},
        })


def copy_record(rec: SessionRecord) -> SessionRecord:
    return SessionRecord.from_dict(rec.to_dict())


def _utc(stamp: float | None) -> str:
    return "an unknown time" if stamp is None else \
        datetime.fromtimestamp(stamp, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def result_header(s: ActiveSession) -> str:
    """A result's header: the session and cycle; for a bootstrapped session where its
    frame and scale come from (backend/live_bootstrap.py); what the stated std holds, which
    the running pipeline says (its first adjustment adds the lenses' accuracy, long before
    a final batch)."""
    rec, state = s.record, s.state
    head = f"extrcal session {rec.id}, cycle {state.cycle}, {rec.state.value}"
    levelled, lenses = ((rec.final_batch or {}).get(k) for k in ("levelled", "lenses"))
    std = s.pipeline.std_note()
    extra = "\n".join(x for x in (result_comment(rec.bootstrap), levelled and levelled["summary"],
                                   lenses and lenses["summary"], std) if x)
    return f"{head}\n{extra}" if extra else head


def _exported(ext: dict, intrinsics: Callable[[], dict], fmt: str) -> tuple[str | bytes, str]:
    """A calibration in an export format (backend/export.py): (content, media type);
    ``intrinsics`` is read only for a format this build can write."""
    try:
        from . import export as exporter
    except ModuleNotFoundError:
        raise UnknownFormat(f"unknown format {fmt!r}: this build writes json and yaml") from None
    intr = intrinsics()
    try:
        return exporter.export(ext, intr, fmt)
    except ValueError as e:  # ExportError: unknown format, or the cameras do not fit it
        raise UnknownFormat(str(e)) from None
