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

from .config import RefineConfig
from .geometry import pose_local, pose_retract, rotation_angle_deg, umeyama


@dataclass(frozen=True)
class UpdateResult:
    changed_translation: np.ndarray  # (C,) m
    changed_rotation: np.ndarray  # (C,) deg
    scale_applied: float


def initial_covariance(cfg: RefineConfig) -> np.ndarray:
    """(6, 6) diagonal covariance of the initial estimate."""
    return _diag(cfg.initial_std_rotation, cfg.initial_std_translation)


def _diag(std_deg: float, std_m: float) -> np.ndarray:
    r = np.radians(std_deg)
    return np.diag([r * r] * 3 + [std_m * std_m] * 3)


def _sym_pd(P: np.ndarray, floor: float = 1e-14) -> np.ndarray:
    P = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(P)
    return (V * np.maximum(w, floor)) @ V.T


class Refiner:
    """Camera states R (C, 3, 3), t (C, 3), P (C, 6, 6) and their recent changes."""

    def __init__(self, cfg: RefineConfig, R0: np.ndarray, t0: np.ndarray, P0: np.ndarray | None = None):
        C = len(R0)
        assert R0.shape == (C, 3, 3) and t0.shape == (C, 3)
        self.cfg = cfg
        self.R0, self.t0 = R0.copy(), t0.copy()  # the initial estimate: frame and scale
        self.R, self.t = R0.copy(), t0.copy()
        self.P = np.repeat(initial_covariance(cfg)[None], C, axis=0) if P0 is None else P0.copy()
        self.Q = _diag(cfg.filter_std_rotation, cfg.filter_std_translation) * cfg.process_noise**2
        self.cycles = np.zeros(C, dtype=np.int64)
        self.history: list[deque] = [deque(maxlen=cfg.converged_cycles) for _ in range(C)]

    def predicted_covariance(self) -> np.ndarray:
        """(C, 6, 6) prior covariance for the next cycle's graph."""
        return self.P + self.Q[None]

    def update(self, active: np.ndarray, R_new: np.ndarray, t_new: np.ndarray, cov: np.ndarray,
               *, posterior: bool = False) -> UpdateResult:
        """Fold in one cycle's solution for the cameras in ``active`` (C,) bool.

        ``posterior``: the solution is already the full posterior (a batch whose prior
        was the initial estimate): take it as the state whatever the measurement mode."""
        C = len(self.R)
        R_old, t_old = self.R.copy(), self.t.copy()
        Pp = self.predicted_covariance()
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
            for c in np.flatnonzero(~active):
                self.P[c] = Pp[c]
        scale = self.keep_scale() if self.cfg.keep_scale else 1.0
        dt = np.linalg.norm(self.t - t_old, axis=1)
        dr = np.array([rotation_angle_deg(R_old[c], self.R[c]) for c in range(C)])
        for c in np.flatnonzero(active):
            self.cycles[c] += 1
            self.history[c].append((dt[c], dr[c]))
        return UpdateResult(dt, dr, scale)

    def move(self, active: np.ndarray, R_new: np.ndarray, t_new: np.ndarray) -> UpdateResult:
        """Take new poses for the active cameras without touching the covariance."""
        R_old, t_old = self.R.copy(), self.t.copy()
        self.R[active], self.t[active] = R_new[active], t_new[active]
        scale = self.keep_scale() if self.cfg.keep_scale else 1.0
        dt = np.linalg.norm(self.t - t_old, axis=1)
        dr = np.array([rotation_angle_deg(R_old[c], self.R[c]) for c in range(len(self.R))])
        return UpdateResult(dt, dr, scale)

    def keep_scale(self) -> float:
        """Rescale the centres about their centroid to the initial estimate's scale."""
        if len(self.t) < 3:
            return 1.0
        s, _, _ = umeyama(self.t, self.t0, with_scale=True)
        c = self.t.mean(0)
        self.t = c + s * (self.t - c)
        # The uncertainty of a position scales with it.
        self.P[:, 3:, 3:] *= s * s
        self.P[:, :3, 3:] *= s
        self.P[:, 3:, :3] *= s
        return float(s)

    def change(self, c: int) -> tuple[float, float]:
        """Mean per-cycle change (m, deg) of camera c over the last cycles."""
        h = self.history[c]
        if not h:
            return float("inf"), float("inf")
        a = np.array(h)
        return float(a[:, 0].mean()), float(a[:, 1].mean())

    def std(self, c: int) -> tuple[float, float]:
        P = self.P[c]
        return (float(np.sqrt(max(np.trace(P[3:, 3:]) / 3, 0))),
                float(np.degrees(np.sqrt(max(np.trace(P[:3, :3]) / 3, 0)))))

    def converged(self, c: int) -> bool:
        """Converged: enough cycles, and both the recent mean change and the std are
        below the thresholds."""
        if self.cycles[c] < self.cfg.converged_cycles:
            return False
        ct, cr = self.change(c)
        st, sr = self.std(c)
        return (ct <= self.cfg.converged_translation and cr <= self.cfg.converged_rotation
                and st <= self.cfg.converged_translation and sr <= self.cfg.converged_rotation)
