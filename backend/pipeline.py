"""The calibration pipeline: every stage wired top to bottom, driven by a clock.

    message ─► ingest      known sensor, plausible stamp, no duplicate
            ─► sync        framesets of per-sensor messages interpolated to one instant
            ─► preprocess  filters, undistortion
            ─► associate   person hypotheses across views
            ─► queue       bounded, newest kept
            ─► select      one cycle's hypotheses (every `select.interval` s of data time)
            ─► optimize    GTSAM factor graph → poses + marginals   (pure function, any process)
            ─► refine      Kalman update on SE(3), scale kept from the initial estimate
            ─► state       CalibrationState

The clock is the caller's: offline it is the recording's data time (the newest stamp),
live it is the wall clock. ``run_offline`` drives it synchronously; the service drives
``advance`` on its event loop and ``optimize.solve`` in a worker process.
"""

from __future__ import annotations

from collections import Counter, deque
from typing import Callable, Iterable

import numpy as np

from proto import KeypointMessage

from .associate import Associator, Hypothesis, triangulate_torso
from .cameras import CameraSet
from .config import EngineConfig
from .optimize import Problem, Solution, build_problem, solve
from .preprocess import Preprocessor
from .refine import Refiner, initial_covariance
from .selection import HypothesisQueue, select_spaced
from .state import CalibrationState, CameraState, Counters, CycleReport
from .sync import Synchronizer


