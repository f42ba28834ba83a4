"""What the engine knows at a moment: plain, frozen, JSON-able records.

These are the engine's outputs that the service, the API, persistence and the
benchmarks read; they hold no gtsam objects and no references into the pipeline.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from .cameras import Extrinsics, Intrinsics, Pose
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
class Lenses:
    """How far the final batch adjustment found the lenses off their calibration files
    (``optimize.lenses``): per camera, fx and fy as fractions of the file's (+0.01: 1 %
    longer) and the principal point's shift in px (at the file's resolution); spread: the
    std of such deviations the data show across the cameras (focal fraction, px). The
    result's poses are the ones that fit these lenses."""

    cameras: dict[str, tuple[float, float, float, float]]  # name -> (fx, fy fractions, cx, cy px)
    spread_focal: float
    spread_centre_px: float

    @staticmethod
    def of(names: Sequence[str], lenses: np.ndarray, spread: np.ndarray, focal: np.ndarray) -> "Lenses":
        """From ``Solution.lenses`` (C, 4) and ``lens_std`` (4,) (normalised: the principal
        point in focal lengths) and the files' focal lengths (C, 2) px (fx, fy)."""
        assert lenses.shape == (len(names), 4) and spread.shape == (4,) and focal.shape == (len(names), 2)
        cams = {n: (float(d[0]), float(d[1]), float(d[2] * f[0]), float(d[3] * f[1]))
                for n, d, f in zip(names, lenses, focal) if np.all(np.isfinite(d))}
        return Lenses(cams, float(spread[0]), float(spread[2] * np.median(focal)))

    def intrinsics(self, files: Mapping[str, Intrinsics]) -> dict[str, Intrinsics]:
        """The calibration files' intrinsics with these lenses (their distortion kept)."""
        out = dict(files)
        for n, (fx, fy, cx, cy) in self.cameras.items():
            i = files[n]
            out[n] = replace(i, fx=i.fx * (1 + fx), fy=i.fy * (1 + fy), cx=i.cx + cx, cy=i.cy + cy)
        return out

    def then(self, newer: "Lenses") -> "Lenses":
        """These lenses, and ``newer`` found relative to them (a resumed session's final
        batch): each camera's deviation from its file."""
        cams = dict(self.cameras)
        for n, (fx, fy, cx, cy) in newer.cameras.items():
            a = cams.get(n, (0.0, 0.0, 0.0, 0.0))
            cams[n] = ((1 + a[0]) * (1 + fx) - 1, (1 + a[1]) * (1 + fy) - 1, a[2] + cx, a[3] + cy)
        return Lenses(cams, max(self.spread_focal, newer.spread_focal), max(self.spread_centre_px, newer.spread_centre_px))

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> "Lenses":
        """``to_dict``'s inverse (a resumed session keeps the lenses its poses fit)."""
        return Lenses({n: (float(v["fx"]), float(v["fy"]), float(v["cx_px"]), float(v["cy_px"]))
                       for n, v in d["cameras"].items()}, float(d["spread_focal"]), float(d["spread_centre_px"]))

    def summary(self) -> str:
        shown, most = [], []
        if self.spread_focal > 0 and self.cameras:
            n, v = max(self.cameras.items(), key=lambda kv: abs(kv[1][0]) + abs(kv[1][1]))
            shown.append(f"{100 * self.spread_focal:.2f} % in focal length")
            most.append(f"{n} focal {100 * v[0]:+.2f} % / {100 * v[1]:+.2f} %")
        if self.spread_centre_px > 0 and self.cameras:
            n, v = max(self.cameras.items(), key=lambda kv: np.hypot(kv[1][2], kv[1][3]))
            shown.append(f"{self.spread_centre_px:.1f} px in principal point")
            most.append(f"{n} principal point ({v[2]:+.1f}, {v[3]:+.1f}) px")
        return (f"lenses off their calibration files (optimize.lenses): the data show a spread of "
                f"{' and '.join(shown) or 'nothing'} across the cameras; the poses fit the lenses estimated with it"
                + (f" (most off: {', '.join(most)})" if most else ""))

    def to_dict(self) -> dict[str, Any]:
        return {"cameras": {n: {"fx": v[0], "fy": v[1], "cx_px": v[2], "cy_px": v[3]} for n, v in self.cameras.items()},
                "spread_focal": self.spread_focal, "spread_centre_px": self.spread_centre_px, "summary": self.summary()}


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
