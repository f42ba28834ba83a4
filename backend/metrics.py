"""Prometheus metrics of the live service, in a registry per app.

Each ``Metrics`` owns its own ``CollectorRegistry`` (not prometheus_client's global one),
so several apps in one process (tests) do not collide. The engine and the service keep
cumulative totals (``Counters``, per-sensor statistics); ``update_from_state`` turns them
into Prometheus counters by adding what grew since the last call. A total that went down
means a new session (a new pipeline) started from zero: its new total is added, so the
exported counters only ever grow, as Prometheus expects (``rate()`` works across sessions).

Wiring, for the service (see docs/dashboard.md)::

    m = Metrics()
    mount(app, m, refresh=lambda: update_from_state(m, service.active_state(), service.status()))
    # and after every cycle, for the cycle-time histogram:
    observe_cycle(m, report, wall_seconds)

Names (all prefixed ``extrcal_``):

=============================================  =========  =====================================
messages_total{sensor}                          counter    keypoint messages received
messages_rejected_total{reason}                 counter    messages rejected, by reason
framesets_total{result="accepted"|"rejected"}   counter    framesets built
framesets_rejected_total{reason}                counter    framesets rejected, by reason
views_total / views_rejected_total{reason}      counter    person detections after preprocessing
hypotheses_total                                counter    person hypotheses made
hypotheses_dropped_total                        counter    hypotheses dropped from a full queue
queue_length{queue="hypotheses"|"ingest"}       gauge      items waiting
ingest_dropped_total                            counter    payloads dropped from a full ingest queue
cycles_total{result="accepted"|"rejected"}      counter    optimisation cycles
cycle_seconds                                   histogram  solve time of a cycle (s)
cycle_wall_seconds                              histogram  wall time of a cycle incl. hand-off (s)
cycle                                           gauge      cycle number of the current session
reprojection_pixels                             gauge      median reprojection error, last cycle
camera_std_translation_meters{camera}           gauge      per-camera position std
camera_std_rotation_degrees{camera}             gauge      per-camera orientation std
camera_observations{camera}                     gauge      projections used so far
camera_converged{camera}                        gauge      1 when the camera is converged
converged                                       gauge      1 when the calibration is converged
position_error_meters / orientation_error_degrees  gauge   vs reference, when one was given
=============================================  =========  =====================================
"""

from __future__ import annotations

import math
from dataclasses import asdict, is_dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

if TYPE_CHECKING:
    from .state import CalibrationState, CycleReport

# Solve times run from ~10 ms (few cameras) to seconds (100 cameras, batch adjustments).
CYCLE_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class Metrics:
    """The metric objects of one service, registered in ``self.registry``."""

    def __init__(self, registry: CollectorRegistry | None = None, prefix: str = "extrcal"):
        self.registry = registry if registry is not None else CollectorRegistry()
        r, p = self.registry, prefix
        self.messages = Counter(f"{p}_messages", "Keypoint messages received", ["sensor"], registry=r)
        self.messages_rejected = Counter(f"{p}_messages_rejected", "Keypoint messages rejected", ["reason"], registry=r)
        self.framesets = Counter(f"{p}_framesets", "Framesets built", ["result"], registry=r)
        self.framesets_rejected = Counter(f"{p}_framesets_rejected", "Framesets rejected", ["reason"], registry=r)
        self.views = Counter(f"{p}_views", "Person detections that passed preprocessing", registry=r)
        self.views_rejected = Counter(f"{p}_views_rejected", "Person detections dropped", ["reason"], registry=r)
        self.hypotheses = Counter(f"{p}_hypotheses", "Person hypotheses made", registry=r)
        self.hypotheses_dropped = Counter(f"{p}_hypotheses_dropped", "Hypotheses dropped from a full queue", registry=r)
        self.queue_length = Gauge(f"{p}_queue_length", "Items waiting", ["queue"], registry=r)
        self.ingest_dropped = Counter(f"{p}_ingest_dropped", "Payloads dropped from a full ingest queue", registry=r)
        self.cycles = Counter(f"{p}_cycles", "Optimisation cycles", ["result"], registry=r)
        self.cycle_seconds = Histogram(f"{p}_cycle_seconds", "Solve time of an optimisation cycle",
                                       buckets=CYCLE_BUCKETS, registry=r)
        self.cycle_wall_seconds = Histogram(f"{p}_cycle_wall_seconds", "Wall time of a cycle including the hand-off",
                                            buckets=CYCLE_BUCKETS, registry=r)
        self.cycle = Gauge(f"{p}_cycle", "Cycle number of the current session", registry=r)
        self.reprojection = Gauge(f"{p}_reprojection_pixels", "Median reprojection error of the last cycle", registry=r)
        self.std_translation = Gauge(f"{p}_camera_std_translation_meters", "Std of the camera position",
                                     ["camera"], registry=r)
        self.std_rotation = Gauge(f"{p}_camera_std_rotation_degrees", "Std of the camera orientation",
                                  ["camera"], registry=r)
        self.camera_observations = Gauge(f"{p}_camera_observations", "Projections of the camera used so far",
                                         ["camera"], registry=r)
        self.camera_converged = Gauge(f"{p}_camera_converged", "1 when the camera is converged", ["camera"], registry=r)
        self.converged = Gauge(f"{p}_converged", "1 when the calibration is converged", registry=r)
        self.position_error = Gauge(f"{p}_position_error_meters",
                                    "Mean camera position error vs the reference (rigid alignment)", registry=r)
        self.orientation_error = Gauge(f"{p}_orientation_error_degrees",
                                       "Mean camera orientation error vs the reference", registry=r)
        # last totals seen, per (metric, label) — to turn totals into increments
        self._seen: dict[tuple[str, str], float] = {}
        self._cameras: set[str] = set()
        self._observed_cycle: tuple[Any, int] | None = None


