"""Archived views timed again when a sensor's clock offset changes (issue 9, part 2).

The batch adjustments (the final one above all) re-associate the archived framesets. A
sensor's views in them were interpolated at frameset time + the offset applied then; when
the estimate of its offset moves later, those views are off in time, and the pipeline
leaves them out (``clock.retime_tolerance``). A sensor whose offset was found late in a
session then has little data in the final batch, and its camera ends worse than with
synchronised clocks (docs/clock_offsets.md, session 8: seed 1's cam_5). Keeping every
sensor's raw detections for ``clock.retime_seconds`` lets the archive be interpolated
again at the final offsets instead.

Only while the clock offsets are estimated (``clock.estimate``; "auto": from the moment the
stamps start it), without which no offset ever changes. Memory: one entry per
message, its keypoints as the synchroniser holds them (bench/clock_offsets.py prints it).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable

from proto import KeypointMessage

from .config import SyncConfig
from .sync import Buffered, View, view_at

_PRUNE = 256  # messages past ``seconds`` removed at once


class RawArchive:
    """Per sensor, its messages of the last ``seconds`` (raw sensor stamps, sorted; up to
    ``_PRUNE`` older ones wait to be removed in one go)."""

    def __init__(self, sensors: Iterable[str], seconds: float):
        self.seconds = float(seconds)
        self._stamps: dict[str, list[float]] = {s: [] for s in sensors}
        self._msgs: dict[str, list[Buffered]] = {s: [] for s in self._stamps}

    def __len__(self) -> int:
        return sum(len(v) for v in self._stamps.values())

    @property
    def sensors(self) -> tuple[str, ...]:
        return tuple(self._stamps)

    def push(self, msg: KeypointMessage) -> None:
        """One message the synchroniser accepted (raw stamp; an unknown sensor is ignored)."""
        stamps = self._stamps.get(msg.sensor)
        if stamps is None:
            return
        msgs = self._msgs[msg.sensor]
        # the persons are in the entry's arrays: the message itself need not keep them twice
        e = Buffered.of(msg).replaced(persons=())
        i = bisect.bisect_right(stamps, msg.stamp)
        if i > 0 and stamps[i - 1] == msg.stamp:
            return  # a duplicate (the synchroniser counted it)
        stamps.insert(i, msg.stamp)
        msgs.insert(i, e)
        k = bisect.bisect_left(stamps, stamps[-1] - self.seconds)
        if k >= _PRUNE or (k and k == len(stamps) - 1):  # in chunks: deleting a list's head moves all of it
            del stamps[:k], msgs[:k]

    def span(self, sensor: str) -> tuple[float, float] | None:
        """(first, last) raw stamp kept for the sensor, or None."""
        st = self._stamps.get(sensor)
        return (st[0], st[-1]) if st else None

    def views(self, sensor: str, offset: float, times: Iterable[float], cfg: SyncConfig) -> list[View | None]:
        """The sensor's view at each frameset time (synchronised clock) with its stamps
        less ``offset``, exactly as the synchroniser would have made it."""
        stamps = [s - offset for s in self._stamps[sensor]]
        msgs = [e.replaced(stamp=e.stamp - offset) for e in self._msgs[sensor]]
        cache: dict = {}
        return [view_at(stamps, msgs, T, cfg, cache) for T in times]

    def keep(self, sensors: Iterable[str]) -> "RawArchive":
        """A copy with these sensors only (those it lacks start empty)."""
        out = RawArchive(sensors, self.seconds)
        for s in out._stamps:
            if s in self._stamps:
                out._stamps[s] = list(self._stamps[s])
                out._msgs[s] = list(self._msgs[s])
        return out
