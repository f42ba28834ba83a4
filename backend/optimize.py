"""One cycle's factor graph: camera priors, projection factors, LM, marginals.

``build_problem`` turns selected hypotheses and the current estimate into a
``Problem`` of plain arrays (picklable: the service solves it in another process,
because GTSAM holds the GIL while it optimises). ``solve`` is a pure function of the
Problem. gtsam objects never leave this module.

Landmarks are one per (hypothesis, joint) seen in >= 2 views, initialised by
triangulation with the current estimate. Observations are undistorted normalised
coordinates, so one unit calibration serves every camera and the noise is the pixel
std divided by the focal length.

People keep their size (``optimize.bones``, docs/bones.md): the hypotheses are told apart
into persons (``people.label_persons``: tracks grouped by their size) and each person gets
one length per bone, measured anew before each of ``solve``'s rounds; a range factor per
bone of each hypothesis ties its joints' distance to it. Keypoints alone leave the scale
of each part of a camera network that shares no person with a third camera free; these
factors carry it along. With them the floor (``optimize.floor``, backend/floor.py): each
hypothesis' lower ankle on one plane, a variable of the solve, so a chain cannot bend.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy.stats import wilcoxon

from .associate import Associator, Hypothesis, triangulate_hypotheses
from .config import AssociateConfig, OptimizeConfig
from .floor import Floor, fit_floor, held_ankles
from .geometry import centres_fix_rotation, rotation_angle_deg, triangulate_batch
from .people import label_persons, oversized, segments
from .preprocess import Detection
from .selection import select_spaced
from .split_check import interleaved_halves

# a solve's reason when no landmark could be placed: the data, not the optimizer, failed
NOTHING_TO_SOLVE = "no camera has enough observations"


@dataclass(frozen=True, eq=False)
class Problem:
    """One cycle's inputs, picklable (the service solves it in a worker process).

    R: (C, 3, 3), t: (C, 3) current poses (world_R_cam, centre): the linearisation point
    and the start of the solve. prior_R, prior_t: (C, 3, 3), (C, 3) and prior_cov
    (C, 6, 6): the camera priors (tangent covariance, rotation then translation).
    focal: (C,) px. Either ``hypotheses`` are given, or ``frames`` (time, detections per
    view) that the solve re-associates with R, t first and thins to ``max_hypotheses``
    spaced by ``spacing`` m.
    """

    cycle: int
    R: np.ndarray
    t: np.ndarray
    prior_R: np.ndarray
    prior_t: np.ndarray
    prior_cov: np.ndarray
    focal: np.ndarray
    config: OptimizeConfig
    hypotheses: tuple[Hypothesis, ...] = ()
    frames: tuple[tuple[float, tuple[tuple[Detection, ...], ...]], ...] = ()
    associate: AssociateConfig | None = None
    gate_px: np.ndarray | None = None
    pose_px: np.ndarray | None = None  # (C,) px: the association's epipolar test of two views (Associator)
    follow_px: np.ndarray | None = None  # (C,) px: views with one side hidden that may follow a hypothesis (Associator)
    max_hypotheses: int = 0
    spacing: float = 0.0
    fill: bool = False  # after the spaced hypotheses, the others up to max_hypotheses (``select_spaced``)
    seed: int = 0
    marginals: bool = True
    kind: str = "cycle"  # cycle | first | batch | relocalize | recalibrate | dispute
    lost: tuple[int, ...] = ()  # relocalize: the cameras to find again
    moved: tuple[int, ...] = ()  # recalibrate: the cameras calibrated again (the others held by tight priors); dispute: the camera in question
    # bones in the first solve too: the start's links already share one scale (the
    # bootstrap's, related by bones), and only weak priors hold them (see ``solve``)
    bones_from_start: bool = False
    level: bool = False  # also fit the plane of the solved lower ankles (``Solution.level``)
    # the final solve also estimates how far these cameras' lenses are off their files (``_lens_prior``)
    lenses: tuple[int, ...] = ()
    # the final solve's covariance also with the calibration files' accuracy
    # (``optimize.lens_accuracy_*``: ``Solution.cov_shape_lenses``)
    lens_accuracy: bool = False

    def __post_init__(self) -> None:
        C = len(self.R)
        assert self.R.shape == (C, 3, 3) and self.t.shape == (C, 3)
        assert self.prior_R.shape == (C, 3, 3) and self.prior_t.shape == (C, 3)
        assert self.prior_cov.shape == (C, 6, 6) and self.focal.shape == (C,)
        assert not self.frames or self.associate is not None
        assert all(0 <= c < C for c in self.lenses), self.lenses


@dataclass(frozen=True, eq=False)
class Graph:
    """The factor graph in plain arrays.

    active: (C,) bool cameras with a variable; obs_cam, obs_lm: (M,) int;
    obs_xy: (M, 2) normalised; obs_sigma: (M,) normalised std; landmarks: (L, 3)
    initial positions; lm_hyp, lm_joint: (L,) int.
    """

    active: np.ndarray
    obs_cam: np.ndarray
    obs_lm: np.ndarray
    obs_xy: np.ndarray
    obs_sigma: np.ndarray
    landmarks: np.ndarray
    lm_hyp: np.ndarray
    lm_joint: np.ndarray

    def views(self) -> np.ndarray:
        """(M,) int id of the view (hypothesis, camera) of each observation."""
        return self.lm_hyp[self.obs_lm] * 100003 + self.obs_cam

    def without(self, drop_obs: np.ndarray, config: OptimizeConfig) -> "Graph":
        """The graph without some observations, re-pruned (cameras, landmarks < 2 views)."""
        keep = ~drop_obs
        C = len(self.active)
        counts = np.bincount(self.obs_cam[keep], minlength=C)
        active = self.active & (counts >= config.min_camera_observations)
        keep &= active[self.obs_cam]
        lm_ok = np.bincount(self.obs_lm[keep], minlength=len(self.landmarks)) >= 2
        keep &= lm_ok[self.obs_lm]
        remap = np.cumsum(lm_ok) - 1
        return Graph(active, self.obs_cam[keep], remap[self.obs_lm[keep]], self.obs_xy[keep], self.obs_sigma[keep],
                     self.landmarks[lm_ok], self.lm_hyp[lm_ok], self.lm_joint[lm_ok])


@dataclass(frozen=True, eq=False)
class Solution:
    """R, t: (C, 3, 3), (C, 3) solved poses (inactive cameras unchanged); cov: (C, 6, 6)
    marginal covariances (NaN for inactive cameras or when not computed);
    residual_px: (M,) reprojection error after the solve; obs_per_camera: (C,)."""

    ok: bool
    reason: str
    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    cov_shape: np.ndarray  # (C, 6, 6) the same with the similarity gauge projected out
    active: np.ndarray
    obs_per_camera: np.ndarray
    hypotheses: int
    residual_px: np.ndarray
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    bone_lengths: np.ndarray | None = None  # (K, len(BONE_NAMES)) bone lengths per person after the solve, NaN = unseen
    residual_cam_px: np.ndarray | None = None  # (C,) median of each camera's residual_px, NaN = no observation
    # (C,) median distance of each camera's observed landmarks from it, NaN = none; batch adjustments only
    depth_cam: np.ndarray | None = None
    phantoms: int = 0  # hypotheses dropped as far larger than anyone seen (optimize.max_size_ratio)
    floor: Floor | None = None  # the floor's plane as the last solve left it (optimize.floor; None: no floor)
    floor_points: int = 0  # lower ankles held to it
    # with ``Problem.level``: the plane of its solved lower ankles (floor.fit_floor), held or
    # not: the floor the world frame is levelled on (``Pipeline._level``); None: not asked, or no plane
    level: Floor | None = None
    # with ``Problem.lenses`` and lenses the data show off their files: (C, 4) each camera's
    # fx / fx_file - 1, fy / fy_file - 1 and principal point shift (x, y) in focal lengths
    # (NaN: not in the solve), and lens_std (4,) the spread of such deviations the data
    # show (the prior they were estimated with); None: the files' lenses were kept
    lenses: np.ndarray | None = None
    lens_std: np.ndarray | None = None
    # with ``Problem.lens_accuracy``: (C, 6, 6) ``cov_shape`` plus what the errors of the lens
    # parameters the solve held at their files (``optimize.lens_accuracy_*`` std) move the
    # poses by (``_with_lens_accuracy``), NaN = none; None: not asked, or nothing to state
    cov_shape_lenses: np.ndarray | None = None


# COCO-17 bones; left and right share one length: (length index, joint a, joint b)
BONE_NAMES = ("shoulder width", "hip width", "upper arm", "forearm", "thigh", "shank", "flank")
BONES = np.array([(0, 5, 6), (1, 11, 12), (2, 5, 7), (2, 6, 8), (3, 7, 9), (3, 8, 10),
                  (4, 11, 13), (4, 12, 14), (5, 13, 15), (5, 14, 16), (6, 5, 11), (6, 6, 12)], dtype=np.int64)


# ------------------------------------------------------------------ building


def build_graph(hyps: Sequence[Hypothesis], R: np.ndarray, t: np.ndarray, config: OptimizeConfig) -> Graph:
    """Landmarks per (hypothesis, joint) triangulated with R, t; cameras with too few
    observations are left out, and so are landmarks left with < 2 views or whose rays
    meet at less than ``min_triangulation_angle``."""
    C, H = len(R), len(hyps)
    empty = Graph(np.zeros(C, bool), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)),
                  np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64))
    if H == 0:
        return empty
    V = max(len(h.cams) for h in hyps)
    cams = np.zeros((H, V), np.int64)
    xy = np.full((H, V, 17, 2), np.nan)
    sig = np.full((H, V, 17), np.nan)
    for i, h in enumerate(hyps):
        n = len(h.cams)
        cams[i, :n], xy[i, :n], sig[i, :n] = h.cams, h.xy, h.sigma
    # one landmark candidate per (hypothesis, joint): (H*17, V, ...)
    lc = np.repeat(cams, 17, axis=0)
    lxy = xy.transpose(0, 2, 1, 3).reshape(H * 17, V, 2)
    lsig = sig.transpose(0, 2, 1).reshape(H * 17, V)
    X = triangulate_batch(R, t, lc, lxy)
    seen = np.all(np.isfinite(lxy), axis=2)
    ok = np.all(np.isfinite(X), axis=1) & (seen.sum(1) >= config.min_landmark_views)
    # the widest angle between two of a landmark's rays
    rays = X[:, None, :] - t[lc]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    cosines = np.einsum("lvk,lwk->lvw", rays, rays)
    both = seen[:, :, None] & seen[:, None, :]
    min_cos = np.where(both, cosines, 1.0).min(axis=(1, 2))
    ok &= min_cos <= np.cos(np.radians(config.min_triangulation_angle))
    obs = seen & ok[:, None]  # (H*17, V)
    lm_of = np.cumsum(ok) - 1
    li, vi = np.nonzero(obs)
    obs_cam = lc[li, vi]
    counts = np.bincount(obs_cam, minlength=C)
    active = counts >= config.min_camera_observations
    keep = active[obs_cam]
    li, vi, obs_cam = li[keep], vi[keep], obs_cam[keep]
    lm_ok = np.zeros(len(ok), bool)
    per = np.bincount(li, minlength=len(ok))
    lm_ok[per >= 2] = True
    keep2 = lm_ok[li]
    li, vi, obs_cam = li[keep2], vi[keep2], obs_cam[keep2]
    remap = np.cumsum(lm_ok) - 1
    idx = np.flatnonzero(lm_ok)
    del lm_of
    return Graph(
        active=active,
        obs_cam=obs_cam,
        obs_lm=remap[li],
        obs_xy=lxy[li, vi],
        obs_sigma=lsig[li, vi],
        landmarks=X[idx],
        lm_hyp=idx // 17,
        lm_joint=idx % 17,
    )


def hypotheses_of(p: Problem) -> list[Hypothesis]:
    """The problem's hypotheses: given, or re-associated from its frames with R, t."""
    return hypotheses_and_persons(p)[0]


