"""Framesets from free-running sensors.

Sensors are not triggered together (10-30 Hz, random phases), so a frameset is a
capture instant T on a regular grid of data time, not "one message per sensor within
50 ms". For every sensor the two messages that bracket T are found; persons are
matched between them and their keypoints interpolated to T. A sensor without a
bracketing pair falls back to its nearest message within ``max_offset``; a sensor
with neither sits this frameset out. The paper's span/std limits then apply to the
stamps the frameset really uses.
"""

from __future__ import annotations

import bisect
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from proto import KeypointMessage

from .config import SyncConfig

N_J = 17
# Persons in consecutive frames of one sensor are the same person when their joints
# moved less than this fraction of the image diagonal per second (a sprinter at 3 m
# from a wide lens crosses ~0.8 diagonals/s).
_MATCH_DIAG_PER_S = 1.0
_MATCH_MIN_FRAC = 0.03


@dataclass(frozen=True, eq=False)
class View:
    """One sensor's detections at the frameset time.

    kp: (P, 17, 3) float64 raw pixels (u, v) and confidence; interpolated when
        ``interpolated``.
    boxes: (P, 4) float64 [x0, y0, x1, y1], NaN when the sensor sent none.
    cov: (P, 17, 3) float64 pixel² [xx, xy, yy], or None.
    offset: s between the stamp used and the frameset time (0 when interpolated).
    speed: (P, 17) float64 px/s image speed of each joint where known, else 0.
    seq, index: where each person came from: message ``seq`` of this sensor (the earlier
        one when interpolated) and (P,) int64 positions in its ``persons``.
    """

    sensor: str
    stamp: float
    offset: float
    size: tuple[int, int]
    kp: np.ndarray
    boxes: np.ndarray
    cov: np.ndarray | None
    speed: np.ndarray
    interpolated: bool
    seq: int = -1
    index: np.ndarray | None = None

    def __post_init__(self) -> None:
        P = self.kp.shape[0]
        assert self.index is None or self.index.shape == (P,)
        assert self.kp.shape == (P, N_J, 3)
        assert self.boxes.shape == (P, 4)
        assert self.speed.shape == (P, N_J)
        assert self.cov is None or self.cov.shape == (P, N_J, 3)


@dataclass(frozen=True)
class Frameset:
    time: float
    views: tuple[View, ...]


@dataclass(frozen=True, eq=False)
class Buffered:
    """A buffered message with its arrays stacked once (kp (P, 17, 3), boxes (P, 4))."""

    msg: KeypointMessage
    kp: np.ndarray
    boxes: np.ndarray
    cov: np.ndarray | None

    @property
    def stamp(self) -> float:
        return self.msg.stamp

    @staticmethod
    def of(msg: KeypointMessage) -> "Buffered":
        boxes = np.array([p.bbox if p.bbox is not None else np.full(4, np.nan) for p in msg.persons]).reshape(-1, 4)
        cov = None
        if msg.persons and all(p.cov is not None for p in msg.persons):
            cov = np.stack([p.cov for p in msg.persons])
        return Buffered(msg, msg.keypoints(), boxes, cov)

    def replaced(self, **changes) -> "Buffered":
        """The same arrays with the message's fields changed (``stamp=...``)."""
        return Buffered(replace(self.msg, **changes), self.kp, self.boxes, self.cov)


class _Recent:
    """The last ``n`` (seq, stamp) of one sensor, for the duplicate check in O(1): a deque's
    ``in`` compares all of them, for every message."""

    def __init__(self, n: int):
        self._order: deque = deque()
        self._set: set = set()
        self._n = n

    def __contains__(self, x: object) -> bool:
        return x in self._set

    def copy(self) -> "_Recent":
        c = _Recent(self._n)
        c._order, c._set = deque(self._order), set(self._set)
        return c

    def add(self, x: tuple) -> None:
        if x in self._set:
            return
        if len(self._order) >= self._n:
            self._set.discard(self._order.popleft())
        self._order.append(x)
        self._set.add(x)


