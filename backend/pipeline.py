"""The calibration pipeline: every stage wired top to bottom, driven by a clock.

    message ─► ingest      known sensor, plausible stamp, no duplicate
            ─► clocks      sensor clock offsets from the raw streams (applied by sync)
            ─► sync        framesets of per-sensor messages interpolated to one instant
            ─► preprocess  filters, undistortion
            ─► associate   person hypotheses across views
            ─► queue       bounded, newest kept
            ─► select      one cycle's hypotheses (every `select.interval` s of data time)
            ─► optimize    GTSAM factor graph → poses + marginals   (pure function, any process)
            ─► refine      Kalman update on SE(3), scale kept from the initial estimate
            ─► monitor     converged cameras that moved are flagged and calibrated again
  at the end   archive timed with the final clock offsets (retime), final batch, then the
               initial estimate's scale checked against the people's
            ─► state       CalibrationState

The clock is the caller's: offline it is the recording's data time (the newest stamp),
live it is the wall clock. ``run_offline`` drives it synchronously; the service drives
``advance`` on its event loop, ``optimize.solve`` in a worker process and the clock
offsets' estimate (``clock_job``) in a thread.

``Pipeline`` is this module with three parts of its own: backend/clock_stage.py (the
clocks: when the estimate starts, its jobs, the offsets applied, the archive timed
again), backend/end_of_run.py (the final batch and the checks after it) and
backend/snapshot.py (its estimate as JSON, to resume from).
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from dataclasses import replace
from typing import Callable, Iterable, Sequence

import numpy as np

from proto import KeypointMessage

from .associate import Associator, Hypothesis
from .cameras import CameraSet
from .clock_offsets import ClockOffsetEstimator
from .clock_stage import ClockStage
from .config import EngineConfig
from .end_of_run import EndOfRun
from .geometry import from_prior, pose_std
from .monitor import Monitor
from .optimize import NOTHING_TO_SOLVE, Problem, Solution, solve
from .people import relative_size, segments
from .preprocess import Detection, Preprocessor
from .refine import Refiner
from .retime import RawArchive
from .scale_check import ScaleCheck
from .selection import HypothesisQueue
from .snapshot import Snapshots
from .split_check import SplitCheck
from .stamp_watch import StampWatch
from .state import CalibrationState, CameraState, Counters, CycleReport, Lenses, Levelled
from .sync import Synchronizer


log = logging.getLogger(__name__)

_CLOCK_SAMPLES = 16  # offline: messages held back to find a plausible start of time


Moves = dict[int, tuple[float, float, float]]


def _moves(problem: Problem, solution: Solution) -> Moves:
    """Each camera the solution moved: its (m, deg, χ²) from the problem's prior."""
    return {int(c): from_prior(problem.prior_R[c], problem.prior_t[c], problem.prior_cov[c], solution.R[c],
                                solution.t[c]) for c in np.flatnonzero(solution.active)}


def _gated(moves: Moves, C: int, gate: float) -> np.ndarray:
    """(C,) bool the cameras ``moves`` put further than χ² ``gate`` (6 dof) from their
    prior. None is far when the gate is off (0), or when most of the cameras moved went
    that far: then the stated uncertainty is what is wrong, not the data. NaN (a singular
    prior) is not far."""
    far = np.zeros(C, bool)
    if gate <= 0 or not moves:
        return far
    idx = np.fromiter(moves, dtype=np.int64)
    far[idx] = [moves[c][2] > gate for c in idx]
    if far.sum() * 2 > len(idx):
        far[:] = False
    return far