def _grow(m: Metrics, counter: Counter, key: str, label: str | None, total: Any) -> None:
    """Add to ``counter`` what ``total`` grew since the last call (all of it after a reset)."""
    if isinstance(total, bool) or not isinstance(total, (int, float)) or not math.isfinite(total) or total < 0:
        return
    k = (key, label or "")
    last = m._seen.get(k, 0.0)
    inc = total - last if total >= last else total
    m._seen[k] = float(total)
    if inc > 0:
        (counter.labels(label) if label is not None else counter).inc(inc)


def _grow_map(m: Metrics, counter: Counter, key: str, totals: Any) -> None:
    if isinstance(totals, Mapping):
        for label, total in totals.items():
            _grow(m, counter, key, str(label), total)


def observe_cycle(m: Metrics, report: "CycleReport | Mapping[str, Any]", wall_seconds: float | None = None,
                  session: Any = None) -> None:
    """Record one optimisation cycle in the histograms (once per (session, cycle))."""
    d = report.to_dict() if hasattr(report, "to_dict") else dict(report)
    key = (session, int(d["cycle"]))
    if m._observed_cycle == key:
        return
    m._observed_cycle = key
    solve = d.get("solve_seconds")
    if isinstance(solve, (int, float)) and math.isfinite(solve) and solve >= 0:
        m.cycle_seconds.observe(solve)
    if wall_seconds is not None and math.isfinite(wall_seconds) and wall_seconds >= 0:
        m.cycle_wall_seconds.observe(wall_seconds)