class Pipeline:
    def __init__(self, cameras: CameraSet, config: EngineConfig | None = None, *, seed: int = 0):
        self.cameras = cameras
        self.cfg = config or EngineConfig()
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
        self.refiner = Refiner(self.cfg.refine, R0, t0)
        # every hypothesis, for the final batch adjustment
        self.archive: deque[Hypothesis] = deque(maxlen=4 * self.cfg.refine.batch_size)
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

    # ------------------------------------------------------------ front end

    def push(self, msg: KeypointMessage, arrival: float | None = None) -> str | None:
        """Take one validated message; returns the rejection reason or None.

        ``arrival`` is the receiver's clock (live); offline the newest stamp so far
        stands in for it, so a stamp absurdly far ahead cannot drag the clock along.
        """
        self.messages += 1
        now = arrival if arrival is not None else self.clock
        reason = self.sync.push(msg, now)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        self.last_seen[msg.sensor] = msg.stamp
        if arrival is None and (self.clock is None or msg.stamp > self.clock):
            self.clock = msg.stamp
        return None

    def advance(self, now: float) -> int:
        """Run sync/preprocess/associate up to clock time ``now``; returns new hypotheses."""
        if self.clock is None or now > self.clock:
            self.clock = now
        new = 0
        R, t = self.refiner.R, self.refiner.t
        gate = self._gate()
        for fs in self.sync.pop_ready(now):
            dets = self.preprocess(fs)
            if len(dets) < 2:
                continue
            hyps = self.associate(fs.time, dets, R, t, gate)
            self.queue.extend(hyps)
            self.archive.extend(hyps)
            new += len(hyps)
        return new

    def _gate(self) -> np.ndarray | None:
        """(C,) reprojection gate in px for cameras the filter is already sure of."""
        a = self.cfg.associate
        if not a.reassociate:
            return None
        C = len(self.names)
        gate = np.full(C, np.inf)
        for c in range(C):
            if self.refiner.cycles[c] >= 3:
                st, sr = self.refiner.std(c)
                gate[c] = a.gate_pixels + 3 * self.focal[c] * (np.radians(sr) + st / 3.0)
        return gate

    # ------------------------------------------------------------ optimisation

    def next_problem(self, now: float) -> Problem | None:
        """A cycle's problem when one is due, else None. Only one is in flight at a time."""
        if self._inflight is not None or not self.queue.ready():
            return None
        if self.last_cycle_time is not None and now - self.last_cycle_time < self.cfg.select.interval:
            return None
        hyps = self.queue.select(self.rng)
        self.last_cycle_time = now
        self.cycle += 1
        p = build_problem(self.cycle, hyps, self.refiner.R, self.refiner.t,
                          self.refiner.predicted_covariance(), self.focal, self.cfg.optimize)
        self._inflight = p
        return p

    def apply(self, problem: Problem, solution: Solution) -> CycleReport:
        """Fold a solved cycle into the estimate (or reject it, keeping the estimate)."""
        assert problem is self._inflight or self._inflight is None, "apply() of a problem that is not in flight"
        self._inflight = None
        dt = np.linalg.norm(solution.t - problem.t, axis=1)
        moved = bool(np.any(dt > 1e-9)) or solution.final_error < solution.initial_error * (1 - 1e-9)
        reason = solution.reason if not solution.ok else ""
        if not reason and solution.final_error > solution.initial_error * (1 + 1e-6):
            reason = "error increased"
        if not reason and not moved and len(problem.obs_cam):
            reason = "solver did not move the estimate"
        accepted = reason == ""
        change_t = change_r = 0.0
        if accepted:
            upd = self.refiner.update(problem.active, solution.R, solution.t, solution.cov)
            change_t = float(upd.changed_translation.max())
            change_r = float(upd.changed_rotation.max())
            self.observations += np.bincount(problem.obs_cam, minlength=len(self.names))
        else:
            self.cycles_rejected += 1
        finite = solution.residual_px[np.isfinite(solution.residual_px)]
        report = CycleReport(
            cycle=problem.cycle,
            data_time=float(self.clock or 0.0),
            hypotheses=int(len(np.unique(problem.lm_hyp))),
            observations=int(len(problem.obs_cam)),
            cameras=tuple(self.names[c] for c in np.flatnonzero(problem.active)),
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
        )
        self.last_report = report
        return report

    def step(self, now: float) -> CycleReport | None:
        """Front end up to ``now`` and, when due, one cycle solved in this thread."""
        self.advance(now)
        p = self.next_problem(now)
        if p is None:
            return None
        return self.apply(p, solve(p))

    # ------------------------------------------------------------ end of a run

    def finish(self) -> CalibrationState:
        """Flush the front end, then one batch adjustment over the archived hypotheses
        (re-gated with the final estimate), keeping the initial estimate's scale."""
        if self.clock is not None:
            self.advance(self.clock + self.cfg.sync.wait + 1.0 / self.cfg.sync.rate)
        if self.cfg.refine.final_batch and len(self.archive) >= 2:
            self.batch_adjust()
        return self.state()

    def batch_adjust(self) -> CycleReport | None:
        cfg = self.cfg
        R, t = self.refiner.R, self.refiner.t
        hyps = [h for h in (_regate(h, R, t, self.focal, cfg.associate.gate_pixels) for h in self.archive) if h is not None]
        hyps = select_spaced(hyps, cfg.refine.batch_size, cfg.select.min_spacing / 2, self.rng)
        if not hyps:
            return None
        # A wide prior at the filter's estimate is a soft gauge: frame and scale, not data.
        prior = np.repeat((initial_covariance(cfg.refine) * 100.0)[None], len(self.names), axis=0)
        opt = cfg.optimize.model_copy(update={"max_iterations": max(cfg.optimize.max_iterations, 100)})
        p = build_problem(self.cycle + 1, hyps, R, t, prior, self.focal, opt)
        sol = solve(p)
        if not sol.ok or sol.final_error > sol.initial_error:
            self.last_report = None
            return None
        self.cycle += 1
        self._inflight = p
        # The batch solution replaces the state outright (its prior is no data).
        saved = self.refiner.cfg
        self.refiner.cfg = saved.model_copy(update={"measurement": "posterior"})
        try:
            return self.apply(p, sol)
        finally:
            self.refiner.cfg = saved

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
        cams = []
        for c, n in enumerate(self.names):
            ct, cr = rf.change(c)
            cams.append(CameraState(
                name=n, R=rf.R[c].copy(), t=rf.t[c].copy(), cov=rf.P[c].copy(),
                observations=int(self.observations[c]), cycles=int(rf.cycles[c]),
                change_translation=ct, change_rotation=cr, converged=rf.converged(c),
                last_seen=self.last_seen.get(n),
            ))
        calibrated = [c for c in cams if c.cycles > 0]
        converged = bool(calibrated) and all(c.converged for c in calibrated)
        return CalibrationState(self.clock, self.cycle, tuple(cams), converged, self.counters(), self.last_report)

    def snapshot(self) -> dict:
        """JSON-able state to resume from: the estimate, not the buffered data."""
        rf = self.refiner
        return {
            "version": 1,
            "names": list(self.names),
            "R": rf.R.tolist(), "t": rf.t.tolist(), "P": rf.P.tolist(),
            "R0": rf.R0.tolist(), "t0": rf.t0.tolist(),
            "cycles": rf.cycles.tolist(),
            "history": [list(map(list, h)) for h in rf.history],
            "cycle": self.cycle,
            "observations": self.observations.tolist(),
            "clock": self.clock,
        }

    @classmethod
    def restore(cls, cameras: CameraSet, config: EngineConfig, snapshot: dict, *, seed: int = 0) -> "Pipeline":
        if snapshot.get("version") != 1 or list(snapshot.get("names", [])) != list(cameras.names):
            raise ValueError("snapshot does not belong to this camera set")
        p = cls(cameras, config, seed=seed)
        rf = p.refiner
        rf.R, rf.t, rf.P = (np.array(snapshot[k], dtype=np.float64) for k in ("R", "t", "P"))
        rf.R0, rf.t0 = np.array(snapshot["R0"]), np.array(snapshot["t0"])
        rf.cycles = np.array(snapshot["cycles"], dtype=np.int64)
        for h, items in zip(rf.history, snapshot["history"]):
            h.extend(tuple(x) for x in items)
        p.cycle = int(snapshot["cycle"])
        p.observations = np.array(snapshot["observations"], dtype=np.int64)
        return p


def _regate(h: Hypothesis, R: np.ndarray, t: np.ndarray, focal: np.ndarray, gate_px: float) -> Hypothesis | None:
    """The hypothesis without views whose torso joints reproject beyond the gate."""
    X, err = triangulate_torso(h, R, t, focal)
    if X is None:
        return None
    keep = err <= gate_px
    if keep.sum() < 2:
        return None
    if keep.all():
        return h
    return Hypothesis(h.time, h.cams[keep], h.xy[keep], h.sigma[keep], h.com)


def run_offline(cameras: CameraSet, config: EngineConfig, messages: Iterable[KeypointMessage], *, seed: int = 0,
                progress: Callable[[CalibrationState, CycleReport], None] | None = None,
                finish: bool = True) -> Pipeline:
    """Run the online pipeline on recorded messages on virtual time (the newest stamp)."""
    p = Pipeline(cameras, config, seed=seed)
    for msg in messages:
        p.push(msg)
        if p.clock is None:
            continue
        report = p.step(p.clock)
        if report is not None and progress is not None:
            progress(p.state(), report)
    if finish:
        before = p.cycle
        p.finish()
        if progress is not None and p.cycle > before and p.last_report is not None:
            progress(p.state(), p.last_report)
    return p
