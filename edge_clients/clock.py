"""The sensor's clock: system time, optionally checked (and corrected) against an NTP server.

The paper assumes NTP-synchronised sensors: a frameset may span at most 50 ms of stamps,
so a sensor whose clock is off by more than a few ms costs accuracy and one off by more
than 50 ms drops out. ``--ntp-server`` measures the offset periodically in a background
thread (ntplib); ``--clock-correct`` adds it to every stamp, otherwise it is only shown
in the client's status line so that someone fixes the host's NTP daemon.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class NtpSample:
    offset: float  # s to add to the local clock to get the server's time
    delay: float  # s round trip
    at: float  # monotonic time of the measurement


class Clock:
    """System time; the base class of NtpClock and the clock of a client without NTP."""

    correct = False

    def now(self) -> float:
        """Seconds since the Unix epoch, as stamps should carry them."""
        return time.time()

    def offset(self) -> float | None:
        return None

    def status(self) -> str:
        return "clock: system (no NTP check)"

    def close(self) -> None:
        pass

    def __enter__(self) -> "Clock":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class NtpClock(Clock):
    """System time checked against an NTP server every ``interval`` s.

    The offset estimate is the one of the sample with the shortest round trip among the
    last ``keep`` (the classic NTP clock filter: a long round trip means an asymmetric,
    less trustworthy path). Until the first answer arrives, ``offset()`` is None and no
    correction is applied.
    """

    def __init__(
        self,
        server: str,
        *,
        port: int = 123,
        interval: float = 64.0,
        timeout: float = 2.0,
        correct: bool = False,
        keep: int = 8,
        start: bool = True,
    ):
        import ntplib  # the [edge] / [camera] extra

        self.server, self.port = server, port
        self.interval, self.timeout = interval, timeout
        self.correct = correct
        self._client = ntplib.NTPClient()
        self._samples: deque[NtpSample] = deque(maxlen=keep)
        self._lock = threading.Lock()
        self.last_error: str | None = None
        self.checks = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if start:
            self._thread = threading.Thread(target=self._run, name="ntp-check", daemon=True)
            self._thread.start()

    def check(self) -> NtpSample | None:
        """One NTP exchange now; returns the sample, or None (error kept in last_error)."""
        try:
            r = self._client.request(self.server, version=3, port=self.port, timeout=self.timeout)
        except Exception as e:  # ntplib raises NTPException, socket errors, gaierror
            with self._lock:
                self.checks += 1
                self.last_error = f"{type(e).__name__}: {e}"
            return None
        sample = NtpSample(offset=float(r.offset), delay=float(r.delay), at=time.monotonic())
        with self._lock:
            self.checks += 1
            self._samples.append(sample)
            self.last_error = None
        return sample

    def wait_first(self, timeout: float) -> bool:
        """Wait until one check has finished (answered or failed)."""
        deadline = time.monotonic() + timeout
        while self.checks == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.checks > 0

    def best(self) -> NtpSample | None:
        with self._lock:
            return min(self._samples, key=lambda s: s.delay) if self._samples else None

    def offset(self) -> float | None:
        b = self.best()
        return None if b is None else b.offset

    def now(self) -> float:
        t = time.time()
        if self.correct:
            off = self.offset()
            if off is not None:
                t += off
        return t

    def status(self) -> str:
        b = self.best()
        where = f"ntp {self.server}" + (f":{self.port}" if self.port != 123 else "")
        if b is None:
            return f"{where}: " + (f"no answer ({self.last_error})" if self.last_error else "waiting")
        age = time.monotonic() - b.at
        mode = "corrected" if self.correct else "not corrected"
        warn = " ⚠ beyond the 25 ms frameset std" if abs(b.offset) > 0.025 and not self.correct else ""
        err = f", last check failed: {self.last_error}" if self.last_error else ""
        return (f"{where}: offset {b.offset * 1e3:+.1f} ms ({mode}), rtt {b.delay * 1e3:.1f} ms, "
                f"{age:.0f} s ago{warn}{err}")

    def _run(self) -> None:
        while not self._stop.is_set():
            self.check()
            self._stop.wait(self.interval)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.timeout + 1)


def make_clock(ntp_server: str | None, *, correct: bool = False, interval: float = 64.0) -> Clock:
    """The clock of a client from its ``--ntp-server HOST[:PORT]`` and ``--clock-correct`` flags."""
    if not ntp_server:
        if correct:
            raise ValueError("--clock-correct needs --ntp-server")
        return Clock()
    host, port = ntp_server, 123
    if ntp_server.count(":") == 1:  # host:port (a bare IPv6 address has more colons)
        host, p = ntp_server.rsplit(":", 1)
        port = int(p)
    return NtpClock(host, port=port, correct=correct, interval=interval)