def update_from_state(m: Metrics, calibration_state: "CalibrationState | None",
                      counters: Mapping[str, Any] | None = None) -> None:
    """Bring the metrics up to date.

    ``calibration_state``: the current session's ``CalibrationState`` (None when no session
    runs: per-camera gauges are then removed). Its ``counters`` feed framesets, views,
    hypotheses, queue and cycles; its ``last_cycle`` the cycle histogram (once per cycle).

    ``counters``: what the service counts outside the pipeline, either the dict of the
    service's ``status()`` (keys ``sensors``, ``messages``, ``queues``, ``session``) or a
    plain mapping with any of ``messages_by_sensor`` (sensor → total),
    ``rejected_by_reason`` (reason → total), ``ingest_queue`` (length),
    ``ingest_dropped`` (total), ``accuracy`` (``position_mean`` m, ``orientation_mean`` deg),
    ``session`` (an id, so that cycle numbers of different sessions are told apart).
    """
    c = dict(counters or {})
    session_id = c.get("session")
    if isinstance(session_id, Mapping):
        session_id = session_id.get("id")

    # --- service-level counts: the status() shape or the plain one
    if isinstance(c.get("sensors"), Mapping):
        by_sensor = {n: s.get("messages") for n, s in c["sensors"].items() if isinstance(s, Mapping)}
    else:
        by_sensor = c.get("messages_by_sensor")
    _grow_map(m, m.messages, "messages", by_sensor)
    msgs = c.get("messages")
    rejected = msgs.get("rejected") if isinstance(msgs, Mapping) else c.get("rejected_by_reason")
    _grow_map(m, m.messages_rejected, "messages_rejected", rejected)
    queues = c.get("queues") if isinstance(c.get("queues"), Mapping) else {}
    ingest = queues.get("ingest") if isinstance(queues.get("ingest"), Mapping) else {}
    qlen = ingest.get("length", c.get("ingest_queue"))
    if isinstance(qlen, (int, float)) and not isinstance(qlen, bool):
        m.queue_length.labels("ingest").set(qlen)
    _grow(m, m.ingest_dropped, "ingest_dropped", None, ingest.get("dropped", c.get("ingest_dropped")))

    acc = c.get("accuracy")
    if acc is None and isinstance(c.get("session"), Mapping):
        acc = c["session"].get("accuracy")
    if isinstance(acc, Mapping):
        for gauge, k in ((m.position_error, "position_mean"), (m.orientation_error, "orientation_mean")):
            v = acc.get(k)
            if isinstance(v, (int, float)) and math.isfinite(v):
                gauge.set(v)

    # --- the pipeline's state
    st = calibration_state
    if st is None:
        for name in m._cameras:
            for g in (m.std_translation, m.std_rotation, m.camera_observations, m.camera_converged):
                g.remove(name)
        m._cameras = set()
        m.converged.set(0)
        return
    k = asdict(st.counters) if is_dataclass(st.counters) else dict(st.counters)
    _grow(m, m.framesets, "framesets", "accepted", k.get("framesets"))
    _grow(m, m.framesets, "framesets", "rejected", sum((k.get("framesets_rejected") or {}).values()))
    _grow_map(m, m.framesets_rejected, "framesets_rejected", k.get("framesets_rejected"))
    _grow(m, m.views, "views", None, k.get("views"))
    _grow_map(m, m.views_rejected, "views_rejected", k.get("views_rejected"))
    _grow(m, m.hypotheses, "hypotheses", None, k.get("hypotheses"))
    _grow(m, m.hypotheses_dropped, "hypotheses_dropped", None, k.get("queue_dropped"))
    rej = k.get("cycles_rejected") or 0
    _grow(m, m.cycles, "cycles", "accepted", max((k.get("cycles") or 0) - rej, 0))
    _grow(m, m.cycles, "cycles", "rejected", rej)
    if k.get("queue_length") is not None:
        m.queue_length.labels("hypotheses").set(k["queue_length"])

    m.cycle.set(st.cycle)
    m.converged.set(1 if st.converged else 0)
    names = set()
    for cam in st.cameras:
        names.add(cam.name)
        for g, v in ((m.std_translation, cam.std_translation), (m.std_rotation, cam.std_rotation)):
            g.labels(cam.name).set(v if math.isfinite(v) else math.nan)
        m.camera_observations.labels(cam.name).set(cam.observations)
        m.camera_converged.labels(cam.name).set(1 if cam.converged else 0)
    for gone in m._cameras - names:
        for g in (m.std_translation, m.std_rotation, m.camera_observations, m.camera_converged):
            g.remove(gone)
    m._cameras = names
    if st.last_cycle is not None:
        if st.last_cycle.reprojection_px is not None and math.isfinite(st.last_cycle.reprojection_px):
            m.reprojection.set(st.last_cycle.reprojection_px)
        observe_cycle(m, st.last_cycle, session=session_id)


def asgi_app(m: Metrics, refresh: Callable[[], None] | None = None) -> Callable:
    """The ``/metrics`` ASGI app (prometheus_client's, on this registry); ``refresh`` runs
    before every scrape, on the event loop, so it must be quick and must not block."""
    from prometheus_client import make_asgi_app

    return _MetricsASGI(make_asgi_app(m.registry), refresh)


class _MetricsASGI:
    """An ASGI object, not a function: Starlette's Route passes non-functions the raw
    (scope, receive, send) instead of treating them as request handlers."""

    def __init__(self, inner: Callable, refresh: Callable[[], None] | None):
        self.inner, self.refresh = inner, refresh

    async def __call__(self, scope, receive, send) -> None:  # noqa: ANN001 - ASGI
        if scope["type"] == "http" and self.refresh is not None:
            self.refresh()
        await self.inner(scope, receive, send)


def mount(app: Any, m: Metrics, refresh: Callable[[], None] | None = None, path: str = "/metrics") -> None:
    """Serve the metrics at exactly ``path`` on a FastAPI/Starlette app.

    A plain ``app.mount(path, ...)`` answers ``path`` with a redirect to ``path/``; a route
    whose endpoint is an ASGI app answers it directly.
    """
    from starlette.routing import Route

    app.router.routes.append(Route(path, endpoint=asgi_app(m, refresh), methods=["GET", "HEAD"],
                                   include_in_schema=False))
