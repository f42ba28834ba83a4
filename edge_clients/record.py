"""Record every keypoint message of a site to a recording file.

The Zenoh callback only copies the key and the payload into a bounded queue (it runs on
Zenoh's thread and must not block); the main loop decodes and validates each message
(proto.decode), counts what it rejects, writes the rest in arrival order and flushes at
least every second, so that a crash loses at most the last second.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Iterable

from proto import MessageError, RecordingWriter, decode, keys


@dataclass
class RecordReport:
    path: str
    written: Counter = field(default_factory=Counter)  # per sensor
    rejected: Counter = field(default_factory=Counter)  # per reason (field)
    first_rejects: list[str] = field(default_factory=list)
    dropped: int = 0  # queue full: the writer could not keep up
    seconds: float = 0.0

    def reject(self, key: str, reason: str) -> None:
        self.rejected[reason.split(":")[0]] += 1
        if len(self.first_rejects) < 10:
            self.first_rejects.append(f"{key}: {reason}")

    @property
    def total(self) -> int:
        return sum(self.written.values())

    def lines(self) -> list[str]:
        out = [f"wrote {self.total} messages from {len(self.written)} sensors to {self.path} "
               f"in {self.seconds:.1f} s"]
        for k in sorted(self.written):
            out.append(f"  {k}: {self.written[k]}")
        if self.rejected:
            reasons = ", ".join(f"{r} ×{c}" for r, c in self.rejected.most_common(5))
            out.append(f"rejected {sum(self.rejected.values())} invalid messages ({reasons}); "
                       f"first: {self.first_rejects[0]}")
        if self.dropped:
            out.append(f"dropped {self.dropped} messages: the disk could not keep up (raise --queue)")
        return out


class Recorder:
    """Subscribes to the keypoints of ``site`` (optionally only ``sensors``) and writes
    them to ``out`` (format from the file name, see proto.RecordingWriter).

    ``started`` is set once the subscriber is declared: messages published after that
    are recorded.
    """

    def __init__(
        self,
        session,
        out: str | os.PathLike,
        *,
        site: str = keys.DEFAULT_SITE,
        sensors: Iterable[str] | None = None,
        queue_size: int = 20000,
        flush_every: float = 1.0,
        append: bool = False,
    ):
        self.session = session
        self.out = out
        self.site = site
        self.sensors = set(sensors) if sensors else None
        self.flush_every = flush_every
        self.append = append
        self._q: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=queue_size)
        self.report = RecordReport(path=str(out))
        self.started = threading.Event()
        self._dropped = 0

    def _on_sample(self, sample) -> None:
        # Zenoh's thread: copy and hand over, never block.
        try:
            self._q.put_nowait((str(sample.key_expr), sample.payload.to_bytes()))
        except queue.Full:
            self._dropped += 1

    def run(
        self,
        stop: threading.Event,
        *,
        duration: float | None = None,
        on_tick: Callable[[], None] | None = None,
    ) -> RecordReport:
        """Record until ``stop`` is set or ``duration`` s have passed; returns the report."""
        writer = RecordingWriter(self.out, append=self.append)
        sub = self.session.declare_subscriber(keys.all_keypoints(self.site), self._on_sample)
        t0 = time.monotonic()
        last_flush = t0
        self.started.set()
        try:
            while not stop.is_set():
                now = time.monotonic()
                if duration is not None and now - t0 >= duration:
                    break
                timeout = min(0.1, self.flush_every)
                if duration is not None:
                    timeout = max(0.0, min(timeout, t0 + duration - now))
                try:
                    key, payload = self._q.get(timeout=timeout)
                    self._write(writer, key, payload)
                except queue.Empty:
                    pass
                if time.monotonic() - last_flush >= self.flush_every:
                    writer.flush()
                    last_flush = time.monotonic()
                if on_tick:
                    on_tick()
        finally:
            sub.undeclare()
            # What arrived before the subscriber was gone is kept.
            while True:
                try:
                    key, payload = self._q.get_nowait()
                except queue.Empty:
                    break
                self._write(writer, key, payload)
            writer.flush()
            writer.close()
            self.report.dropped = self._dropped
            self.report.seconds = time.monotonic() - t0
        return self.report

    def _write(self, writer: RecordingWriter, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload)
        except MessageError as e:
            self.report.reject(key, str(e))
            return
        if keys.sensor_of(key) != msg.sensor:
            self.report.reject(key, f"sensor: {msg.sensor!r} published on another sensor's key")
            return
        if self.sensors is not None and msg.sensor not in self.sensors:
            return
        writer.write(msg)
        self.report.written[msg.sensor] += 1