def _match(a: np.ndarray, b: np.ndarray, max_dist: float) -> list[tuple[int, int]]:
    """Greedy matching of persons a (P, 17, 3) and b (Q, 17, 3) by mean joint distance."""
    if len(a) == 0 or len(b) == 0:
        return []
    both = (a[:, None, :, 2] > 0) & (b[None, :, :, 2] > 0)  # (P, Q, 17)
    d = np.linalg.norm(a[:, None, :, :2] - b[None, :, :, :2], axis=-1)
    n = both.sum(-1)
    cost = np.where(n >= 4, np.where(both, d, 0).sum(-1) / np.maximum(n, 1), np.inf)
    pairs = []
    used_a, used_b = set(), set()
    for flat in np.argsort(cost, axis=None):
        i, j = divmod(int(flat), cost.shape[1])
        if cost[i, j] > max_dist:
            break
        if i in used_a or j in used_b:
            continue
        pairs.append((i, j))
        used_a.add(i)
        used_b.add(j)
    return pairs


def _single(e: Buffered, T: float) -> View:
    m = e.msg
    P = len(e.kp)
    return View(m.sensor, m.stamp, m.stamp - T, m.size, e.kp, e.boxes, e.cov, np.zeros((P, N_J)), False,
                m.seq, np.arange(P))


def interpolate(m0: KeypointMessage, m1: KeypointMessage, T: float) -> View:
    """Keypoints of the persons seen in both messages, linearly interpolated to T."""
    return _interpolate(Buffered.of(m0), Buffered.of(m1), T, {})


def _interpolate(e0: Buffered, e1: Buffered, T: float, cache: dict) -> View:
    """Keypoints of persons seen in both messages, linearly interpolated to T.

    A joint missing in either message is missing. Persons seen in only one message are
    dropped: their time offset is unknown to the frameset.
    """
    m0, m1 = e0.msg, e1.msg
    dt = m1.stamp - m0.stamp
    assert dt > 0 and m0.stamp <= T <= m1.stamp
    w = (T - m0.stamp) / dt
    k0, k1 = e0.kp, e1.kp
    key = (m0.sensor, m0.stamp, m1.stamp)
    if key not in cache:  # the same pair brackets several frameset times
        diag = float(np.hypot(*m0.size))
        cache[key] = _match(k0, k1, diag * max(_MATCH_MIN_FRAC, _MATCH_DIAG_PER_S * dt))
    pairs = cache[key]
    if not pairs:
        return View(m0.sensor, T, 0.0, m0.size, np.zeros((0, N_J, 3)), np.zeros((0, 4)), None,
                    np.zeros((0, N_J)), True, m0.seq, np.zeros(0, np.int64))
    i0 = [i for i, _ in pairs]
    i1 = [j for _, j in pairs]
    a, b = k0[i0], k1[i1]
    kp = (1 - w) * a + w * b
    ok = (a[..., 2] > 0) & (b[..., 2] > 0)
    kp[..., 2] = np.where(ok, np.minimum(a[..., 2], b[..., 2]), 0.0)
    speed = np.where(ok, np.linalg.norm(b[..., :2] - a[..., :2], axis=-1) / dt, 0.0)
    boxes = (1 - w) * e0.boxes[i0] + w * e1.boxes[i1]
    c0, c1 = e0.cov, e1.cov
    cov = None if c0 is None or c1 is None else (1 - w) * c0[i0] + w * c1[i1]
    return View(m0.sensor, T, 0.0, m0.size, kp, boxes, cov, speed, True, m0.seq, np.array(i0, dtype=np.int64))


_UNKNOWN_NAMES = 32


