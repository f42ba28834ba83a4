"""Person hypotheses across views (the paper's association, plus a reprojection gate).

Each detection's torso size bounds its depth for persons of 1.70-2.00 m in any
orientation; its torso-centre ray cut to that interval is a 3D line segment. Detections
are grouped greedily by the closest-point distance of their segments (closest pairs
first, complete linkage below ``max_distance``, at most one detection per camera). Once
the camera poses are known well, every view of a hypothesis must also reproject its
torso within a gate, which splits wrong associations that segments alone allow.

A hypothesis of two views has no third to show a wrong one: two people, each seen by
one camera only (one walked out of the other's view, or behind someone), pair up
whenever their torso rays pass within ``max_distance``, and a solve explains them by
bending the cameras (in a chain, by a link's scale). Their joints then miss each other's
epipolar lines, which need only the cameras' relative rotation and baseline direction,
not the scale; such pairs are dropped once the poses are known well enough to tell.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .config import AssociateConfig
from .geometry import closest_points_segments, hat, triangulate_batch, triangulate_views
from .preprocess import L_HIP, L_SHOULDER, R_HIP, R_SHOULDER, TORSO, Detection


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """One person at one instant, seen by >= 2 cameras.

    cams: (V,) int camera indices, distinct.
    xy: (V, 17, 2) float64 undistorted normalised coordinates, NaN = missing.
    sigma: (V, 17) float64 normalised std (pixel std / focal), NaN = missing.
    com: (3,) float64 centre of mass (torso centre) in the world.
    """

    time: float
    cams: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    com: np.ndarray

    def __post_init__(self) -> None:
        V = len(self.cams)
        assert V >= 2 and self.xy.shape == (V, 17, 2) and self.sigma.shape == (V, 17)
        assert self.com.shape == (3,)


def depth_interval(xy: np.ndarray, cfg: AssociateConfig) -> tuple[float, float]:
    """Depth range (along the optical axis) of a person from its torso in normalised
    coordinates xy (17, 2).

    An image length l of a body segment of length L at depth d is at most L/d
    (foreshortening only shrinks), so d <= L_max/l for each segment. The torso is
    perpendicular to the shoulder and hip lines, so their foreshortenings cannot both be
    large: (l_t d/L_t)² + (l_w d/L_w)² >= 1, which bounds d from below with L_min.
    A width whose far joint is hidden (``PreprocessConfig.partial_torso``) bounds nothing.
    """
    sh = np.linalg.norm(xy[L_SHOULDER] - xy[R_SHOULDER])
    hp = np.linalg.norm(xy[L_HIP] - xy[R_HIP])
    to = np.linalg.norm(np.nanmean(xy[[L_SHOULDER, R_SHOULDER]], 0) - np.nanmean(xy[[L_HIP, R_HIP]], 0))
    eps = 1e-6
    lo_h, hi_h = cfg.min_height, cfg.max_height
    d_max = min(cfg.shoulders_ratio * hi_h / max(sh, eps) if np.isfinite(sh) else np.inf,
                cfg.hips_ratio * hi_h / max(hp, eps) if np.isfinite(hp) else np.inf,
                cfg.torso_ratio * hi_h / max(to, eps))
    lows = [1.0 / np.sqrt((to / (cfg.torso_ratio * lo_h)) ** 2 + (w / (r * lo_h)) ** 2 + eps)
            for w, r in ((sh, cfg.shoulders_ratio), (hp, cfg.hips_ratio)) if np.isfinite(w)]
    # One side hidden (a profile view): no width, and the torso alone bounds nothing from
    # below, since a camera looking steeply down sees it end-on (a lower bound of half the
    # torso's unforeshortened depth missed 2.5 % of such persons)
    d_min = max(lows) if lows else 0.0
    # Off the optical axis a segment can look longer than L/d by up to sqrt(1 + |x|²)
    # (it faces the ray, not the image plane): widen the upper bound by that much.
    c = torso_centre(xy)
    d_max *= float(np.sqrt(1.0 + c @ c))
    m = cfg.depth_margin
    d_min, d_max = d_min * (1 - m), d_max * (1 + m)
    if d_min > d_max:  # noisy keypoints: keep an interval around the geometric mean
        c = np.sqrt(d_min * d_max)
        d_min, d_max = c * (1 - m), c * (1 + m)
    return float(max(d_min, 0.1)), float(max(d_max, 0.2))


def _cluster(dist: np.ndarray, cams: np.ndarray, depth: np.ndarray, limit: float) -> list[list[int]]:
    """Complete-linkage grouping of detections: pairs closest first (nearer persons
    first on ties), two groups merge when every cross pair is within ``limit`` and they
    share no camera.

    The paper walks detections by ascending depth and lets each join the best group
    open at that moment; a near-miss of another person then takes a detection before its
    true partners are seen. Taking the closest pairs first, over the whole frameset,
    does not have that order dependence.
    """
    n = len(dist)
    group = list(range(n))
    members: dict[int, list[int]] = {i: [i] for i in range(n)}
    ii, jj = np.triu_indices(n, 1)
    d = dist[ii, jj]
    ok = d < limit
    ii, jj, d = ii[ok], jj[ok], d[ok]
    for k in np.lexsort((depth[ii] + depth[jj], d)):
        gi, gj = group[ii[k]], group[jj[k]]
        if gi == gj:
            continue
        a, b = members[gi], members[gj]
        if set(cams[a]) & set(cams[b]):
            continue
        if dist[np.ix_(a, b)].max() >= limit:
            continue
        for m in b:
            group[m] = gi
        a.extend(b)
        del members[gj]
    return [sorted(g, key=lambda m: depth[m]) for g in members.values()]


def torso_segments(dets: Sequence[Detection], R: np.ndarray, t: np.ndarray, cfg: AssociateConfig
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each detection's torso-centre ray cut to its depth interval (``depth_interval``):
    the segments' near and far ends (n, 3) in the world and their mid depths (n,)."""
    seg0, seg1, depth = [], [], []
    for d in dets:
        lo, hi = depth_interval(d.xy, cfg)
        c = torso_centre(d.xy)
        dw = R[d.cam] @ np.array([c[0], c[1], 1.0])
        seg0.append(t[d.cam] + lo * dw)
        seg1.append(t[d.cam] + hi * dw)
        depth.append(0.5 * (lo + hi))
    return np.array(seg0).reshape(-1, 3), np.array(seg1).reshape(-1, 3), np.array(depth)


