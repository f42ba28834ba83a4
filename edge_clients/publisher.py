"""Publishing keypoint messages over Zenoh: shared by the simulated, replayed and camera sensors.

One Zenoh session per process. Per sensor, a publisher on
``extrcal/<site>/sensors/<sensor>/keypoints`` and a liveliness token on
``extrcal/<site>/sensors/<sensor>/alive``, declared when the sensor is first seen and
undeclared on close. Messages go out as msgpack with packed float32 keypoints
(``proto.encode``).

Edge clients are plain synchronous loops, so the blocking Zenoh calls (open, close,
undeclare) run on the main thread; nothing here is called from a Zenoh callback.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from proto import KeypointMessage, encode, keys
from proto.transport import ZenohSettings, open_session


@contextmanager
def zenoh_session(settings: ZenohSettings) -> Iterator:
    """An open Zenoh session, closed explicitly on exit."""
    session = open_session(settings)
    try:
        yield session
    finally:
        session.close()


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM (a second one exits at once).

    Loops wait on the event instead of sleeping, so that a stop takes effect within one
    message interval and the caller still closes its files and Zenoh session.
    """
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop  # signal handlers can only be installed from the main thread (tests)
        return

    def handler(signum, frame):  # noqa: ARG001
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class RateMeter:
    """Events per second over a sliding window of monotonic time."""

    def __init__(self, window: float = 5.0):
        self.window = window
        self._t: deque[float] = deque()

    def tick(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self._t.append(now)
        self._trim(now)

    def rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        self._trim(now)
        if len(self._t) < 2:
            return 0.0
        span = max(now - self._t[0], self._t[-1] - self._t[0])
        return (len(self._t) - 1) / span if span > 0 else 0.0

    def _trim(self, now: float) -> None:
        while self._t and self._t[0] < now - self.window:
            self._t.popleft()


@dataclass
class SensorStats:
    sent: int = 0
    persons: int = 0
    first_stamp: float | None = None
    last_stamp: float | None = None
    last_seq: int | None = None
    rate: RateMeter = field(default_factory=RateMeter)


class SensorPublisher:
    """Publishes the keypoint messages of any number of sensors on one Zenoh session.

    ``block=True`` makes a congested link slow the publisher down instead of dropping
    messages (replay, simulation); a live camera uses the default, dropping, so that a
    slow network never stalls its capture loop.
    """

    def __init__(self, session, site: str = keys.DEFAULT_SITE, *, block: bool = False):
        import zenoh

        self.session = session
        self.site = site
        self._cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pubs: dict[str, object] = {}
        self._tokens: dict[str, object] = {}
        self.stats: dict[str, SensorStats] = {}

    def declare(self, sensor: str) -> None:
        """Publisher and liveliness token for ``sensor`` (idempotent)."""
        if sensor in self._pubs:
            return
        import zenoh

        key = keys.keypoints(self.site, sensor)  # validates site and sensor names
        self._pubs[sensor] = self.session.declare_publisher(
            key,
            encoding=zenoh.Encoding("application/msgpack"),
            congestion_control=self._cc,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._tokens[sensor] = self.session.liveliness().declare_token(keys.alive(self.site, sensor))
        self.stats[sensor] = SensorStats()

    def publish(self, msg: KeypointMessage) -> None:
        self.declare(msg.sensor)
        self._pubs[msg.sensor].put(encode(msg))
        s = self.stats[msg.sensor]
        s.sent += 1
        s.persons += len(msg.persons)
        s.first_stamp = msg.stamp if s.first_stamp is None else s.first_stamp
        s.last_stamp, s.last_seq = msg.stamp, msg.seq
        s.rate.tick()

    def matched(self, sensor: str) -> bool:
        return bool(self._pubs[sensor].matching_status.matching)

    def wait_matched(self, sensors: Iterable[str], timeout: float, stop: threading.Event | None = None) -> bool:
        """Declare ``sensors`` and wait until each has a subscriber (or ``timeout`` s)."""
        sensors = list(sensors)
        for s in sensors:
            self.declare(s)
        deadline = time.monotonic() + timeout
        while not all(self.matched(s) for s in sensors):
            if time.monotonic() > deadline or (stop is not None and stop.is_set()):
                return False
            time.sleep(0.02)
        return True

    @property
    def total(self) -> int:
        return sum(s.sent for s in self.stats.values())

    def close(self) -> None:
        for tok in self._tokens.values():
            tok.undeclare()
        for pub in self._pubs.values():
            pub.undeclare()
        self._tokens.clear()
        self._pubs.clear()

    def __enter__(self) -> "SensorPublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StatusLine:
    """One status line: redrawn in place on a terminal, logged every ``period`` s otherwise.

    ``render`` builds the text; it is called at most a few times a second.
    """

    def __init__(self, render: Callable[[], str], *, period: float = 5.0, enabled: bool = True, stream=None):
        self.render = render
        self.period = period
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._tty = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last = 0.0
        self._live = None

    def __enter__(self) -> "StatusLine":
        if self._tty:
            from rich.console import Console
            from rich.live import Live

            self._live = Live("", console=Console(file=self.stream), refresh_per_second=4, transient=False)
            self._live.__enter__()
        return self

    def update(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        every = 0.25 if self._tty else self.period
        if not force and now - self._last < every:
            return
        self._last = now
        text = self.render()
        if self._live is not None:
            self._live.update(text)
        else:
            print(text, file=self.stream, flush=True)

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.update(self.render())
            self._live.__exit__(None, None, None)
            self._live = None


def format_rate_summary(stats: dict[str, SensorStats], limit: int = 6) -> str:
    """`cam_0 30.0/s, cam_1 29.8/s, ... (20 sensors)`."""
    items = [f"{k} {v.rate.rate():.1f}/s" for k, v in sorted(stats.items())]
    more = f", … ({len(items)} sensors)" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


@dataclass
class Paced:
    """How a paced run went."""

    seconds: float = 0.0  # wall time
    max_late: float = 0.0  # s the publisher fell behind its schedule at worst
    stopped: bool = False  # by the stop event (signal)


def publish_paced(
    publisher: SensorPublisher,
    items: Iterable[tuple[float, KeypointMessage]],
    *,
    speed: float = 1.0,
    start_mono: float | None = None,
    stop: threading.Event | None = None,
    on_message: Callable[[], None] | None = None,
) -> Paced:
    """Publish (due, message) pairs, ``due`` in s of data time since the start of the run,
    each when ``start_mono + due / speed`` (time.monotonic) is reached; ``speed <= 0``:
    as fast as possible. Items must come in due order (arrival order)."""
    stop = stop or threading.Event()
    start_mono = time.monotonic() if start_mono is None else start_mono
    res = Paced()
    t0 = time.monotonic()
    for due, msg in items:
        if speed > 0:
            wait = start_mono + due / speed - time.monotonic()
            if wait > 0:
                if stop.wait(wait):
                    break
            else:
                res.max_late = max(res.max_late, -wait)
        elif stop.is_set():
            break
        publisher.publish(msg)
        if on_message:
            on_message()
    res.stopped = stop.is_set()
    res.seconds = time.monotonic() - t0
    return res