def bones_wanted(p: Problem) -> bool:
    """Bone-length factors in this problem (``optimize.bones``)."""
    b = p.config.bones
    return b == "all" or (b == "batch" and p.kind in ("first", "batch"))


def _links(hyps: Sequence[Hypothesis]) -> np.ndarray:
    """(H,) int: which cameras saw each hypothesis (one id per camera set): the part of
    the network whose scale its bones are measured in."""
    ids: dict[tuple[int, ...], int] = {}
    return np.array([ids.setdefault(tuple(sorted(int(c) for c in h.cams)), len(ids)) for h in hyps], np.int64)


def hypotheses_and_persons(p: Problem) -> tuple[list[Hypothesis], np.ndarray]:
    """The problem's hypotheses and (H,) int the person of each (-1 = none; all -1 when
    ``bones_wanted`` is not). Persons are told apart on every hypothesis before the
    thinning to ``max_hypotheses``: tracking needs the neighbours in time."""
    hyps, person, _ = _hypotheses_persons_phantoms(p)
    return hyps, person


def _hypotheses_persons_phantoms(p: Problem) -> tuple[list[Hypothesis], np.ndarray, int]:
    """``hypotheses_and_persons`` and how many hypotheses it dropped as phantoms
    (``people.oversized``)."""
    if p.frames:
        assoc = Associator(p.associate)
        hyps: list[Hypothesis] = []
        for time_, views in p.frames:
            hyps.extend(assoc(time_, views, p.R, p.t, p.gate_px, p.pose_px, p.follow_px))
    else:
        hyps = list(p.hypotheses)
    person = np.full(len(hyps), -1, np.int64)
    phantoms = 0
    if bones_wanted(p) and hyps:
        seg = segments(hyps, p.R, p.t)
        person = label_persons(seg, links=_links(hyps))
        keep = ~oversized(seg, person, p.config.max_size_ratio)
        hyps, person = [h for h, k in zip(hyps, keep) if k], person[keep]
        phantoms = int((~keep).sum())
    if p.frames and (p.max_hypotheses and len(hyps) > p.max_hypotheses or p.spacing > 0):
        index = {id(h): i for i, h in enumerate(hyps)}
        hyps = select_spaced(hyps, p.max_hypotheses or len(hyps), p.spacing, np.random.default_rng(p.seed),
                             fill=p.fill)
        person = person[[index[id(h)] for h in hyps]]
    return hyps, person, phantoms


