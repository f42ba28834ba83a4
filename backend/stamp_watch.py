"""Whether a sensor's stamps run apart from the others' as they arrive
(``clock.estimate = "auto"``; docs/clock_offsets.md, Session 17).

A message arrives a network and detector delay after its capture, so a sensor's newest
stamp, against the other sensors' newest, is ahead or behind by its clock's offset minus
the differences of delays. Every 0.5 s of data each sensor's newest stamp, plus half its
frame period (how old its newest frame is on average), minus the median of all sensors'
(those heard from in the last 2 s) is a sample of its lead; every 5 s its median over
the last minute (at least 10 s of samples) is compared with ``auto_lead``. The stamps
cannot tell a short delay from a clock that runs ahead (only the estimate can); this is
the cheap signal that starts it. A few float ops per sensor twice a second.
"""

from __future__ import annotations

from collections import deque

import numpy as np

SAMPLE_EVERY = 0.5  # s of data between samples of the leads
FRESH = 2.0  # s: a sensor not heard from for longer is left out of a sample
SAMPLES_PER_CHECK = 10  # the medians every 5 s
WINDOW = 120  # samples: the last minute
MIN_SAMPLES = 20  # 10 s


class StampWatch:
    """``observe`` every accepted message's stamp; ``sample(now)`` as the data clock
    advances. ``leads()``: each sensor's median lead (s) over the last minute."""

    def __init__(self, auto_lead: float):
        assert auto_lead > 0
        self.auto_lead = auto_lead
        self.first_stamp: float | None = None
        self._periods: dict[str, list[float]] = {}  # per sensor: [newest stamp, its frame period (s, average)]
        self._leads: dict[str, deque[float]] = {}
        self._last_sample: float | None = None
        self._samples = 0

    def observe(self, sensor: str, stamp: float) -> None:
        """A sensor's frame period: the running mean of the steps between its stamps, a
        gap (a pause, a restart) left out (with the gap in, a 30 Hz sensor back from a
        minute's silence read +87 ms)."""
        if self.first_stamp is None:
            self.first_stamp = stamp
        p = self._periods.setdefault(sensor, [stamp, 0.0])
        step = stamp - p[0]
        if 0.0 < step < 1.0:
            p[1] = step if p[1] == 0.0 else 0.95 * p[1] + 0.05 * step
        p[0] = stamp

    def period(self, sensor: str) -> float:
        """s: the sensor's frame period (0 before two of its stamps)."""
        return self._periods.get(sensor, (0.0, 0.0))[1]

    def leads(self) -> dict[str, float]:
        """Each sensor's median lead (s) over the last minute, once it has 10 s of samples."""
        return {s: float(np.median(d)) for s, d in self._leads.items() if len(d) >= MIN_SAMPLES}

    def sample(self, now: float) -> dict[str, float] | None:
        """A sample of the leads when 0.5 s of data passed since the last; every 10th, the
        sensors whose median lead lies beyond ``auto_lead`` (s, signed; empty: none), else
        None."""
        if self._last_sample is not None and now - self._last_sample < SAMPLE_EVERY:
            return None
        self._last_sample = now
        fresh = {s: t + 0.5 * period for s, (t, period) in self._periods.items() if now - t < FRESH}
        if len(fresh) < 3:
            return None
        mid = float(np.median(list(fresh.values())))
        for s, t in fresh.items():
            self._leads.setdefault(s, deque(maxlen=WINDOW)).append(t - mid)
        self._samples += 1
        if self._samples % SAMPLES_PER_CHECK:
            return None
        return {s: v for s, v in self.leads().items() if abs(v) > self.auto_lead}
