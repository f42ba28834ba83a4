"""Refinement: a Kalman filter per camera on SE(3), and the scale of the initial estimate.

State per camera: a pose and a 6x6 covariance in its tangent space (rotation,
translation; GTSAM's right-perturbation convention). Every cycle first adds process
noise (prediction); the cycle's graph uses the predicted state as its prior; the
update then either

- 'posterior' (default): takes the graph's solution and marginal covariance as the
  new state. The graph had the predicted state as a prior, so this *is* the Bayesian
  update with the cycle's data counted once; or
- 'marginal' (the paper): a Kalman update with the solution as measurement and the
  marginal covariance as its noise (which counts the prior a second time: the filter
  grows overconfident; kept for comparison).

Persons' size is unknown, so the graph does not observe scale; the filter would let it
drift. After each update the camera centres are similarity-aligned to the initial
estimate and only the scale of that alignment is applied (about their centroid),
keeping the initial estimate's scale and leaving position and orientation to the data.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .config import BootstrapConfig, RefineConfig
from .geometry import pose_local, pose_retract, pose_std, rotation_angle_deg, trimmed_similarity


@dataclass(frozen=True)
class UpdateResult:
    changed_translation: np.ndarray  # (C,) m
    changed_rotation: np.ndarray  # (C,) deg
    scale_applied: float


_HELD = 1e-4  # a held camera's share of its covariance in the cycles' graph


def initial_covariance(cfg: RefineConfig) -> np.ndarray:
    """(6, 6) diagonal covariance of the initial estimate."""
    return _diag(cfg.initial_std_rotation, cfg.initial_std_translation)


def handover_covariance(cfg: BootstrapConfig, std_m: float, std_deg: float) -> np.ndarray:
    """(6, 6) the prior of a camera started from the data's shape (the bootstrap), its
    std ``cfg.handover_std`` of the bootstrap's own ``std_m`` m / ``std_deg`` deg."""
    st, sr = cfg.handover_std(std_m, std_deg)
    return _diag(sr, st)


def _diag(std_deg: float, std_m: float) -> np.ndarray:
    r = np.radians(std_deg)
    return np.diag([r * r] * 3 + [std_m * std_m] * 3)


def _sym_pd(P: np.ndarray, floor: float = 1e-14) -> np.ndarray:
    P = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(P)
    return (V * np.maximum(w, floor)) @ V.T