def _without_view(h: Hypothesis, k: int) -> Hypothesis:
    rest = np.delete(np.arange(len(h.cams)), k)
    return Hypothesis(h.time, h.cams[rest], h.xy[rest], h.sigma[rest], h.com)


def _drop_inconsistent_views(hyps: list[Hypothesis], person: np.ndarray, p: Problem
                             ) -> tuple[list[Hypothesis], np.ndarray]:
    """Before a batch's first solve: in each hypothesis of >= 3 views, a view that the
    others' triangulation misses by more than the outlier limit plus 3 stds of the poses
    (``p.pose_px``, this camera's and the others' worst) is a wrong association, and it
    is dropped. The outlier rounds look only after a solve, and a camera seen little
    follows its wrong views there: its right ones, mostly of two views, cannot hold it
    (docs/accuracy.md, Session 15). A camera the filter is unsure of has a wide limit,
    so the batch can still put it right. person: (H,) as ``hypotheses_and_persons``."""
    pose_px = np.asarray(p.pose_px, dtype=np.float64)
    where = [(i, k) for i, h in enumerate(hyps) if len(h.cams) >= 3 for k in range(len(h.cams))]
    if not where:
        return hyps, person
    X = triangulate_hypotheses([_without_view(hyps[i], k) for i, k in where], p.R, p.t)  # (N, 17, 3)
    N, J = X.shape[:2]
    cam = np.repeat([int(hyps[i].cams[k]) for i, k in where], J)
    xy = np.stack([hyps[i].xy[k] for i, k in where]).reshape(-1, 2)
    e = residuals_px(p.R, p.t, X.reshape(-1, 3), cam, np.arange(N * J), xy, p.focal).reshape(N, J)
    e[~np.isfinite(e)] = np.nan  # behind the camera, or a joint not seen
    seen = np.isfinite(e).sum(1) >= 4
    miss = np.full(N, np.nan)
    miss[seen] = np.nanmedian(e[seen], axis=1)
    if not np.isfinite(miss).any():
        return hyps, person
    base = max(p.config.outlier_px, 4.0 * float(np.nanmedian(miss)))
    drop: dict[int, list[int]] = {}
    for n, (i, k) in enumerate(where):
        cams = hyps[i].cams
        if miss[n] > base + 3.0 * (pose_px[cams[k]] + np.delete(pose_px[cams], k).max()):
            drop.setdefault(i, []).append(k)
    out, keep_person = [], []
    for i, h in enumerate(hyps):
        ks = drop.get(i, [])
        if len(ks) > 1:  # several views at odds with the rest: no telling which
            continue
        out.append(_without_view(h, ks[0]) if ks else h)
        keep_person.append(person[i])
    return out, np.asarray(keep_person, np.int64)


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
    """Build and solve a Problem with GTSAM; never raises for numerical failures (ok=False).

    After each solve, views (one person in one camera) whose median joint residual is
    far above the rest are wrong associations or detections: they are dropped and the
    graph solved again from the last solution, up to ``outlier_rounds`` times."""
    if p.kind == "relocalize":
        return _relocalize(p)
    t0 = time.perf_counter()
    C = len(p.R)
    hyps, person, phantoms = _hypotheses_persons_phantoms(p)
    if p.kind == "batch" and p.pose_px is not None and p.config.batch_view_check:
        hyps, person = _drop_inconsistent_views(hyps, person, p)
    person = person if (person >= 0).any() else None
    g = build_graph(hyps, p.R, p.t, p.config)
    R, t = p.R, p.t
    first_error = None
    iterations = 0
    floor = None
    for round_ in range(p.config.outlier_rounds + 1):
        last = round_ == p.config.outlier_rounds
        # The first round without bones: the lengths are measured on its solution (from a
        # rough start, links at different scales make the first steps of LM with them stall).
        # Not where the priors are weak (the bootstrap's gauge): there nothing else holds
        # a chain's links, and a corridor's first solve without bones shrank them to 0.4x.
        who = person if round_ > 0 or p.bones_from_start else None
        # outlier rounds only need to find the bad views: a loose tolerance will do
        out = _solve_graph(p, g, R, t, marginals=False, tolerance=max(p.config.relative_tolerance, 1e-3),
                           person=who, floor=floor)
        if isinstance(out, str):
            return _failed(p, g, out, first_error, t0)
        R, t, lms = out.R, out.t, out.landmarks
        # the error at the start of the first solve with the final solve's kinds of factors
        first_error = out.initial_error if first_error is None or (round_ == 1 and who is not None) else first_error
        iterations += out.iterations
        if person is not None and p.config.floor:  # held in the next solve: see backend/floor.py
            floor = fit_floor(lms, g.lm_hyp, g.lm_joint, p.config.floor_sigma)
        if person is not None:  # the next solve measures the people's bones on this solution
            g = replace(g, landmarks=_retriangulate(g, R, t))
        if last:
            break
        res = residuals_px(R, t, lms, g.obs_cam, g.obs_lm, g.obs_xy, p.focal)
        views = g.views()
        uniq, inv = np.unique(views, return_inverse=True)
        med = np.array([np.median(res[inv == k]) for k in range(len(uniq))])
        limit = max(p.config.outlier_px, 4.0 * float(np.median(med)))
        bad_views = med > limit
        if not bad_views.any():
            if person is None or who is not None:
                break
            continue  # with bones: at least one round with them before the final solve
        g = g.without(bad_views[inv], p.config)
        # landmarks move with the solution: start the next round from it
        g = Graph(g.active, g.obs_cam, g.obs_lm, g.obs_xy, g.obs_sigma,
                  _retriangulate(g, R, t), g.lm_hyp, g.lm_joint)
    lens_std = _lens_prior(p, g, R, t, person, floor, np.array([h.time for h in hyps])) if p.lenses else None
    lens_prior = _lens_stds(C, p.lenses, lens_std)
    out = _solve_graph(p, g, R, t, marginals=p.marginals, person=person, floor=floor, lens_prior=lens_prior)
    if isinstance(out, str):
        return _failed(p, g, out, first_error, t0)
    cov_shape_lenses = _with_lens_accuracy(p, g, out, person, floor, lens_prior) if p.lens_accuracy else None
    if person is not None and p.config.outlier_rounds == 0:  # the first solve with bones
        first_error = out.initial_error
    R, t, lms, final_error, its = out.R, out.t, out.landmarks, out.final_error, out.iterations
    nan = np.full((C, 6, 6), np.nan)
    cov = out.cov if out.cov is not None else nan
    cov_shape = out.cov_shape if out.cov_shape is not None else nan.copy()
    res = residuals_px(R, t, lms, g.obs_cam, g.obs_lm, normalised_by_lenses(g.obs_xy, g.obs_cam, out.lenses), p.focal)
    per_cam = np.full(C, np.nan)
    # the distances only a batch adjustment reports (the bootstrap's, for backend/reconcile.py):
    # not on every cycle's solve
    depth = np.full(C, np.nan) if p.kind == "batch" else None
    reach = np.linalg.norm(lms[g.obs_lm] - t[g.obs_cam], axis=1) if depth is not None else None
    for c in np.unique(g.obs_cam):
        m = g.obs_cam == c
        per_cam[c] = np.median(res[m])
        if depth is not None:
            depth[c] = np.median(reach[m])
    level = fit_floor(lms, g.lm_hyp, g.lm_joint, p.config.floor_sigma) if p.level else None
    return Solution(out.reason == "", out.reason, R, t, cov, cov_shape, g.active, np.bincount(g.obs_cam, minlength=C),
                    int(len(np.unique(g.lm_hyp))), res, float(first_error), float(final_error),
                    iterations + its, time.perf_counter() - t0, bone_lengths=out.lengths, residual_cam_px=per_cam,
                    depth_cam=depth, phantoms=phantoms, floor=floor if out.held else None, floor_points=out.held,
                    level=level, lenses=out.lenses, lens_std=lens_std, cov_shape_lenses=cov_shape_lenses)


