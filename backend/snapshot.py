"""A pipeline's estimate as JSON and back (a part of ``Pipeline``): the service persists it
after every cycle, and a session resumes from it after a restart, its buffered data lost."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .cameras import CameraSet
from .config import EngineConfig
from .monitor import Alarm
from .scale_check import ScaleCheck
from .split_check import SplitCheck
from .state import Lenses

if TYPE_CHECKING:
    from .pipeline import Pipeline


class Snapshots:
    """``Pipeline``'s snapshot (``version`` 2) and ``restore``."""

    def snapshot(self) -> dict:
        """JSON-able state to resume from: the estimate, not the buffered data."""
        rf = self.refiner
        return {
            "version": 2,
            "names": list(self.names),
            "R": rf.R.tolist(), "t": rf.t.tolist(), "P": rf.P.tolist(), "S": rf.S.tolist(),
            "R0": rf.R0.tolist(), "t0": rf.t0.tolist(),
            "prior_R": rf.prior_R.tolist(), "prior_t": rf.prior_t.tolist(), "P0": rf.P0.tolist(),
            "cycles": rf.cycles.tolist(),
            "history": [[[t.tolist(), R.tolist()] for t, R in h] for h in rf.history],
            "cycle": self.cycle,
            "first_passes": self.first_passes,
            "moved": [[a.time, a.cam, a.chi2, a.translation, a.rotation, a.since] for a in self.monitor.alarms],
            "restarted": [[c, t, why] for c, (t, why) in self.restarted.items()],
            "watched": self.watched.tolist(),
            "batched": rf.batched.tolist(),
            "observations": self.observations.tolist(),
            "observations_batch": self.observations_batch.tolist(),
            "clock": self.clock,
            "clock_offsets": {n: float(o) for n, o in zip(self.names, self.clocks.applied) if o},
            "clock_estimating": self.estimating,
            "scale_heights": None if self.scale_heights is None else list(self.scale_heights),
            "scale_check": self.scale_check.to_dict() if self.scale_check is not None else None,
            "split_check": self.split_check.to_dict() if self.split_check is not None else None,
            "lenses": self.lenses.to_dict() if self.lenses is not None else None,
            "lens_cov": None if self.lens_cov is None else
            [x.tolist() if np.all(np.isfinite(x)) else None for x in self.lens_cov],
            "data_shape": None if self.data_shape is None else _shape_rows(*self.data_shape),
        }

    @classmethod
    def restore(cls, cameras: CameraSet, config: EngineConfig, snapshot: dict, *, seed: int = 0) -> "Pipeline":
        """A pipeline that goes on from ``snapshot``; ``cameras`` as the session began
        (the calibration files' lenses: the snapshot's poses fit the lenses it found)."""
        lenses = Lenses.from_dict(snapshot["lenses"]) if snapshot.get("lenses") else None
        if lenses is not None and not set(lenses.cameras) <= set(cameras.names):
            lenses = None  # another camera set: _load says so
        if lenses is not None:
            cameras = replace(cameras, intrinsics=lenses.intrinsics(cameras.intrinsics))
        p = cls(cameras, config, seed=seed)
        p._load(snapshot)
        p.lenses = lenses
        return p

    def _load(self, snapshot: dict) -> None:
        """The estimate of a ``snapshot`` (of these cameras) into this new pipeline."""
        if snapshot.get("version") != 2 or list(snapshot.get("names", [])) != list(self.names):
            raise ValueError("snapshot does not belong to this camera set")
        p, config = self, self.cfg
        if snapshot.get("scale_heights") is not None:
            p.scale_heights = tuple(float(h) for h in snapshot["scale_heights"])
        if snapshot.get("scale_check") is not None:
            p.scale_check = ScaleCheck.from_dict(snapshot["scale_check"])
        if snapshot.get("split_check") is not None:
            p.split_check = SplitCheck.from_dict(snapshot["split_check"])
        rf = p.refiner
        rf.R, rf.t, rf.P, rf.S = (np.array(snapshot[k], dtype=np.float64) for k in ("R", "t", "P", "S"))
        rf.R0, rf.t0 = np.array(snapshot["R0"]), np.array(snapshot["t0"])
        # snapshots from before a prior of its own existed: the initial estimate was it
        rf.prior_R = np.array(snapshot.get("prior_R", snapshot["R0"]), dtype=np.float64)
        rf.prior_t = np.array(snapshot.get("prior_t", snapshot["t0"]), dtype=np.float64)
        if "P0" in snapshot:
            rf.P0 = np.array(snapshot["P0"], dtype=np.float64)
        rf.cycles = np.array(snapshot["cycles"], dtype=np.int64)
        for h, items in zip(rf.history, snapshot["history"]):
            h.extend((np.array(t, dtype=np.float64), np.array(R, dtype=np.float64)) for t, R in items)
        p.cycle = int(snapshot["cycle"])
        # a snapshot from before first passes existed had its first cycles long ago
        p.first_passes = int(snapshot.get("first_passes", 2))
        p.monitor.alarms = [Alarm(float(a[0]), int(a[1]), *map(float, a[2:])) for a in snapshot.get("moved", [])]
        p.restarted = {int(c): (float(t), str(why)) for c, t, why in snapshot.get("restarted", [])}
        p.watched = np.array(snapshot.get("watched", [False] * len(p.names)), dtype=bool)
        if config.monitor.on:  # held from the first cycle after the restart, not the monitor's first turn
            rf.held = p.watched & config.monitor.hold
        rf.batched = np.array(snapshot.get("batched", [False] * len(p.names)), dtype=bool)
        if snapshot.get("data_shape") is not None and len(snapshot["data_shape"]) == len(p.names):
            p.data_shape = _shape_arrays(snapshot["data_shape"])
        if snapshot.get("lens_cov") is not None and len(snapshot["lens_cov"]) == len(p.names):
            p.lens_cov = np.array([np.full((6, 6), np.nan) if x is None else x for x in snapshot["lens_cov"]],
                                  dtype=np.float64)
        p.observations = np.array(snapshot["observations"], dtype=np.int64)
        p.observations_batch = np.array(snapshot.get("observations_batch", [0] * len(p.names)), dtype=np.int64)
        applied = {n: float(o) for n, o in snapshot.get("clock_offsets", {}).items() if n in p.names}
        if snapshot.get("clock_estimating", bool(applied)) and config.clock.estimate is not False:
            p._start_estimating()  # the data timed as before the restart
        if p.estimating:
            p.clocks.set_applied(applied)
            for n, o in applied.items():
                p.sync.set_offset(n, o)


def _shape_rows(R: np.ndarray, t: np.ndarray, std: np.ndarray) -> list:
    """``Pipeline.data_shape`` as JSON: per camera None (not placed) or [R (9), t (3),
    std m, std deg] (a std unknown: None)."""
    return [None if not np.all(np.isfinite(t[c])) else
            [*R[c].ravel().tolist(), *t[c].tolist(), *(float(x) if np.isfinite(x) else None for x in std[c])]
            for c in range(len(t))]


def _shape_arrays(rows: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_shape_rows`` back to (R (C, 3, 3), t (C, 3), std (C, 2)), NaN where unknown."""
    C = len(rows)
    R, t, std = np.full((C, 3, 3), np.nan), np.full((C, 3), np.nan), np.full((C, 2), np.nan)
    for c, row in enumerate(rows):
        if row is None:
            continue
        R[c] = np.array(row[:9], dtype=np.float64).reshape(3, 3)
        t[c] = np.array(row[9:12], dtype=np.float64)
        std[c] = [np.nan if x is None else float(x) for x in row[12:14]]
    return R, t, std
