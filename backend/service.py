"""The live service: one asyncio process around the synchronous pipeline.

    Zenoh threads: refuse sensors outside the session (counted), queue the rest
        ──► HandOff (bounded, drops oldest, counted; the loop woken once per batch)
        │                                        │
        │ liveliness, queries                    ▼ ingest task: decode, pipeline.push
        ▼                                   front-end task: pipeline.advance(clock)
    loop callbacks                          optimizer task: next_problem → solve in a
                                              worker *process* → apply → persist, publish
                                            writer task: files, one at a time, in a thread
    HTTP thread (its own loop): uvicorn; /status and /healthz answered there from what
    the service publishes, every other request run on the service loop (api/bridge.py)

The solver process is backend/solver.py, the writer backend/writer.py, the event fan-out
backend/events.py; what the API reads (sessions, calibrations, versions, /status) is
backend/service_api.py; backend/server.py runs the service with its HTTP server.

One ``asyncio.TaskGroup`` owns every task. SIGTERM/SIGINT: the HTTP server and event
streams close, the cycle in flight ends and is applied, the session's result, snapshot
and record are written atomically, the Zenoh session is closed (in a thread). A session
that was running when the service stopped (cleanly or not) resumes at the next start
from its last snapshot.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import signal
import time
from collections import Counter, deque
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable

from proto import MessageError, decode, keys
from proto.keys import sensor_of

from .cameras import dump_extrinsics, natural_key, parse_intrinsics
from .config import ConfigError, EngineConfig
from .events import EventBus
from .history import CalibrationHistory
from .ingest import HandOff, SensorTable, ServiceClock
from .live_bootstrap import Collector, LiveOptions, late_record, reason_suffix
from .service_api import STATUS_ASKED, STATUS_FRESH, ServiceApi, copy_record, result_header
from .session import (
    SessionConflict, SessionInputError, SessionInputs, SessionRecord, SessionState, SessionStore, StopCriteria,
    dumps_json, new_session_id,
)
from .settings import ServiceSettings
from .solver import Solver, failed_solution, finish_pipeline, warm_up
from .writer import Writer

if TYPE_CHECKING:
    from .pipeline import Pipeline
    from .state import CalibrationState, CycleReport

log = logging.getLogger("extrcal.service")

MAX_CONSECUTIVE_FAILURES = 10  # failed solves in a row before a session is marked failed
LINK_CHECK = 1.0  # s between checks of the Zenoh session's links
INGEST_BATCH = 32  # messages taken per turn of the ingest task before it yields (~5 ms)
ADVANCE_SLICE = 0.25  # s of data time per advance() call when catching up


class StorageError(Exception):
    """The state directory cannot be written (503): the service runs on, the request failed."""


# ------------------------------------------------------------------ loop work


class WorkTimes:
    """How long the synchronous steps on the loop take (advance, push, apply...): the
    first place to look when the loop lags. Wall time, and the loop thread's CPU time:
    when they differ, the loop waited for the CPU or for the GIL (other threads)."""

    def __init__(self) -> None:
        self._d: dict[str, list[float]] = {}  # name → [count, wall total, wall max, cpu total]

    @contextlib.contextmanager
    def measure(self, name: str):
        t, c = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            dt, dc = time.perf_counter() - t, time.thread_time() - c
            x = self._d.setdefault(name, [0, 0.0, 0.0, 0.0])
            x[0] += 1
            x[1] += dt
            x[2] = max(x[2], dt)
            x[3] += dc

    def to_dict(self) -> dict[str, dict[str, float]]:
        return {k: {"count": v[0], "mean": v[1] / v[0], "max": v[2], "cpu_mean": v[3] / v[0]}
                for k, v in self._d.items() if v[0]}


# ------------------------------------------------------------------ the running session


@dataclass
class ActiveSession:
    record: SessionRecord
    inputs: SessionInputs
    pipeline: "Pipeline"
    state: "CalibrationState"
    finishing: bool = False
    in_cycle: bool = False
    failures: int = 0  # cycles in a row the optimizer failed (CycleReport.starved ones not counted)
    last_snapshot: float = 0.0
    # the optimizer's last failure in this session (None: none yet); replaced, never changed
    solver_fault: dict[str, Any] | None = None
    last_accepted: int | None = None  # the last cycle folded into the estimate
    # "resumed at cycle N after a restart (...)": kept in the reason while it waits for data
    resumed: str | None = None
    # the live check of the initial estimate found it rough: the pipeline from the data's
    # shape, swapped in by the optimizer between cycles (``Service._check_initial``)
    checked: Any = None
    checking: bool = False  # its bootstrap is in the solver
    idle: asyncio.Event = field(default_factory=asyncio.Event)  # no cycle in flight
    clock_idle: asyncio.Event = field(default_factory=asyncio.Event)  # no clock offset estimate in flight
    done: asyncio.Event = field(default_factory=asyncio.Event)  # stopped or failed, persisted

    def __post_init__(self) -> None:
        self.idle.set()
        self.clock_idle.set()

    @functools.cached_property
    def names(self) -> frozenset[str]:
        """The session's sensors (its cameras)."""
        return frozenset(self.inputs.cameras.names)

    @property
    def sensors(self) -> frozenset[str]:
        """The sensors whose messages it takes: its cameras and those its bootstrap has not
        placed yet (backend/late_join.py archives them)."""
        return self.names | frozenset(getattr(self.pipeline, "unplaced", ()))

    @property
    def resolutions(self) -> dict[str, tuple[int, int]]:
        return {n: self.inputs.cameras.extrinsics[n].resolution for n in self.inputs.cameras.names}


# ------------------------------------------------------------------ the service