def _relocalize(p: Problem) -> Solution:
    """Poses for the lost cameras by PnP against people the others triangulate."""
    from .relocalize import relocalize

    t0 = time.perf_counter()
    C = len(p.R)
    R, t = p.R.copy(), p.t.copy()
    active = np.zeros(C, bool)
    found = []
    for c in p.lost:
        r = relocalize(p.frames, c, p.R, p.t, float(p.focal[c]), p.associate,
                       reprojection_px=p.associate.relocalize_px, seed=p.seed)
        if r is None:
            continue
        # The prior (the initial estimate and its uncertainty) bounds where the camera can
        # be: a pose beyond 6 sigma of it (the frame may drift a little meanwhile) is a wrong
        # correspondence (the other person).
        P = p.prior_cov[c]
        max_t = 6.0 * float(np.sqrt(np.trace(P[3:, 3:]) / 3))
        max_r = 6.0 * float(np.sqrt(np.trace(P[:3, :3]) / 3))
        moved_t = float(np.linalg.norm(r.t - p.prior_t[c]))
        moved_r = float(np.radians(rotation_angle_deg(r.R, p.prior_R[c])))
        if moved_t > max_t or moved_r > max_r:
            continue
        R[c], t[c], active[c] = r.R, r.t, True
        found.append(f"{c}: {r.inliers}/{r.correspondences} inliers")
    nan = np.full((C, 6, 6), np.nan)
    reason = "" if found else "no lost camera could be re-localised"
    return Solution(bool(found), reason, R, t, nan, nan.copy(), active, np.zeros(C, np.int64), 0,
                    np.zeros(0), 0.0, 0.0, 0, time.perf_counter() - t0)


def failed(p: Problem, reason: str) -> Solution:
    """A Solution saying the solve did not happen (a worker died, a time limit): apply()
    rejects it and the estimate stays as it was."""
    C = len(p.R)
    nan = np.full((C, 6, 6), np.nan)
    return Solution(False, reason, p.R.copy(), p.t.copy(), nan, nan.copy(), np.zeros(C, bool),
                    np.zeros(C, np.int64), 0, np.zeros(0), float("nan"), float("nan"), 0, 0.0)


def _failed(p: Problem, g: Graph, reason: str, initial: float | None, t0: float) -> Solution:
    C = len(p.R)
    e = float("nan") if initial is None else initial
    nan = np.full((C, 6, 6), np.nan)
    return Solution(False, reason, p.R.copy(), p.t.copy(), nan, nan.copy(), g.active,
                    np.bincount(g.obs_cam, minlength=C), int(len(np.unique(g.lm_hyp))),
                    np.zeros(len(g.obs_cam)), e, e, 0, time.perf_counter() - t0)


