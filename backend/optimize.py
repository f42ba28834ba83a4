"""One cycle's factor graph: camera priors, projection factors, LM, marginals.

``build_problem`` turns selected hypotheses and the current estimate into a
``Problem`` of plain arrays (picklable: the service solves it in another process,
because GTSAM holds the GIL while it optimises). ``solve`` is a pure function of the
Problem. gtsam objects never leave this module.

Landmarks are one per (hypothesis, joint) seen in >= 2 views, initialised by
triangulation with the current estimate. Observations are undistorted normalised
coordinates, so one unit calibration serves every camera and the noise is the pixel
std divided by the focal length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .associate import Hypothesis
from .config import OptimizeConfig
from .geometry import triangulate_views


@dataclass(frozen=True, eq=False)
class Problem:
    """A cycle's graph in plain arrays.

    R: (C, 3, 3), t: (C, 3) current poses (world_R_cam, centre); prior_cov: (C, 6, 6)
    tangent covariance (rot, trans) of the prior on each camera; active: (C,) bool,
    cameras that get a variable (enough observations).
    obs_cam, obs_lm: (M,) int; obs_xy: (M, 2) normalised; obs_sigma: (M,) normalised std.
    landmarks: (L, 3) initial positions; lm_hyp: (L,) index of the hypothesis, lm_joint: (L,).
    focal: (C,) px, to report residuals in pixels.
    """

    cycle: int
    R: np.ndarray
    t: np.ndarray
    prior_cov: np.ndarray
    active: np.ndarray
    obs_cam: np.ndarray
    obs_lm: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    landmarks: np.ndarray
    lm_hyp: np.ndarray
    lm_joint: np.ndarray
    focal: np.ndarray
    config: OptimizeConfig
    marginals: bool = True

    def __post_init__(self) -> None:
        C, M, L = len(self.R), len(self.obs_cam), len(self.landmarks)
        assert self.R.shape == (C, 3, 3) and self.t.shape == (C, 3) and self.prior_cov.shape == (C, 6, 6)
        assert self.active.shape == (C,) and self.focal.shape == (C,)
        assert self.obs_lm.shape == (M,) and self.obs_xy.shape == (M, 2) and self.obs_sigma.shape == (M,)
        assert self.landmarks.shape == (L, 3) and self.lm_hyp.shape == (L,) and self.lm_joint.shape == (L,)


@dataclass(frozen=True, eq=False)
class Solution:
    """R, t: (C, 3, 3), (C, 3) solved poses (inactive cameras unchanged); cov: (C, 6, 6)
    marginal covariances (NaN for inactive or when not computed); landmarks (L, 3);
    residual_px: (M,) reprojection error after the solve."""

    ok: bool
    reason: str
    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    landmarks: np.ndarray
    residual_px: np.ndarray
    initial_error: float
    final_error: float
    iterations: int
    seconds: float


# ------------------------------------------------------------------ building


def build_problem(cycle: int, hyps: Sequence[Hypothesis], R: np.ndarray, t: np.ndarray, prior_cov: np.ndarray,
                  focal: np.ndarray, config: OptimizeConfig, *, marginals: bool = True) -> Problem:
    C = len(R)
    obs_cam, obs_lm, obs_xy, obs_sig, lms, lm_hyp, lm_joint = [], [], [], [], [], [], []
    L = 0
    for hi, h in enumerate(hyps):
        X, n = triangulate_views(R, t, h.cams, h.xy)
        for j in range(17):
            if not np.all(np.isfinite(X[j])) or n[j] < config.min_landmark_views:
                continue
            v = np.flatnonzero(np.all(np.isfinite(h.xy[:, j]), axis=1))
            obs_cam.extend(h.cams[v])
            obs_lm.extend([L] * len(v))
            obs_xy.extend(h.xy[v, j])
            obs_sig.extend(h.sigma[v, j])
            lms.append(X[j])
            lm_hyp.append(hi)
            lm_joint.append(j)
            L += 1
    obs_cam_a = np.array(obs_cam, dtype=np.int64)
    counts = np.bincount(obs_cam_a, minlength=C) if len(obs_cam_a) else np.zeros(C, int)
    active = counts >= config.min_camera_observations
    # Observations of cameras left out are dropped; so are landmarks left with < 2 views.
    keep = active[obs_cam_a] if len(obs_cam_a) else np.zeros(0, bool)
    obs_lm_a = np.array(obs_lm, dtype=np.int64)[keep]
    per_lm = np.bincount(obs_lm_a, minlength=L)
    lm_ok = per_lm >= 2
    keep2 = lm_ok[obs_lm_a]
    remap = np.cumsum(lm_ok) - 1
    return Problem(
        cycle=cycle,
        R=R.copy(), t=t.copy(), prior_cov=prior_cov.copy(), active=active,
        obs_cam=obs_cam_a[keep][keep2],
        obs_lm=remap[obs_lm_a[keep2]],
        obs_xy=np.array(obs_xy, dtype=np.float64).reshape(-1, 2)[keep][keep2],
        obs_sigma=np.array(obs_sig, dtype=np.float64)[keep][keep2],
        landmarks=np.array(lms, dtype=np.float64).reshape(-1, 3)[lm_ok],
        lm_hyp=np.array(lm_hyp, dtype=np.int64)[lm_ok],
        lm_joint=np.array(lm_joint, dtype=np.int64)[lm_ok],
        focal=np.asarray(focal, dtype=np.float64),
        config=config,
        marginals=marginals,
    )


def residuals_px(R, t, landmarks, obs_cam, obs_lm, obs_xy, focal) -> np.ndarray:
    """(M,) reprojection error in pixels (inf for points behind the camera)."""
    if len(obs_cam) == 0:
        return np.zeros(0)
    Rt = np.transpose(R[obs_cam], (0, 2, 1))
    Xc = np.einsum("mij,mj->mi", Rt, landmarks[obs_lm] - t[obs_cam])
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(Xc[:, :2] / z[:, None] - obs_xy, axis=1) * focal[obs_cam]
    return np.where(z > 0, e, np.inf)


# ------------------------------------------------------------------ solving


def solve(p: Problem) -> Solution:
    """Solve a Problem with GTSAM; never raises for numerical failures (ok=False)."""
    import gtsam

    t0 = time.perf_counter()
    C, L = len(p.R), len(p.landmarks)
    cams = np.flatnonzero(p.active)
    nan_cov = np.full((C, 6, 6), np.nan)

    def failed(reason: str, initial: float = float("nan")) -> Solution:
        return Solution(False, reason, p.R.copy(), p.t.copy(), nan_cov, p.landmarks.copy(),
                        np.zeros(len(p.obs_cam)), initial, initial, 0, time.perf_counter() - t0)

    if len(cams) == 0 or L == 0:
        return failed("no camera has enough observations")

    X = lambda c: gtsam.symbol("x", int(c))  # noqa: E731
    Lk = lambda l: gtsam.symbol("l", int(l))  # noqa: E731
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for c in cams:
        pose = gtsam.Pose3(gtsam.Rot3(p.R[c]), p.t[c])
        values.insert(X(c), pose)
        cov = 0.5 * (p.prior_cov[c] + p.prior_cov[c].T)
        graph.add(gtsam.PriorFactorPose3(X(c), pose, gtsam.noiseModel.Gaussian.Covariance(cov)))
    for l in range(L):
        values.insert(Lk(l), p.landmarks[l])
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    cfg = p.config
    robust = None
    if cfg.robust == "huber":
        robust = gtsam.noiseModel.mEstimator.Huber.Create(cfg.robust_k)
    elif cfg.robust == "cauchy":
        robust = gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.robust_k)
    for c, l, xy, s in zip(p.obs_cam, p.obs_lm, p.obs_xy, p.obs_sigma):
        noise = gtsam.noiseModel.Isotropic.Sigma(2, float(s))
        if robust is not None:
            noise = gtsam.noiseModel.Robust.Create(robust, noise)
        graph.add(gtsam.GenericProjectionFactorCal3_S2(xy, noise, X(c), Lk(l), K))

    initial_error = graph.error(values)
    if cfg.solver == "lm":
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.max_iterations)
        params.setRelativeErrorTol(1e-6)
        params.setAbsoluteErrorTol(1e-9)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    else:
        params = gtsam.DoglegParams()
        params.setMaxIterations(cfg.max_iterations)
        optimizer = gtsam.DoglegOptimizer(graph, values, params)
    try:
        result = optimizer.optimize()
    except RuntimeError as e:  # IndeterminantLinearSystem and friends
        return failed(f"optimizer failed: {str(e).splitlines()[0][:200]}", initial_error)
    final_error = graph.error(result)
    if not np.isfinite(final_error):
        return failed("optimizer diverged (non-finite error)", initial_error)

    R, t = p.R.copy(), p.t.copy()
    for c in cams:
        pose = result.atPose3(X(c))
        R[c] = pose.rotation().matrix()
        t[c] = pose.translation()
    lms = np.array([result.atPoint3(Lk(l)) for l in range(L)]).reshape(-1, 3)
    cov = nan_cov.copy()
    reason = ""
    if p.marginals:
        try:
            marg = gtsam.Marginals(graph, result)
            for c in cams:
                cov[c] = marg.marginalCovariance(X(c))
        except RuntimeError as e:
            reason = f"marginals failed: {str(e).splitlines()[0][:200]}"
    res = residuals_px(R, t, lms, p.obs_cam, p.obs_lm, p.obs_xy, p.focal)
    return Solution(reason == "", reason, R, t, cov, lms, res, float(initial_error), float(final_error),
                    int(optimizer.iterations()), time.perf_counter() - t0)