def torso_centre(xy: np.ndarray) -> np.ndarray:
    return np.nanmean(xy[list(TORSO)], 0)


def intersect_rays(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to rays: origins (V, 3), unit dirs (V, 3)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, dirs):
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ o
    return np.linalg.lstsq(A, b, rcond=None)[0]


class Associator:
    """Detections of one frameset → hypotheses, with the current camera poses.

    R: (C, 3, 3) world_R_cam and t: (C, 3) centres are read from ``poses`` at each call.
    """

    def __init__(self, config: AssociateConfig):
        self.cfg = config
        self.rejected: Counter = Counter()
        self.created = 0
        self.followed = 0  # views with one side hidden that joined a hypothesis (``_follow``)

    def __call__(self, time: float, views: Sequence[Sequence[Detection]], R: np.ndarray, t: np.ndarray,
                 gate_px: np.ndarray | None = None, pose_px: np.ndarray | None = None,
                 follow_px: np.ndarray | None = None) -> list[Hypothesis]:
        """gate_px: (C,) px reprojection gate per camera (inf = not gated), or None.
        pose_px: (C,) px one std of how far the cameras' poses may move an image point
        (``Pipeline._pose_px``), for the epipolar test of two-view hypotheses; None: no test.
        follow_px: (C,) px how far a view with one side of the torso hidden may miss the
        torso of a hypothesis to join it (``_follow``; inf = such views of that camera
        are dropped), or None: all such views dropped."""
        dets = [d for v in views for d in v]
        # A view with one side hidden has no width to bound its depth from below: its
        # segment reaches back to its camera and pairs with anyone along its ray. It only
        # follows a hypothesis of whole views, where its camera's pose is known well.
        sides = [d for d in dets if not d.whole_torso]
        if sides:
            dets = [d for d in dets if d.whole_torso]
        if len(dets) < 2:
            self.rejected["side_view_unmatched"] += len(sides)
            return []
        seg0, seg1, depth = torso_segments(dets, R, t, self.cfg)
        n = len(dets)
        ii, jj = np.triu_indices(n, 1)
        dist = np.full((n, n), np.inf)
        dd, _, _ = closest_points_segments(seg0[ii], seg1[ii], seg0[jj], seg1[jj])
        dist[ii, jj] = dd
        dist[jj, ii] = dd
        cams = np.array([d.cam for d in dets])
        dist[cams[:, None] == cams[None, :]] = np.inf

        groups = _cluster(dist, cams, depth, self.cfg.max_distance)
        if sides:
            groups = self._unrivalled(groups, dist, dets, seg0, seg1, sides, R, t)
        out = []
        for g in groups:
            if len(g) < self.cfg.min_views:
                continue
            h = self._hypothesis(time, [dets[k] for k in g], R, t, gate_px, pose_px)
            if h is not None:
                out.append(h)
        if sides:
            out = self._follow(out, sides, R, t, follow_px)
        self.created += len(out)
        return out

    def _unrivalled(self, groups: list[list[int]], dist: np.ndarray, dets: list[Detection], seg0: np.ndarray,
                    seg1: np.ndarray, sides: list[Detection], R: np.ndarray, t: np.ndarray) -> list[list[int]]:
        """``groups`` without the pairs of two views that a view with one side hidden
        rivals: one of the two cameras sees someone else in profile whose segment passes
        closer to the other view's than the pair's own do. The pair was made because the
        profile took no part; it is probably two people, each seen whole by one camera
        (the west room, a camera that sees one walker whole while the other camera sees
        him in profile and the other walker whole: two such pairs turned the camera 0.2°).
        dist: (n, n) the whole views' segment distances, seg0/seg1: (n, 3) their ends."""
        side_cams = np.array([s.cam for s in sides])
        pairs = [i for i, g in enumerate(groups) if len(g) == 2 and np.isin([dets[k].cam for k in g], side_cams).any()]
        if not pairs:
            return groups
        s0, s1, _ = torso_segments(sides, R, t, self.cfg)
        drop = set()
        for i in pairs:
            a, b = groups[i]
            for mine, other in ((a, b), (b, a)):
                near = side_cams == dets[mine].cam
                if near.any():
                    d, _, _ = closest_points_segments(s0[near], s1[near], np.broadcast_to(seg0[other], s0[near].shape),
                                                      np.broadcast_to(seg1[other], s1[near].shape))
                    if d.min() < dist[a, b]:
                        drop.add(i)
        self.rejected["pair_rivalled_by_side_view"] += 2 * len(drop)
        return [g for i, g in enumerate(groups) if i not in drop]

    def _follow(self, hyps: list[Hypothesis], sides: list[Detection], R: np.ndarray, t: np.ndarray,
                follow_px: np.ndarray | None) -> list[Hypothesis]:
        """Each view with one side of the torso hidden joins the hypothesis whose
        triangulated torso its seen torso joints meet best (mean reprojection error, px),
        within ``follow_px`` (C,) of its camera, one view per camera; the hypothesis'
        centre stays that of its whole views. R (C, 3, 3), t (C, 3) as in ``__call__``."""
        # only where its camera is known: before any is (early in a run) nothing to triangulate
        known = [d for d in sides if follow_px is not None and np.isfinite(follow_px[d.cam])]
        if not known or not hyps:
            self.rejected["side_view_unmatched"] += len(sides)
            return hyps
        idx = np.array(TORSO)
        torsos = [triangulate_views(R, t, h.cams, h.xy[:, idx])[0] for h in hyps]
        pairs = []  # (error px, side, hypothesis)
        for i, d in enumerate(known):
            lo, hi = depth_interval(d.xy, self.cfg)
            seen = np.isfinite(d.xy[idx, 0])
            for j, (h, X) in enumerate(zip(hyps, torsos)):
                if d.cam in h.cams or not np.all(np.isfinite(X[seen])):
                    continue
                Xc = (X[seen] - t[d.cam]) @ R[d.cam]  # R^T (X - t)
                if np.any(Xc[:, 2] <= 0.1) or not lo <= float(Xc[:, 2].mean()) <= hi:
                    continue
                err = float(np.linalg.norm(Xc[:, :2] / Xc[:, 2:3] - d.xy[idx[seen]], axis=1).mean() * d.focal)
                if err <= follow_px[d.cam]:
                    pairs.append((err, i, j))
        taken, joined = set(), {}
        for err, i, j in sorted(pairs):
            key = (j, known[i].cam)
            if i in taken or key in joined:
                continue
            taken.add(i)
            joined[key] = known[i]
        self.followed += len(joined)
        self.rejected["side_view_unmatched"] += len(sides) - len(joined)
        if not joined:
            return hyps
        more: dict[int, list[Detection]] = {}
        for (j, _), d in joined.items():
            more.setdefault(j, []).append(d)
        return [Hypothesis(h.time, np.r_[h.cams, [d.cam for d in more[j]]], np.concatenate([h.xy, [d.xy for d in more[j]]]),
                           np.concatenate([h.sigma, [d.sigma / d.focal for d in more[j]]]), h.com) if j in more else h
                for j, h in enumerate(hyps)]

    def _hypothesis(self, time: float, dets: list[Detection], R: np.ndarray, t: np.ndarray,
                    gate_px: np.ndarray | None, pose_px: np.ndarray | None = None) -> Hypothesis | None:
        cams = np.array([d.cam for d in dets])
        xy = np.stack([d.xy for d in dets])
        sigma = np.stack([d.sigma / d.focal for d in dets])
        centres = np.array([torso_centre(d.xy) for d in dets])
        origins = t[cams]
        dirs = np.einsum("vij,vj->vi", R[cams], np.c_[centres, np.ones(len(dets))])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        com = intersect_rays(origins, dirs)
        if gate_px is not None and np.any(np.isfinite(gate_px[cams])):
            # Reprojection gate: drop views whose torso centre misses the joint estimate by
            # more than the gate (in pixels), re-estimating after each removal.
            focal = np.array([d.focal for d in dets])
            keep = np.ones(len(dets), bool)
            while keep.sum() >= self.cfg.min_views:
                Xc = np.einsum("vji,vj->vi", R[cams], com - origins)  # R^T (X - t)
                behind = Xc[:, 2] <= 0.1
                proj = Xc[:, :2] / np.where(behind, 1.0, Xc[:, 2])[:, None]
                err = np.linalg.norm(proj - centres, axis=1) * focal
                err[behind] = np.inf
                with np.errstate(invalid="ignore"):  # inf / inf: not gated
                    excess = np.nan_to_num(err / gate_px[cams], nan=0.0)
                excess[~keep] = -1
                worst = int(np.argmax(excess))
                if excess[worst] <= 1.0:
                    break
                keep[worst] = False
                self.rejected["reprojection_gate"] += 1
                if keep.sum() >= 2:
                    com = intersect_rays(origins[keep], dirs[keep])
            if keep.sum() < self.cfg.min_views:
                self.rejected["gate_too_few_views"] += 1
                return None
            cams, xy, sigma = cams[keep], xy[keep], sigma[keep]
            dets = [d for d, k in zip(dets, keep) if k]
        if pose_px is not None and len(dets) == 2 and self.cfg.epipolar_sigmas > 0:
            miss = epipolar_miss(dets[0], dets[1], R, t)
            if miss is not None and miss[0] > self.cfg.epipolar_sigmas * miss[1] + 2.0 * float(
                    np.hypot(pose_px[dets[0].cam], pose_px[dets[1].cam])):
                self.rejected["epipolar"] += 1
                return None
        # A centre behind any of its cameras is a wrong association, not a person.
        Xc = np.einsum("vji,vj->vi", R[cams], com - t[cams])
        if np.any(Xc[:, 2] <= 0):
            self.rejected["behind_camera"] += 1
            return None
        return Hypothesis(time, cams, xy, sigma, com)