def _retriangulate(g: Graph, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(L, 3) landmarks triangulated again from their observations with R, t."""
    L = len(g.landmarks)
    if L == 0:
        return g.landmarks.copy()
    order = np.argsort(g.obs_lm, kind="stable")
    lm = g.obs_lm[order]
    starts = np.searchsorted(lm, np.arange(L))
    slot = np.arange(len(lm)) - starts[lm]
    V = int(slot.max()) + 1
    cams = np.zeros((L, V), np.int64)
    xy = np.full((L, V, 2), np.nan)
    cams[lm, slot] = g.obs_cam[order]
    xy[lm, slot] = g.obs_xy[order]
    X = triangulate_batch(R, t, cams, xy)
    bad = ~np.all(np.isfinite(X), axis=1)
    X[bad] = g.landmarks[bad]
    return X


@dataclass(frozen=True, eq=False)
class _Solved:
    """One GTSAM solve (``_solve_graph``): R, t (C, 3, 3), (C, 3); landmarks (L, 3);
    lengths as ``bone_lengths`` (None: no bones); held: lower ankles held to the floor;
    lenses (C, 4) as ``Solution.lenses`` (None: not estimated); cov, cov_shape (C, 6, 6)
    (None: not asked)."""

    R: np.ndarray
    t: np.ndarray
    landmarks: np.ndarray
    initial_error: float
    final_error: float
    iterations: int
    lengths: np.ndarray | None
    held: int
    lenses: np.ndarray | None = None
    cov: np.ndarray | None = None
    cov_shape: np.ndarray | None = None
    reason: str = ""


def normalised_by_lenses(obs_xy: np.ndarray, obs_cam: np.ndarray, lenses: np.ndarray | None) -> np.ndarray:
    """(M, 2) observations as the estimated lenses (``Solution.lenses``, None: the files')
    see them: normalised by the calibration file, they are K_file^-1 K_lens x."""
    if lenses is None:
        return obs_xy
    d = np.nan_to_num(lenses[obs_cam])
    return (obs_xy - d[:, 2:]) / (1.0 + d[:, :2])


def _lens_prior(p: Problem, g: Graph, R: np.ndarray, t: np.ndarray, person: np.ndarray | None,
                floor: Floor | None, times: np.ndarray) -> np.ndarray | None:
    """(4,) std of the lenses' deviations from their calibration files (fx, fy as
    fractions, the principal point in focal lengths) that the data show, or None when they
    show none: an empirical Bayes prior. The graph's hypotheses (times (H,) s) in two
    halves of alternate blocks each estimate every camera's deviation under a loose prior
    (``optimize.lens_focal_std``, ``lens_centre_std``); the halves' noise is independent,
    their lenses are the same, so the mean over the cameras of the product of the two
    estimates is the lenses' own spread (per group: focal lengths, principal points),
    taken when it is significant: the products are symmetric about 0 if the lenses are
    the files' (Wilcoxon's signed-rank test at 1 - ``_LENS_LEVEL``, robust to the few
    cameras with little data whose products are large either way). No stated noise
    enters: the solve's marginals overstate the lab's (the detector's noise is correlated
    in time). Lenses as good as their files: no spread, and the files' lenses are kept,
    since free lenses cost the lab twice its shape error (0.0057 -> 0.0145 m). Lenses 1 %
    off: the final solve takes most of it (docs/accuracy.md, Session 37)."""
    cfg = p.config
    loose = np.array([cfg.lens_focal_std] * 2 + [cfg.lens_centre_std] * 2)
    half = interleaved_halves(times, _LENS_BLOCK)[g.lm_hyp[g.obs_lm]]
    found = []
    for k in (0, 1):
        gk = g.without(half != k, cfg)
        out = _solve_graph(p, gk, R, t, marginals=False, tolerance=max(cfg.relative_tolerance, 1e-3), person=person,
                           floor=floor, lens_prior=_lens_stds(len(p.R), p.lenses, loose))
        if isinstance(out, str) or out.lenses is None:
            return None
        found.append(out.lenses)
    spread = []
    for group in (slice(0, 2), slice(2, 4)):
        a, b = found[0][:, group], found[1][:, group]
        both = np.all(np.isfinite(a) & np.isfinite(b), axis=1)
        if both.sum() < 3:
            return None
        # per camera: the mean square of the halves' mean (the lens's square and the noise's) less
        # that of their half difference (the noise's alone: the same lens in both halves)
        z = np.mean(a * b, axis=1)[both]
        shown = z.mean() > 0 and wilcoxon(z, alternative="greater").pvalue < 1.0 - _LENS_LEVEL
        spread.append(float(z.mean()) if shown else 0.0)
    if not any(spread):
        return None
    return np.sqrt(np.repeat(spread, 2))


# the spread is taken as shown at this level; one shown by chance is about the halves' noise, a
# tight prior. Four cameras can never show one (1/16 at best): a room's four, their lenses
# estimated on a spread of chance (0.7 %), went 0.0289 -> 0.0382 m shape.
_LENS_LEVEL = 0.95
_LENS_BLOCK = 10.0  # s: the halves' blocks, far longer than the detector noise's correlation (0.3 s)
# a parameter the data show no spread of is held at its file's value by this std
_LENS_HELD = 1e-5


def _lens_stds(C: int, cams: Sequence[int], std: np.ndarray | None) -> np.ndarray | None:
    """(C, 4) lens prior std per camera: ``std`` (4,) for ``cams``, NaN (no lens variable)
    for the others; None when ``std`` is."""
    if std is None:
        return None
    out = np.full((C, 4), np.nan)
    out[list(cams)] = std
    return out


def _with_lens_accuracy(p: Problem, g: Graph, out: "_Solved", person: np.ndarray | None, floor: Floor | None,
                        lens_prior: np.ndarray | None) -> np.ndarray | None:
    """(C, 6, 6) ``out``'s shape covariance with the errors of the lens parameters it held
    at their files, of ``optimize.lens_accuracy_*`` std, considered (Schmidt's consider
    covariance: what such errors would move the solution by, added to its noise's; a
    parameter the solve estimated is in its marginals already; one the data showed no
    spread of was held), at the solution, not a solve again. The
    projections hardly tell a focal length from the camera's distance to the people, nor
    a principal point from the camera's turn, and the files' errors move the poses as
    much as the keypoints' noise or more (docs/accuracy.md, Session 39). None when there
    is nothing to add, or the marginals fail."""
    cfg = p.config
    acc = np.array([cfg.lens_accuracy_focal] * 2 + [cfg.lens_accuracy_centre] * 2)
    if not p.marginals or out.cov_shape is None or not acc.any():
        return None
    C = len(p.R)
    consider = np.repeat(acc[None], C, axis=0)
    g_at = replace(g, landmarks=out.landmarks)
    m = _solve_graph(p, g_at, out.R, out.t, marginals=True, person=person, floor=floor, lens_prior=lens_prior,
                     lens_at=out.lenses, iterate=False, consider=consider)
    if isinstance(m, str) or m.reason or m.cov_shape is None:
        return None
    return m.cov_shape


def _considered(marg, poses: list[int], lenses: list[int], estimated: np.ndarray, std: np.ndarray,
                gtsam) -> np.ndarray:
    """(6N, 6N) the joint covariance of the poses (N keys) when of the ``lenses``' (K keys)
    parameters (Cal3_S2's fx, fy, skew, u0, v0) only the ``estimated`` (5K,) bool were
    estimated with them and the others held at their files, though off them by ``std``
    (5K,): Λ_ee⁻¹ + Λ_ee⁻¹ Λ_eh Σ Λ_he Λ_ee⁻¹ from the joint information Λ of all of them
    (the landmarks marginalised; e: the estimated, h: the held)."""
    keys = poses + lenses
    info = marg.jointMarginalInformation(gtsam.KeyVector(keys))
    M = np.block([[info.at(a, b) for b in keys] for a in keys])
    est = np.r_[np.ones(6 * len(poses), bool), estimated]
    A, B = M[np.ix_(est, est)], M[np.ix_(est, ~est)]
    sd = std[~estimated]
    Ainv = np.linalg.inv(A)
    G = Ainv @ B
    cov = Ainv + G @ (sd[:, None] ** 2 * G.T)
    return cov[:6 * len(poses), :6 * len(poses)]


def _consider_parts(with_lens: np.ndarray, lensed: np.ndarray, prior: np.ndarray, consider: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """For ``_considered``: of the cameras ``with_lens`` (C,) bool, which lens parameters
    (5 each, Cal3_S2's order) the solve estimated (``lensed`` (C,) cameras, those with a
    prior (C, 4) beyond the held one) and the std (5 each) of the others' errors
    (``consider`` (C, 4); the skew: none)."""
    est, std = [], []
    for c in np.flatnonzero(with_lens):
        free = lensed[c] & (np.nan_to_num(prior[c]) > 10 * _LENS_HELD)
        est.append(np.r_[free[:2], False, free[2:]])
        std.append(np.r_[np.nan_to_num(consider[c, :2]), 0.0, np.nan_to_num(consider[c, 2:])])
    return np.concatenate(est), np.concatenate(std)


def _solve_graph(p: Problem, g: Graph, R0: np.ndarray, t0: np.ndarray, *, marginals: bool,
                 tolerance: float | None = None, person: np.ndarray | None = None, floor: Floor | None = None,
                 lens_prior: np.ndarray | None = None, lens_at: np.ndarray | None = None,
                 iterate: bool = True, consider: np.ndarray | None = None) -> "_Solved | str":
    """One GTSAM solve of graph g from poses R0, t0; ``person`` (H,) int labels of the
    hypotheses for bone-length factors (None: none), and with them the lower ankles held
    to ``floor`` (None: not). ``lens_prior`` (C, 4), NaN rows = none: the lenses of those
    cameras are variables too, with this prior std about their files' (fx, fy, principal
    point x, y: ``Solution.lenses``), started at ``lens_at`` (C, 4) deviations (None: the
    files'). ``iterate`` False: no optimisation, the marginals at the start. ``consider``
    (C, 4), NaN rows = none: the std of the errors of the lens parameters held at their
    files (a camera's without a prior in ``lens_prior``, and those it holds), which the
    covariances then also carry (``_with_lens_accuracy``). Returns a failure reason (str)
    or the solve."""
    import gtsam

    C, L = len(p.R), len(g.landmarks)
    cams = np.flatnonzero(g.active)
    if len(cams) == 0 or L == 0:
        return NOTHING_TO_SOLVE
    X = lambda c: gtsam.symbol("x", int(c))  # noqa: E731
    Lk = lambda l: gtsam.symbol("l", int(l))  # noqa: E731
    # keys by list lookup: a final batch has ~10^5 observations, and two gtsam.symbol calls
    # each were a tenth of its Python time
    xkey = [X(c) for c in range(C)]
    lkey = [Lk(l) for l in range(L)]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for c in cams:
        values.insert(X(c), gtsam.Pose3(gtsam.Rot3(R0[c]), t0[c]))
        prior = gtsam.Pose3(gtsam.Rot3(p.prior_R[c]), p.prior_t[c])
        cov = 0.5 * (p.prior_cov[c] + p.prior_cov[c].T)
        graph.add(gtsam.PriorFactorPose3(X(c), prior, gtsam.noiseModel.Gaussian.Covariance(cov)))
    for l in range(L):
        values.insert(lkey[l], g.landmarks[l])
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    cfg = p.config
    robust = None
    if cfg.robust == "huber":
        robust = gtsam.noiseModel.mEstimator.Huber.Create(cfg.robust_k)
    elif cfg.robust == "cauchy":
        robust = gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.robust_k)
    Sigma, Robust, Factor = gtsam.noiseModel.Isotropic.Sigma, gtsam.noiseModel.Robust.Create, \
        gtsam.GenericProjectionFactorCal3_S2
    lensed = np.zeros(C, bool)  # cameras whose lens the solve estimates
    kkey: list[int] = []  # their keys, by camera (not built for a cycle's solve)
    with_lens = lensed  # cameras with a lens variable: those, and those only ``consider``ed
    if lens_prior is not None or consider is not None:  # a unit calibration per camera: its deviation from the file
        nan = np.full((C, 4), np.nan)
        lens_prior = nan if lens_prior is None else lens_prior
        consider = nan if consider is None else consider
        assert lens_prior.shape == consider.shape == (C, 4) and (lens_at is None or lens_at.shape == (C, 4))
        kkey = [gtsam.symbol("k", c) for c in range(C)]
        lensed = g.active & np.all(np.isfinite(lens_prior), axis=1)
        with_lens = g.active & (lensed | np.all(np.isfinite(consider), axis=1))
        for c in np.flatnonzero(with_lens):
            # a held lens's prior only keeps the system definite: its errors enter by ``consider``
            sd = np.maximum(lens_prior[c] if lensed[c] else consider[c], _LENS_HELD)
            d = np.zeros(4) if lens_at is None else np.nan_to_num(lens_at[c])
            values.insert(kkey[c], gtsam.Cal3_S2(1.0 + d[0], 1.0 + d[1], 0.0, d[2], d[3]))
            graph.add(gtsam.PriorFactorCal3_S2(kkey[c], K, gtsam.noiseModel.Diagonal.Sigmas(
                np.array([sd[0], sd[1], _LENS_HELD, sd[2], sd[3]]))))
    lensed_list = with_lens.tolist()
    for c, l, xy, s in zip(g.obs_cam.tolist(), g.obs_lm.tolist(), g.obs_xy, g.obs_sigma.tolist()):
        noise = Sigma(2, s)
        if robust is not None:
            noise = Robust(robust, noise)
        if not lensed_list[c]:
            graph.add(Factor(xy, noise, xkey[c], lkey[l], K))
        else:
            graph.add(gtsam.GeneralSFMFactor2Cal3_S2(xy, noise, xkey[c], lkey[l], kkey[c]))
    lengths = _add_bones(graph, g, person, cfg, robust, Lk, gtsam) if person is not None else None
    on_floor = _add_floor(graph, values, g, floor, cfg, robust, Lk, gtsam) if person is not None and floor is not None \
        else []

    initial_error = graph.error(values)
    # Landmarks first, cameras last: the Schur complement of bundle adjustment; with
    # sequential Cholesky about twice as fast as COLAMD + multifrontal on these graphs.
    ordering = gtsam.Ordering()
    for l in range(L):
        ordering.push_back(lkey[l])
    for k in on_floor:
        ordering.push_back(k)
    for c in cams:
        ordering.push_back(X(c))
    for c in np.flatnonzero(with_lens):
        ordering.push_back(kkey[c])
    if on_floor:
        ordering.push_back(FLOOR_KEY)
    if cfg.solver == "lm":
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.max_iterations)
        params.setRelativeErrorTol(tolerance or cfg.relative_tolerance)
        params.setAbsoluteErrorTol(1e-9)
        params.setOrdering(ordering)
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    else:
        params = gtsam.DoglegParams()
        params.setMaxIterations(cfg.max_iterations)
        params.setRelativeErrorTol(cfg.relative_tolerance)
        params.setOrdering(ordering)
        optimizer = gtsam.DoglegOptimizer(graph, values, params)
    try:
        result = optimizer.optimize() if iterate else values
    except RuntimeError as e:  # IndeterminantLinearSystem and friends
        return f"optimizer failed: {_first_line(e)}"
    final_error = graph.error(result)
    if not np.isfinite(final_error):
        return "optimizer diverged (non-finite error)"
    R, t = R0.copy(), t0.copy()
    for c in cams:
        pose = result.atPose3(X(c))
        R[c] = pose.rotation().matrix()
        t[c] = pose.translation()
    lms = np.array([result.atPoint3(k) for k in lkey]).reshape(-1, 3)
    if on_floor:
        T = result.atPose3(FLOOR_KEY)  # floor_T_world: its third row is the plane
        floor = replace(floor, n=T.rotation().matrix()[2].copy(), d=-float(T.translation()[2]))
    held = len(on_floor)
    if lengths is not None:
        lengths = bone_lengths(g, person, lms)
    lenses = None
    if lensed.any():
        lenses = np.full((C, 4), np.nan)
        for c in np.flatnonzero(lensed):
            lenses[c] = result.atCal3_S2(kkey[c]).vector()[[0, 1, 3, 4]] - [1.0, 1.0, 0.0, 0.0]
    out = _Solved(R, t, lms, float(initial_error), float(final_error), int(optimizer.iterations()) if iterate else 0,
                  lengths, held, lenses)
    if not marginals:
        return out
    cov = np.full((C, 6, 6), np.nan)
    cov_shape = cov.copy()
    reason = ""
    # Marginals factor without damping: a landmark seen along nearly one ray, or a camera
    # hanging on a few of them, is singular there though LM solved fine. Drop what GTSAM
    # names and try again, a few times.
    dropped: set[int] = set()
    for _attempt in range(8):
        try:
            marg = gtsam.Marginals(graph, result)
            live = [c for c in cams if X(c) not in dropped]
            if consider is not None:
                J = _considered(marg, [X(c) for c in live], [kkey[c] for c in np.flatnonzero(with_lens)],
                                *_consider_parts(with_lens, lensed, lens_prior, consider), gtsam)
            else:
                joint = marg.jointMarginalCovariance(gtsam.KeyVector([X(c) for c in live]))
                J = np.block([[joint.at(X(a), X(b)) for b in live] for a in live])
            for i, c in enumerate(live):
                cov[c] = J[6 * i:6 * i + 6, 6 * i:6 * i + 6]
            S = shape_covariance(R[live], t[live], J)
            for i, c in enumerate(live):
                cov_shape[c] = S[6 * i:6 * i + 6, 6 * i:6 * i + 6]
            reason = ""
            break
        except RuntimeError as e:
            reason = f"marginals failed: {_first_line(e)}"
            key = _named_key(str(e))
            if key is None or key in dropped:
                break
            dropped.add(key)
            graph = _without_key(graph, key, gtsam)
    return replace(out, cov=cov, cov_shape=cov_shape, reason=reason)


def _bone_instances(g: Graph, person: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bones of the graph's hypotheses that have a person and both landmarks:
    (hypothesis, length index, landmark a, landmark b), each (N,) int."""
    L = len(g.landmarks)
    H = int(g.lm_hyp.max()) + 1 if L else 0
    lm_of = np.full((H, 17), -1, np.int64)
    lm_of[g.lm_hyp, g.lm_joint] = np.arange(L)
    h = np.repeat(np.arange(H), len(BONES))
    kind, a, b = (np.tile(BONES[:, i], H) for i in range(3))
    la, lb = lm_of[h, a], lm_of[h, b]
    ok = (la >= 0) & (lb >= 0) & (person[h] >= 0)
    return h[ok], kind[ok], la[ok], lb[ok]


def bone_lengths(g: Graph, person: np.ndarray, landmarks: np.ndarray | None = None) -> np.ndarray:
    """(K, len(BONE_NAMES)) each person's bone lengths: the median over its hypotheses of
    the distances between the landmarks (default: the graph's), NaN where unseen."""
    X = g.landmarks if landmarks is None else landmarks
    h, kind, la, lb = _bone_instances(g, person)
    K = int(person.max()) + 1 if len(person) else 0
    out = np.full((K, len(BONE_NAMES)), np.nan)
    d = np.linalg.norm(X[la] - X[lb], axis=1)
    who = person[h]
    for k in range(K):
        for j in range(len(BONE_NAMES)):
            m = (who == k) & (kind == j)
            if m.any():
                out[k, j] = float(np.median(d[m]))
    return out


def _add_bones(graph, g: Graph, person: np.ndarray, cfg: OptimizeConfig, robust, Lk, gtsam) -> np.ndarray:
    """A range factor per bone of each hypothesis with a person: its two landmarks
    ``bone_lengths`` apart, ``bone_sigma`` each. Returns the lengths used.

    The lengths are the people's, measured anew before each solve of ``solve``'s rounds
    (block coordinate descent of the same least squares: lengths given the landmarks,
    landmarks and cameras given the lengths). A length variable inside the graph would
    need a Python factor, which made GTSAM's LM ten times slower here; GTSAM's native
    range factors cost next to nothing."""
    lengths = bone_lengths(g, person)
    h, kind, la, lb = _bone_instances(g, person)
    noise = gtsam.noiseModel.Isotropic.Sigma(1, cfg.bone_sigma)
    if robust is not None:
        noise = gtsam.noiseModel.Robust.Create(robust, noise)
    for k, j, a, b in zip(person[h], kind, la, lb):
        graph.add(gtsam.RangeFactor3(Lk(a), Lk(b), float(lengths[k, j]), noise))
    return lengths


FLOOR_KEY = ord("f") << 56  # gtsam.symbol("f", 0), without importing gtsam here


def _add_floor(graph, values, g: Graph, floor: Floor, cfg: OptimizeConfig, robust, Lk, gtsam) -> list[int]:
    """The floor as a variable of the solve, started at ``floor``: a pose floor_T_world
    (``FLOOR_KEY``), and per hypothesis' lower ankle (``floor.held_ankles``) a point in the
    floor's frame tied to its landmark, whose height is 0 with ``floor_sigma`` (robust) and
    free along the floor. A variable, not a plane held fixed: the plane turns with the
    network at no cost, so holding the ankles to it cannot turn the network. Returns the
    keys of the floor-frame points, for the ordering (the floor's own key goes last)."""
    held = held_ankles(g.landmarks, g.lm_hyp, g.lm_joint, floor)
    if not len(held):
        return []
    n = floor.n
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    Rf = np.stack([a, np.cross(n, a), n])  # rows: the floor's axes in the world
    T = gtsam.Pose3(gtsam.Rot3(Rf), -Rf @ (floor.d * n))
    values.insert(FLOOR_KEY, T)
    # barely held anywhere: it is the ankles' plane (in-plane shifts and turns are free)
    graph.add(gtsam.PriorFactorPose3(FLOOR_KEY, T, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([1.0, 1.0, 1.0, 10.0, 10.0, 10.0]))))
    tie = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    # height 0 with floor_sigma; free along the floor: 100 m there keeps the matrix definite
    level = gtsam.noiseModel.Diagonal.Sigmas(np.array([100.0, 100.0, cfg.floor_sigma]))
    if robust is not None:
        level = gtsam.noiseModel.Robust.Create(robust, level)
    keys = []
    for i, l in enumerate(held.tolist()):
        k = gtsam.symbol("a", i)
        x = T.transformFrom(g.landmarks[l])
        values.insert(k, x)
        graph.add(gtsam.ReferenceFrameFactorPoint3Pose3(Lk(l), FLOOR_KEY, k, tie))
        graph.add(gtsam.PriorFactorPoint3(k, np.array([x[0], x[1], 0.0]), level))
        keys.append(k)
    return keys


def _named_key(message: str) -> int | None:
    """The key in GTSAM's 'Indeterminant linear system ... near variable x12' message."""
    import re

    import gtsam

    m = re.search(r"Symbol: ([a-z])(\d+)", message) or re.search(r"variable ([a-z])(\d+)", message)
    if not m:
        return None
    return int(gtsam.symbol(m.group(1), int(m.group(2))))


def _without_key(graph, key: int, gtsam):
    """The graph without the factors on ``key``: the variable drops out of the marginals
    (a camera left out keeps NaN covariance), the rest can be computed."""
    out = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        f = graph.at(i)
        if f is not None and key not in list(f.keys()):
            out.add(f)
    return out


def shape_covariance(R: np.ndarray, t: np.ndarray, joint: np.ndarray) -> np.ndarray:
    """Joint pose covariance with the 7 similarity gauge directions projected out.

    R: (K, 3, 3), t: (K, 3) poses; joint: (6K, 6K) covariance in GTSAM's body-frame
    tangent (rotation, translation) per camera. The data see the cameras' shape, not
    where the world is: this is the uncertainty of the shape (what a similarity-aligned
    error measures), without the frame's uncertainty, which only the priors bound.
    """
    K = len(R)
    assert joint.shape == (6 * K, 6 * K)
    G = np.zeros((6 * K, 7))
    for k in range(K):
        Rt = R[k].T
        tx = np.array([[0, -t[k, 2], t[k, 1]], [t[k, 2], 0, -t[k, 0]], [-t[k, 1], t[k, 0], 0]])
        G[6 * k:6 * k + 3, 0:3] = Rt  # world rotation ω seen in the body frame
        G[6 * k + 3:6 * k + 6, 0:3] = -Rt @ tx  # ω × t moves the centre
        G[6 * k + 3:6 * k + 6, 3:6] = Rt  # world translation
        G[6 * k + 3:6 * k + 6, 6] = Rt @ t[k]  # scale about the origin
    if centres_fix_rotation(t):
        P = np.eye(6 * K) - G @ np.linalg.pinv(G)
    else:
        # two cameras (or all on one line) leave a turn about their line to the
        # orientations, as evaluate.align_poses does: the gauge's turn is taken out of
        # the orientations and its shift and scale out of the centres; projected out
        # unweighed, their relative translation went into the orientations (std 0.06 mm)
        w = np.tile(np.r_[np.ones(3), np.full(3, 1e-6)], K)
        Gw = G * w[:, None]
        P = np.eye(6 * K) - G @ np.linalg.pinv(G.T @ Gw) @ Gw.T
    return P @ joint @ P.T


def _first_line(e: BaseException) -> str:
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return (lines[0] if lines else type(e).__name__)[:200]
