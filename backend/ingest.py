"""From Zenoh's threads to the event loop: hand-off queue, service clock, sensor statistics.

Zenoh calls subscriber callbacks on its own threads. A callback here only copies the
payload, reads the wall clock and hands both to the loop with
``loop.call_soon_threadsafe``; the loop puts them into a bounded queue that drops the
oldest item when full and counts it. Decoding and the pipeline run on the loop.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import Counter, deque
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


class HandOff:
    """Bounded queue on the loop fed from any thread; drops the oldest and counts it.

    Newest data is worth more to an online calibration than old data, so overflow
    discards from the front.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, capacity: int):
        assert capacity > 0
        self._loop = loop
        self._items: deque[Arrival] = deque()
        self._capacity = capacity
        self._ready = asyncio.Event()
        self.received = 0
        self.dropped = 0
        self.closed = False

    # Zenoh thread ------------------------------------------------------------
    def on_sample(self, sample: Any) -> None:
        """Zenoh subscriber callback: copy, stamp, hand over. Never blocks, never calls Zenoh."""
        item = Arrival(str(sample.key_expr), sample.payload.to_bytes(), time.time())
        try:
            self._loop.call_soon_threadsafe(self._put, item)
        except RuntimeError:  # the loop is closed: the service is shutting down
            pass

    # loop ----------------------------------------------------------------------
    def _put(self, item: Arrival) -> None:
        if self.closed:
            return
        self.received += 1
        if len(self._items) >= self._capacity:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._ready.set()

    def put_nowait(self, item: Arrival) -> None:
        """For producers already on the loop."""
        self._put(item)

    async def get_batch(self, limit: int) -> list[Arrival]:
        """Wait for at least one item, return up to ``limit`` (FIFO)."""
        while not self._items:
            if self.closed:
                return []
            self._ready.clear()
            await self._ready.wait()
        n = min(limit, len(self._items))
        return [self._items.popleft() for _ in range(n)]

    def close(self) -> None:
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
    (and make their messages late); a stamp more than ``max_jump`` seconds ahead does not
    count at all.
    """

    def __init__(self, mode: Literal["wall", "data"], *, speed: float = 1.0, grace: float = 1.0,
                 max_jump: float = 5.0):
        assert mode in ("wall", "data") and speed > 0
        self.mode = mode
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
        idle = time.monotonic() - self._last - self.grace
        return self._high + self.speed * idle if idle > 0 else self._high

    def observe(self, stamp: float, sensor: str | None = None) -> float:
        """A message with ``stamp`` arrives (from ``sensor``); returns its arrival time on
        this clock."""
        if self.mode == "wall":
            return time.time()
        now = self.now()
        # Data flows again: the run-on time (if any) is kept, so the clock never goes back.
        self._high = now
        self._last = time.monotonic()
        if now is not None and stamp - now > self.max_jump:
            return now
        key = sensor if sensor is not None else ""
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
    _arrivals: deque = field(default_factory=lambda: deque(maxlen=256))  # wall times
    _latency: deque = field(default_factory=lambda: deque(maxlen=256))  # arrival - stamp

    def seen(self, wall: float) -> None:
        self.messages += 1
        self.last_seen_wall = wall
        self._arrivals.append(wall)

    def timing(self, stamp: float, arrival: float, seq: int) -> None:
        self.last_stamp = stamp
        self.last_seq = seq
        self._latency.append(arrival - stamp)

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1

    def rate(self, now_wall: float) -> float:
        """Messages per wall second over the recent window (0 once the sensor went quiet)."""
        a = self._arrivals
        if len(a) < 2 or now_wall - a[-1] > 5.0:
            return 0.0
        span = a[-1] - a[0]
        return (len(a) - 1) / span if span > 0 else 0.0

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
                                f"(limit {1000 * max_offset:.0f} ms): check its NTP")
            lat = d["latency"]
            if lat is not None and lat["median"] > max_latency:
                warnings.append(f"messages arrive {1000 * lat['median']:.0f} ms after capture, later than "
                                f"framesets wait ({1000 * max_latency:.0f} ms)")
            d["warnings"] = warnings
        return out


def finite_or_none(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None
