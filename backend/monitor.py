"""Watching a calibrated camera network for cameras that moved (bumped, re-mounted).

Once a camera has converged, its reprojection residual in the cycles is steady. A camera
that is moved no longer fits the others: its converged prior holds it where it was, so
its views' residual jumps, and keeps being high cycle after cycle. The test is relative
twice over: a camera's median residual is divided by the median over the cycle's
cameras (busy scenes, people far away or a detector having a bad moment raise everyone's),
and that ratio is compared with the camera's own baseline of the same ratio. A camera
whose ratio is well above its baseline in ``consecutive`` cycles in a row, each with
enough views, is flagged; the pipeline then re-opens its uncertainty so the cycles
calibrate it again while the others, still certain, hold the frame.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .config import MonitorConfig


@dataclass(frozen=True)
class Alarm:
    """A camera found moved: data time, camera index, its residual ratio (to the cycle's
    median camera) and its baseline ratio when flagged."""

    time: float
    cam: int
    ratio: float
    baseline: float
    residual_px: float


class Monitor:
    def __init__(self, cfg: MonitorConfig, cameras: int):
        self.cfg = cfg
        self.baseline: list[deque[float]] = [deque(maxlen=cfg.baseline_cycles) for _ in range(cameras)]
        self.suspect = np.zeros(cameras, dtype=np.int64)
        self.alarms: list[Alarm] = []

    def observe(self, time: float, watched: np.ndarray, residual_px: np.ndarray, views: np.ndarray) -> list[Alarm]:
        """One cycle: watched (C,) bool cameras to test (converged ones); residual_px (C,)
        median reprojection error of each camera's observations (NaN = not in the cycle);
        views (C,) its views. Returns the cameras flagged now."""
        cfg = self.cfg
        C = len(self.baseline)
        assert watched.shape == residual_px.shape == views.shape == (C,)
        if not cfg.enabled:
            return []
        present = np.isfinite(residual_px) & (views >= cfg.min_views)
        if present.sum() < 3:
            return []  # no reference for what the cycle's residuals are
        median = max(float(np.median(residual_px[present])), 1e-9)
        ratio = residual_px / median
        out = []
        for c in range(C):
            if not watched[c]:
                self.baseline[c].clear()  # re-learnt once it has converged (again)
                self.suspect[c] = 0
                continue
            if not present[c]:
                continue
            base = self.baseline[c]
            if len(base) < cfg.min_baseline:
                base.append(float(ratio[c]))
                continue
            b = float(np.median(base))
            high = ratio[c] > cfg.ratio * b and residual_px[c] > b * median + cfg.margin_px
            if not high:
                self.suspect[c] = 0
                base.append(float(ratio[c]))
                continue
            self.suspect[c] += 1
            if self.suspect[c] >= cfg.consecutive:
                a = Alarm(time, c, float(ratio[c]), b, float(residual_px[c]))
                out.append(a)
                self.alarms.append(a)
                self.suspect[c] = 0
                base.clear()
        return out
