"""The pipeline's clock stage (a part of ``Pipeline``): when the estimate of the sensors'
clock offsets starts (``clock.estimate = "auto"``: once a sensor's stamps run apart from
the others' as they arrive), its jobs, the offsets it finds applied to the synchroniser,
and at the end the archived views timed again with the final offsets.
backend/clock_offsets.py estimates them; backend/retime.py keeps the raw messages."""

from __future__ import annotations

import logging
from collections import deque
from typing import Iterable

import numpy as np

from .clock_offsets import ClockJob, ClockResult, SensorClock
from .preprocess import Preprocessor
from .retime import RawArchive

log = logging.getLogger("backend.pipeline")  # the pipeline's: its messages keep their logger


class ClockStage:
    """``Pipeline``'s methods for the sensors' clocks: they work on its ``clocks``
    (the estimator), ``sync``, ``frames`` (the archive), ``raw`` and ``_offset_history``."""

    def _start_estimating(self) -> None:
        self.estimating = True
        if self.raw is None and self.cfg.clock.retime_seconds > 0:
            self.raw = RawArchive(self.names, self.cfg.clock.retime_seconds)

    @property
    def _watching_stamps(self) -> bool:
        """``clock.estimate = "auto"`` and the estimate not started yet."""
        return not self.estimating and self.cfg.clock.estimate == "auto"

    def _watch_stamps(self, now: float) -> None:
        """``clock.estimate = "auto"``: the estimate starts once a sensor's stamps run
        ``clock.auto_lead`` apart from the others' as they arrive (backend/stamp_watch.py),
        live and in a recording alike."""
        far = self.stamps.sample(now)
        if far:
            log.warning("the stamps of %s run %s from the other sensors' as they arrive: estimating the sensors' clock "
                        "offsets from the data from now on, %.0f s into it (clock.estimate = auto)", ", ".join(far),
                        ", ".join(f"{1000 * v:+.0f} ms" for v in far.values()),
                        now - self.stamps.first_stamp)
            self._far = frozenset(far)
            self._start_estimating()

    def clock_states(self) -> tuple[SensorClock, ...]:
        """The sensors' clock offsets as ``state()`` reports them (none while not estimating)."""
        return self.clocks.clocks() if self.estimating else ()

    def timing_undecided(self) -> list[str]:
        """Sensors the data say are mistimed whose offset is not applied yet: those whose
        stamps started the estimate ("auto") while they have no estimate, and those with an
        estimate of at least ``clock.min_apply`` and a std within ``clock.max_std`` (one
        that can be applied) awaiting its confirmation. Work on the archived frames that
        cannot time them again (the check of the initial estimate) waits for them."""
        if not self.estimating:
            return []
        c, cfg = self.clocks, self.cfg.clock
        out = []
        for i, n in enumerate(self.names):
            if c.applied[i] != 0.0:
                continue
            if not np.isfinite(c.offset[i]):
                if n in self._far:
                    out.append(n)
            elif abs(c.offset[i]) >= cfg.min_apply and c.std[i] <= cfg.max_std:
                out.append(n)
        return out

    def clock_job(self, now: float | None) -> ClockJob | None:
        """The clock offsets' estimate when due (``clock.estimate``, every
        ``clock.interval``, after the first adjustment): a job whose ``run`` may go to
        another thread while push/advance go on; its result goes to ``apply_clock``."""
        if not self.clocks.due(now) or not self._calibrated():
            return None
        return self.clocks.begin(now, self.refiner.R, self.refiner.t, P=self.refiner.S)

    def apply_clock(self, job: ClockJob, result: ClockResult | None) -> list[str]:
        """Fold a clock job's result in (None: it failed or was cancelled): newly
        estimated offsets are applied; returns the sensors whose offset changed."""
        changed = self.clocks.finish(job, result)
        self._retime(changed)
        return changed

    def cancel_clock(self) -> None:
        """Ask the clock job in flight (if any) to end early; ``apply_clock`` still takes it."""
        self.clocks.cancel()

    def _retime(self, sensors: list[str]) -> None:
        """Apply newly estimated clock offsets. Archived views stay as they are;
        ``_timed_frames`` leaves out those timed with an offset that differs from the
        sensor's current one by more than ``clock.retime_tolerance`` (an offset taken
        back brings its earlier views back)."""
        start = self.sync.next_time if self.sync.next_time is not None else -np.inf
        rf = self.refiner
        for name in sensors:
            c = self.names.index(name)
            new = float(self.clocks.applied[c])
            if not self._offset_history[c] or self._offset_history[c][-1][1] == 0.0:  # a first offset
                pose = self.clocks.relocation(c, rf.R[c], rf.t[c], rf.S[c], bool(rf.cycles[c] > 0))
                if pose is not None:  # the camera where the clock's estimate put it
                    rf.relocate(c, *pose)
                    self.relocalized.append(name)
                    self._restart_noted(c, "relocalized after its clock offset was applied", say=True)
            self.sync.set_offset(name, new)
            self._offset_history[c].append((start, new))

    def _stale(self, c: int, times: np.ndarray) -> np.ndarray:
        """(N,) bool: camera c's views at frameset ``times`` were timed with an offset
        more than ``clock.retime_tolerance`` from its current one."""
        hist = self._offset_history[c]  # (start, offset): from which frameset time on each was used; 0 before
        if not hist:
            return np.zeros(len(times), bool)
        starts = np.array([-np.inf] + [h[0] for h in hist])
        offsets = np.array([0.0] + [h[1] for h in hist])
        used = offsets[np.searchsorted(starts, times, side="right") - 1]
        return np.abs(used - hist[-1][1]) > self.cfg.clock.retime_tolerance

    def _timed_frames(self, frames: Iterable[tuple[float, tuple]] | None = None) -> list[tuple[float, tuple]]:
        """The archived frames (or ``frames``) without the views timed with an offset
        more than ``clock.retime_tolerance`` from their sensor's current one (the
        batch adjustments must not use them)."""
        frames = list(self.frames if frames is None else frames)
        times = np.array([T for T, _ in frames])
        stale = {c: self._stale(c, times) for c in range(len(self.names)) if self._offset_history[c]}
        stale = {c: s for c, s in stale.items() if s.any()}
        if not stale:
            return frames
        return [(T, tuple(v for v in views if not (v[0].cam in stale and stale[v[0].cam][k])))
                for k, (T, views) in enumerate(frames)]

    def retime_archive(self) -> dict[str, int]:
        """Interpolate the archived views of every sensor that were timed with another
        offset than its current one again, at the current one, from the raw messages kept
        (``clock.retime_seconds``): the batch adjustments then have all of its data, not
        only the views timed since its offset was last changed. Frames older than the raw
        messages kept stay as ``_timed_frames`` leaves them. Returns (and adds to
        ``retimed``) the views timed again per sensor."""
        if self.raw is None or not self.frames:
            return {}
        pre = None  # its own preprocessor: the session's counts are of the live data
        frames = list(self.frames)
        times = np.array([T for T, _ in frames])
        out: dict[str, int] = {}
        for c, hist in enumerate(self._offset_history):
            name, span = self.names[c], self.raw.span(self.names[c])
            if span is None:
                continue
            current = hist[-1][1] if hist else 0.0
            cut = span[0] - current + self.cfg.sync.max_offset  # earlier frames lack a bracketing message
            idx = np.flatnonzero(self._stale(c, times) & (times >= cut))
            if not len(idx):
                continue
            pre = pre or Preprocessor(self.cfg.preprocess, self.names, self.cameras.intrinsics,
                                      self.preprocess.confidence)
            n = 0
            for k, v in zip(idx, self.raw.views(name, current, times[idx], self.cfg.sync)):
                T, old = frames[k]
                dets = tuple(pre.view(v)) if v is not None else ()
                n += len(dets)
                keep = [w for w in old if w[0].cam != c] + ([dets] if dets else [])
                frames[k] = (T, tuple(sorted(keep, key=lambda w: w[0].cam)))
            # from the cut on, every view of this sensor is timed with the current offset
            first = float(times[times >= cut][0])
            self._offset_history[c] = [h for h in hist if h[0] < first] + [(first, current)]
            out[name] = n
            log.info("%s: %d archived views timed again with its offset of %+.1f ms", name, n, 1000 * current)
        if out:
            self.frames = deque(frames, maxlen=self.frames.maxlen)
        for k, n in out.items():
            self.retimed[k] = self.retimed.get(k, 0) + n
        return out