class Refiner:
    """Camera states R (C, 3, 3), t (C, 3), P (C, 6, 6) and their recent changes."""

    def __init__(self, cfg: RefineConfig, R0: np.ndarray, t0: np.ndarray, P0: np.ndarray | None = None,
                 prior: tuple[np.ndarray, np.ndarray] | None = None):
        """R0 (C, 3, 3), t0 (C, 3): the initial estimate, which gives the frame and the
        scale. ``prior``: (R, t) where the estimate starts and what the adjustments over all
        data are anchored to, with ``P0`` (C, 6, 6); default the initial estimate with
        ``refine.initial_std_*``. They differ when the data's shape, aligned onto a rough
        initial estimate, is the better start (backend/reconcile.py)."""
        C = len(R0)
        assert R0.shape == (C, 3, 3) and t0.shape == (C, 3)
        self.cfg = cfg
        self.R0, self.t0 = R0.copy(), t0.copy()  # the initial estimate: frame and scale
        pR, pt = (R0, t0) if prior is None else prior
        assert pR.shape == (C, 3, 3) and pt.shape == (C, 3)
        self.prior_R, self.prior_t = pR.copy(), pt.copy()
        self.R, self.t = pR.copy(), pt.copy()
        self.P = np.repeat(initial_covariance(cfg)[None], C, axis=0) if P0 is None else P0.copy()
        assert self.P.shape == (C, 6, 6)
        self.P0 = self.P.copy()
        # what is reported: the filter's covariance, or a solve's shape covariance (gauge removed)
        self.S = self.P.copy()
        self.Q = _diag(cfg.filter_std_rotation, cfg.filter_std_translation) * cfg.process_noise**2
        self.q_scale = np.ones(C)  # per camera: a factor of Q (the monitor lowers it for watched cameras)
        # per camera: held at its pose (the monitor's watched cameras): cycles leave it, and
        # while any camera is held they also give the frame and scale (no keep_scale)
        self.held = np.zeros(C, dtype=bool)
        self.cycles = np.zeros(C, dtype=np.int64)
        self.batched = np.zeros(C, dtype=bool)  # the last update was a batch over all data
        # pose after each of the last cycles a camera took part in: (t (3,), R (3, 3))
        self.history: list[deque] = [deque(maxlen=cfg.converged_cycles + 1) for _ in range(C)]

    def predicted_covariance(self) -> np.ndarray:
        """(C, 6, 6) prior covariance for the next cycle's graph. A held camera's is a
        ten-thousandth of its own: the cycle then calibrates the others in the held
        cameras' frame, not in one its solve moved by their std (which the held cameras
        would not follow)."""
        P = self.P + self.q_scale[:, None, None] * self.Q[None]
        P[self.held] *= _HELD
        return P

    def update(self, active: np.ndarray, R_new: np.ndarray, t_new: np.ndarray, cov: np.ndarray,
               *, posterior: bool = False, cov_shape: np.ndarray | None = None, final: bool | None = None) -> UpdateResult:
        """Fold in one cycle's solution for the cameras in ``active`` (C,) bool.

        ``posterior``: the solution is already the full posterior (a batch whose prior
        was the initial estimate): take it as the state whatever the measurement mode.
        ``final`` (default: ``posterior``): a batch over all the data, after which the
        std alone decides convergence."""
        C = len(self.R)
        R_old, t_old = self.R.copy(), self.t.copy()
        Pp = self.predicted_covariance()
        batch = posterior if final is None else final
        if not batch:  # a batch over all data is the posterior of every camera, held or not
            active = active & ~self.held
        for c in np.flatnonzero(active):
            S = cov[c]
            if not np.all(np.isfinite(S)):
                continue
            if posterior or self.cfg.measurement == "posterior":
                self.R[c], self.t[c] = R_new[c], t_new[c]
                self.P[c] = _sym_pd(S)
            else:
                innov = pose_local(self.R[c], self.t[c], R_new[c], t_new[c])
                K = Pp[c] @ np.linalg.inv(Pp[c] + S)
                self.R[c], self.t[c] = pose_retract(self.R[c], self.t[c], K @ innov)
                self.P[c] = _sym_pd((np.eye(6) - K) @ Pp[c])
        if not posterior:  # cameras without data this cycle still become less certain
            for c in np.flatnonzero(~active & ~self.held):
                self.P[c] = Pp[c]
        S_held = self.S[self.held]
        self.S = self.P.copy()
        self.S[self.held] = S_held
        if cov_shape is not None:
            for c in np.flatnonzero(active):
                if np.all(np.isfinite(cov_shape[c])):
                    self.S[c] = _sym_pd(cov_shape[c])
        scale = self.keep_scale(active) if self.cfg.keep_scale and not self.held.any() else 1.0
        dt = np.linalg.norm(self.t - t_old, axis=1)
        dr = np.array([rotation_angle_deg(R_old[c], self.R[c]) for c in range(C)])
        if batch:  # the cycles' way to it is no drift: their net change is measured from here
            for c in np.flatnonzero(active):
                self.history[c].clear()
        self._record(active)
        self.batched[active] = batch
        return UpdateResult(dt, dr, scale)

    def _record(self, active: np.ndarray) -> None:
        for c in np.flatnonzero(active):
            self.cycles[c] += 1
            self.history[c].append((self.t[c].copy(), self.R[c].copy()))

    def relocate(self, c: int, R: np.ndarray, t: np.ndarray) -> None:
        """Camera c found elsewhere: new pose, the initial uncertainty, no history."""
        self.R[c], self.t[c] = R, t
        self._restart(c, initial_covariance(self.cfg))

    def reopen(self, c: int, std_translation: float, std_rotation: float) -> None:
        """Camera c moved: its pose stays the starting point, its uncertainty is re-opened
        and it counts as uncalibrated until cycles have calibrated it again."""
        self._restart(c, _diag(std_rotation, std_translation))
        self.batched[c] = False

    def recalibrated(self, c: int, R: np.ndarray, t: np.ndarray, P: np.ndarray) -> None:
        """Camera c calibrated again (after it moved) with the others held: new pose and
        covariance; the cycles must show it converged again."""
        self.R[c], self.t[c] = R, t
        self._restart(c, _sym_pd(P))

    def _restart(self, c: int, P: np.ndarray) -> None:
        """Camera c starts over from its current pose with covariance P: no history, no cycles."""
        self.P[c] = P
        self.S[c] = P.copy()
        self.history[c].clear()
        self.cycles[c] = 0

    def keep_scale(self, active: np.ndarray | None = None) -> float:
        """Rescale the calibrated cameras' centres about their centroid to the initial
        estimate's scale. Cameras that never had data keep their initial pose exactly.

        The scale is a least-squares similarity fit of the centres to the initial ones
        (every camera's perturbation averages out), trimmed: cameras whose residual after
        the fit is far above the others' (one camera metres off would rescale everyone)
        are left out and the fit repeated. The median of pairwise distance ratios, robust
        too, carried every pair's perturbations as ratio noise: measured, it raised the
        limit's rigid error from 0.021 to 0.031 m."""
        m = self.cycles > 0
        if active is not None:
            m = m | active
        idx = np.flatnonzero(m)
        if len(idx) < 3:
            return 1.0
        fit = trimmed_similarity(self.t[idx], self.t0[idx])
        if fit is None:
            return 1.0
        s = fit[0]
        c = self.t[m].mean(0)
        self.t[m] = c + s * (self.t[m] - c)
        # The uncertainty of a position scales with it.
        for M in (self.P, self.S):
            M[m, 3:, 3:] *= s * s
            M[m, :3, 3:] *= s
            M[m, 3:, :3] *= s
        return float(s)

    def rescale_frame(self, apply) -> float:
        """The initial estimate's scale corrected: ``apply`` maps its centres (C, 3) to the
        corrected ones (``scale_check.ScaleCheck.apply``). Cameras that never had data move
        with it, the others are brought to its new scale (``keep_scale``); returns that scale."""
        self.t0 = apply(self.t0)
        self.prior_t = apply(self.prior_t)
        never = self.cycles == 0
        self.t[never] = apply(self.t[never])
        return self.keep_scale()

    def reframe(self, F: np.ndarray, o: np.ndarray) -> None:
        """Every pose (estimate, initial estimate, prior, history) in a new world frame,
        X' = F (X - o), F (3, 3) a rotation. The covariances are in each camera's own
        tangent space (right perturbations), which a new world frame leaves as it is."""
        assert F.shape == (3, 3) and o.shape == (3,) and np.allclose(F @ F.T, np.eye(3), atol=1e-9)
        for R, t in ((self.R, self.t), (self.R0, self.t0), (self.prior_R, self.prior_t)):
            R[:] = np.einsum("ij,cjk->cik", F, R)
            t[:] = (t - o) @ F.T
        for h in self.history:
            moved = [(F @ (t - o), F @ R) for t, R in h]
            h.clear()
            h.extend(moved)

    def widen(self, factor: np.ndarray) -> None:
        """Each camera's covariances scaled by ``factor`` (C,) squared (std by ``factor``):
        the spread the data show where it exceeds what the solve stated
        (backend/split_check.py)."""
        assert factor.shape == (len(self.P),) and np.all(factor >= 1.0)
        f2 = (factor ** 2)[:, None, None]
        self.P = self.P * f2
        self.S = self.S * f2

    def change(self, c: int) -> tuple[float, float]:
        """Net pose change (m, deg) of camera c over its last ``converged_cycles`` cycles:
        a converging camera drifts; a converged one only jitters, which the filter averages."""
        h = self.history[c]
        if len(h) < 2:
            return float("inf"), float("inf")
        (t0, R0), (t1, R1) = h[0], h[-1]
        return float(np.linalg.norm(t1 - t0)), rotation_angle_deg(R0, R1)

    def std(self, c: int, *, shape: bool = True) -> tuple[float, float]:
        """(m, deg) of camera c: by default without the uncertainty of the world frame
        when a solve provided it; ``shape=False``: the filter's own covariance."""
        st, sr = pose_std(self.S[c] if shape else self.P[c])
        return float(st), float(np.degrees(sr))

    def converged(self, c: int) -> bool:
        """Converged: at least ``converged_cycles`` cycles, the net change over them below
        ``converged_translation``/``converged_rotation`` and the std below
        ``converged_std_translation``/``converged_std_rotation``."""
        cfg = self.cfg
        st, sr = self.std(c)
        precise = st <= cfg.converged_std_translation and sr <= cfg.converged_std_rotation
        if self.batched[c]:
            return bool(self.cycles[c] > 0 and precise)
        if self.cycles[c] < cfg.converged_cycles:
            return False
        ct, cr = self.change(c)
        return ct <= cfg.converged_translation and cr <= cfg.converged_rotation and precise