class Service(ServiceApi):
    """Owns the Zenoh session, the active session's pipeline and the solver."""

    def __init__(self, settings: ServiceSettings):
        self.settings = settings
        self.store = SessionStore(settings.state_dir / "sessions")
        self.versions = CalibrationHistory(settings.state_dir / "calibrations")
        self.base_config = EngineConfig.load(settings.engine_config) if settings.engine_config else EngineConfig()
        self.clock = self._new_clock(self.base_config)
        self.sensors = SensorTable()
        self.events = EventBus()
        self.writer = Writer()
        self.solver = Solver(settings.solver_start)
        self.solve_fn: Callable | None = None  # optimize.solve; a picklable stand-in for fault tests
        self.bootstrap_fn: Callable | None = None  # live_bootstrap.run_job; a picklable stand-in for tests
        self.solver_faults = 0  # cycles whose solve raised, crashed the worker or failed numerically
        self._active: ActiveSession | None = None
        self.ignored = Counter()  # decoded but not for any session, by reason
        self.rejected = Counter()  # all rejections of messages, by reason
        self.messages = 0
        self._last_arrival: float | None = None  # wall time of the newest message taken from Zenoh
        self.cycle_wall: deque[float] = deque(maxlen=200)  # s from problem to applied, per cycle
        self.cycle_solve: deque[float] = deque(maxlen=200)
        self.frameset_delay: deque[float] = deque(maxlen=500)
        self._framesets_seen = 0
        self.lag: deque[float] = deque(maxlen=1000)  # loop lag samples, s
        self.lag_max = 0.0
        self.work = WorkTimes()
        self._starting = False
        self.started_wall = time.time()
        self.started = asyncio.Event()
        self.http_address: tuple[str, int] | None = None
        self.handoff: HandOff | None = None
        self._status_snapshot: dict[str, Any] | None = None  # published by status(), read by any thread
        self._status_pub: dict[str, Any] | None = None
        self._status_stale = False  # the session changed so that older snapshots must not be served (``_changed``)
        self._status_asked = -math.inf  # monotonic time of the last /status from the HTTP thread
        # Zenoh links of this session (routers, peers), checked every LINK_CHECK s; the wall
        # time they all went, while endpoints to connect to are configured
        self.links: dict[str, Any] = {"routers": None, "peers": None, "lost_since": None, "losses": 0}
        self._closing = False
        self._stop = asyncio.Event()
        self._wake = asyncio.Event()  # front end advanced: the optimizer may find a problem
        self._queries: asyncio.Queue = asyncio.Queue(maxsize=64)
        self._tg: asyncio.TaskGroup | None = None
        self._zenoh = None
        self._publisher = None
        self._loop: asyncio.AbstractEventLoop | None = None
        # Called on the loop after every applied cycle with (session id, report, wall s);
        # metrics and other observers hook in here. They must be quick.
        self.cycle_listeners: list[Callable[[str, "CycleReport", float], None]] = []

    @property
    def active(self) -> ActiveSession | None:
        """The running session (None: none)."""
        return self._active

    @active.setter
    def active(self, s: ActiveSession | None) -> None:
        self._active = s
        self._changed(stale=True)  # a session started or ended: no snapshot from before is served
        if self.handoff is not None:  # sensors outside the session are refused on Zenoh's threads
            self.handoff.accept(None if s is None else s.sensors)

    def _new_clock(self, cfg: EngineConfig) -> ServiceClock:
        return ServiceClock(self.settings.clock, speed=self.settings.speed,
                            max_jump=cfg.sync.max_stamp_future)

    # ------------------------------------------------------------ lifecycle

    def request_stop(self) -> None:
        """SIGTERM, SIGINT, tests. Idempotent; safe to call from the loop only."""
        self._stop.set()

    async def run(self, server: Any | None = None, *, install_signals: bool = False) -> None:
        """Run until request_stop(); ``server`` is a uvicorn.Server to serve alongside."""
        loop = self._loop = asyncio.get_running_loop()
        self.handoff = HandOff(loop, self.settings.ingest_queue)
        if install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, self.request_stop)
        self._resume()
        from proto.transport import open_session

        z = self.settings.zenoh
        try:
            zs = await asyncio.to_thread(open_session, z.transport())
        except Exception as e:  # zenoh.ZError and friends: say which endpoints
            raise OSError(f"cannot open the Zenoh session ({z.mode}, listen {', '.join(z.listen) or '-'}, "
                          f"connect {', '.join(z.connect) or '-'}): {e}") from None
        self._zenoh = zs
        declared: list[Any] = []
        try:
            declared = await asyncio.to_thread(self._declare, zs)
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                tg.create_task(self.writer.run(), name="writer")
                tg.create_task(self._ingest_loop(), name="ingest")
                tg.create_task(self._frontend_loop(), name="frontend")
                tg.create_task(self._optimizer_loop(), name="optimizer")
                tg.create_task(self._clock_loop(), name="clock-offsets")
                tg.create_task(self._bootstrap_loop(), name="bootstrap")
                tg.create_task(self._query_loop(), name="queries")
                tg.create_task(self._status_loop(), name="status")
                tg.create_task(self._lag_loop(), name="lag")
                tg.create_task(self._link_loop(zs), name="zenoh-links")
                warm = tg.create_task(self._warm(), name="warm-up")
                server_task = tg.create_task(server.serve(), name="http") if server is not None else None
                if server is not None:
                    while not server.started and not server_task.done() and not self._stop.is_set():
                        await asyncio.sleep(0.01)
                if server_task is not None and server_task.done():
                    raise RuntimeError("the HTTP server did not start")
                self.started.set()
                self.events.publish("service", {"event": "started"})
                await self._stop.wait()
                await self._shutdown(server)
                warm.cancel()
        finally:
            if install_signals:
                for sig in (signal.SIGTERM, signal.SIGINT):
                    loop.remove_signal_handler(sig)
            await asyncio.to_thread(self._close_zenoh, zs, declared)
            s = self.active
            if s is not None and isinstance(s.pipeline, Collector) and s.pipeline.running is not None:
                self.solver.kill()  # also when a task failed: do not wait minutes for a bootstrap attempt
            await asyncio.to_thread(self.solver.shutdown)

    def _declare(self, zs: Any) -> list[Any]:
        """Blocking Zenoh declarations (in a thread)."""
        import zenoh

        site = self.settings.site
        assert self.handoff is not None and self._loop is not None
        loop = self._loop  # this runs in a thread: the service's loop, captured in run()
        sub = zs.declare_subscriber(keys.all_keypoints(site), self.handoff.on_sample)

        def on_alive(sample: Any) -> None:  # Zenoh thread
            alive = sample.kind == zenoh.SampleKind.PUT
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self.sensors.liveliness, str(sample.key_expr), alive)

        live = zs.liveliness().declare_subscriber(keys.all_alive(site), on_alive, history=True)

        def on_query(query: Any) -> None:  # Zenoh thread: hand over, answer on the loop
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._enqueue_query, query)

        qbl = zs.declare_queryable(keys.calibration(site), on_query)
        self._publisher = zs.declare_publisher(keys.calibration(site), encoding=zenoh.Encoding("application/json"))
        return [sub, live, qbl, self._publisher]

    @staticmethod
    def _close_zenoh(zs: Any, declared: list[Any]) -> None:
        for d in reversed(declared):
            with contextlib.suppress(Exception):
                d.undeclare()
        zs.close()

    async def _warm(self) -> None:
        try:
            await self.solver.run(warm_up)
        except Exception as e:  # the first real cycle reports it again
            log.warning("solver warm-up failed: %s", e)

    async def _shutdown(self, server: Any | None) -> None:
        self._closing = True
        self.events.close()
        if server is not None:
            server.should_exit = True
        s = self.active
        if s is not None and isinstance(s.pipeline, Collector) and s.pipeline.running is not None:
            self.solver.kill()  # a bootstrap attempt in flight: minutes, and a resume collects again anyway
        if s is not None:
            if s.finishing:
                await s.done.wait()
            else:
                await s.idle.wait()  # the cycle in flight ends and is applied
                s.pipeline.cancel_clock()
                await s.clock_idle.wait()
                if s.record.state.active:
                    self._persist(s, snapshot=True, note="service stopped; resumes at the next start")
        assert self.handoff is not None
        self.handoff.close()
        self._wake.set()
        if self._queries.full():  # the sentinel must get in: an unanswered query times out
            self._queries.get_nowait()
        self._queries.put_nowait(None)
        await self.writer.flush()
        self.writer.close()

    # ------------------------------------------------------------ resume

    def _resume(self) -> None:
        """Sessions that were running when the service stopped: newest resumes, others fail."""
        running = []
        for sid in self.store.ids():
            try:
                rec = self.store.load_record(sid)
            except SessionInputError as e:
                log.error("%s", e)
                continue
            if rec.state.active:
                running.append(rec)
        for rec in running[:-1]:
            rec.state, rec.reason, rec.ended_wall = SessionState.failed, "interrupted: a newer session was running", time.time()
            self.store.save_record(rec)
        if not running:
            return
        rec = running[-1]
        try:
            inputs = self.store.load_inputs(rec)
            snap = self.store.load_snapshot(rec.id)
            from .pipeline import Pipeline

            if rec.bootstrap is not None and rec.bootstrap.get("phase") != "done":
                # stopped while collecting or bootstrapping: the frames were not kept, collect again
                pipeline = Collector(inputs.cameras, inputs.config, LiveOptions.from_dict(rec.bootstrap.get("options")),
                                     initial=inputs.initial_yaml is not None, seed=rec.seed + rec.resumed + 1)
                rec.bootstrap = {**rec.bootstrap, **pipeline.progress()}
            else:
                intr = parse_intrinsics(inputs.intrinsics_yaml)
                if rec.bootstrap is not None and inputs.config.bootstrap.late and set(intr) - set(inputs.cameras.names):
                    from .late_join import JoiningPipeline  # cameras its bootstrap left out: new data may place them

                    names = tuple(sorted(intr, key=natural_key))
                    pipeline = (JoiningPipeline.resume(inputs.cameras, inputs.config, snap, intrinsics=intr, names=names,
                                                       seed=rec.seed + rec.resumed + 1) if snap is not None else
                                JoiningPipeline(inputs.cameras, inputs.config, intrinsics=intr, names=names, seed=rec.seed))
                elif snap is not None:
                    pipeline = Pipeline.restore(inputs.cameras, inputs.config, snap, seed=rec.seed + rec.resumed + 1)
                else:
                    pipeline = Pipeline(inputs.cameras, inputs.config, seed=rec.seed, scale_heights=None if rec.scale is None
                                        else tuple(rec.scale.get("person_height") or ()))
        except Exception as e:  # a snapshot or files that no longer load: say so, keep the files
            rec.state, rec.reason, rec.ended_wall = SessionState.failed, f"could not resume: {e}", time.time()
            self.store.save_record(rec)
            log.error("session %s %s", rec.id, rec.reason)
            return
        kept = self.store.cut_history(rec.id, pipeline.cycle)
        rec.resumed += 1
        rec.cycles = pipeline.cycle
        rec.reason = f"resumed at cycle {pipeline.cycle} after a restart ({kept} cycles of history kept)"
        if isinstance(pipeline, Collector):
            rec.reason = "resumed after a restart while bootstrapping: collecting again (frames are not kept)"
        self.clock = self._new_clock(inputs.config)
        self.active = ActiveSession(rec, inputs, pipeline, pipeline.state(), resumed=rec.reason)
        self.store.save_record(rec)
        log.info("session %s %s", rec.id, rec.reason)

    # ------------------------------------------------------------ ingest

    def _enqueue_query(self, query: Any) -> None:
        try:
            self._queries.put_nowait(query)
        except asyncio.QueueFull:  # answered by nobody: the querier times out
            self.ignored["query_overflow"] += 1

    async def _ingest_loop(self) -> None:
        assert self.handoff is not None
        while True:
            batch = await self.handoff.get_batch(INGEST_BATCH)
            if not batch:
                return
            with self.work.measure("ingest"):
                for a in batch:
                    self._ingest_one(a.key, a.payload, a.wall)
                self._fold_refused()
            await asyncio.sleep(0)

    def _fold_refused(self) -> None:
        """Count what the Zenoh threads refused by key (sensors outside the session)."""
        if self.handoff is None:
            return
        for name, r in self.handoff.take_refused().items():
            self.messages += r.count
            self._last_arrival = max(self._last_arrival or 0.0, r.last_wall)
            self.rejected["unknown_sensor"] += r.count
            stats = self.sensors.get(name)
            if stats is None:
                self.sensors.unattributed["unknown_sensor"] += r.count
                continue
            stats.seen(r.last_wall, r.count)
            stats.rejected["unknown_sensor"] += r.count

    def _reject(self, stats: Any, reason: str) -> None:
        self.rejected[reason] += 1
        if stats is not None:
            stats.reject(reason)
        else:
            self.sensors.unattributed[reason] += 1

    def _ingest_one(self, key: str, payload: bytes, wall: float) -> None:
        self.messages += 1
        self._last_arrival = wall
        name = sensor_of(key)
        stats = self.sensors.get(name)
        if stats is not None:
            stats.seen(wall)
        try:
            msg = decode(payload)
        except MessageError as e:
            self._reject(stats, f"malformed:{e.field.split('[')[0].split('.')[0] or 'payload'}")
            return
        except Exception as e:  # a decoder bug: one message must not end the ingest task (and the service)
            log.exception("decoding a message failed")
            self._reject(stats, f"internal:{type(e).__name__}")
            return
        if name is not None and msg.sensor != name:
            self._reject(stats, "sensor_mismatch")
            return
        s = self.active
        if self.clock.mode == "wall":
            arrival = wall
        elif s is None or msg.sensor in s.names:
            arrival = self.clock.observe(msg.stamp, msg.sensor)
        else:  # a sensor outside the session must not move the session's clock (a flood of them would)
            now = self.clock.now()
            arrival = msg.stamp if now is None else now
        if stats is not None:
            stats.timing(msg.stamp, arrival, msg.seq)
        if s is None or s.finishing:
            self.ignored["no_session"] += 1
            return
        try:
            reason = s.pipeline.push(msg, arrival)
        except Exception as e:  # a bug must not take the service down with one message
            log.exception("pipeline.push failed")
            reason = f"internal:{type(e).__name__}"
        if reason is not None:
            self._reject(stats, reason)
            return
        if stats is not None:
            stats.accepted += 1
        if s.record.first_data is None:
            s.record.first_data = arrival
            self._save_record(s)

    # ------------------------------------------------------------ front end

    async def _frontend_loop(self) -> None:
        advanced_to: float | None = None
        while not self._closing:
            await asyncio.sleep(self.settings.tick)
            s = self.active
            now = self.clock.now()
            if s is None or s.finishing or now is None:
                continue
            # After a backlog (a restart, a stall), catch up in slices so that the loop
            # keeps answering between them.
            t = now if advanced_to is None or now - advanced_to <= ADVANCE_SLICE else advanced_to + ADVANCE_SLICE
            while True:
                try:
                    with self.work.measure("advance"):
                        s.pipeline.advance(t, clock_offsets=False)  # _clock_loop runs that
                except Exception as e:
                    log.exception("pipeline.advance failed")
                    self._fail(s, f"the front end failed: {type(e).__name__}: {e}")
                    break
                advanced_to = t
                if t >= now or self._closing or s is not self.active:
                    break
                await asyncio.sleep(0)
                t = min(now, t + ADVANCE_SLICE)
            self._frameset_delay(s, now)
            self._wake.set()
            self._check_duration(s, now)

    async def _clock_loop(self) -> None:
        """Sensor clock offsets (``clock.estimate``, docs/clock_offsets.md): the estimate
        takes seconds of numpy, so it runs in a thread; taking its job and folding its
        result in are cheap and run here, on the loop. A thread, not the solver process:
        the job reads minutes of tracks and keeps caches in its records, too much to ship
        every few seconds; and numpy code gives the GIL back every few ms (a gtsam solve
        does not)."""
        while not self._closing:
            await asyncio.sleep(self.settings.tick)
            s = self.active
            if s is None or s.finishing or self._closing or not s.record.state.active:
                continue
            with self.work.measure("clock_job"):
                job = s.pipeline.clock_job(self.clock.now())
            if job is None:
                continue
            s.clock_idle.clear()
            try:
                result = await asyncio.to_thread(job.run)
            except Exception:
                log.exception("the clock offset estimate failed")
                result = None
            finally:
                s.clock_idle.set()
            with self.work.measure("apply_clock"):
                s.pipeline.apply_clock(job, result)
                # /status shows the estimate as it is now: the state is otherwise taken after
                # a cycle, and cycles wait while the solver runs a long job
                s.state = replace(s.state, clocks=s.pipeline.clock_states())

    async def _bootstrap_loop(self) -> None:
        """Sessions that bootstrap (backend/live_bootstrap.py): the collector says when an
        attempt is due; ``bootstrap`` runs in the solver process (its bundle adjustment is
        GTSAM, which holds the GIL for seconds: in a thread it would stall the loop, like a
        cycle's solve) on a frozen copy of the frames while collecting goes on; an accepted
        result is handed over, the pipeline built in a thread, and swapped in here."""
        while not self._closing:
            await asyncio.sleep(self.settings.tick)
            s = self.active
            if s is None or s.finishing or self._closing:
                continue
            if not isinstance(s.pipeline, Collector):
                if self._check_due(s):
                    s.checking = True
                    try:
                        await self._check_initial(s)
                    except Exception:  # the check is a bonus: the session goes on from its initial estimate
                        log.exception("the live check of the initial estimate failed")
                        s.record.initial_check = {"phase": "done", "used": False,
                                                  "note": "the check failed (see the log): the initial estimate kept"}
                        self._save_record(s)
                    finally:
                        s.checking = False
                continue
            try:
                await self._bootstrap_turn(s, s.pipeline)
            except Exception as e:  # a bug here ends the session, never the service
                log.exception("the live bootstrap failed")
                if s is self.active and not s.finishing:
                    self._fail(s, f"the live bootstrap failed: {type(e).__name__}: {e}")

    async def _bootstrap_turn(self, s: ActiveSession, col: Collector) -> None:
        """One attempt when due: run it, judge it, hand an accepted one over."""
        from .live_bootstrap import Handover, Outcome, run_job

        job = col.job()
        if job is None:
            return
        self._bootstrap_progress(s)
        log.info("session %s: bootstrap attempt %d on %.0f s of data", s.record.id, job.attempt, job.data_seconds)
        try:
            outcome = await self.solver.run(self.bootstrap_fn or run_job, job)
        except Exception as e:  # SolverCrashed, a bug: this attempt failed, the next has more data
            if s is not self.active or s.finishing or self._closing:
                return  # killed by a stop or the shutdown
            log.exception("bootstrap attempt %d failed", job.attempt)
            outcome = Outcome(None, f"{type(e).__name__}: {e}", 0.0)
        if s is not self.active or s.finishing or self._closing:
            return
        with self.work.measure("bootstrap_conclude"):
            result = col.conclude(job, outcome)
        if result is None:
            log.info("session %s: bootstrap attempt %d not accepted: %s", s.record.id, job.attempt,
                     col.attempts[-1].get("error"))
            self._bootstrap_progress(s)
            return
        self._bootstrap_progress(s)
        try:
            h = await asyncio.to_thread(Handover.build, job, result, s.inputs.cameras, s.inputs.config,
                                        col.initial, seed=s.record.seed, frames=tuple(col.frames))
        except Exception as e:  # the result does not make a pipeline: not a reason to stop the service
            log.exception("handing the bootstrap over failed")
            self._fail(s, f"handing the bootstrap over to the online pipeline failed: {type(e).__name__}: {e}")
            return
        if s is not self.active or s.finishing or self._closing:
            return
        with self.work.measure("bootstrap_handover"):
            self._hand_over(s, col, h)

    def _gone(self, s: ActiveSession) -> bool:
        """Session ``s`` ended (stopped, failed, replaced, or the service closing) while
        the loop awaited something: what was awaited must not be applied to it."""
        return s is not self.active or s.finishing or self._closing or not s.record.state.active

    def _check_due(self, s: ActiveSession) -> bool:
        """A session with an initial estimate it was not told to distrust, not checked yet
        (``bootstrap.live_check``), with ``bootstrap.max_seconds`` of frames archived (what
        ``extrcal calibrate`` bootstraps on: at 60 s a camera of the lab was chained 160°
        off) and, after an attempt the data did not allow, ``live_interval`` more. It waits
        while a sensor's clock is found off and its offset not yet applied
        (``Pipeline.timing_undecided``), up to twice ``max_seconds`` of frames."""
        b, rec, p = s.inputs.config.bootstrap, s.record, s.pipeline
        if not b.live_check or b.with_initial == "never" or s.inputs.initial_yaml is None or rec.bootstrap is not None:
            return False
        check = rec.initial_check or {}
        if check.get("phase") == "done" or s.checking or s.checked is not None or not rec.state.active:
            return False
        frames = getattr(p, "frames", None)
        if not frames or (span := frames[-1][0] - frames[0][0]) < b.max_seconds:
            return False
        # a bootstrap on views mistimed by tens of ms would judge the estimate by a distorted
        # shape; once the offsets are applied it is skipped (``_check_initial``). Up to twice
        # max_seconds of data: an estimate that is never confirmed must not hold it for good.
        undecided = p.timing_undecided()
        if undecided and span < 2 * b.max_seconds:
            note = f"waiting for the clock offsets of {', '.join(undecided)} to be decided"
            if check.get("note") != note:
                rec.initial_check = {**check, "phase": "waiting", "data_seconds": span, "note": note}
                self._save_record(s)
            return False
        return check.get("tried_at") is None or frames[-1][0] >= check["tried_at"] + b.live_interval

    async def _check_initial(self, s: ActiveSession) -> None:
        """The initial estimate against the data's shape, as ``extrcal calibrate`` does it
        (backend/reconcile.py): a bootstrap on the archived frames in the solver process
        (the cycles wait for it), reconciled with the initial estimate. When the data's
        shape is to be used, a pipeline from it with every frame archived is built in a
        thread and the optimizer swaps it in between cycles (``_swap_checked``); else the
        session goes on as it was. A bootstrap the data do not allow yet is tried again
        ``live_interval`` later, three times in all."""
        from .live_bootstrap import BootstrapJob, Handover, run_job, seen_per_camera
        from .reconcile import reconcile_cameras

        rec, p, cfg = s.record, s.pipeline, s.inputs.config
        frames = tuple(p.frames)
        span = frames[-1][0] - frames[0][0]
        tries = int((rec.initial_check or {}).get("attempts", 0)) + 1
        if p.clocks.applied.any():  # archived views timed with offsets a new pipeline would not know
            rec.initial_check = {"phase": "done", "used": False, "data_seconds": span,
                                 "note": "not checked: clock offsets were applied, and the archived views were "
                                         "timed without them"}
            self._save_record(s)
            return
        job = BootstrapJob(tries, frames, tuple(p.names), p.focal.copy(), cfg, tuple(p.scale_heights or ()),
                           rec.seed, span, seen_per_camera(frames, len(p.names)), True)
        rec.initial_check = {"phase": "running", "data_seconds": span, "attempts": tries}
        self._save_record(s)
        log.info("session %s: checking the initial estimate against a bootstrap on %.0f s of data", rec.id, span)
        outcome = await self.solver.run(self.bootstrap_fn or run_job, job)
        if self._gone(s):
            return
        if outcome.result is None:
            last = tries >= 3
            rec.initial_check = {"phase": "done" if last else "waiting", "used": False, "data_seconds": span,
                                 "attempts": tries, "tried_at": frames[-1][0],
                                 "note": f"bootstrap not possible ({outcome.error}): the initial estimate kept"
                                 + ("" if last else ", tried again with more data")}
            self._save_record(s)
            return
        reconciled, _, note = reconcile_cameras(outcome.result, s.inputs.cameras, cfg)
        used = reconciled is not None and reconciled.used
        rec.initial_check = {"phase": "running" if used else "done", "used": used, "data_seconds": span,
                             "attempts": tries, "seconds": outcome.seconds,
                             "reconciled": reconciled.to_dict() if reconciled is not None else None, "note": note}
        log.info("session %s: the initial estimate against the data: %s", rec.id, note)
        self._save_record(s)
        if not used:
            # kept: the session's final batch also tries from the data's shape where it ends apart from it
            if reconciled is not None and s.pipeline is p:
                p.data_shape = reconciled.data_shape()
            return
        h = await asyncio.to_thread(Handover.build, job, outcome.result, s.inputs.cameras, cfg, True,
                                    seed=rec.seed, frames=frames, reconciled=(reconciled, note))
        if self._gone(s):
            rec.initial_check = {**rec.initial_check, "phase": "done", "note": f"{note}; the session ended first"}
            return
        s.checked = h
        self._wake.set()

    def _swap_checked(self, s: ActiveSession) -> None:
        """The pipeline from the data's shape in place of the running one (between cycles:
        nothing in flight); it takes the frames the running one archived since the check
        and goes on where its clock and sync are, its cycles numbered on."""
        h, old, rec = s.checked, s.pipeline, s.record
        s.checked = None
        h.catch_up(old)
        h.pipeline.cycle = old.cycle
        self._swap_pipeline(s, h.pipeline, replace(s.inputs, cameras=h.cameras, config=h.config))
        s.failures = 0
        rec.initial_check = {**(rec.initial_check or {}), "phase": "done", "cycle": old.cycle}
        rec.reason = f"the initial estimate checked against the data: {h.meta.get('note')}; calibrating from it"
        log.warning("session %s: %s", rec.id, rec.reason)
        self.writer.submit(self.store.save_start, rec.id, None, h.config)
        self._changed(stale=True)
        self._persist(s, snapshot=True)  # a resume must not restore the pipeline from before the swap
        self.events.publish("session", {"id": rec.id, "state": rec.state.value, "reason": rec.reason,
                                        "initial_check": "used"})

    @staticmethod
    def _swap_pipeline(s: ActiveSession, pipeline: Any, inputs: SessionInputs) -> None:
        """A new pipeline in place of the session's, with its inputs (on the loop, between
        cycles): the cached camera names dropped, the state taken from it now."""
        s.pipeline = pipeline
        s.inputs = inputs
        s.__dict__.pop("names", None)
        s.state = pipeline.state()

    def _bootstrap_progress(self, s: ActiveSession) -> None:
        col = s.pipeline
        assert isinstance(col, Collector)
        s.record.bootstrap = {**(s.record.bootstrap or {}), **col.progress()}
        s.record.reason = col.reason()
        self._save_record(s)

    def _hand_over(self, s: ActiveSession, col: Collector, h: Any) -> None:
        """Swap the online pipeline in for the collector (on the loop: nothing in between)."""
        h.catch_up(col)
        rec = s.record
        self._swap_pipeline(s, h.pipeline, SessionInputs(
            s.inputs.intrinsics_yaml, h.initial_yaml or s.inputs.initial_yaml, s.inputs.reference_yaml, h.cameras,
            s.inputs.reference, h.config))  # the placed cameras
        if self.handoff is not None:  # and the cameras it did not place, archived for later (backend/late_join.py)
            self.handoff.accept(s.sensors)
        s.last_snapshot = time.monotonic()
        data_time = None if rec.first_data is None or col.clock is None else col.clock - rec.first_data
        rec.bootstrap = {**(rec.bootstrap or {}), **col.progress(), **h.meta, "phase": "done",
                         "pose_data_seconds": data_time, "pose_wall": time.time()}
        rec.reason = f"bootstrapped: {h.meta['note']}; calibrating from it" + reason_suffix(rec.bootstrap)
        log.info("session %s: %s", rec.id, rec.reason)
        self.writer.submit(self.store.save_start, rec.id, h.initial_yaml, h.config)
        self._save_record(s)
        self.events.publish("session", {"id": rec.id, "state": rec.state.value, "reason": rec.reason,
                                        "bootstrap": "done"})
        self._wake.set()

    def _frameset_delay(self, s: ActiveSession, now: float) -> None:
        """Clock time from a frameset's instant to its emission: with sensors stamping at
        capture, this is the publish → frameset latency (mostly the sync stage's wait)."""
        sync = getattr(s.pipeline, "sync", None)
        try:
            total = sync.framesets + sum(sync.framesets_rejected.values())
            latest = sync.next_time - 1.0 / s.inputs.config.sync.rate
        except (AttributeError, TypeError):  # an engine without these: no figure
            return
        if total > self._framesets_seen:
            self.frameset_delay.append(now - latest)
        self._framesets_seen = total

    # ------------------------------------------------------------ optimizer

    async def _optimizer_loop(self) -> None:
        while not self._closing:
            await self._wake.wait()
            self._wake.clear()
            s = self.active
            if s is None or s.finishing or self._closing or not s.record.state.active:
                continue
            now = self.clock.now()
            if now is None:
                continue
            if s.checked is not None:
                self._swap_checked(s)  # between cycles: nothing of the pipeline is in flight
            if not isinstance(s.pipeline, Collector) and s.pipeline.late_join_due(now):
                await self._join_late(s, now)  # between cycles: nothing of the pipeline is in flight
                if self._gone(s):
                    continue
            with self.work.measure("next_problem"):
                problem = s.pipeline.next_problem(now)
            if problem is None:
                continue
            s.in_cycle = True
            s.idle.clear()
            t0 = time.monotonic()
            try:
                from .optimize import solve

                try:
                    solution = await self.solver.run(self.solve_fn or solve, problem)
                except Exception as e:  # SolverCrashed, or solve raised in the worker
                    log.warning("cycle %d: solve failed: %s", problem.cycle, e)
                    solution = failed_solution(problem, f"solve failed: {type(e).__name__}: {e}")
                self._solver_outcome(s, problem.cycle, None if solution.ok else solution.reason)
                if s is not self.active or not s.record.state.active:
                    continue  # the session failed meanwhile: nothing to fold in
                with self.work.measure("apply"):
                    report = s.pipeline.apply(problem, solution)
                wall = time.monotonic() - t0
                self.cycle_wall.append(wall)
                self.cycle_solve.append(report.solve_seconds)
                with self.work.measure("after_cycle"):
                    self._after_cycle(s, report)
                for listener in self.cycle_listeners:
                    try:
                        listener(s.record.id, report, wall)
                    except Exception:  # an observer's bug must not stop calibrating
                        log.exception("cycle listener failed")
            finally:
                s.in_cycle = False
                s.idle.set()

    async def _join_late(self, s: ActiveSession, now: float) -> None:
        """Cameras the bootstrap left out, resected against the running estimate in the
        solver process; those placed join the session (backend/late_join.py): the
        pipeline grown by them is swapped in, its start saved (a resume has them)."""
        from .late_join import run_late_job

        job = s.pipeline.late_job(now)
        try:
            found = await self.solver.run(run_late_job, job)
        except Exception as e:  # a failed try is tried again an interval later
            log.warning("session %s: resecting the cameras without a pose failed: %s", s.record.id, e)
            return
        if self._gone(s):
            return
        with self.work.measure("late_join"):
            q = s.pipeline.join_live(job, found)
        if q is None:
            return
        rec = s.record
        joined = [j.name for j in q.late if j.live and j.name not in s.names]
        self._swap_pipeline(s, q, replace(s.inputs, cameras=q.cameras))  # now with the joined cameras
        rec.bootstrap = {**(rec.bootstrap or {}), **(late_record(q, final=False) or {})}
        log.info("session %s: %s placed after the bootstrap, joined the running calibration", rec.id, ", ".join(joined))
        initial_yaml = dump_extrinsics(dict(q.cameras.extrinsics), comment="the bootstrap's cameras and those placed "
                                       "after it (their resected pose), the start of a resumed session")
        self.writer.submit(self.store.save_start, rec.id, initial_yaml, s.inputs.config)
        self._save_record(s)
        self.events.publish("session", {"id": rec.id, "state": rec.state.value, "joined": joined,
                                        "reason": f"placed after the bootstrap: {', '.join(joined)}"})

    def _solver_outcome(self, s: ActiveSession, cycle: int, error: str | None) -> None:
        """Track the optimizer's failures (an exception or a dead worker, or a numerical
        failure such as an indeterminant system): /status and the session show the last
        one, how many cycles in a row failed, and the cycle that recovered."""
        f = s.solver_fault
        if error is None:
            if f is not None and f["failing"]:
                s.solver_fault = {**f, "failing": 0, "recovered_cycle": cycle}
                log.info("cycle %d: the optimizer works again after %d failed cycles", cycle, f["failing"])
            return
        self.solver_faults += 1
        s.solver_fault = {"cycle": cycle, "error": error, "wall": time.time(),
                          "failing": (f["failing"] if f else 0) + 1, "count": (f["count"] if f else 0) + 1,
                          "recovered_cycle": None, "kept_cycle": s.last_accepted}

    def _after_cycle(self, s: ActiveSession, report: "CycleReport") -> None:
        with self.work.measure("state"):
            state = s.pipeline.state()
        s.state = state
        rec = s.record
        rec.cycles = state.cycle
        was = rec.state
        if report.accepted:
            s.failures = 0
            s.last_accepted = report.cycle
        elif not report.starved:  # a cycle with nothing to solve neither counts nor resets
            s.failures += 1
        acc = self._accuracy(s, state)
        if acc is not None:
            rec.accuracy = acc
        if s.failures >= MAX_CONSECUTIVE_FAILURES:
            self._fail(s, f"{s.failures} cycles in a row failed, last: {report.reason}")
            return
        if rec.state.active:
            if state.converged:
                if rec.converged_cycle is None:
                    rec.converged_cycle = state.cycle
                rec.state, rec.reason = SessionState.converged, _converged_reason(state)
            else:
                rec.state = SessionState.calibrating
                rec.reason = _calibrating_reason(state, report)
            rec.reason += reason_suffix(rec.bootstrap)
            f = s.solver_fault
            if f is not None and f["failing"]:
                rec.reason += (f"; the optimizer failed in the last {f['failing']} cycle(s) ({f['error']}): "
                               f"the estimate of the last good cycle is kept")
        for name in report.moved_cameras:
            log.warning("session %s: camera %s moved (its residuals jumped after it had converged): "
                        "calibrating it again", rec.id, name)
            self.events.publish("camera_moved", {"session": rec.id, "camera": name, "data_time": state.data_time,
                                                 "cycle": report.cycle})
        why = {c.name: c.restart_reason for c in state.cameras} if report.restarted else {}
        for name in report.restarted:
            log.info("session %s: camera %s started over from a pose found elsewhere (%s)", rec.id, name, why.get(name))
            self.events.publish("camera_restarted", {"session": rec.id, "camera": name, "reason": why.get(name),
                                                     "data_time": state.data_time, "cycle": report.cycle})
        if rec.state is not was or report.moved_cameras or report.recalibrated or report.restarted:
            self._changed(stale=True)
        if report.recalibrated and self._tg is not None:
            self._tg.create_task(self._record_recalibration(s, report), name=f"version {rec.id} {report.cycle}")
        self._write_cycle(rec, report, state, acc)
        if self.events.subscribers:
            self.events.publish("hypotheses", {"session": rec.id, "persons": s.pipeline.skeletons()})
        due = time.monotonic() - s.last_snapshot >= self.settings.snapshot_interval
        self._persist(s, snapshot=due)
        self._publish_calibration(s)
        if rec.stop.max_cycles is not None and state.cycle >= rec.stop.max_cycles:
            self._begin_stop(s, "max_cycles")
        elif rec.stop.converged and state.converged:
            self._begin_stop(s, "converged")

    def _write_cycle(self, rec: SessionRecord, report: "CycleReport", state: "CalibrationState",
                     acc: dict[str, Any] | None, **extra: Any) -> None:
        """The cycle's history line, built and appended in the writer thread (per camera
        work for 100 cameras is milliseconds), then sent to the event stream in order."""
        sid, state_name, store, loop, events = rec.id, rec.state.value, self.store, self._loop, self.events

        def write() -> None:
            line = {**_history_line(report, state, state_name, acc), **extra}
            try:
                store.append_history(sid, [line])
            finally:
                if loop is not None:
                    with contextlib.suppress(RuntimeError):
                        loop.call_soon_threadsafe(events.publish, "cycle", {"session": sid, **line})

        self.writer.submit(write)

    def _check_duration(self, s: ActiveSession, now: float) -> None:
        rec = s.record
        if rec.stop.duration is not None and rec.first_data is not None and not s.finishing \
                and rec.state.active and now - rec.first_data >= rec.stop.duration:
            self._begin_stop(s, "duration")

    def _accuracy(self, s: ActiveSession, state: "CalibrationState") -> dict[str, Any] | None:
        ref = s.inputs.reference
        if ref is None or state.cycle == 0:
            return None
        from .evaluate import evaluate

        try:
            acc = evaluate(state.poses(), ref)
        except ValueError:
            return None
        return {
            "position_mean": acc.position.mean, "position_max": acc.position.max,
            "orientation_mean": acc.orientation.mean, "orientation_max": acc.orientation.max,
            "shape_position_mean": acc.shape_position.mean, "shape_orientation_mean": acc.shape_orientation.mean,
            "scale": acc.scale,
        }

    # ------------------------------------------------------------ persistence and publication

    def _save_record(self, s: ActiveSession) -> None:
        self._changed()
        self.writer.submit(self.store.save_record, copy_record(s.record))

    def _changed(self, *, stale: bool = False) -> None:
        """The session's record changed: the published status is out of date. ``stale``:
        so much that no snapshot from before may be served either, however busy the loop
        (a session started or ended, its state changed, a camera was found moved): an
        operator told of it by POST /sessions, /sessions/{id} or /events must see it in
        /status too."""
        self._status_pub = None
        if stale:
            self._status_stale = True

    def _persist(self, s: ActiveSession, *, snapshot: bool, note: str | None = None) -> None:
        rec = s.record
        if note:
            rec.reason = note
        state = s.state
        ext = state.extrinsics(s.resolutions)
        comment = result_header(s)
        store = self.store

        def write_result() -> None:  # in the writer thread: YAML and JSON take their time
            store.save_result(rec.id, dump_extrinsics(ext, comment=comment), state.to_dict())

        self.writer.submit(write_result)
        if snapshot:
            s.last_snapshot = time.monotonic()
            with self.work.measure("snapshot"):
                snap = s.pipeline.snapshot()
            self.writer.submit(self.store.save_snapshot, rec.id, snap)
        self._save_record(s)

    def _publish_calibration(self, s: ActiveSession) -> None:
        if self._publisher is None:
            return
        build = self._calibration_doc(s)
        pub = self._publisher

        def put() -> None:
            payload = dumps_json(build()).encode()
            with contextlib.suppress(Exception):  # a closing session: the update is moot
                pub.put(payload)

        # put() can block on a congested link: not on the loop. Through the writer task
        # so that updates go out in order.
        self.writer.submit(put, storage=False)

    async def _query_loop(self) -> None:
        while True:
            query = await self._queries.get()
            if query is None:
                return
            s = self.active
            payload = dumps_json(self.calibration_dict(s)).encode() if s is not None else None
            if payload is None and self.versions.active_doc() is not None:
                payload = dumps_json(self.versions.active_doc()).encode()
            if payload is None:
                last = self._latest_finished()
                payload = dumps_json(last).encode() if last is not None else None
            key = keys.calibration(self.settings.site)

            def answer(q: Any = query, p: bytes | None = payload) -> None:
                try:
                    if p is None:
                        q.reply_err(b"no calibration yet")
                    else:
                        q.reply(key, p)
                finally:
                    q.drop()

            try:
                await asyncio.to_thread(answer)
            except Exception as e:
                log.warning("answering a calibration query failed: %s", e)

    # ------------------------------------------------------------ periodic

    async def _status_loop(self) -> None:
        last_brief = 0.0
        while not self._closing:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), STATUS_FRESH / 2)
            if self._closing:
                return
            now = time.monotonic()
            # the snapshot /status serves: every STATUS_FRESH / 2 while someone asks for it
            # (~16 ms of the loop's time each under overload), else once a second
            if now - self._status_asked < STATUS_ASKED or now - last_brief >= 1.0:
                self.status()
            if now - last_brief < 1.0:
                continue
            last_brief = now
            s = self.active
            if s is not None and s.record.state == SessionState.waiting_for_data:
                if isinstance(s.pipeline, Collector):
                    reason = s.pipeline.reason()
                    s.record.bootstrap = {**(s.record.bootstrap or {}), **s.pipeline.progress()}
                else:
                    reason = _waiting_reason(s.pipeline.counters(), s.inputs.config, self.sensors,
                                             s.inputs.cameras.names) + reason_suffix(s.record.bootstrap)
                if s.resumed is not None:  # what the operator sees after a restart says so
                    reason = f"{s.resumed}; {reason}"
                if reason != s.record.reason:
                    s.record.reason = reason
                    self._save_record(s)
            if self.events.subscribers:
                self.events.publish("status", self.status_brief())

    async def _link_loop(self, zs: Any) -> None:
        """Are we still linked to the routers / peers we connect to? A restarted router or
        peer drops the link; Zenoh reconnects by itself (connect/retry), and /status says
        meanwhile that the link is gone and since when."""

        def count() -> tuple[int, int]:  # Zenoh calls: in a thread
            return len(list(zs.info.routers_zid())), len(list(zs.info.peers_zid()))

        while not self._closing:
            try:
                routers, peers = await asyncio.to_thread(count)
            except Exception as e:  # a closing session
                log.debug("reading the Zenoh links failed: %s", e)
                routers = peers = None
            if routers is not None:
                lost = self.links["lost_since"]
                down = bool(self.settings.zenoh.connect) and routers + peers == 0
                if down and lost is None:
                    lost = time.time()
                    log.warning("Zenoh: no link to %s; reconnecting", ", ".join(self.settings.zenoh.connect))
                    self.links = {**self.links, "losses": self.links["losses"] + 1}
                elif not down and lost is not None:
                    log.info("Zenoh: linked again after %.1f s", time.time() - lost)
                    lost = None
                self.links = {**self.links, "routers": routers, "peers": peers, "lost_since": lost}
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), LINK_CHECK)

    async def _lag_loop(self) -> None:
        """How late the loop wakes up: the number that says whether it ever stalls."""
        period = 0.01
        while not self._closing:
            t = time.monotonic()
            await asyncio.sleep(period)
            lag = max(time.monotonic() - t - period, 0.0)
            self.lag.append(lag)
            self.lag_max = max(self.lag_max, lag)

    # ------------------------------------------------------------ sessions (API)

    async def start_session(self, *, inputs: SessionInputs, name: str | None, stop: StopCriteria,
                            overrides: dict[str, Any], sources: dict[str, str], seed: int = 0,
                            live: LiveOptions | None = None) -> dict[str, Any]:
        """``live``: the bootstrap's options (backend/live_bootstrap.py). A session without
        an initial estimate, or told to distrust it, bootstraps its start from the people."""
        live = live or LiveOptions()
        boot = inputs.initial_yaml is None or live.distrust_initial

        def check() -> None:
            if self._closing:
                raise SessionConflict("the service is shutting down")
            if self.active is not None:
                raise SessionConflict(f"session {self.active.record.id} is {self.active.record.state.value}; "
                                      f"stop it first (POST /sessions/{self.active.record.id}/stop)")
            if self._starting:
                raise SessionConflict("another session is being started")

        await self._settled()  # a session that just failed or stopped is still writing its files
        check()
        self._starting = True
        try:
            from .pipeline import Pipeline

            with self.work.measure("new_pipeline"):
                # with an initial estimate, its scale is checked against the people's at the end
                pipeline = Collector(inputs.cameras, inputs.config, live, initial=inputs.initial_yaml is not None,
                                     seed=seed) if boot else Pipeline(inputs.cameras, inputs.config, seed=seed,
                                                                       scale_heights=live.heights)
            rec = SessionRecord(
                id=new_session_id(), name=name, state=SessionState.waiting_for_data,
                reason="no messages from the session's cameras yet", stop=stop, config_overrides=overrides,
                sources=sources, seed=seed, bootstrap=pipeline.progress() if boot else None,
                scale=None if inputs.initial_yaml is None else {"person_height": list(live.heights) or None,
                                                                "check": None},
            )
            try:  # on disk before we answer with its id; fsyncs, so not on the loop
                await asyncio.to_thread(self.store.create, rec, inputs)
            except OSError as e:
                raise StorageError(f"cannot write the session to {self.store.root}: {e}") from None
        finally:
            self._starting = False
        check()
        self.clock = self._new_clock(inputs.config)
        self._framesets_seen = 0
        self.active = ActiveSession(rec, inputs, pipeline, pipeline.state())
        self.active.last_snapshot = time.monotonic()
        self.events.publish("session", {"id": rec.id, "state": rec.state.value, "reason": rec.reason})
        return self.session_dict(rec.id)

    def make_inputs(self, *, texts: dict[str, str | None], names: dict[str, str | None],
                    config: dict[str, Any]) -> tuple[SessionInputs, dict[str, str]]:
        """Camera files from the request (text or configured names), config merged and validated."""
        st = self.settings
        resolved: dict[str, str | None] = {}
        sources: dict[str, str] = {}
        for what in ("intrinsics", "initial", "reference"):
            text, name = texts.get(what), names.get(what)
            if text is not None and name is not None:
                raise SessionInputError(f"give either {what}_yaml or {what}, not both")
            if text is None and name is None:
                name = getattr(st.defaults, what)
            if text is not None:
                resolved[what], sources[what] = text, "upload"
            elif name is not None:
                path = st.camera_files.get(name)
                if path is None:
                    known = ", ".join(sorted(st.camera_files)) or "none configured"
                    raise SessionInputError(f"{what}: no camera file named {name!r} on this server (known: {known})")
                try:
                    resolved[what] = path.read_text()
                except OSError as e:
                    raise SessionInputError(f"{what}: configured file {name!r} ({path}) cannot be read: {e}") from None
                sources[what] = f"file:{name}"
            else:
                resolved[what] = None
        if resolved["intrinsics"] is None:
            raise SessionInputError("intrinsics: give intrinsics_yaml (the file's text) or intrinsics (a configured file name)")
        try:
            cfg = (self.base_config.merged(config) if config else self.base_config).live()
        except ConfigError as e:
            raise SessionInputError(f"config: {e}") from None
        except (TypeError, AttributeError) as e:
            raise SessionInputError(f"config: expected sections of objects, e.g. {{\"select\": {{\"scope\": 60}}}} ({e})") from None
        inputs = SessionInputs.parse(resolved["intrinsics"], resolved["initial"], resolved["reference"], cfg, sources)
        return inputs, sources

    async def stop_session(self, sid: str, *, wait: bool = True, by: str = "request") -> dict[str, Any]:
        s = self.active
        if s is None or s.record.id != sid:
            return await self.session_view(sid)  # 404 if unknown; a finished one is already stopped
        if self._closing and not s.finishing:
            raise SessionConflict("the service is shutting down; the session resumes when it starts again")
        self._begin_stop(s, by)
        if wait:
            await asyncio.shield(s.done.wait())
        return await self.session_view(sid)

    def _begin_stop(self, s: ActiveSession, by: str) -> None:
        if s.finishing or not s.record.state.active or self._closing:
            return  # shutting down: the session stays as it is and resumes at the next start
        s.finishing = True
        s.record.stopped_by = by
        assert self._tg is not None
        self._tg.create_task(self._finish(s), name=f"finish {s.record.id}")

    async def _finish(self, s: ActiveSession) -> None:
        """The cycle in flight ends; the final batch adjustment runs in the solver process."""
        rec = s.record
        try:
            await s.idle.wait()
            s.pipeline.cancel_clock()  # the final batch estimates once more, with all data
            await s.clock_idle.wait()  # the pipeline goes to the solver process: nothing may run on it
            before = s.pipeline.cycle
            t0 = time.monotonic()
            try:
                if isinstance(s.pipeline, Collector):  # no pose yet: nothing to adjust
                    if s.pipeline.running is not None:
                        self.solver.kill()  # the attempt in flight is worth nothing now
                    rec.final_batch = {"ran": False, "error": "stopped while bootstrapping: no camera has a pose"}
                else:
                    s.pipeline = await self.solver.run(finish_pipeline, s.pipeline)
                    batch = s.pipeline.cycle > before
                    late = late_record(s.pipeline)
                    if late is not None:  # cameras the bootstrap left out, resected now (backend/late_join.py)
                        rec.bootstrap = {**(rec.bootstrap or {}), **late}
                        if s.pipeline.joined is not None:
                            s.inputs = replace(s.inputs, cameras=s.pipeline.joined.cameras)
                            s.__dict__.pop("names", None)
                    rec.final_batch = {"ran": batch, "seconds": time.monotonic() - t0, "report":
                                       s.pipeline.last_report.to_dict() if batch and s.pipeline.last_report else None,
                                       # which start the kept final batch came from, where two were tried: the
                                       # "estimate", the bootstrap's "start", the "data"'s shape, held to it
                                       # ("anchored"); None: one tried
                                       "kept_from": s.pipeline.final_batch_start,
                                       # cameras far beyond the stated std of their start: a user should look
                                       "far_from_start": [{"camera": n, "translation": m, "rotation": d, "chi2": x}
                                                          for n, m, d, x in s.pipeline.far_from_start()],
                                       # per sensor: archived views timed again with its final clock offset
                                       "retimed": dict(s.pipeline.retimed),
                                       # the final batch on two halves of the data: stds widened where they disagree
                                       "split_check": None if s.pipeline.split_check is None else
                                       {**s.pipeline.split_check.to_dict(), "summary": s.pipeline.split_check.summary()},
                                       # a bootstrapped session's floor frame, levelled on the final batch's floor
                                       "levelled": None if s.pipeline.levelled is None else s.pipeline.levelled.to_dict(),
                                       # the lenses the final batch found off their calibration files
                                       "lenses": None if s.pipeline.lenses is None else s.pipeline.lenses.to_dict(),
                                       # what the stated std holds (optimize.lens_accuracy_*)
                                       "std_note": s.pipeline.std_note()}
                    check = s.pipeline.scale_check
                    if check is not None:  # the initial estimate's scale against the people's
                        rec.scale = {**(rec.scale or {}), "check": check.to_dict(), "summary": check.summary()}
            except Exception as e:
                log.warning("final batch adjustment of %s failed: %s", rec.id, e)
                rec.final_batch = {"ran": False, "error": f"{type(e).__name__}: {e}"}
            s.state = s.pipeline.state()
            rec.cycles = s.state.cycle
            acc = self._accuracy(s, s.state)
            if acc is not None:
                rec.accuracy = acc
            if rec.final_batch.get("ran") and s.pipeline.last_report is not None:
                self._write_cycle(rec, s.pipeline.last_report, s.state, acc, final_batch=True)
            rec.state = SessionState.stopped
            rec.reason = {
                "request": "stopped on request", "duration": f"stop criterion: duration {rec.stop.duration:g} s reached"
                if rec.stop.duration else "duration", "converged": "stop criterion: converged",
                "max_cycles": f"stop criterion: {rec.stop.max_cycles} cycles",
            }.get(rec.stopped_by or "", f"stopped ({rec.stopped_by})")
            rec.ended_wall = time.time()
            self._persist(s, snapshot=True)
            if s.state.cameras:  # stopped while bootstrapping: no calibration to record
                await self._record_version(s)
        finally:
            if self.active is s:
                self.active = None
            self.events.publish("session", {"id": rec.id, "state": rec.state.value, "reason": rec.reason})
            await self.writer.flush()
            s.done.set()

    def _fail(self, s: ActiveSession, reason: str) -> None:
        """The session ends as failed. It stays the active one (finishing) until its files
        are written, as a stopped one does: whoever reads "failed" may fetch its result
        at once (``_settled``), and a new session starts only after that."""
        rec = s.record
        rec.state, rec.reason, rec.ended_wall = SessionState.failed, reason, time.time()
        log.error("session %s failed: %s", rec.id, reason)
        self._persist(s, snapshot=True)
        s.finishing = True
        try:
            if self._tg is None:
                raise RuntimeError("no task group")
            self._tg.create_task(self._failed(s), name=f"failed {rec.id}")
        except RuntimeError:  # no task group, or it is shutting down: end it here
            self._end_failed(s)

    async def _failed(self, s: ActiveSession) -> None:
        try:
            await self.writer.flush()
        finally:
            self._end_failed(s)

    def _end_failed(self, s: ActiveSession) -> None:
        if self.active is s:
            self.active = None
        self.events.publish("session", {"id": s.record.id, "state": s.record.state.value, "reason": s.record.reason})
        s.done.set()