class Pipeline(ClockStage, EndOfRun, Snapshots):
    def __init__(self, cameras: CameraSet, config: EngineConfig | None = None, *, seed: int = 0,
                 start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                 scale_heights: Sequence[float] | None = None,
                 data_shape: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        """``start``: (R (C, 3, 3), t (C, 3), P (C, 6, 6)): where the estimate starts and
        what adjustments over all data are anchored to, when that is not the initial
        estimate with ``refine.initial_std_*`` (e.g. the data's shape aligned onto a rough
        initial estimate, backend/reconcile.py); the initial estimate keeps the frame and
        the scale. ``scale_heights``: when not None, ``finish`` checks the initial
        estimate's scale against the people's (the walkers' heights in m if known, else
        ``()``: the population prior) and corrects it as ``bootstrap.initial_scale`` says
        (backend/scale_check.py); None for cameras whose scale is the people's already
        (a bootstrap's). ``data_shape``: (R (C, 3, 3), t (C, 3), std (C, 2) m, deg; NaN
        rows: unknown) where the data's shape puts the cameras in the initial estimate's
        frame when the run starts from the estimate itself (``Reconciled.data_shape``): the
        final batch tries from there too where its result disagrees (``_batch_from_data``)."""
        self.cameras = cameras
        self.cfg = (config or EngineConfig()).for_images(cameras.sizes)
        self.names = cameras.names
        C = len(self.names)
        R0 = np.array([cameras.extrinsics[n].pose.R for n in self.names])
        t0 = np.array([cameras.extrinsics[n].pose.t for n in self.names])
        self.focal = np.array([0.5 * (cameras.intrinsics[n].fx + cameras.intrinsics[n].fy) for n in self.names])
        self.rng = np.random.default_rng(seed)
        self.sync = Synchronizer(self.cfg.sync, self.names)
        self.preprocess = Preprocessor(self.cfg.preprocess, self.names, cameras.intrinsics)
        self.associate = Associator(self.cfg.associate)
        self.queue = HypothesisQueue(self.cfg.select)
        self.refiner = Refiner(self.cfg.refine, R0, t0, None if start is None else start[2],
                               None if start is None else start[:2])
        self.monitor = Monitor(self.cfg.monitor, self.focal, outlier_px=self.cfg.optimize.outlier_px,
                               min_angle_deg=self.cfg.optimize.min_triangulation_angle)
        self.watched = np.zeros(C, dtype=bool)
        # moved cameras' adjustments: (data time due, camera, data time of its move)
        self._recalibrate_due: list[tuple[float, int, float]] = []
        self.clocks = ClockOffsetEstimator(self.cfg.clock, self.names, cameras.intrinsics,
                                           self.cfg.preprocess.min_confidence, self.preprocess.confidence)
        # per camera: (frameset time from which, offset applied), to know how archived views were timed
        self._offset_history: list[list[tuple[float, float]]] = [[] for _ in self.names]
        # raw messages, to time the archived views again with the final offsets (backend/retime.py)
        self.raw: RawArchive | None = None
        self.estimating = False  # the clock offsets' estimate runs (clock.estimate; "auto": once the stamps say so)
        self.stamps = StampWatch(self.cfg.clock.auto_lead)  # "auto": whether the stamps run apart
        self._far: frozenset[str] = frozenset()  # the sensors whose stamps started the estimate ("auto")
        if self.cfg.clock.estimate is True:
            self._start_estimating()
        self.retimed: dict[str, int] = {}  # sensor -> archived views timed again at the end
        # preprocessed framesets, re-associated with a better estimate by warm-up and final batch
        self.frames: deque[tuple[float, tuple[tuple[Detection, ...], ...]]] = deque(
            maxlen=self.cfg.refine.archive_frames)
        self.observations_batch = np.zeros(C, dtype=np.int64)
        # detections and associated detections per camera since the last lost-camera check
        self.detected = np.zeros(C, dtype=np.int64)
        self.associated = np.zeros(C, dtype=np.int64)
        self.detected_total = np.zeros(C, dtype=np.int64)
        self.associated_total = np.zeros(C, dtype=np.int64)
        self.associated_multi = np.zeros(C, dtype=np.int64)  # ... in hypotheses of >= min_views_unsettled views
        # shank, thigh, torso lengths of recent hypotheses (_without_giants), NaN = not measured
        self.sizes: deque[tuple[float, float, float]] = deque(maxlen=2000)
        self.last_lost_check: float | None = None
        self.first_passes = 0  # passes of the first adjustment done (select.first_scope)
        self.first_gated: list[str] = []  # cameras a first pass put implausibly far, kept at their start
        self.cycle_gated: Counter = Counter()  # per camera: cycles whose move of it was not taken (select.cycle_gate)
        self.disputes = np.zeros(C, dtype=np.int64)  # per camera: cycles in a row that refused its move
        self.confirmed = np.zeros(C, dtype=np.int64)  # per camera: dispute adjustments that kept its estimate
        self.disputed: list[int] = []  # cameras due for a dispute adjustment (select.dispute_cycles)
        self.redone: list[str] = []  # cameras a dispute adjustment put elsewhere
        self.relocalized: list[str] = []
        # per camera: (data time, why) it last started over from a pose found elsewhere
        # (a dispute adjustment, a re-localisation); the cycle's report lists those since the last
        self.restarted: dict[int, tuple[float, str]] = {}
        self._restarted_new: list[str] = []
        # the final batch kept: from the "estimate", the "start", the "data", held to it ("anchored")
        self.final_batch_start: str | None = None
        if data_shape is not None:
            assert data_shape[0].shape == (C, 3, 3) and data_shape[1].shape == (C, 3) and data_shape[2].shape == (C, 2)
        self.data_shape = data_shape
        self.scale_heights = None if scale_heights is None else tuple(float(h) for h in scale_heights)
        self.scale_check: ScaleCheck | None = None
        self.split_check: SplitCheck | None = None  # the final batch on two halves of the data
        self.levelled: Levelled | None = None  # a bootstrap's floor frame levelled on the final batch's floor
        # the lenses the final batch found off their files (optimize.lenses); the poses fit them
        self.lenses: Lenses | None = None
        # (C, 6, 6) what the lenses' accuracy adds to the stated covariance (``state``), from the
        # final batch (``optimize.lens_accuracy_*``), NaN = nothing. Kept apart from the
        # refiner's: convergence, the split-half check (both halves share the lenses) and the
        # monitor go by the noise's alone; a lens's error is no less for more data
        self.lens_cov: np.ndarray | None = None
        self.clock: float | None = None
        self.cycle = 0
        self.cycles_rejected = 0
        self.last_cycle_time: float | None = None
        self.last_report: CycleReport | None = None
        self.observations = np.zeros(C, dtype=np.int64)
        self.last_seen: dict[str, float] = {}
        self.messages = 0
        self.rejected: Counter = Counter()
        self._inflight: Problem | None = None
        self._pending: list[KeypointMessage] = []  # offline: held until the clock is known

    # ------------------------------------------------------------ front end

    def push(self, msg: KeypointMessage, arrival: float | None = None) -> str | None:
        """Take one validated message; returns the rejection reason or None.

        ``arrival`` is the receiver's clock (live). Offline the newest plausible stamp
        stands in for it; until there is one, the first messages are held back and their
        median stamp decides which are absurd (one bad stamp at the start of a recording
        must not become the clock and reject everything after it).
        """
        if arrival is None and self.clock is None:
            self._pending.append(msg)
            if len(self._pending) < _CLOCK_SAMPLES:
                return None
            return self._release_pending()
        self.messages += 1
        now = arrival if arrival is not None else self.clock
        reason = self.sync.push(msg, now)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        if self.estimating:
            self.clocks.push(msg)
            if self.raw is not None:
                self.raw.push(msg)
        self.last_seen[msg.sensor] = msg.stamp
        if self._watching_stamps:
            self.stamps.observe(msg.sensor, msg.stamp)
        stamp = msg.stamp - self.sync.offset(msg.sensor)
        if arrival is None and (self.clock is None or stamp > self.clock):
            self.clock = stamp
        return None

    def _release_pending(self) -> str | None:
        """Establish the offline clock from the held-back messages and push them."""
        pending, self._pending = self._pending, []
        med = float(np.median([m.stamp for m in pending]))
        limit = self.cfg.sync.max_stamp_future
        ok = [m.stamp for m in pending if abs(m.stamp - med) <= limit]
        self.clock = max(ok) if ok else med
        reason = None
        for m in sorted(pending, key=lambda m: m.stamp):
            reason = self.push(m)
        return reason

    def advance(self, now: float | None, *, clock_offsets: bool = True) -> int:
        """Run sync/preprocess/associate up to clock time ``now``; returns new hypotheses.
        ``None`` (offline, before the clock is known) does nothing. ``clock_offsets``:
        also the clock offsets' estimate when due, here (seconds of CPU); the service
        says False and runs ``clock_job`` in a thread instead."""
        if now is None:
            return 0
        if self.clock is None or now > self.clock:
            self.clock = now
        new = 0
        if self._watching_stamps:
            self._watch_stamps(now)
        R, t = self.refiner.R, self.refiner.t
        job = self.clock_job(now) if clock_offsets else None
        if job is not None:
            self.apply_clock(job, job.run())
        ready = self.sync.pop_ready(now)
        gates = self._gates() if ready else (None, None, None)
        for fs in ready:
            dets = self.preprocess(fs)
            if len(dets) < 2:
                continue
            new += self._take(fs.time, tuple(tuple(v) for v in dets), R, t, *gates)
        return new

    def take_frames(self, frames: Iterable[tuple[float, tuple[tuple[Detection, ...], ...]]]) -> int:
        """Preprocessed framesets from before this pipeline existed (the live bootstrap
        collected them; their detections' ``cam`` index this pipeline's cameras), archived,
        associated and queued as if they had just come out of ``preprocess``; returns the
        new hypotheses."""
        R, t = self.refiner.R, self.refiner.t
        gates = self._gates()
        return sum(self._take(T, views, R, t, *gates) for T, views in frames if len(views) >= 2)

    def _take(self, time: float, views: tuple[tuple[Detection, ...], ...], R: np.ndarray, t: np.ndarray,
              gate: np.ndarray | None, pose_px: np.ndarray | None, follow: np.ndarray | None) -> int:
        """One preprocessed frameset (>= 2 views): archive, associate, queue, count."""
        self.frames.append((time, views))
        hyps = self.associate(time, views, R, t, gate, pose_px, follow)
        # Only while some camera sees people with one other camera alone: there no third
        # view checks a pair. In the lab with two walkers (none such) the check everywhere
        # cost convergence (0.074 against 0.064 m at 60 s of data), though not the result.
        if hyps and self.cfg.optimize.max_size_ratio > 0 and self._pairwise_only().any():
            hyps = self._without_giants(hyps, R, t)
        self.queue.extend(hyps)
        self.monitor.add(hyps)
        if self.estimating:
            self.clocks.add(hyps)
        for v in views:
            # whole views only: a view with one side hidden follows only cameras the
            # cycles know, so counted it would make a camera that sees people side-on
            # look lost (``_lost_cameras``) before its first cycles
            n = sum(d.whole_torso for d in v)
            self.detected[v[0].cam] += n
            self.detected_total[v[0].cam] += n
        for h in hyps:
            self.associated[h.cams] += 1
            self.associated_total[h.cams] += 1
            if len(h.cams) >= self.cfg.associate.min_views_unsettled:
                self.associated_multi[h.cams] += 1
        return len(hyps)

    def _calibrated(self) -> bool:
        """The first adjustment is done: the poses are good enough to time the sensors
        against (before it, 3D from cameras 10° off says nothing about time)."""
        s = self.cfg.select
        return self.cycle > 0 and (s.first_scope <= 0 or self.first_passes >= s.first_passes)

    def _pose_px(self, start: bool = False) -> np.ndarray:
        """(C,) px a camera's reprojections may be off by its pose's uncertainty (one std;
        a person ~3 m away, as in the association gate); ``start``: the start's (the prior
        of the adjustments over all data)."""
        st, sr = pose_std(self.refiner.P0 if start else self.refiner.P)
        return self.focal * (sr + st / 3.0)

    def _gates(self) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """The association's gates, from one ``_pose_px``: (C,) reprojection gate in px
        for cameras the filter is already sure of (None without ``reassociate``), the
        pose term of the epipolar test of two views, and (C,) px how far a view with one
        side of its torso hidden may miss a hypothesis to follow it (inf: not sure of the
        camera yet, such views are dropped)."""
        a, pose_px = self.cfg.associate, self._pose_px()
        sure = self.refiner.cycles >= 2
        gate = np.where(sure, a.gate_pixels + 3 * pose_px, np.inf) if a.reassociate else None
        # Not widened by the pose's uncertainty, as the whole views' gate is: such a view
        # cannot be placed by itself, so a wider gate only widens the chance of a wrong
        # follow (the west room's 30 s: the one view between 25 px and the widened gate
        # took the result from 0.0222 to 0.0272 m shape), and an uncertain camera that
        # misses a few loses little.
        follow = np.where(sure, a.gate_pixels, np.inf)
        return gate, pose_px, follow

    # ------------------------------------------------------------ optimisation

    def next_problem(self, now: float | None) -> Problem | None:
        """A cycle's problem when one is due, else None. Only one is in flight at a time:
        re-localisation of lost cameras when one is due; at the start the first adjustment
        (two passes, see ``_first_problem``); else the paper's cycle over the queue's
        newest hypotheses with the filter's predicted state as the prior."""
        if self._inflight is not None or now is None:
            return None
        rf, cfg = self.refiner, self.cfg
        lost = self._lost_cameras(now)
        if lost:
            self.cycle += 1
            horizon = self.frames[-1][0] - 180.0 if self.frames else 0.0
            p = self._relocalize_problem(lost, self._timed_frames(f for f in self.frames if f[0] >= horizon))
        elif self.disputed:
            p = self._dispute_problem(self.disputed.pop(0))
        elif any(due <= now for due, _, _ in self._recalibrate_due):
            k = next(i for i, (due, _, _) in enumerate(self._recalibrate_due) if due <= now)
            _, cam, since = self._recalibrate_due.pop(k)
            p = self._recalibrate_problem(cam, since)
        else:
            if self.last_cycle_time is not None and now - self.last_cycle_time < cfg.select.interval:
                return None
            a = cfg.associate
            if cfg.select.first_scope > 0 and self.first_passes < cfg.select.first_passes:
                if self.first_passes == 0 and (not self.queue.ready() or (
                        now - self.queue.first_time < cfg.select.first_wait
                        and self.queue.spread(a.min_views_unsettled) < cfg.select.first_scope)):
                    self.last_cycle_time = now  # look again an interval later
                    return None
                p = self._first_problem()
            else:
                if not self.queue.ready():
                    return None
                settled = (rf.cycles >= a.settled_cycles) | self._pairwise_only()
                hyps = self.queue.select(self.rng, None,
                                         lambda h: len(h.cams) >= a.min_views_unsettled or settled[h.cams].all())
                if not hyps:  # queued, but none usable yet: no cycle; look again an interval later
                    self.last_cycle_time = now
                    return None
                self.cycle += 1
                p = Problem(cycle=self.cycle, R=rf.R.copy(), t=rf.t.copy(), prior_R=rf.R.copy(), prior_t=rf.t.copy(),
                            prior_cov=rf.predicted_covariance(), focal=self.focal, config=cfg.optimize,
                            hypotheses=tuple(hyps), kind="cycle")
        self.last_cycle_time = now
        self._inflight = p
        return p

    def _first_problem(self) -> Problem:
        """The first adjustment, in passes over every frame so far, each associated with
        the estimate the pass before left (min_views_unsettled views): from a rough start
        a cycle of a few dozen hypotheses lets a handful of wrong associations drag a
        camera metres off, and even a hundred can pull one that sees little; the next
        association, with everyone else about right, no longer makes those mistakes.
        select.first_passes passes (2: measured from 20° starts, 4 passes ended worse
        than 2; a pass more cannot undo what a wrong association did to the one before)."""
        a, s = self.cfg.associate, self.cfg.select
        p = self._batch_problem(s.first_scope, s.min_spacing)
        self.first_passes += 1
        self.queue.clear()  # their data are in this adjustment: a cycle must not count them again
        # the std a running session states carries the lenses' accuracy from here on (``_lens_part``)
        return replace(p, associate=a.model_copy(update={"min_views": a.min_views_unsettled}), kind="first",
                       lens_accuracy=True)

    def _recalibrate_problem(self, cam: int, since: float) -> Problem:
        """A moved camera calibrated again by an adjustment over every archived frame since
        its move, the watched cameras held (tight priors), its own prior the monitor's
        resection with the uncertainty re-opened: the resection a bin at a time took the
        others' points as given; the adjustment weighs every view, as the session did.
        Its hypotheses need ``associate.min_views_unsettled`` views, as the first
        adjustment's: the camera is unsettled, and two views, its own and one other, pair
        people along their epipolar line that no third view checks (the generated steep
        room's 2° turn: 0.60° off at +120 s with two views allowed, 0.02° with three)."""
        m, a = self.cfg.monitor, self.cfg.associate
        cov = np.diag([np.radians(m.reopen_std_rotation) ** 2] * 3 + [m.reopen_std_translation ** 2] * 3)
        p = self._one_camera_problem(cam, cov, (f for f in self.frames if f[0] >= since), "recalibrate")
        return replace(p, associate=p.associate.model_copy(update={"min_views": max(a.min_views, a.min_views_unsettled)}))

    def _dispute_problem(self, cam: int) -> Problem:
        """A camera the cycles keep disagreeing with (``_count_disputes``) decided by an
        adjustment over the archived frames in which it sees someone, re-associated, its
        own prior re-opened to the start's std and its views not gated by its pose; the
        others' priors their filtered state. Only that camera's result is taken (``_settle``)."""
        frames = (f for f in self.frames if any(v[0].cam == cam for v in f[1]))  # a view: one camera's detections
        # its own seed: a dispute must not change what the run's other draws select
        return self._one_camera_problem(cam, self.refiner.P0[cam], frames, "dispute", seed=self.cycle * 7919 + cam)

    def _one_camera_problem(self, cam: int, cov: np.ndarray, frames: Iterable, kind: str, *,
                            seed: int | None = None) -> Problem:
        """An adjustment over ``frames`` (re-associated, up to ``refine.batch_size``
        hypotheses) for camera ``cam``: its prior the estimate with covariance ``cov`` (6, 6),
        its views not gated by its pose (where it is is what the adjustment is to find); the
        others' priors their filtered state."""
        rf = self.refiner
        P = rf.predicted_covariance()
        P[cam] = cov
        p = self._batch_problem(self.cfg.refine.batch_size, self.cfg.select.min_spacing / 2, frames, seed=seed)
        pose_px, follow_px = p.pose_px.copy(), p.follow_px.copy()
        pose_px[cam] = follow_px[cam] = np.inf
        return replace(p, prior_R=rf.R.copy(), prior_t=rf.t.copy(), prior_cov=P, kind=kind, moved=(cam,),
                       pose_px=pose_px, follow_px=follow_px)

    def _relocalize_problem(self, lost, frames) -> Problem:
        """Prior = the start and its uncertainty: where a lost camera can be
        (the filter may have dragged it anywhere)."""
        rf = self.refiner
        return Problem(cycle=self.cycle, R=rf.R.copy(), t=rf.t.copy(), prior_R=rf.prior_R.copy(),
                       prior_t=rf.prior_t.copy(), prior_cov=rf.P0.copy(), focal=self.focal, config=self.cfg.optimize,
                       frames=tuple(frames), associate=self.cfg.associate, seed=int(self.rng.integers(2**31)),
                       kind="relocalize", lost=tuple(int(c) for c in lost))

    def _lost_cameras(self, now: float) -> list[int]:
        """Cameras that see people but whose detections almost never join a hypothesis."""
        a = self.cfg.associate
        if not a.relocalize or self.cycle < a.relocalize_after:
            return []
        if self.last_lost_check is None:
            self.last_lost_check = now
        if now - self.last_lost_check < a.relocalize_interval:
            return []
        self.last_lost_check = now
        det, assoc = self.detected, self.associated
        lost = (det >= a.lost_min_detections) & (assoc < a.lost_ratio * det)
        # decay rather than reset: recent behaviour counts most
        self.detected = det // 2
        self.associated = assoc // 2
        return [int(c) for c in np.flatnonzero(lost | self._never_associated())]

    def _without_giants(self, hyps: list[Hypothesis], R: np.ndarray, t: np.ndarray) -> list[Hypothesis]:
        """The hypotheses without phantoms, while some camera sees people only in pairs
        (``_pairwise_only``): views of two walkers whose rays meet where their joints form
        a body far larger than anyone (``people.oversized``, which the final batch uses with
        the persons told apart; two cameras that share no floor, each with one walker in
        front of it). The cycles have no persons told apart; per bone, a high quantile
        (0.9) of the recent hypotheses' lengths stands in for the largest person's, and a
        hypothesis more than ``optimize.max_size_ratio`` times its size
        (``people.relative_size``) is dropped (counted as the association's "phantom"). A
        few phantoms in one cycle dragged a camera of a two-walker corridor 0.7 m, and
        cam_5 of the lab with six walkers 1.2 m (docs/bones.md, Session 33)."""
        seg = segments(hyps, R, t)
        ref = None
        if len(self.sizes) >= 200:
            with np.errstate(all="ignore"):
                ref = np.nanquantile(np.array(self.sizes), 0.9, axis=0)
        self.sizes.extend(zip(seg.shank.tolist(), seg.thigh.tolist(), seg.torso.tolist()))
        if ref is None or not np.all(np.isfinite(ref)):
            return hyps
        giant = np.nan_to_num(relative_size(seg, ref)) > self.cfg.optimize.max_size_ratio
        if not giant.any():
            return hyps
        self.associate.rejected["phantom"] += int(giant.sum())
        return [h for h, g in zip(hyps, giant) if not g]

    def _pairwise_only(self) -> np.ndarray:
        """(C,) cameras that see people with one other camera but (almost) never with two
        more (a corridor): waiting for min_views_unsettled views would leave them out for good."""
        a = self.cfg.associate
        n = self.associated_total
        return (n >= a.lost_min_detections) & (self.associated_multi < 0.05 * n)

    def lens_cameras(self) -> tuple[int, ...]:
        """The cameras whose lenses a final batch may find off their files: those that see
        people together with two more cameras. A lens (focal length, principal point) and
        a pose differ only in what three views show; seen in pairs, as along a corridor, a
        lens trades with the link's scale and bend (the corridor's shape error went 0.028
        -> 0.046 m with them free; docs/accuracy.md, Session 37)."""
        seen = self.associated_total >= self.cfg.associate.lost_min_detections
        return tuple(int(c) for c in np.flatnonzero(seen & ~self._pairwise_only()))

    def _never_associated(self) -> np.ndarray:
        """(C,) cameras that never took part in a cycle though they saw people often."""
        a = self.cfg.associate
        det, assoc = self.detected_total, self.associated_total
        return (self.refiner.cycles == 0) & (det >= a.lost_min_detections) & (assoc < a.lost_ratio * det)

    def _batch_problem(self, max_hypotheses: int, spacing: float, frames: Iterable | None = None, *,
                       final: bool = False, seed: int | None = None) -> Problem:
        """Every archived frame (or ``frames``), re-associated in the solve with the current
        estimate; prior = the start (the initial estimate, or the data's shape aligned onto
        it) with its covariance, so the result is the honest posterior of all the data.
        ``final``: the run's last adjustment, the one ``optimize.bones = "auto"`` gives
        bones when the cameras form a chain (judged on the whole run's associations)."""
        rf = self.refiner
        self.cycle += 1
        opt = self.cfg.optimize.model_copy(update={"max_iterations": max(self.cfg.optimize.max_iterations, 100)})
        if opt.bones == "auto":  # bones carry the scale along a chain, where projections cannot
            opt = opt.model_copy(update={"bones": "batch" if final and self._pairwise_only().any() else "off"})
        _, pose_px, follow_px = self._gates()
        return Problem(cycle=self.cycle, R=rf.R.copy(), t=rf.t.copy(), prior_R=rf.prior_R.copy(),
                       prior_t=rf.prior_t.copy(), prior_cov=rf.P0.copy(), focal=self.focal, config=opt,
                       frames=tuple(self._timed_frames(frames)),
                       associate=self.cfg.associate,
                       # the batch re-associates ungated: a camera the filter got wrong must
                       # keep its views to be put right; the solve's outlier rounds drop bad ones
                       gate_px=None, pose_px=pose_px, follow_px=follow_px, max_hypotheses=max_hypotheses,
                       spacing=spacing, fill=final and self.cfg.refine.batch_fill,
                       seed=int(self.rng.integers(2**31)) if seed is None else seed, kind="batch",
                       lenses=self.lens_cameras() if final and opt.lenses == "auto" else ())

    def apply(self, problem: Problem, solution: Solution) -> CycleReport:
        """Fold a solved cycle into the estimate (or reject it, keeping the estimate)."""
        assert problem is self._inflight or self._inflight is None, "apply() of a problem that is not in flight"
        self._inflight = None
        dt = np.linalg.norm(solution.t - problem.t, axis=1)
        moved = bool(np.any(dt > 1e-9)) or solution.final_error < solution.initial_error * (1 - 1e-9)
        reason = solution.reason if not solution.ok else ""
        if not reason and solution.final_error > solution.initial_error * (1 + 1e-6):
            reason = "error increased"
        if not reason and not moved and len(solution.residual_px):
            reason = "solver did not move the estimate"
        accepted = reason == ""
        change_t = change_r = 0.0
        alarms: list[str] = []
        recalibrated: tuple[str, ...] = ()
        batch = problem.kind == "batch"
        first = problem.kind == "first"  # the posterior of all data so far, but not the final word
        if accepted and problem.kind == "relocalize":
            for c in np.flatnonzero(solution.active):
                self.refiner.relocate(c, solution.R[c], solution.t[c])
                self.relocalized.append(self.names[c])
                self._restart_noted(c, "relocalized: lost, found elsewhere", say=True)
        elif problem.kind == "dispute":
            self._settle(problem.moved[0], solution if accepted else None)
            self.cycles_rejected += not accepted
        elif accepted and problem.kind == "recalibrate":
            # the moved camera's posterior over the data since its move; the held keep theirs
            only = np.zeros(len(self.names), bool)
            only[list(problem.moved)] = True
            upd = self.refiner.update(solution.active & only, solution.R, solution.t, solution.cov, posterior=True,
                                      final=True)
            change_t = float(upd.changed_translation.max())
            change_r = float(upd.changed_rotation.max())
            if not any(c in problem.moved for _, c, _ in self._recalibrate_due):  # its last adjustment
                recalibrated = tuple(self.names[c] for c in problem.moved)
        elif accepted:
            if first:
                active = solution.active & ~self._beyond_prior(problem, solution)
            elif problem.kind == "cycle":
                active = solution.active & ~self._beyond_prediction(problem, solution)
            elif batch:
                active = solution.active & ~self._batch_thin_first_move(problem, solution)
            else:
                active = solution.active
            upd = self.refiner.update(active, solution.R, solution.t, solution.cov, posterior=batch or first,
                                      cov_shape=solution.cov_shape, final=batch)
            if first:
                self._lens_part(solution, active)
            change_t = float(upd.changed_translation.max())
            change_r = float(upd.changed_rotation.max())
            if batch:
                self.observations_batch = np.where(active, solution.obs_per_camera, 0)
            else:
                self.observations += np.where(active, solution.obs_per_camera, 0)
            if problem.kind == "cycle" and self.cfg.monitor.on:
                alarms = self._monitor()
        else:
            self.cycles_rejected += 1
        finite = solution.residual_px[np.isfinite(solution.residual_px)]
        report = CycleReport(
            cycle=problem.cycle,
            data_time=float(self.clock or 0.0),
            hypotheses=solution.hypotheses,
            observations=int(solution.obs_per_camera.sum()),
            cameras=tuple(self.names[c] for c in np.flatnonzero(solution.active)),
            initial_error=float(solution.initial_error),
            final_error=float(solution.final_error),
            iterations=solution.iterations,
            solve_seconds=float(solution.seconds),
            moved=moved,
            accepted=accepted,
            reason=reason,
            max_change_translation=change_t,
            max_change_rotation=change_r,
            reprojection_px=float(np.median(finite)) if len(finite) else float("nan"),
            moved_cameras=tuple(alarms),
            recalibrated=recalibrated,
            restarted=tuple(dict.fromkeys(self._restarted_new)),
            starved=not accepted and solution.reason == NOTHING_TO_SOLVE,
            phantoms=solution.phantoms,
            floor_points=solution.floor_points,
            floor_spread=solution.floor.spread if solution.floor is not None else 0.0,
        )
        self._restarted_new.clear()
        self.last_report = report
        return report

    def _beyond_prior(self, problem: Problem, solution: Solution) -> np.ndarray:
        """(C,) bool the cameras a pass of the first adjustment put further from their
        prior than ``select.first_gate`` (Mahalanobis χ², 6 dof), when they are a minority
        of the cameras it moved: from a rough start a handful of consistently wrong
        associations (a camera that sees one walker while the others see the other) can
        outvote a camera's prior and put it metres off with a small std, and the cycles
        after it then associate to the wrong pose. Left at its start, the next pass, with
        the others about right, associates it again. A camera seen on few projections
        is held by the cycles' stricter gate too (``_thin_first_move``): the realistic
        detector with clock offsets (seed 1 of bench/clock_offsets.py) had a first pass put
        the lab's cam_6 1.42 m / 24° off on 34 projections, χ² 38, just inside
        ``first_gate``, and no cycle after it moved it back (docs/accuracy.md, Session 51)."""
        moves = _moves(problem, solution)
        far = _gated(moves, len(solution.R), self.cfg.select.first_gate)
        thin = self._thin_first_move(solution, moves) & ~far
        for c in np.flatnonzero(far | thin):
            log.warning("the first adjustment put %s %.2f m from its initial estimate (χ² %.0f against its stated "
                        "std%s): kept at its start, the next cycles associate it again", self.names[c], moves[c][0],
                        moves[c][2], f", on {solution.obs_per_camera[c]} projections" if thin[c] else "")
            self.first_gated.append(self.names[c])
        return far | thin

    def _beyond_prediction(self, problem: Problem, solution: Solution) -> np.ndarray:
        """(C,) bool the cameras a cycle put further from the filter's prediction (the
        cycle's prior) than ``select.cycle_gate`` allows, or, for a camera not calibrated
        yet and seen on fewer than ``select.first_cycle_observations`` projections, than
        ``select.first_cycle_gate``; when they are a minority of the cameras it moved
        (``_gated``); counted per camera in ``cycle_gated``."""
        moves = _moves(problem, solution)
        far = _gated(moves, len(solution.R), self.cfg.select.cycle_gate) | self._thin_first_move(solution, moves)
        for c in np.flatnonzero(far):
            log.debug("cycle %d would have moved %s %.2f m / %.1f° (χ² %.0f against its predicted std): not taken",
                      problem.cycle, self.names[c], *moves[c])
            self.cycle_gated[self.names[c]] += 1
        self._count_disputes(solution.active & ~self.refiner.held, far)
        return far

    def _thin_first_move(self, solution: Solution, moves: Moves) -> np.ndarray:
        """(C,) bool the cameras not calibrated yet that ``moves`` put beyond
        ``select.first_cycle_gate`` on fewer than ``select.first_cycle_observations``
        projections: a few views of a camera still at its rough start are the likeliest
        wrong associations."""
        sel = self.cfg.select
        fresh = (self.refiner.cycles == 0) & ~self.refiner.batched & (solution.obs_per_camera
                                                                     < sel.first_cycle_observations)
        return _gated(moves, len(solution.R), sel.first_cycle_gate) & fresh

    def _batch_thin_first_move(self, problem: Problem, solution: Solution) -> np.ndarray:
        """``_thin_first_move`` of a batch: a camera no cycle calibrated that the batch would
        move far on a handful of views keeps its start and stays "not calibrated". With a
        preprocessing variant tried in session 38, fast walkers left the lab's cam_13
        (seen 3 s in 180) to a final batch whose 5 views of it were 4 of one walker joined
        to the other: 1.35 m / 19° off, "calibrated", with a stated 0.18 m / 1.5°
        (docs/accuracy.md, Session 38)."""
        moves = _moves(problem, solution)
        thin = self._thin_first_move(solution, moves)
        for c in np.flatnonzero(thin):
            log.warning("the final batch would have moved %s, which no cycle calibrated, %.2f m / %.1f° on %d "
                        "projections (χ² %.0f against its stated std): kept at its start, not calibrated",
                        self.names[c], *moves[c][:2], solution.obs_per_camera[c], moves[c][2])
            self.first_gated.append(self.names[c])
        return thin

    def _count_disputes(self, seen: np.ndarray, refused: np.ndarray) -> None:
        """A camera whose move ``select.dispute_cycles`` cycles in a row refused is due for
        a dispute adjustment (``_dispute_problem``): one refused cycle is a bad association,
        a run of them says its stated uncertainty may be wrong (a pass of the first
        adjustment can leave a camera far off with a small std), and the gate would hold it
        there. Each adjustment that kept its estimate doubles the run the next one needs."""
        n = self.cfg.select.dispute_cycles
        self.disputes[seen & ~refused] = 0
        self.disputes[seen & refused] += 1
        if n <= 0:
            return
        for c in np.flatnonzero(self.disputes >= n * 2 ** np.minimum(self.confirmed, 10)):
            log.info("%d cycles in a row would have moved %s further than its std allows: an adjustment over its "
                     "archived views decides", self.disputes[c], self.names[c])
            if c not in self.disputed:
                self.disputed.append(int(c))
            self.disputes[c] = 0

    def _settle(self, c: int, solution: Solution | None) -> None:
        """A dispute adjustment's verdict on camera c: beyond ``select.cycle_gate`` of its
        estimate, the estimate was wrong and the camera starts over from the adjustment's
        pose and covariance; within it (or no verdict), the cycles' associations were what
        was wrong and the estimate stays."""
        rf = self.refiner
        if rf.held[c]:  # watched since its dispute began: the monitor judges it now
            return
        if solution is not None and solution.active[c] and np.all(np.isfinite(solution.cov[c])):
            m, deg, chi2 = from_prior(rf.R[c], rf.t[c], rf.predicted_covariance()[c], solution.R[c], solution.t[c])
            if chi2 > self.cfg.select.cycle_gate:
                log.warning("%s was %.2f m / %.1f° off (χ² %.0f against its std), an adjustment over its archived "
                            "views says: it starts over from there", self.names[c], m, deg, chi2)
                rf.recalibrated(c, solution.R[c], solution.t[c], solution.cov[c])
                self.confirmed[c] = 0
                self.redone.append(self.names[c])
                self._restart_noted(c, f"disputed: {m:.2f} m / {deg:.1f}° off, an adjustment over its archived "
                                       f"views said")
                return
            log.info("%s: an adjustment over its archived views keeps its estimate (%.2f m / %.1f° from it, χ² %.0f)",
                     self.names[c], m, deg, chi2)
        self.confirmed[c] += 1

    def _restart_noted(self, c: int, why: str, *, say: bool = False) -> None:
        """Camera c started over from a pose found elsewhere: kept per camera for the state
        and listed in the next cycle's report; ``say``: log it (the caller has not)."""
        if say:
            log.warning("%s started over from a pose found elsewhere: %s", self.names[c], why)
        self.restarted[int(c)] = (float(self.clock or 0.0), why)
        self._restarted_new.append(self.names[c])

    def _monitor(self) -> list[str]:
        """The monitor's turn after a cycle: watch the converged cameras, flag moved ones
        (their uncertainty re-opened), take the poses of those calibrated again."""
        m, rf = self.cfg.monitor, self.refiner
        C = len(self.names)
        converged = np.array([rf.converged(c) for c in range(C)])
        # The watch begins once most of the calibrated cameras have converged: a camera
        # watched earlier would have its points triangulated from the few converged then
        # (the cameras joining later are left out of them: they would change its points).
        calibrated = rf.cycles > 0
        if not self.watched.any() and converged.sum() < max(3, m.start_fraction * calibrated.sum()):
            converged[:] = False
        # watched from their convergence until the monitor finds them moved; a camera
        # calibrated again once its adjustments are done: its watch's reference is the pose
        # they leave (one begun before the last would see it as a step)
        self.watched |= converged & ~self._calibrating_again()
        found, poses = self.monitor.evaluate(float(self.clock or 0.0), self.watched, rf.R, rf.t)
        names = []
        for alarm in found:
            rf.reopen(alarm.cam, m.reopen_std_translation, m.reopen_std_rotation)
            self._recalibrate_due = [x for x in self._recalibrate_due if x[1] != alarm.cam]  # moved again
            self.watched[alarm.cam] = False
            names.append(self.names[alarm.cam])
        for r in poses:
            rf.recalibrated(r.cam, r.R, r.t, r.cov)
            if r.final:
                # then adjustments over all of its data since the move, from now until it has
                # twice as much: a translation across the view trades against a small turn,
                # and a minute of people in one part of the room may not tell them apart
                # (the generated 4-camera room's 2° turn: 0.68° off after a minute's, 0.22°
                # after two minutes'); the camera is held in between, so every
                # `recalibrate_every` s one more, not one only at the end
                since = float(self.clock or 0.0) - r.seconds
                steps = max(1, math.ceil(r.seconds / m.recalibrate_every - 1e-9))
                self._recalibrate_due += [(since + r.seconds * (1 + k / steps), r.cam, since) for k in range(steps + 1)]
        rf.q_scale = np.where(self.watched, m.process_noise, 1.0)
        # A camera being calibrated again is held too, from its alarm to its last adjustment:
        # the resections (a bin at a time) and the adjustments over all its data since the
        # move place it; a cycle's few dozen hypotheses only pull it about (cam_3's 2° bump:
        # 0.16-0.20° off after its first adjustment, 0.27-0.36° after the next half minute
        # of cycles, 0.69° for a moment between two resections)
        rf.held = (self.watched | self._calibrating_again()) & m.hold
        return names

    def _calibrating_again(self) -> np.ndarray:
        """(C,) bool: the cameras being calibrated again, from their alarm (the monitor's
        resections) to their last adjustment (``_recalibrate_due``)."""
        adjusting = np.isin(np.arange(len(self.names)), [c for _, c, _ in self._recalibrate_due])
        return self.monitor.recalibrating() | adjusting

    def step(self, now: float) -> CycleReport | None:
        """Front end up to ``now`` and, when due, one cycle solved in this thread."""
        self.advance(now)
        p = self.next_problem(now)
        if p is None:
            return None
        return self.apply(p, solve(p))

    # ------------------------------------------------------------ end of a run

    def finish(self) -> CalibrationState:
        """Flush the front end, then (if configured) one batch adjustment over every
        archived frame re-associated with the final estimate."""
        if self._pending:
            self._release_pending()
        if self.clock is not None:
            self.advance(self.clock + self.cfg.sync.wait + 1.0 / self.cfg.sync.rate)
            if self.estimating and self._calibrated():
                self._retime(self.clocks.update(self.clock, self.refiner.R, self.refiner.t, flush=True,
                                                P=self.refiner.S))
            self.retime_archive()
        lost = np.flatnonzero(self._never_associated()) if self.cfg.associate.relocalize else []
        if len(lost) and self.frames and self._inflight is None:
            # one more try with the final estimate of the others, before the batch needs them
            self.cycle += 1
            p = self._relocalize_problem(lost, self._timed_frames())
            self._inflight = p
            self.apply(p, solve(p))
        if self.cfg.refine.final_batch and self.frames:
            self.batch_adjust()
            if self.estimating and self._calibrated():  # the offsets as the final poses see them
                self.clocks.reestimate(self.clock, self.refiner.R, self.refiner.t, P=self.refiner.S)
            self.check_halves_safely()
        if self.scale_heights is not None and self.scale_check is None and self.frames and self.cycle > 0:
            try:
                self.check_scale()  # once: a second correction would scale the scale
            except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
                # a report on top of the result: its failure must not cost the final batch
                log.warning("the scale check failed, the initial estimate's scale is kept: %s", e)
        return self.state()

    def late_join_due(self, now: float | None) -> bool:
        """Whether cameras without a pose are to be resected now (backend/late_join.py's
        ``JoiningPipeline``; this pipeline has none)."""
        return False

    # ------------------------------------------------------------ state

    def counters(self) -> Counters:
        rej = Counter(self.rejected)
        return Counters(
            messages=self.messages,
            rejected=dict(rej),
            framesets=self.sync.framesets,
            framesets_rejected=dict(self.sync.framesets_rejected),
            views=self.preprocess.accepted,
            views_rejected=dict(self.preprocess.rejected + self.associate.rejected),
            hypotheses=self.associate.created,
            queue_length=len(self.queue),
            queue_dropped=self.queue.dropped,
            cycles=self.cycle,
            cycles_rejected=self.cycles_rejected,
        )

    def state(self) -> CalibrationState:
        rf = self.refiner
        moved = {a.cam: a.time for a in self.monitor.alarms}
        cams = []
        for c, n in enumerate(self.names):
            ct, cr = rf.change(c)
            cams.append(CameraState(
                name=n, R=rf.R[c].copy(), t=rf.t[c].copy(), cov=self._stated_cov(c),
                observations=int(self.observations[c] + self.observations_batch[c]), cycles=int(rf.cycles[c]),
                change_translation=ct, change_rotation=cr, converged=rf.converged(c),
                last_seen=self.last_seen.get(n), moved_at=moved.get(c),
                restarted_at=self.restarted[c][0] if c in self.restarted else None,
                restart_reason=self.restarted[c][1] if c in self.restarted else None,
            ))
        # a camera found moved counts while it is calibrated again (its cycles start over)
        calibrated = [c for c in cams if c.cycles > 0 or c.moved_at is not None]
        converged = bool(calibrated) and all(c.converged for c in calibrated)
        return CalibrationState(self.clock, self.cycle, tuple(cams), converged, self.counters(), self.last_report,
                                clocks=self.clock_states(),
                                scale_check=self.scale_check.to_dict() if self.scale_check is not None else None,
                                split_check=self.split_check.to_dict() if self.split_check is not None else None)

    def skeletons(self, n: int = 4) -> list[list[list[float] | None]]:
        """The newest ``n`` hypotheses of distinct persons as 3D skeletons (17 joints, world
        frame, None where a joint is not triangulated), for display."""
        from .associate import triangulate_hypotheses

        chosen = []
        for h in reversed(self.queue.newest(8 * n)):
            if any(np.linalg.norm(h.com - c.com) < 0.5 for c in chosen):
                continue  # the same person a moment earlier
            chosen.append(h)
            if len(chosen) >= n:
                break
        X = triangulate_hypotheses(chosen, self.refiner.R, self.refiner.t)
        return [[x.tolist() if np.all(np.isfinite(x)) else None for x in person] for person in X]


def run_offline(cameras: CameraSet, config: EngineConfig, messages: Iterable[KeypointMessage], *, seed: int = 0,
                progress: Callable[[CalibrationState, CycleReport], None] | None = None,
                finish: bool = True, start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                pipeline: Pipeline | None = None, scale_heights: Sequence[float] | None = None,
                data_shape: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Pipeline:
    """Run the online pipeline on recorded messages on virtual time (the newest stamp);
    ``start``, ``scale_heights``, ``data_shape`` as for ``Pipeline``; ``pipeline``: one built
    by the caller instead (e.g. backend/late_join.py's), whose cameras and config are then its own."""
    p = Pipeline(cameras, config, seed=seed, start=start, scale_heights=scale_heights, data_shape=data_shape) \
        if pipeline is None else pipeline
    for msg in messages:
        p.push(msg)
        if p.clock is None:
            continue
        report = p.step(p.clock)
        if report is not None and progress is not None:
            progress(p.state(), report)
        if p.late_join_due(p.clock):  # cameras the bootstrap left out, placed while the run goes on
            job = p.late_job(p.clock)
            p = p.join_live(job, job.run()) or p
    if finish:
        before = p.cycle
        p.finish()
        if progress is not None and p.cycle > before and p.last_report is not None:
            progress(p.state(), p.last_report)
    return p
