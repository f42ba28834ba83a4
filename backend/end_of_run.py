"""The end of a run (a part of ``Pipeline``; ``Pipeline.finish`` calls them in order): the
final batch adjustment over every archived frame, also from the start when that explains
the data better, the world frame levelled again on its floor, what the lenses' accuracy
adds to the stated std, the split-half check of that std, and the initial estimate's
scale checked against the people's."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .floor import Floor, world_frame
from .geometry import align_poses, from_prior, within_std
from .optimize import Problem, Solution, solve
from .refine import handover_covariance
from .scale_check import ScaleCheck, check_run
from .split_check import SplitCheck, compare_halves, interleaved_halves
from .state import CycleReport, Lenses, Levelled

log = logging.getLogger("backend.pipeline")  # the pipeline's: its messages keep their logger


def _added(cov: np.ndarray, more: np.ndarray | None) -> np.ndarray | None:
    """(C, 6, 6) ``more`` - ``cov``, each made positive semi-definite (the marginals of a
    graph with more variables hold at least as much uncertainty, up to rounding); None
    when ``more`` is."""
    if more is None:
        return None
    assert cov.shape == more.shape and cov.shape[1:] == (6, 6)
    d = 0.5 * ((more - cov) + np.swapaxes(more - cov, 1, 2))
    out = np.full_like(d, np.nan)
    ok = np.all(np.isfinite(d), axis=(1, 2))
    w, V = np.linalg.eigh(d[ok])
    out[ok] = np.einsum("cij,cj,ckj->cik", V, np.maximum(w, 0.0), V)
    return out


class EndOfRun:
    """``Pipeline``'s methods for the end of a run and what it reports: they work on its
    ``refiner``, ``frames`` (the archive) and ``cfg``."""

    def far_from_start(self) -> list[tuple[str, float, float, float]]:
        """The calibrated cameras whose estimate lies beyond ``select.first_gate`` (χ², 6
        dof) of where they started (the initial estimate with its stated std, or the
        bootstrap's poses with the hand-over std): (name, m, deg, χ²). Either the start
        was that wrong for them (a swapped or mislabelled camera), or the data put them
        there wrongly; a user should look at them."""
        gate, rf = self.cfg.select.first_gate, self.refiner
        out = []
        if gate <= 0:
            return out
        for c in np.flatnonzero(rf.cycles > 0):
            move = from_prior(rf.prior_R[c], rf.prior_t[c], rf.P0[c], rf.R[c], rf.t[c])
            if move[2] > gate:
                out.append((self.names[c], *move))
        return out

    def check_scale(self) -> ScaleCheck | None:
        """The initial estimate's scale against the people's on the archived frames, and
        the correction ``bootstrap.initial_scale`` asks for made to the frame the estimate
        keeps (``Refiner.rescale_frame``)."""
        rf = self.refiner
        self.scale_check = check_run(self.frames, rf.R, rf.t, rf.cycles > 0, rf.t0, self.cfg, self.scale_heights or ())
        if self.scale_check is not None and self.scale_check.corrected:
            rf.rescale_frame(self.scale_check.apply)
        return self.scale_check

    def check_halves_safely(self) -> None:
        """``check_halves`` once, if ``refine.split_check``: a report on top of the result,
        whose failure must not cost the final batch."""
        if not self.cfg.refine.split_check or self.split_check is not None or not self.frames:
            return
        try:
            self.check_halves()
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as e:
            log.warning("the split-half check failed, the stated std is kept: %s", e)

    def check_halves(self) -> SplitCheck | None:
        """The final batch on each of two interleaved halves of the archived frames, from
        the result, compared with each other (backend/split_check.py): the cameras they
        place further apart than their own stds allow get their covariance widened.
        None when there are too few frames or a half fails."""
        cfg = self.cfg.refine
        frames = list(self.frames)
        half = interleaved_halves(np.array([T for T, _ in frames]), cfg.split_block)
        if min(int((half == 0).sum()), int((half == 1).sum())) < 10:
            return None
        cycle, out = self.cycle, []
        try:
            for k in (0, 1):
                p = self._batch_problem(max(10, cfg.batch_size // 2), self.cfg.select.min_spacing / 2,
                                        [f for f, h in zip(frames, half) if h == k], final=True, seed=k)
                sol = solve(p)
                if not sol.ok:
                    return None
                cov = np.where(np.isfinite(sol.cov_shape), sol.cov_shape, sol.cov)
                out.append((sol.R, sol.t, sol.active & (self.refiner.cycles > 0), cov))
        finally:
            self.cycle = cycle  # the check is not a cycle of the calibration
        rf = self.refiner
        self.split_check = compare_halves(self.names, rf.S, out, cfg.split_ratio)
        rf.widen(self.split_check.factor)
        return self.split_check

    def batch_adjust(self) -> CycleReport:
        p = self._batch_problem(self.cfg.refine.batch_size, self.cfg.select.min_spacing / 2, final=True)
        # the floor ``_level`` makes the frame on; the std with the lenses' accuracy (``lens_cov``)
        p = replace(p, level=self.cfg.refine.floor_frame is not None, lens_accuracy=True)
        sol = solve(p)
        if sol.ok and sol.phantoms:
            # Phantoms are judged by their size in the start's scale, and a link of a chain
            # that the online cycles drew 1.3x too long loses its right hypotheses with them.
            # Its bones put the link right in this solve: associated and judged again from
            # there, those come back and the phantoms stay out. The problem kept for the
            # report is the first: what moved is measured from the online estimate.
            again = solve(replace(p, R=sol.R.copy(), t=sol.t.copy()))
            if again.ok:
                sol = again
        if self.cfg.refine.final_batch_from_start:
            p, sol = self._batch_from_start(p, sol)
        if self.data_shape is not None and self.cfg.refine.final_batch_from_data:
            p, sol = self._batch_from_data(p, sol)
        self._inflight = p
        report = self.apply(p, sol)
        if report.accepted:  # the final word: a camera it did not place keeps no earlier part
            self.lens_cov = None
            self._lens_part(sol, np.ones(len(self.names), bool))
        if report.accepted and sol.lenses is not None and sol.lens_std is not None:
            # relative to the intrinsics this pipeline works with: a resumed session's are its lenses already
            used = np.array([(self.cameras.intrinsics[n].fx, self.cameras.intrinsics[n].fy) for n in self.names])
            found = Lenses.of(self.names, sol.lenses, sol.lens_std, used)
            self.lenses = found if self.lenses is None else self.lenses.then(found)
        if self.cfg.refine.floor_frame is not None:
            self.levelled = self._level(sol.level) if report.accepted else Levelled(False, "the final batch was rejected")
        return report

    def _level(self, floor: Floor | None) -> Levelled:
        """The bootstrap's floor frame (``refine.floor_frame``) made again on ``floor``, the
        final batch's: the bootstrap's was the floor of the people the cameras it placed
        saw, one pair's when the others joined later (docs/bootstrap.md, Session 36)."""
        spec, rf = self.cfg.refine.floor_frame, self.refiner
        if floor is None:
            return Levelled(False, "the final batch's lower ankles fit no one floor")
        if spec.first not in self.names:
            return Levelled(False, f"{spec.first}, the origin's camera, is not in the network")
        first = self.names.index(spec.first)
        rest = [c for c in np.flatnonzero(rf.cycles > 0) if c != first]
        if spec.second in self.names:  # x towards the same camera where it can
            rest.insert(0, self.names.index(spec.second))
        order = [first] + list(dict.fromkeys(rest))
        found = world_frame(floor.n, floor.d - spec.ankle_height, rf.t[order])
        if found is None:
            return Levelled(False, "the cameras' floor points coincide: no x axis")
        F, o, k = found
        rf.reframe(F, o)
        return Levelled(True, "", float(np.degrees(np.arccos(np.clip(floor.n[2], -1.0, 1.0)))), float(np.linalg.norm(o)),
                        floor.points, floor.spread, spec.first, self.names[order[k]])

    def _batch_from_start(self, p: Problem, sol: Solution) -> tuple[Problem, Solution]:
        """The same batch (same frames, selection seed, prior) started from the start
        instead of the estimate; kept when it explains at least as many observations at a
        lower cost per observation. The batch is a local optimisation that re-associates
        from where it starts: a camera the online cycles dragged off (few hypotheses, a
        wide prior) can end in another minimum than from the start the bootstrap found
        with all the data (docs/bootstrap.md, seed 2's cam_13)."""
        return self._batch_from(p, sol, self.refiner.prior_R.copy(), self.refiner.prior_t.copy(), "start")

    def _batch_from_data(self, p: Problem, sol: Solution) -> tuple[Problem, Solution]:
        """The same batch also from the data's shape (``data_shape``, aligned onto its
        result) when the two disagree on a camera beyond the bootstrap's tolerance
        (``bootstrap.agree_*``, or 3x its std): held to it (``_batch_anchored``), else
        with the initial estimate's prior, kept by ``_batch_from``'s test. A run
        from an initial estimate within its stated std can still associate wrongly for good
        (four walkers in a 4 x 4 m room: a camera 26° off at the end; from the data's shape
        the batch ends 12 mm from the truth's shape); the extra batch is solved only where
        the two disagree."""
        R_d, t_d, std = self.data_shape
        placed = np.isfinite(t_d).all(axis=1)
        # a camera the monitor saw move since (a live session) is no longer where the data had it
        placed[[a.cam for a in self.monitor.alarms]] = False
        idx = np.flatnonzero(placed)
        if len(idx) < 3:
            return p, sol
        R_e, t_e = (sol.R, sol.t) if sol.ok else (p.R, p.t)
        # aligned on the cameras the batch held (a camera dragged so far that it joins nobody
        # is not, and is then one of those it differs on)
        use = sol.active[idx] if sol.ok and sol.active[idx].sum() >= 3 else None
        al = align_poses(R_d[idx], t_d[idx], R_e[idx], t_e[idx], use, orientations=True)
        if al is None:
            return p, sol
        b = self.cfg.bootstrap
        # the test ``reconcile`` agrees by, the data's std in the estimate's units
        apart = ~within_std(al.dt, al.dr, al.s * std[idx, 0], std[idx, 1], b.agree_translation, b.agree_rotation)
        if sol.ok and not apart.any():
            return p, sol
        R, t = R_e.copy(), t_e.copy()
        R[idx], t[idx] = al.R, al.t
        far = ", ".join(f"{self.names[c]} {d:.2f} m / {a:.1f}°" for c, d, a, x in zip(idx, al.dt, al.dr, apart) if x)
        P = p.prior_cov.copy()
        for c, st, sr in zip(idx, al.s * std[idx, 0], std[idx, 1]):
            P[c] = handover_covariance(b, st, sr)
        kept = self._batch_anchored(p, sol, R, t, P)
        if kept is not None:
            log.warning("the online estimate ended apart from the data's shape (%s off it): the final batch held to the "
                        "data's shape explains as much of the data within its hold, and was kept", far)
            return kept
        p, sol = self._batch_from(p, sol, R, t, "data")
        if self.final_batch_start == "data":
            log.warning("the final batch from the data's shape explains the data better than from the online "
                        "estimate, which had %s off it: kept", far)
        else:
            log.info("the final batch from the online estimate (%s off the data's shape) explains the data better "
                     "than from the data's shape: kept", far)
        return p, sol

    def _batch_anchored(self, p: Problem, sol: Solution, R: np.ndarray, t: np.ndarray, P: np.ndarray
                        ) -> tuple[Problem, Solution] | None:
        """The batch ``p`` (solved: ``sol``) solved again from the data's shape R (C, 3, 3),
        t (C, 3), held to it by the prior P (C, 6, 6) (the hand-over's, as a run started
        there has: ``Reconciled.start``). Tried when the estimate lies beyond
        ``refine.hold_gate`` (χ², 6 dof) of that hold on some camera, kept (and returned)
        when every camera of its result lies within it and it explains at least as many
        observations as ``sol``; else None.

        Where the online estimate and the data's shape disagree, one of them is wrong, and
        cost per observation cannot say which: wrong associations (walkers of two rooms, each
        seen by one camera, paired across the wall) are views the estimate they dragged
        explains well. From the data's shape with the initial estimate's wide prior the batch
        re-associates and is dragged the same way (the two rooms, four walkers, seed 0: shape
        0.069 m from the online estimate, 0.077 m from the data's shape). Held there, the
        data associated there either keep it there (that run: χ² 0.3-4.4 a camera, the
        estimate's 0.6-27; shape 0.025 m), so they do not contradict the bootstrap, whose
        frames' association is not in doubt; or pull it out towards the estimate, and the
        data's shape is what is wrong (the steep room with a harsh detector: the bootstrap
        2-3° off, the batch held there 21 against the estimate's 21). An estimate within
        the hold everywhere is left to the test of ``_batch_from``: the hold is not known to
        be better than the data there (measured: held anyway, the steep room's
        orientation 0.61-0.77° became 0.64-0.83°)."""
        gate = self.cfg.refine.hold_gate
        R_e, t_e = (sol.R, sol.t) if sol.ok else (p.R, p.t)
        C = len(R)
        if not any(from_prior(R[c], t[c], P[c], R_e[c], t_e[c])[2] > gate for c in range(C)):
            return None
        q = replace(p, R=R, t=t, prior_R=R.copy(), prior_t=t.copy(), prior_cov=P, pose_px=self._pose_px(start=True))
        alt = solve(q)
        if not alt.ok:
            return None
        n_p, n_q = int(sol.obs_per_camera.sum()), int(alt.obs_per_camera.sum())
        out = [self.names[c] for c in np.flatnonzero(alt.active)
               if from_prior(R[c], t[c], P[c], alt.R[c], alt.t[c])[2] > gate]
        if out or (sol.ok and n_q < n_p):
            log.info("the final batch held to the data's shape not kept: %s", f"the data pull {', '.join(out)} out of it"
                     if out else f"it explains fewer observations ({n_q} against {n_p})")
            return None
        self.final_batch_start = "anchored"
        return q, alt

    def _batch_from(self, p: Problem, sol: Solution, R: np.ndarray, t: np.ndarray, name: str
                    ) -> tuple[Problem, Solution]:
        """The batch ``p`` (solved: ``sol``) solved again from R (C, 3, 3), t (C, 3), the
        association gated by the start's std; kept when it explains at least as many
        observations at a lower cost per observation (or ``sol`` failed). Records which was
        kept in ``final_batch_start``: ``name`` or "estimate"."""
        q = replace(p, R=R, t=t, pose_px=self._pose_px(start=True))
        alt = solve(q)
        n_p, n_q = int(sol.obs_per_camera.sum()), int(alt.obs_per_camera.sum())
        better = alt.ok and (not sol.ok or (n_q >= n_p > 0 and alt.final_error / n_q < sol.final_error / n_p))
        self.final_batch_start = name if better else "estimate"
        return (q, alt) if better else (p, sol)

    def _lens_part(self, sol: Solution, cams: np.ndarray) -> None:
        """Take what the lenses' accuracy adds to the stated covariance of ``cams`` (C,) bool
        from an adjustment with the start's prior (the first, the final batch): how far a
        lens off its file moves a pose depends on where the people are in the views more
        than on how much data there are (the west room's 30 s: 11-20 mm from the first
        adjustment, 13-24 mm from the final batch), so the first adjustment's part stands
        for the running session's until the final batch's replaces it (a cycle's, with the
        filter's prior, would be held down by it)."""
        add = _added(sol.cov_shape, sol.cov_shape_lenses)
        if add is None:
            return
        if self.lens_cov is None:
            self.lens_cov = np.full((len(self.names), 6, 6), np.nan)
        take = cams & np.all(np.isfinite(add), axis=(1, 2))
        self.lens_cov[take] = add[take]

    def _stated_cov(self, c: int) -> np.ndarray:
        """(6, 6) camera c's covariance as stated: the solves' (shape), and what its lens's
        accuracy adds once the first adjustment or a final batch has found it."""
        S = self.refiner.S[c].copy()
        if self.lens_cov is not None and np.all(np.isfinite(self.lens_cov[c])):
            S += self.lens_cov[c]
        return S

    def std_note(self) -> str | None:
        """What the stated std holds, once the first adjustment or a final batch added the
        lenses' accuracy (for a result's header); None before."""
        if self.lens_cov is None:
            return None
        o = self.cfg.optimize
        return (f"stated std: the keypoints' noise and the calibration files' lens accuracy, "
                f"{100 * o.lens_accuracy_focal:.2g} % in focal length and {100 * o.lens_accuracy_centre:.2g} % of it in "
                f"principal point (optimize.lens_accuracy_*)")