def epipolar_miss(a: Detection, b: Detection, R: np.ndarray, t: np.ndarray) -> tuple[float, float] | None:
    """How far the joints of two views of one person miss each other's epipolar lines
    with poses R (C, 3, 3), t (C, 3): (median over the joints both see of the mean of the
    two distances, px; median of the joints' noise on that distance, px, from their
    stds), or None with fewer than 4 joints in common."""
    both = np.isfinite(a.xy[:, 0]) & np.isfinite(b.xy[:, 0])
    if both.sum() < 4:
        return None
    R_ab = R[b.cam].T @ R[a.cam]  # a's camera frame into b's
    t_ab = R[b.cam].T @ (t[a.cam] - t[b.cam])
    n = np.linalg.norm(t_ab)
    if n < 1e-9:
        return None
    E = hat(t_ab / n) @ R_ab  # x_b^T E x_a = 0
    xa = np.c_[a.xy[both], np.ones(both.sum())]
    xb = np.c_[b.xy[both], np.ones(both.sum())]
    la, lb = xb @ E, xa @ E.T  # a's lines in a, b's lines in b
    alg = np.abs(np.einsum("ij,ij->i", xb, lb))
    with np.errstate(divide="ignore", invalid="ignore"):
        miss = 0.5 * (alg / np.linalg.norm(lb[:, :2], axis=1) * b.focal + alg / np.linalg.norm(la[:, :2], axis=1) * a.focal)
    noise = np.hypot(a.sigma[both], b.sigma[both])
    ok = np.isfinite(miss) & np.isfinite(noise)
    if ok.sum() < 4:
        return None
    return float(np.median(miss[ok])), float(np.median(noise[ok]))


