"""From Zenoh's threads to the event loop: hand-off queue, service clock, sensor statistics.

Zenoh calls subscriber callbacks on its own threads. A callback here reads the key and
the wall clock; a payload from a sensor the running session does not use is only counted
(by sensor, on the Zenoh thread: no copy, no hand-over); any other payload is copied into
a bounded queue that drops the oldest item when full and counts it. The loop is woken
once per batch (``loop.call_soon_threadsafe`` when it waits for an empty queue), not once
per message. Decoding and the pipeline run on the loop.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from proto.keys import sensor_of

# ------------------------------------------------------------------ hand-off


@dataclass(frozen=True, slots=True)
class Arrival:
    """One payload as it left Zenoh: key expression, bytes, wall-clock arrival (s)."""

    key: str
    payload: bytes
    wall: float


@dataclass(frozen=True, slots=True)
class Refused:
    """Payloads of one sensor refused by key on the Zenoh threads since the last ``take_refused``:
    how many, the wall time of the first and the last."""

    count: int
    first_wall: float
    last_wall: float


class HandOff:
    """Bounded queue fed from Zenoh's threads, drained by the loop; drops the oldest and counts it.

    Newest data is worth more to an online calibration than old data, so overflow
    discards from the front. ``accept(names)`` (from the loop) sets the sensors whose
    payloads are queued; the others are refused on the Zenoh thread and only counted,
    so that a flood from sensors outside the session costs the loop nothing. A lock
    guards the queue; it is held for an append or a pop, never across an await.
    """

    MAX_REFUSED_NAMES = 4096  # names refused per interval; beyond that they count under None

    def __init__(self, loop: asyncio.AbstractEventLoop, capacity: int):
        assert capacity > 0
        self._loop = loop
        self._lock = threading.Lock()
        self._items: deque[Arrival] = deque()
        self._capacity = capacity
        self._ready = asyncio.Event()
        self._waiting = False  # the loop waits for an item: the next one wakes it
        self._accept: frozenset[str] | None = None  # None: every sensor's payloads are queued
        self._refused: dict[str | None, list] = {}  # sensor -> [count, first wall, last wall]
        self.received = 0  # queued (dropped ones included)
        self.dropped = 0
        self.refused = 0  # refused by key, in all
        self.wakeups = 0  # hand-overs to the loop
        self.closed = False

    # Zenoh thread ------------------------------------------------------------
    def on_sample(self, sample: Any) -> None:
        """Zenoh subscriber callback: filter, copy, stamp, queue. Never blocks (the lock
        is only held for an append), never calls Zenoh."""
        key = str(sample.key_expr)
        wall = time.time()
        accept = self._accept
        if accept is not None:
            name = sensor_of(key)
            if name is not None and name not in accept:
                with self._lock:
                    self.refused += 1
                    r = self._refused.get(name)
                    if r is None and len(self._refused) >= self.MAX_REFUSED_NAMES:
                        name, r = None, self._refused.get(None)
                    if r is None:
                        self._refused[name] = [1, wall, wall]
                    else:
                        r[0] += 1
                        r[2] = wall
                return
        self._put(Arrival(key, sample.payload.to_bytes(), wall))

    def _put(self, item: Arrival) -> None:
        with self._lock:
            if self.closed:
                return
            self.received += 1
            if len(self._items) >= self._capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            wake, self._waiting = self._waiting, False
        if wake:
            self.wakeups += 1
            try:
                self._loop.call_soon_threadsafe(self._ready.set)
            except RuntimeError:  # the loop is closed: the service is shutting down
                pass

    # loop ----------------------------------------------------------------------
    def accept(self, names: frozenset[str] | None) -> None:
        """Queue only payloads whose key names one of ``names`` (None: all). Keys without a
        sensor name are always queued (the loop counts them)."""
        self._accept = names

    def put_nowait(self, item: Arrival) -> None:
        """For producers already on the loop."""
        self._put(item)

    async def get_batch(self, limit: int) -> list[Arrival]:
        """Wait for at least one item, return up to ``limit`` (FIFO)."""
        while True:
            with self._lock:
                if self._items:
                    n = min(limit, len(self._items))
                    return [self._items.popleft() for _ in range(n)]
                if self.closed:
                    return []
                self._ready.clear()
                self._waiting = True
            await self._ready.wait()

    def take_refused(self) -> dict[str | None, Refused]:
        """What was refused by key since the last call, by sensor (None: names beyond the cap)."""
        with self._lock:
            r, self._refused = self._refused, {}
        return {k: Refused(*v) for k, v in r.items()}

    def close(self) -> None:
        with self._lock:
            self.closed = True
        self._ready.set()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def capacity(self) -> int:
        return self._capacity


# ------------------------------------------------------------------ clock


class ServiceClock:
    """The time the pipeline runs on, in the sensors' time base (seconds since the epoch).

    ``wall``: this host's clock; sensors and host are NTP-synchronised, so a message's
    age is ``arrival - stamp``. The mode for real sensors.

    ``data``: the clock follows the data: it is the newest stamp the loop has taken
    (never decreasing), so a replay or a simulation that runs K times faster than real
    time, or a loop that falls behind under load, sees consistent data time and no
    message ages on the way. When no data came for ``grace`` wall seconds, the clock
    runs on at ``speed`` data seconds per wall second, so that framesets waiting for
    late messages are closed and stop criteria by duration still fire; data arriving
    slower than ``speed`` (a simulator that cannot keep up) never lets the clock run
    ahead of it. The clock follows the median of the sensors' newest stamps, not the
    newest of all, so one sensor whose clock jumped ahead cannot drag everyone along
    (and make their messages late). A lone stream's stamp more than ``max_jump`` seconds
    ahead does not count at all; with several sensors it counts towards the median, so
    that the clock follows when most of them are ahead (it had fallen behind).
    """

    def __init__(self, mode: Literal["wall", "data"], *, speed: float = 1.0, grace: float = 1.0,
                 max_jump: float = 5.0, monotonic: Callable[[], float] = time.monotonic):
        assert mode in ("wall", "data") and speed > 0
        self.mode = mode
        # injectable so that tests step it rather than race the scheduler with sleeps
        self._monotonic = monotonic
        self.speed = speed
        self.grace = grace
        self.max_jump = max_jump
        self._high: float | None = None  # the clock's value at the last message (data mode)
        self._last = 0.0  # monotonic time of the last message
        self._newest: dict[str, float] = {}  # sensor → its newest plausible stamp

    def now(self) -> float | None:
        """Current clock time, or None before the data clock has seen any message."""
        if self.mode == "wall":
            return time.time()
        if self._high is None:
            return None
        idle = self._monotonic() - self._last - self.grace
        return self._high + self.speed * idle if idle > 0 else self._high

    def observe(self, stamp: float, sensor: str | None = None) -> float:
        """A message with ``stamp`` arrives (from ``sensor``); returns its arrival time on
        this clock."""
        if self.mode == "wall":
            return time.time()
        now = self.now()
        # Data flows again: the run-on time (if any) is kept, so the clock never goes back.
        self._high = now
        self._last = self._monotonic()
        key = sensor if sensor is not None else ""
        if now is not None and stamp - now > self.max_jump and (len(self._newest) < 2 or sensor is None):
            return now  # a lone stream far ahead: nothing confirms it
        # Far-ahead stamps of many sensors are recorded too: the median moves only when
        # most sensors are ahead, and then the clock is behind (the loop stalled while
        # data runs many times faster than real time, and the hand-off dropped the oldest).
        if len(self._newest) < 4096 or key in self._newest:
            self._newest[key] = max(stamp, self._newest.get(key, stamp))
        stamps = sorted(self._newest.values())
        typical = stamps[(len(stamps) - 1) // 2]  # the lower median: one sensor ahead is not enough
        if now is None or typical > now:
            self._high = typical
        return self._high

    def to_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "speed": self.speed, "now": self.now()}


# ------------------------------------------------------------------ per-sensor statistics


@dataclass
class SensorStats:
    """What /status shows per sensor. Times in the service clock's base."""

    name: str
    messages: int = 0
    accepted: int = 0
    rejected: Counter = field(default_factory=Counter)
    last_seen_wall: float | None = None  # host wall clock, for "seconds ago"
    last_stamp: float | None = None
    last_seq: int | None = None
    online: bool | None = None  # from liveliness; None: the sensor declares no token
    _arrivals: deque = field(default_factory=lambda: deque(maxlen=256))  # (wall time, messages)
    _latency: deque = field(default_factory=lambda: deque(maxlen=256))  # arrival - stamp

    def seen(self, wall: float, n: int = 1) -> None:
        """``n`` messages arrived, the last at ``wall`` (n > 1: counted together, e.g.
        refused on a Zenoh thread)."""
        self.messages += n
        self.last_seen_wall = wall
        self._arrivals.append((wall, n))

    def timing(self, stamp: float, arrival: float, seq: int) -> None:
        self.last_stamp = stamp
        self.last_seq = seq
        self._latency.append(arrival - stamp)

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1

    def rate(self, now_wall: float) -> float:
        """Messages per wall second over the recent window (0 once the sensor went quiet)."""
        a = self._arrivals
        if len(a) < 2 or now_wall - a[-1][0] > 5.0:
            return 0.0
        span = a[-1][0] - a[0][0]
        return (sum(n for _, n in a) - a[0][1]) / span if span > 0 else 0.0

    def to_dict(self, now_wall: float) -> dict[str, Any]:
        lat = sorted(self._latency)
        latency = None
        offset = None
        if lat:
            latency = {"median": lat[len(lat) // 2], "p95": lat[min(len(lat) - 1, int(0.95 * len(lat)))],
                       "max": lat[-1]}
            # The smallest (arrival - stamp) over the window is the one-way delay of the
            # fastest message plus the clock offset; transport on a LAN takes ~ms, so
            # it estimates how far the sensor's clock lags ours (negative: it runs ahead).
            offset = lat[0]
        return {
            "name": self.name,
            "online": self.online,
            "messages": self.messages,
            "accepted": self.accepted,
            "rejected": dict(self.rejected),
            "last_seen_ago": None if self.last_seen_wall is None else max(now_wall - self.last_seen_wall, 0.0),
            "last_stamp": self.last_stamp,
            "last_seq": self.last_seq,
            "rate": self.rate(now_wall),
            "latency": latency,
            "clock_offset": offset,
        }


class SensorTable:
    """Statistics of every sensor that published or declared liveliness (bounded)."""

    MAX_SENSORS = 4096  # beyond this, unknown names are lumped together (a flood of fake ids)

    def __init__(self) -> None:
        self._by_name: dict[str, SensorStats] = {}
        self.unattributed = Counter()  # rejections with no usable sensor name, by reason

    def get(self, name: str | None) -> SensorStats | None:
        if name is None:
            return None
        s = self._by_name.get(name)
        if s is None:
            if len(self._by_name) >= self.MAX_SENSORS:
                return None
            s = self._by_name[name] = SensorStats(name)
        return s

    def liveliness(self, key: str, alive: bool) -> None:
        s = self.get(sensor_of(key))
        if s is not None:
            s.online = alive

    def names(self) -> list[str]:
        return list(self._by_name)

    def to_dict(self, now_wall: float | None = None, *, max_offset: float = 0.025,
                max_latency: float = 0.25) -> dict[str, Any]:
        """Per-sensor status with ``warnings``: a clock set apart from the others' by more
        than ``max_offset`` (the frameset std limit: its messages miss framesets or skew
        them), or messages arriving later than ``max_latency`` (the framesets' wait)."""
        from .cameras import natural_key

        now_wall = time.time() if now_wall is None else now_wall
        out = {n: self._by_name[n].to_dict(now_wall) for n in sorted(self._by_name, key=natural_key)}
        offsets = [d["clock_offset"] for d in out.values() if d["clock_offset"] is not None]
        typical = sorted(offsets)[len(offsets) // 2] if offsets else None
        for d in out.values():
            warnings = []
            off = d["clock_offset"]
            if off is not None and typical is not None and len(offsets) >= 3 and abs(off - typical) > max_offset:
                warnings.append(f"clock {1000 * (typical - off):+.0f} ms from the other sensors' "
                                f"(limit {1000 * max_offset:.0f} ms): check its NTP; sessions estimate it from the data "
                                "once its stamps run more than clock.auto_lead apart (clock.estimate = auto, the "
                                "default; true: from the start)")
            lat = d["latency"]
            if lat is not None and lat["median"] > max_latency:
                warnings.append(f"messages arrive {1000 * lat['median']:.0f} ms after capture, later than "
                                f"framesets wait ({1000 * max_latency:.0f} ms)")
            d["warnings"] = warnings
        return out


def finite_or_none(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None
