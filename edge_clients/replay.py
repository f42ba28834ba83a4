"""Replay a recording over Zenoh with its original timing, stamps shifted to now.

A recording is in arrival order and its stamps need not be sorted (sensors have their
own clock offsets and latencies). Replay publishes in file order and paces each sensor
by its own stamps: a sensor is anchored to the replay clock where it first appears, and
each of its messages waits until its stamp (relative to that anchor) is due, never
before the message ahead of it in the file. So every sensor keeps its exact relative
timing, the arrival order is kept, and a sensor whose clock is far off (hours) neither
stalls the others nor is "fixed".

Stamps get one shift for all sensors, ``origin - t0``, so the sensors' clock offsets
are kept: ``t0`` is the median stamp of the file's first messages and ``origin`` the
start of the run (now, or ``--start-at`` so that several replay processes, one per
sensor, agree). ``--loop`` replays again, shifted once more by the recording's length,
with each sensor's ``seq`` continuing to increase.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import statistics
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from proto import KeypointMessage, ReadStats, read_recording

T0_SAMPLE = 64  # messages at the head of the file whose median stamp is t0


@dataclass
class RecordingSummary:
    """What a full validating pass over a recording found."""

    messages: int = 0
    sensors: Counter = field(default_factory=Counter)
    stats: ReadStats = field(default_factory=ReadStats)


def check_recording(path: str | os.PathLike, *, skip_bad: bool = False) -> RecordingSummary:
    """Read and validate every record (raises RecordingError on the first bad one unless
    ``skip_bad``), so that a broken file is refused before anything is published."""
    s = RecordingSummary()
    for msg in read_recording(path, skip_bad=skip_bad, stats=s.stats):
        s.messages += 1
        s.sensors[msg.sensor] += 1
    return s


@dataclass
class _Sensor:
    anchor: float  # s of recording time: stamp - t0 - anchor = the sensor's replay clock
    first_stamp: float
    last_stamp: float
    min_seq: int
    max_seq: int
    count: int = 0
    first_anchor: float = 0.0  # where the sensor first appeared: every loop starts from it


@dataclass
class Schedule:
    """The replay clock, in seconds of recording time since the start of the run."""

    t0: float
    max_gap: float = 10.0
    clock: float = 0.0
    reanchors: int = 0
    sensors: dict[str, _Sensor] = field(default_factory=dict)

    def place(self, msg: KeypointMessage) -> float:
        """When ``msg`` is due (s since the start), given the messages placed before it."""
        rel = msg.stamp - self.t0
        s = self.sensors.get(msg.sensor)
        if s is None:
            s = self.sensors[msg.sensor] = _Sensor(
                anchor=rel - self.clock, first_stamp=msg.stamp, last_stamp=msg.stamp,
                min_seq=msg.seq, max_seq=msg.seq, first_anchor=rel - self.clock,
            )
        due = rel - s.anchor
        if due - self.clock > self.max_gap:
            # A clock step of this sensor, or a pause of the whole recording: don't sit idle.
            s.anchor = rel - self.clock
            due = self.clock
            self.reanchors += 1
        s.first_stamp = min(s.first_stamp, msg.stamp)
        s.last_stamp = max(s.last_stamp, msg.stamp)
        s.min_seq, s.max_seq = min(s.min_seq, msg.seq), max(s.max_seq, msg.seq)
        s.count += 1
        self.clock = max(self.clock, due)
        return self.clock

    def loop_length(self) -> float:
        """Shift between two loops: longer than the run and than any sensor's stamp span,
        plus one typical frame interval, so each sensor's stamps keep increasing."""
        spans = [s.last_stamp - s.first_stamp for s in self.sensors.values()]
        intervals = [(s.last_stamp - s.first_stamp) / (s.count - 1) for s in self.sensors.values() if s.count > 1]
        gap = statistics.median(intervals) if intervals else 0.1
        return max([self.clock, *spans]) + max(gap, 1e-3)