def triangulate_hypotheses(hyps: Sequence[Hypothesis], R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(H, 17, 3) every hypothesis' joints triangulated with poses R (C, 3, 3), t (C, 3)
    in one batched DLT; NaN where a joint is seen in fewer than two views."""
    H = len(hyps)
    if H == 0:
        return np.zeros((0, 17, 3))
    V = max(len(h.cams) for h in hyps)
    cams = np.zeros((H, V), np.int64)
    xy = np.full((H, V, 17, 2), np.nan)
    for i, h in enumerate(hyps):
        cams[i, :len(h.cams)], xy[i, :len(h.cams)] = h.cams, h.xy
    return triangulate_batch(R, t, np.repeat(cams, 17, axis=0),
                             xy.transpose(0, 2, 1, 3).reshape(H * 17, V, 2)).reshape(H, 17, 3)


def triangulate_torso(h: Hypothesis, R: np.ndarray, t: np.ndarray, focal: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """Torso joints of a hypothesis triangulated with poses R (C, 3, 3), t (C, 3), and
    each view's mean torso reprojection error in px (V,); (None, []) if untriangulable."""
    idx = list(TORSO)
    X, _ = triangulate_views(R, t, h.cams, h.xy[:, idx])
    if not np.all(np.isfinite(X)):
        return None, np.zeros(0)
    Rt = np.transpose(R[h.cams], (0, 2, 1))
    Xc = np.einsum("vij,vkj->vki", Rt, X[None] - t[h.cams][:, None])  # (V, 4, 3)
    proj = Xc[..., :2] / Xc[..., 2:3]
    err = np.linalg.norm(proj - h.xy[:, idx], axis=2).mean(1) * focal[h.cams]
    return X, np.where(np.all(Xc[..., 2] > 0, axis=1), err, np.inf)