class Synchronizer:
    """Per-sensor buffers → framesets on a regular grid of data time.

    ``push`` takes messages in arrival order (stamps need not be sorted);
    ``pop_ready(now)`` returns every frameset whose time is at least ``wait`` behind
    ``now``. Rejections and dropped framesets are counted by reason.
    """

    def __init__(self, config: SyncConfig, sensors: list[str] | tuple[str, ...]):
        self.cfg = config
        self.sensors = tuple(sensors)
        self._stamps: dict[str, list[float]] = {s: [] for s in self.sensors}
        self._msgs: dict[str, list[Buffered]] = {s: [] for s in self.sensors}
        self._pairs: dict[tuple[str, float, float], list[tuple[int, int]]] = {}
        self._last_seq: dict[str, _Recent] = {s: _Recent(64) for s in self.sensors}
        self.next_time: float | None = None
        self.rejected: Counter = Counter()
        # per reason, the messages of each sensor (of unknown names the first
        # _UNKNOWN_NAMES: a typo in a sensor's id is named to the user, random names
        # cannot grow it without bound)
        self.rejected_sensors: dict[str, Counter] = {}
        self._unknown_names: set[str] = set()
        self.framesets = 0
        self.framesets_rejected: Counter = Counter()
        self.latest_stamp: float | None = None
        self.offsets: dict[str, float] = {}  # s subtracted from a sensor's stamps

    def offset(self, sensor: str) -> float:
        return self.offsets.get(sensor, 0.0)

    def set_offset(self, sensor: str, offset: float) -> None:
        """From now on subtract ``offset`` s from the sensor's stamps (messages already
        buffered are re-stamped, so its stream stays ordered)."""
        if sensor not in self._stamps:
            raise KeyError(sensor)
        shift = self.offset(sensor) - offset
        self.offsets[sensor] = float(offset)
        if shift:
            self._stamps[sensor] = [x + shift for x in self._stamps[sensor]]
            self._msgs[sensor] = [e.replaced(stamp=e.stamp + shift) for e in self._msgs[sensor]]

    def take_buffers(self, other: "Synchronizer", sensors: Iterable[str]) -> None:
        """The buffered messages of ``sensors`` from ``other`` (which times them with its
        own offsets), nothing else (a camera joining a running pipeline)."""
        for s in sensors:
            shift = other.offset(s) - self.offset(s)
            self._stamps[s] = [x + shift for x in other._stamps.get(s, [])]
            self._msgs[s] = [e.replaced(stamp=e.stamp + shift) if shift else e for e in other._msgs.get(s, [])]
            self._last_seq[s] = other._last_seq[s].copy() if s in other._last_seq else _Recent(64)

    def take_over(self, other: "Synchronizer") -> None:
        """Go on where ``other`` (of the same or more sensors) is: its buffered messages of
        our sensors, its point in time and its counts; nothing it emitted is emitted again
        (a live session's pipeline replacing the bootstrap's collector)."""
        for s in self.sensors:
            self._stamps[s] = list(other._stamps.get(s, []))
            self._msgs[s] = list(other._msgs.get(s, []))
            self._last_seq[s] = other._last_seq[s].copy() if s in other._last_seq else _Recent(64)
            if s in other.offsets:
                self.offsets[s] = other.offsets[s]
        self.next_time = other.next_time
        self.latest_stamp = other.latest_stamp
        self.framesets = other.framesets
        self.framesets_rejected = Counter(other.framesets_rejected)
        self.rejected = Counter(other.rejected)
        self.rejected_sensors = {k: Counter(v) for k, v in other.rejected_sensors.items()}
        self._unknown_names = set(other._unknown_names)

    def push(self, msg: KeypointMessage, now: float | None = None) -> str | None:
        """Buffer one message (raw stamp: the sensor's offset is subtracted here);
        returns a rejection reason or None."""
        s = msg.sensor
        if s not in self._stamps:
            if s not in self._unknown_names and len(self._unknown_names) >= _UNKNOWN_NAMES:
                return self._reject("unknown_sensor")
            self._unknown_names.add(s)
            return self._reject("unknown_sensor", s)
        raw = (msg.seq, msg.stamp)
        if self.offsets.get(s):
            msg = replace(msg, stamp=msg.stamp - self.offsets[s])
        if now is not None:
            if msg.stamp > now + self.cfg.max_stamp_future:
                return self._reject("stamp_in_future", s)
            if msg.stamp < now - self.cfg.max_stamp_past:
                return self._reject("stamp_too_old", s)
        if self.next_time is not None and msg.stamp < self.next_time - self.cfg.wait - 1.0:
            return self._reject("late", s)
        if raw in self._last_seq[s]:
            return self._reject("duplicate", s)
        self._last_seq[s].add(raw)
        stamps, msgs = self._stamps[s], self._msgs[s]
        i = bisect.bisect_right(stamps, msg.stamp)
        if i > 0 and stamps[i - 1] == msg.stamp:
            return self._reject("duplicate", s)
        stamps.insert(i, msg.stamp)
        msgs.insert(i, Buffered.of(msg))
        if self.latest_stamp is None or msg.stamp > self.latest_stamp:
            self.latest_stamp = msg.stamp
        if self.next_time is None:
            step = 1.0 / self.cfg.rate
            self.next_time = np.ceil(msg.stamp / step) * step + step
        return None

    def _reject(self, reason: str, sensor: str | None = None) -> str:
        self.rejected[reason] += 1
        if sensor is not None:
            self.rejected_sensors.setdefault(reason, Counter())[sensor] += 1
        return reason

    def pop_ready(self, now: float) -> list[Frameset]:
        if not np.isfinite(now):  # +inf would emit framesets forever, NaN none ever again
            raise ValueError(f"the sync's clock must be a finite time, not {now}")
        out: list[Frameset] = []
        if self.next_time is None:
            return out
        step = 1.0 / self.cfg.rate
        # After a long silence do not emit thousands of empty framesets: jump ahead, once
        # the framesets the last messages still cover are out (they were waiting for them).
        if self.latest_stamp is not None and now - self.next_time > 10.0:
            self._emit(min(now - self.cfg.wait, self.latest_stamp + self.cfg.max_offset), step, out)
            self.next_time = max(self.next_time, np.floor((now - self.cfg.wait) / step) * step)
        self._emit(now - self.cfg.wait, step, out)
        return out

    def _emit(self, until: float, step: float, out: list[Frameset]) -> None:
        """The framesets of the grid up to ``until`` into ``out``."""
        while self.next_time <= until:
            fs = self._build(self.next_time)
            if fs is not None:
                out.append(fs)
            self.next_time += step
            self._prune(self.next_time - 2.0)

    def _prune(self, before: float) -> None:
        for s in self.sensors:
            stamps = self._stamps[s]
            # keep one message older than `before` so the next bracket still has its left side
            k = bisect.bisect_left(stamps, before) - 1
            if k > 0:
                del stamps[:k]
                del self._msgs[s][:k]
        if len(self._pairs) > 4096:
            self._pairs.clear()

    def _build(self, T: float) -> Frameset | None:
        views = []
        for s in self.sensors:
            v = self._view(s, T)
            if v is not None:
                views.append(v)
        used = [v for v in views if len(v.kp)]
        if len(used) < self.cfg.min_views:
            self.framesets_rejected["too_few_views"] += 1
            return None
        st = np.array([v.stamp for v in used])
        if st.max() - st.min() > self.cfg.max_span:
            self.framesets_rejected["stamp_span"] += 1
            return None
        if st.std() > self.cfg.max_std:
            self.framesets_rejected["stamp_std"] += 1
            return None
        self.framesets += 1
        return Frameset(float(T), tuple(views))

    def _view(self, s: str, T: float) -> View | None:
        return view_at(self._stamps[s], self._msgs[s], T, self.cfg, self._pairs)


def view_at(stamps: list[float], msgs: list[Buffered], T: float, cfg: SyncConfig, cache: dict) -> View | None:
    """One sensor's view at frameset time T from its messages (``stamps`` sorted, on the
    synchronised clock): interpolated between the two that bracket T, else the nearest
    within ``max_offset``; None when it saw nobody there. ``cache``: person matches of
    message pairs, shared between calls."""
    i = bisect.bisect_right(stamps, T)
    m0 = msgs[i - 1] if i > 0 else None
    m1 = msgs[i] if i < len(msgs) else None
    if (m0 is None or not len(m0.kp)) and (m1 is None or not len(m1.kp)):
        return None  # nobody seen: nothing to add
    if m0 is not None and m0.stamp == T:
        return _single(m0, T)
    if (
        cfg.interpolate and m0 is not None and m1 is not None
        and m1.stamp - m0.stamp <= cfg.max_gap + 1e-9
        and m0.msg.size == m1.msg.size
    ):
        return _interpolate(m0, m1, T, cache)
    best = min((m for m in (m0, m1) if m is not None), key=lambda m: abs(m.stamp - T), default=None)
    if best is None or abs(best.stamp - T) > cfg.max_offset:
        return None
    return _single(best, T)
