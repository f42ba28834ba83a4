"""What the engine knows at a moment: plain, frozen, JSON-able records.

These are the engine's outputs that the service, the API, persistence and the
benchmarks read; they hold no gtsam objects and no references into the pipeline.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .cameras import Extrinsics, Pose
from .clock_offsets import SensorClock


@dataclass(frozen=True)
class CameraState:
    """One camera's estimate.

    R: (3, 3) world_R_cam, t: (3,) optical centre, cov: (6, 6) tangent covariance
    (rotation rad, translation m; GTSAM Pose3 order, body frame).
    """

    name: str
    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    observations: int  # projections of this camera used in cycles so far
    cycles: int  # cycles this camera took part in
    change_translation: float  # m, mean pose change per cycle over the last cycles
    change_rotation: float  # deg
    converged: bool
    last_seen: float | None  # data time of its last message
    moved_at: float | None = None  # data time the monitor last found it moved (re-calibrated since)
    # data time it last started over from a pose found elsewhere (a dispute adjustment over
    # its archived views, a re-localisation), and why
    restarted_at: float | None = None
    restart_reason: str | None = None

    @property
    def std_translation(self) -> float:
        return float(np.sqrt(max(np.trace(self.cov[3:, 3:]) / 3, 0.0)))

    @property
    def std_rotation(self) -> float:
        return float(np.degrees(np.sqrt(max(np.trace(self.cov[:3, :3]) / 3, 0.0))))

    @property
    def pose(self) -> Pose:
        return Pose(self.R, self.t)

    def to_dict(self) -> dict[str, Any]:
        from .geometry import R_to_quat

        return {
            "name": self.name,
            "translation": self.t.tolist(),
            "rotation": R_to_quat(self.R).tolist(),
            "std_translation": self.std_translation,
            "std_rotation": self.std_rotation,
            "observations": self.observations,
            "cycles": self.cycles,
            "change_translation": self.change_translation,
            "change_rotation": self.change_rotation,
            "converged": self.converged,
            "last_seen": self.last_seen,
            "moved_at": self.moved_at,
            "restarted_at": self.restarted_at,
            "restart_reason": self.restart_reason,
        }


@dataclass(frozen=True)
class Levelled:
    """The world frame of a bootstrapped run levelled again on the final batch
    adjustment's floor (``refine.floor_frame``), or why not (``reason``)."""

    done: bool
    reason: str = ""
    turn_deg: float = 0.0  # between the bootstrap's z and the final floor's up
    shift: float = 0.0  # m the origin moved
    points: int = 0  # lower ankles of the final floor's plane
    spread: float = 0.0  # m their robust std about it
    first: str = ""  # origin on the floor under this camera ...
    second: str = ""  # ... x towards the floor point under this one

    def summary(self) -> str:
        if not self.done:
            return f"world frame not levelled again (the bootstrap's floor kept): {self.reason}"
        return (f"world frame levelled again on the final batch adjustment's floor (the plane of {self.points} lower "
                f"ankles, spread {self.spread:.3f} m): turned {self.turn_deg:.2f}° from the bootstrap's, origin "
                f"moved {self.shift:.3f} m, still under {self.first}, x towards {self.second}")

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "summary": self.summary()}


@dataclass(frozen=True)
class CycleReport:
    """What one optimisation cycle did."""

    cycle: int
    data_time: float
    hypotheses: int  # used in the graph
    observations: int
    cameras: tuple[str, ...]  # cameras constrained in this cycle
    initial_error: float  # graph error before / after the solve
    final_error: float
    iterations: int
    solve_seconds: float
    moved: bool  # did the solver change the estimate (not a silent stall)
    accepted: bool
    reason: str  # why not accepted, or ''
    max_change_translation: float  # m over cameras
    max_change_rotation: float  # deg
    reprojection_px: float  # median reprojection error of the cycle's projections after the solve
    moved_cameras: tuple[str, ...] = ()  # converged cameras the monitor found moved in this cycle
    # moved cameras this cycle calibrated again for good (the last adjustment over their
    # data since the move): the network has a new calibration, which the service versions
    recalibrated: tuple[str, ...] = ()
    # cameras that started over from a pose found elsewhere since the last report (a dispute
    # adjustment said their estimate was wrong, or they were re-localised)
    restarted: tuple[str, ...] = ()
    # rejected with nothing to solve (no landmark placed: garbled data, or none that fits the
    # estimate); not the optimizer failing, so a session is not failed for such cycles
    starved: bool = False
    # hypotheses dropped as far larger than anyone seen: two walkers' views in cameras that
    # share no floor (optimize.max_size_ratio; adjustments with bones only)
    phantoms: int = 0
    # lower ankles held to the floor's plane, and their robust std about it in m (0 and 0:
    # no floor; optimize.floor, adjustments with bones only)
    floor_points: int = 0
    floor_spread: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["cameras"] = list(self.cameras)
        d["moved_cameras"] = list(self.moved_cameras)
        d["recalibrated"] = list(self.recalibrated)
        d["restarted"] = list(self.restarted)
        return d


@dataclass(frozen=True)
class Counters:
    """Cumulative counts of the front end, with rejections by reason."""

    messages: int = 0
    rejected: dict[str, int] = field(default_factory=dict)  # reason → count
    framesets: int = 0
    framesets_rejected: dict[str, int] = field(default_factory=dict)
    views: int = 0  # person detections that passed preprocessing
    views_rejected: dict[str, int] = field(default_factory=dict)
    hypotheses: int = 0
    queue_length: int = 0
    queue_dropped: int = 0
    cycles: int = 0
    cycles_rejected: int = 0


@dataclass(frozen=True)
class CalibrationState:
    """The current calibration: every camera, convergence, counters."""

    data_time: float | None
    cycle: int
    cameras: tuple[CameraState, ...]
    converged: bool  # every camera that can be calibrated is converged
    counters: Counters
    last_cycle: CycleReport | None
    clocks: tuple[SensorClock, ...] = ()  # sensor clock offsets (reference: the median sensor)
    scale_check: dict[str, Any] | None = None  # the initial estimate's scale against the people's (scale_check.py)
    split_check: dict[str, Any] | None = None  # the final batch on two halves of the data (split_check.py)

    def camera(self, name: str) -> CameraState:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def poses(self) -> dict[str, Pose]:
        return {c.name: c.pose for c in self.cameras}

    def extrinsics(self, resolutions: dict[str, tuple[int, int]]) -> dict[str, Extrinsics]:
        """The FORMATS.md extrinsics of this state (with per-camera std)."""
        return {
            c.name: Extrinsics(c.pose, resolutions[c.name], c.std_translation, c.std_rotation)
            for c in self.cameras
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "data_time": self.data_time,
            "cycle": self.cycle,
            "converged": self.converged,
            "cameras": [c.to_dict() for c in self.cameras],
            "counters": asdict(self.counters),
            "last_cycle": self.last_cycle.to_dict() if self.last_cycle else None,
            "clocks": {c.sensor: c.to_dict() for c in self.clocks},
            "scale_check": self.scale_check,
            "split_check": self.split_check,
        }