def planned(
    path: str | os.PathLike,
    *,
    origin: float,
    sensors: Iterable[str] | None = None,
    loop: bool | int = False,
    skip_bad: bool = False,
    stats: ReadStats | None = None,
    max_gap: float = 10.0,
    on_schedule: Callable[[Schedule], None] | None = None,
) -> Iterator[tuple[float, int, KeypointMessage]]:
    """(due, loop, message) triples: ``due`` in s of recording time since the start of
    the run, the message with its stamp shifted by ``origin - t0 + loop offset`` and its
    ``seq`` continued across loops. ``loop``: False = once, True = forever, n = n times.
    Memory is bounded: the file is streamed."""
    keep = set(sensors) if sensors else None
    stats = stats if stats is not None else ReadStats()
    first = read_recording(path, skip_bad=skip_bad, stats=stats)
    head = list(itertools.islice(first, T0_SAMPLE))
    if not head:
        return
    t0 = statistics.median(m.stamp for m in head)
    sched = Schedule(t0=t0, max_gap=max_gap)
    if on_schedule:
        on_schedule(sched)
    loops = itertools.count() if loop is True else range(max(1, int(loop)))
    base = 0.0  # replay clock at the start of this loop
    seq_span: dict[str, int] = {}
    for n in loops:
        # Later loops skip what loop 0 skipped (and counted) without stopping again.
        source = itertools.chain(head, first) if n == 0 else read_recording(path, skip_bad=True)
        sched.clock = 0.0
        for st in sched.sensors.values():
            st.anchor = st.first_anchor  # undo the re-anchoring of clock steps in the last loop
        for msg in source:
            if keep is not None and msg.sensor not in keep:
                continue
            due = sched.place(msg)
            shifted = dataclasses.replace(
                msg,
                stamp=msg.stamp - t0 + origin + base,
                seq=msg.seq + n * seq_span.get(msg.sensor, 0),
            )
            yield base + due, n, shifted
        if n == 0:
            if not sched.sensors:
                return  # nothing of the selected sensors: looping would spin
            seq_span = {k: s.max_seq - s.min_seq + 1 for k, s in sched.sensors.items()}
        base += sched.loop_length()


@dataclass
class ReplayReport:
    sent: dict[str, int]
    rates: dict[str, float]  # messages per second of wall time, per sensor
    seconds: float  # wall time of the run
    shift: float  # s added to the stamps of the first loop
    loops: int
    skipped: ReadStats
    reanchors: int
    max_late: float  # s the publisher fell behind the schedule at worst
    stopped: bool  # by a signal or the stop event

    def lines(self) -> list[str]:
        total = sum(self.sent.values())
        out = [f"sent {total} messages from {len(self.sent)} sensors in {self.seconds:.1f} s "
               f"({self.loops} loop{'s' if self.loops != 1 else ''}, stamps shifted by {self.shift:+.3f} s)"
               + (", stopped" if self.stopped else "")]
        for k in sorted(self.sent):
            out.append(f"  {k}: {self.sent[k]} messages, {self.rates[k]:.1f}/s")
        if self.skipped.skipped:
            reasons = ", ".join(f"{r} ×{c}" for r, c in self.skipped.reasons.most_common(5))
            out.append(f"skipped {self.skipped.skipped} bad records ({reasons}); first: {self.skipped.first_errors[0]}")
        if self.reanchors:
            out.append(f"{self.reanchors} clock steps or pauses longer than --max-gap were shortened")
        if self.max_late > 0.5:
            out.append(f"fell behind the recording's timing by up to {self.max_late:.2f} s (CPU or network too slow for --speed)")
        return out


def run_replay(
    publisher,
    path: str | os.PathLike,
    *,
    speed: float = 1.0,
    loop: bool | int = False,
    sensors: Iterable[str] | None = None,
    skip_bad: bool = False,
    now: Callable[[], float] = time.time,
    start_at: float | None = None,
    max_gap: float = 10.0,
    stop: threading.Event | None = None,
    on_message: Callable[[], None] | None = None,
) -> ReplayReport:
    """Publish ``path`` through ``publisher`` (a SensorPublisher) and report.

    ``speed`` K replays K× faster (stamps keep the recording's spacing); ``speed <= 0``
    publishes as fast as possible. ``start_at`` (epoch s, of the ``now`` clock) is when
    the recording's start is due; ``now`` is the sensor's clock (NTP-corrected or not).
    """
    from .publisher import publish_paced

    stats = ReadStats()
    t = now()
    origin = t if start_at is None else start_at
    holder: list[Schedule] = []
    loops = [0]

    def items():
        for due, n, msg in planned(path, origin=origin, sensors=sensors, loop=loop, skip_bad=skip_bad,
                                   stats=stats, max_gap=max_gap, on_schedule=holder.append):
            loops[0] = n + 1
            yield due, msg

    paced = publish_paced(publisher, items(), speed=speed, start_mono=time.monotonic() + (origin - t),
                          stop=stop, on_message=on_message)
    sched = holder[0] if holder else None
    secs = paced.seconds
    return ReplayReport(
        sent={k: s.sent for k, s in publisher.stats.items()},
        rates={k: s.sent / secs if secs > 0 else 0.0 for k, s in publisher.stats.items()},
        seconds=secs,
        shift=origin - sched.t0 if sched else 0.0,
        loops=loops[0],
        skipped=stats,
        reanchors=sched.reanchors if sched else 0,
        max_late=paced.max_late,
        stopped=paced.stopped,
    )