# ------------------------------------------------------------------ helpers


def _converged_reason(state: "CalibrationState") -> str:
    n = sum(1 for c in state.cameras if c.cycles > 0)
    idle = [c.name for c in state.cameras if c.cycles == 0]
    msg = f"all {n} calibrated cameras converged"
    if idle:
        msg += f"; never observed: {', '.join(idle[:8])}{' ...' if len(idle) > 8 else ''}"
    return msg


def _calibrating_reason(state: "CalibrationState", report: "CycleReport") -> str:
    calibrated = [c for c in state.cameras if c.cycles > 0]
    if not calibrated:
        return f"cycle {report.cycle}: no camera has an update yet" + (f" ({report.reason})" if report.reason else "")
    done = sum(1 for c in calibrated if c.converged)
    pending = sorted((c for c in calibrated if not c.converged), key=lambda c: -c.std_translation)
    worst = f"; least certain: {pending[0].name}" if pending else ""
    moved = [c.name for c in state.cameras if c.moved_at is not None and not c.converged]
    again = f"; moved, calibrating again: {', '.join(moved)}" if moved else ""
    return f"{done}/{len(calibrated)} cameras converged{worst}{again}"


def _waiting_reason(counters: Any, cfg: EngineConfig, sensors: SensorTable, names: tuple[str, ...]) -> str:
    if counters.messages == 0:
        online = [n for n in names if (x := sensors.get(n)) is not None and x.messages]
        return "no messages from the session's cameras yet" if not online else \
            f"messages from {len(online)} sensors, none accepted yet"
    if counters.framesets == 0:
        return f"{counters.messages} messages, no frameset yet (needs {cfg.sync.min_views} sensors at one instant)"
    need = 2 * cfg.select.scope
    return (f"{counters.framesets} framesets, {counters.hypotheses} person hypotheses; the first cycle "
            f"needs {need} waiting")


def _history_line(report: "CycleReport", state: "CalibrationState", state_name: str,
                  acc: dict[str, Any] | None) -> dict[str, Any]:
    cams = state.cameras
    return {
        **report.to_dict(),
        "wall": time.time(),
        "state": state_name,
        "converged": state.converged,
        "cameras_converged": sum(1 for c in cams if c.converged),
        "cameras_calibrated": sum(1 for c in cams if c.cycles > 0),
        "max_std_translation": max((c.std_translation for c in cams), default=None),
        "max_std_rotation": max((c.std_rotation for c in cams), default=None),
        "accuracy": acc,
        "per_camera": {c.name: [c.std_translation, c.std_rotation, _finite(c.change_translation),
                                _finite(c.change_rotation), c.converged] for c in cams},
    }


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
