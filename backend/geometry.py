"""Rotations, rigid/similarity transforms and alignment, in plain numpy.

Conventions: quaternions are (x, y, z, w); a pose (R, t) maps camera to world
(``X_w = R @ X_c + t``), so ``t`` is the optical centre. Tangent vectors of SE(3)
are ordered (rotation ω, translation ρ) like GTSAM's Pose3.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


def quat_to_R(q) -> np.ndarray:
    """(4,) quaternion x, y, z, w (normalised here) → (3, 3) rotation."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation → (4,) unit quaternion x, y, z, w with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def hat(w) -> np.ndarray:
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w) -> np.ndarray:
    """(3,) rotation vector → (3, 3) rotation (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    th = np.linalg.norm(w)
    K = hat(w)
    if th < 1e-10:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def project_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) the (3, 3) matrix M: a sum of rotations' chordal
    mean, or a Procrustes problem's solution."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation → (3,) rotation vector, robust near 0 and π."""
    R = np.asarray(R, dtype=np.float64)
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-7:
        return 0.5 * v
    if np.pi - th < 1e-4:
        # Near π the antisymmetric part vanishes; take the axis from the symmetric part.
        B = (R + np.eye(3)) / 2
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], 1e-300))
        axis /= np.linalg.norm(axis)
        if np.dot(axis, v) < 0:
            axis = -axis
        return th * axis
    return th / (2 * np.sin(th)) * v


def pose_std(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One std of poses with covariance P (..., 6, 6) (tangent: rotation, then
    translation): the RMS over the three axes, (m, rad), each of shape (...)."""
    assert P.shape[-2:] == (6, 6)
    st = np.sqrt(np.maximum(np.trace(P[..., 3:, 3:], axis1=-2, axis2=-1) / 3, 0))
    sr = np.sqrt(np.maximum(np.trace(P[..., :3, :3], axis1=-2, axis2=-1) / 3, 0))
    return st, sr


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Shortest-arc angle between two rotations, degrees.

    atan2(sin, cos) of the relative rotation: arccos of the trace alone loses half the
    digits near 0 (identical rotations came out ~1e-6° apart)."""
    R = np.asarray(Ra).T @ np.asarray(Rb)
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (np.trace(R) - 1) / 2
    return float(np.degrees(np.arctan2(s, c)))


def _left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    K = hat(w)
    if th < 1e-8:
        return np.eye(3) + 0.5 * K
    return (
        np.eye(3)
        + (1 - np.cos(th)) / th**2 * K
        + (th - np.sin(th)) / th**3 * K @ K
    )


def se3_exp(xi) -> tuple[np.ndarray, np.ndarray]:
    """(6,) tangent (ω, ρ) → (R, t), GTSAM's Pose3.Expmap convention."""
    xi = np.asarray(xi, dtype=np.float64)
    w, rho = xi[:3], xi[3:]
    return so3_exp(w), _left_jacobian_so3(w) @ rho


def se3_log(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(R, t) → (6,) tangent (ω, ρ), inverse of se3_exp."""
    w = so3_log(R)
    return np.concatenate([w, np.linalg.solve(_left_jacobian_so3(w), t)])


def pose_compose(Ra, ta, Rb, tb) -> tuple[np.ndarray, np.ndarray]:
    return Ra @ Rb, Ra @ tb + ta


def pose_inverse(R, t) -> tuple[np.ndarray, np.ndarray]:
    return R.T, -R.T @ t


def pose_retract(R, t, xi) -> tuple[np.ndarray, np.ndarray]:
    """Right perturbation (GTSAM's Pose3.retract with Expmap): pose ⊕ exp(ξ)."""
    dR, dt = se3_exp(xi)
    return pose_compose(R, t, dR, dt)


def pose_local(Ra, ta, Rb, tb) -> np.ndarray:
    """ξ with a ⊕ exp(ξ) = b (GTSAM's Pose3.localCoordinates with Logmap)."""
    Ri, ti = pose_inverse(Ra, ta)
    R, t = pose_compose(Ri, ti, Rb, tb)
    return se3_log(R, t)


def from_prior(R0: np.ndarray, t0: np.ndarray, P: np.ndarray, R: np.ndarray, t: np.ndarray
               ) -> tuple[float, float, float]:
    """How far pose R (3, 3), t (3,) lies from the prior pose R0, t0 with tangent
    covariance P (6, 6): (m between the centres, deg, Mahalanobis χ² with 6 dof; NaN for
    a singular P)."""
    delta = pose_local(R0, t0, R, t)
    try:
        chi2 = float(delta @ np.linalg.solve(P, delta))
    except np.linalg.LinAlgError:
        chi2 = float("nan")
    return float(np.linalg.norm(t - t0)), float(np.degrees(np.linalg.norm(delta[:3]))), chi2


def project_normalised(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) normalised projections of world points X (N, 3) (in front of the camera) by
    the pose R (3, 3), t (3,) (world_R_cam, optical centre), and (N, 2, 6) their Jacobian
    w.r.t. the pose's right perturbation (rotation, translation in the camera frame;
    ``pose_retract``)."""
    Xc = (X - t) @ R  # R^T (X - t), row-wise
    z = Xc[:, 2]
    uv = Xc[:, :2] / z[:, None]
    dproj = np.zeros((len(X), 2, 3))
    dproj[:, 0, 0] = 1 / z
    dproj[:, 1, 1] = 1 / z
    dproj[:, :, 2] = -uv / z[:, None]
    # Xc' = exp(-ω) (Xc - v): dXc/dω = hat(Xc), dXc/dv = -I
    dXc = np.concatenate([hat_batch(Xc), np.broadcast_to(-np.eye(3), (len(X), 3, 3))], axis=2)
    return uv, dproj @ dXc


def hat_batch(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) skew matrices of (N, 3) vectors."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def centres_fix_rotation(centres: np.ndarray) -> bool:
    """Whether points (N, 3) (camera centres) fix a rotation: three or more, not all on
    one line (two, or a line, leave any turn about the line free)."""
    c = np.asarray(centres, dtype=np.float64)
    if len(c) < 3:
        return False
    sv = np.linalg.svd(c - c.mean(0), compute_uv=False)
    return bool(sv[1] > 1e-6 * max(sv[0], 1e-12))


def umeyama(src: np.ndarray, dst: np.ndarray, *, with_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares (s, R, t) with dst ≈ s·R·src + t.

    src, dst: (N, 3) float64, N >= 3 non-collinear points (Umeyama 1991).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    assert src.shape == dst.shape and src.ndim == 2 and src.shape[1] == 3 and len(src) >= 3
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def trimmed_similarity(src: np.ndarray, dst: np.ndarray, *, floor: float = 0.05, min_distance: float = 0.2
                       ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
    """Robust (s, R, t, keep) with dst ≈ s·R·src + t over the points kept.

    src, dst: (N, 3) float64 (camera centres), N >= 3; keep: (N,) bool. A robust start
    (the median ratio of pairwise distances, pairs closer than ``min_distance`` in either
    set left out: co-located points say nothing about scale), a rigid fit, then up to 3
    rounds of: points whose residual exceeds 3x the median of the kept ones (and
    ``floor``) are left out, least squares with scale on the rest (one point metres off
    would otherwise rescale and turn everyone). None when no pair is far enough apart."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    assert src.shape == dst.shape and src.ndim == 2 and src.shape[1] == 3 and len(src) >= 3
    i, j = np.triu_indices(len(src), 1)
    d = np.linalg.norm(src[i] - src[j], axis=1)
    d0 = np.linalg.norm(dst[i] - dst[j], axis=1)
    ok = (d > min_distance) & (d0 > min_distance)
    if not ok.any():
        return None
    s = float(np.median(d0[ok] / d[ok]))
    _, R, tr = umeyama(s * src, dst, with_scale=False)
    s, R, tr = _least_median_start(src, dst, s, R, tr, min_distance)
    keep = np.ones(len(src), bool)
    for _ in range(3):
        res = np.linalg.norm(s * src @ R.T + tr - dst, axis=1)
        fit = res <= max(3.0 * float(np.median(res[keep])), floor)
        if fit.sum() < 3:
            break
        keep = fit
        s, R, tr = umeyama(src[keep], dst[keep], with_scale=True)
    return s, R, tr, keep


_LMEDS_TRIES = 300  # three-point fits ``_least_median_start`` tries (all of them up to 13 points)
_LMEDS_MIN_POINTS = 7  # ... of at least this many points (a median of four others at least)


def _least_median_start(src: np.ndarray, dst: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
                        min_distance: float) -> tuple[float, np.ndarray, np.ndarray]:
    """``trimmed_similarity``'s start (s, R, t), or the similarity through three of the
    points (N, 3) with the least median residual over the others when that median is under
    half the start's (over all; 7 points or more). A fit to all points is pulled by a block
    of points metres off: a room the bootstrap chained through a wrong pair put a quarter of
    the lab's cameras 6-15 m off while the others were 0.75 m; the start's median residual
    was 3.4 m, and trimming at 3x the median kept them all. The median over the others is
    the majority's. Where the start is sound no three points beat it by half, and it stays
    as it was."""
    N = len(src)
    if N < _LMEDS_MIN_POINTS:
        return s, R, t
    start = float(np.median(np.linalg.norm(s * src @ R.T + t - dst, axis=1)))
    if math.comb(N, 3) <= _LMEDS_TRIES:
        tri = np.array(list(itertools.combinations(range(N), 3)))
    else:
        rng = np.random.default_rng(N)
        tri = np.array([rng.choice(N, 3, replace=False) for _ in range(_LMEDS_TRIES)])
    a, b = src[tri], dst[tri]  # (T, 3, 3): each three's points
    # spread enough to hold a turn: not co-located, not (nearly) on a line
    sides = np.linalg.norm(a[:, [0, 0, 1]] - a[:, [1, 2, 2]], axis=2).min(1)
    area = np.linalg.norm(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]), axis=1)
    # Umeyama's fit of every three at once (as ``umeyama``)
    mu_a, mu_b = a.mean(1), b.mean(1)
    xa, xb = a - mu_a[:, None], b - mu_b[:, None]
    U, S, Vt = np.linalg.svd(np.einsum("tni,tnj->tij", xb, xa) / 3)
    D = np.ones((len(tri), 3))
    D[:, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    Rk = U @ (D[:, :, None] * Vt)
    var = (xa ** 2).sum((1, 2)) / 3
    sk = (S * D).sum(1) / np.where(var > 0, var, 1.0)  # three points in one: no scale, and not taken (sides)
    tk = mu_b - sk[:, None] * np.einsum("tij,tj->ti", Rk, mu_a)
    res = np.linalg.norm(sk[:, None, None] * np.einsum("tij,nj->tni", Rk, src) + tk[:, None] - dst[None], axis=2)
    # over the other points: the three fit themselves, and of few points they are the median
    res[np.arange(len(tri))[:, None], tri] = np.nan
    med = np.nanmedian(res, axis=1)
    med[~((sides > min_distance) & (area > min_distance ** 2) & (sk > 0) & np.isfinite(med))] = np.inf
    k = int(np.argmin(med))
    if med[k] < start / 2:
        return float(sk[k]), Rk[k], tk[k]
    return s, R, t


@dataclass(frozen=True)
class AlignedPoses:
    """Camera poses of one estimate mapped onto another's frame (``align_poses``).

    s, Rw (3, 3), tw (3,): the similarity (dst ≈ s·Rw·src + tw); keep (N,) bool: the
    cameras it was fitted on; R (N, 3, 3), t (N, 3): the src poses in dst's frame;
    dt (N,) m (dst's units) and dr (N,) deg: each camera's distance from its dst pose."""

    s: float
    Rw: np.ndarray
    tw: np.ndarray
    keep: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dt: np.ndarray
    dr: np.ndarray


def within_std(dt: np.ndarray, dr: np.ndarray, st: np.ndarray, sr: np.ndarray, floor_t: float, floor_r: float,
               k: float = 3.0) -> np.ndarray:
    """(N,) bool: pose differences dt (N,) m / dr (N,) deg within ``k`` times their std
    st (N,) / sr (N,), or within ``floor_t`` / ``floor_r`` where that is more (a std of
    millimetres does not make 2 cm a disagreement); a NaN difference is not within, a NaN
    std counts as 0."""
    tol_t = np.fmax(floor_t, k * np.nan_to_num(st, nan=0.0))
    tol_r = np.fmax(floor_r, k * np.nan_to_num(sr, nan=0.0))
    return (np.nan_to_num(dt, nan=np.inf) <= tol_t) & (np.nan_to_num(dr, nan=np.inf) <= tol_r)


def align_poses(R_src: np.ndarray, t_src: np.ndarray, R_dst: np.ndarray, t_dst: np.ndarray,
                use: np.ndarray | None = None, *, orientations: bool = False) -> AlignedPoses | None:
    """The src poses (N, 3, 3), (N, 3) (world-from-camera rotations, centres) aligned onto
    the dst poses of the same N cameras by ``trimmed_similarity`` of the centres (of the
    cameras ``use`` (N,) bool, default all), with the per-camera differences; None when
    the centres give no similarity. ``orientations``: where the centres hold the turn
    less firmly than the orientations do (cameras along a corridor leave the turn about
    it to their few decimetres sideways), the turn is fitted to both (``_joint_turn``)."""
    assert R_src.shape == R_dst.shape and t_src.shape == t_dst.shape and len(t_src) == len(R_src)
    use = np.ones(len(t_src), bool) if use is None else use
    fit = trimmed_similarity(t_src[use], t_dst[use])
    if fit is None:
        return None
    s, Rw, tw, kept = fit
    keep = np.zeros(len(t_src), bool)
    keep[np.flatnonzero(use)[kept]] = True
    if orientations:
        s, Rw, tw = _joint_turn(s, Rw, tw, R_src[keep], t_src[keep], R_dst[keep], t_dst[keep])
    R = np.einsum("ij,cjk->cik", Rw, R_src)
    t = s * t_src @ Rw.T + tw
    dr = np.array([rotation_angle_deg(R[i], R_dst[i]) for i in range(len(R))])
    return AlignedPoses(s, Rw, tw, keep, R, t, np.linalg.norm(t - t_dst, axis=1), dr)


LOOSE_TURN_DEG = 5.0  # deg: std of the centres' turn about an axis beyond which orientations may hold it


def _joint_turn(s: float, Rw: np.ndarray, tw: np.ndarray, R_src: np.ndarray, t_src: np.ndarray, R_dst: np.ndarray,
                t_dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, Rw, tw) fitted to the centres (N, 3), refitted to the centres
    and the orientations (N, 3, 3) together when the centres' layout leaves some axis of
    the turn loose, the orientations hold it better, and both agree about the other axes
    (each term weighted by its own scatter about its own fit, the orientations trimmed at
    3x their median turn); else unchanged. An estimate whose orientations are all turned
    alike (a convention mixed up) has centres that hold every axis: it keeps the centres'
    fit."""
    from scipy.stats import chi2

    if len(t_src) < 3:
        return s, Rw, tw
    x = t_src - t_src.mean(0)
    var_t = max(float(np.mean(np.sum((s * t_src @ Rw.T + tw - t_dst) ** 2, axis=1))) / 3, 1e-6)
    Q = np.einsum("nij,nkj->nik", R_dst, R_src)  # each camera's dst_R_src
    Ro = project_so3(Q.sum(0))
    ang = np.array([np.radians(rotation_angle_deg(Ro, q)) for q in Q])
    ok = ang <= max(3.0 * float(np.median(ang)), np.radians(1.0))
    var_r = max(float(np.mean(ang[ok] ** 2)) / 3, np.radians(0.1) ** 2)
    xr = x @ Rw.T  # turns are taken in dst's frame: Rw -> exp(w) Rw
    S = xr.T @ xr
    info_t, axes = np.linalg.eigh(s * s * (np.trace(S) * np.eye(3) - S) / var_t)  # the centres' information
    info_r = ok.sum() / var_r
    # an axis is the orientations' only where the centres' layout leaves it loose (its std
    # 5x the best axis' and above LOOSE_TURN_DEG: a line of cameras) and the orientations
    # hold it better. Elsewhere the centres' fit is kept: orientations turned alike (a
    # convention mixed up) cannot turn the frame, nor can centres that are loose only
    # because many are wrong (swapped cameras) pass the frame to the orientations
    strong = (info_t >= info_r) | (info_t >= np.radians(LOOSE_TURN_DEG) ** -2) | (info_t >= info_t[-1] / 25)
    if strong.all():
        return s, Rw, tw
    # about the axes the centres do hold, the orientations' turn must agree with theirs
    # (p = 0.001): orientations turned alike by a convention agree among themselves only
    d = axes[:, strong].T @ so3_log(Ro @ Rw.T)
    if np.sum(d**2 / (1.0 / info_t[strong] + 1.0 / info_r)) > chi2.ppf(0.999, int(strong.sum())):
        return s, Rw, tw
    y = t_dst - t_dst.mean(0)
    for _ in range(3):  # maximise tr(Rw^T M): the centres' and the orientations' Procrustes terms
        Rw = project_so3((s / var_t) * y.T @ x + Q[ok].sum(0) / (2 * var_r))
        s = float(np.sum(y * (x @ Rw.T)) / max(np.sum(x * x), 1e-12))
    return s, Rw, t_dst.mean(0) - s * Rw @ t_src.mean(0)


def triangulate_dlt(P: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Linear triangulation of one point.

    P: (V, 3, 4) projection matrices on normalised coordinates (cam_R_world | cam_t);
    xy: (V, 2) normalised image coordinates. Returns (3,) world point.
    """
    A = np.concatenate([xy[:, :1] * P[:, 2] - P[:, 0], xy[:, 1:2] * P[:, 2] - P[:, 1]])
    _, _, Vt = np.linalg.svd(A)
    X = Vt[-1]
    return X[:3] / X[3]


def closest_points_segments(p0, p1, q0, q1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points between segments [p0,p1] and [q0,q1], vectorised.

    All inputs (..., 3). Returns (distance (...), point on p (..., 3), point on q (..., 3)).
    """
    p0, p1, q0, q1 = (np.asarray(a, dtype=np.float64) for a in (p0, p1, q0, q1))
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("...i,...i", d1, d1)
    e = np.einsum("...i,...i", d2, d2)
    f = np.einsum("...i,...i", d2, r)
    c = np.einsum("...i,...i", d1, r)
    b = np.einsum("...i,...i", d1, d2)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12, np.clip((b * f - c * e) / denom, 0, 1), 0.0)
        # q is a point: the closest point of p to it (t = 0 below)
        s = np.where((e <= 1e-12) & (a > 1e-12), np.clip(-c / a, 0, 1), s)
        t = np.where(e > 1e-12, (b * s + f) / e, 0.0)
        # Re-clamp t and recompute s for the clamped t (Ericson, Real-Time Collision Detection).
        t_c = np.clip(t, 0, 1)
        s = np.where(t < 0, np.where(a > 1e-12, np.clip(-c / a, 0, 1), 0.0), s)
        s = np.where(t > 1, np.where(a > 1e-12, np.clip((b - c) / a, 0, 1), 0.0), s)
    t = t_c
    cp = p0 + d1 * s[..., None]
    cq = q0 + d2 * t[..., None]
    return np.linalg.norm(cp - cq, axis=-1), cp, cq


def triangulate_views(R: np.ndarray, t: np.ndarray, cams: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batch DLT. cams: (V,) int; xy: (V, J, 2) normalised, NaN = missing.

    Returns points (J, 3) (NaN where fewer than 2 views or behind a camera) and the
    number of views per joint (J,).
    """
    V, J, _ = xy.shape
    Rt = np.transpose(R[cams], (0, 2, 1))  # cam_R_world
    P = np.concatenate([Rt, -np.einsum("vij,vj->vi", Rt, t[cams])[..., None]], axis=2)  # (V, 3, 4)
    valid = np.all(np.isfinite(xy), axis=2)  # (V, J)
    x = np.nan_to_num(xy)
    rows_u = x[:, :, 0, None] * P[:, None, 2, :] - P[:, None, 0, :]  # (V, J, 4)
    rows_v = x[:, :, 1, None] * P[:, None, 2, :] - P[:, None, 1, :]
    A = np.concatenate([rows_u, rows_v], axis=0) * np.concatenate([valid, valid])[..., None]  # (2V, J, 4)
    A = np.transpose(A, (1, 0, 2))  # (J, 2V, 4)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    n = valid.sum(0)
    bad = (n < 2) | ~np.all(np.isfinite(X), axis=1)
    # depth of each joint in each observing camera
    Xc_z = np.einsum("vk,vjk->vj", Rt[:, 2, :], X[None, :, :] - t[cams][:, None, :])
    bad |= np.any(valid & (Xc_z <= 0.05), axis=0)
    X[bad] = np.nan
    return X, n


_TRIANGULATE_CHUNK = 16384  # points per batched DLT


def triangulate_batch(R: np.ndarray, t: np.ndarray, cams: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Many points at once: cams (N, V) int and xy (N, V, 2) normalised, NaN = missing
    (padding); returns (N, 3) world points, NaN where fewer than 2 views or behind a
    camera. The DLT of each point ignores its missing rows."""
    N, V, _ = xy.shape
    if N == 0:
        return np.zeros((0, 3))
    if N > _TRIANGULATE_CHUNK:  # the temporaries are ~100 floats per view and point: bounded
        return np.concatenate([triangulate_batch(R, t, cams[i:i + _TRIANGULATE_CHUNK], xy[i:i + _TRIANGULATE_CHUNK])
                               for i in range(0, N, _TRIANGULATE_CHUNK)])
    valid = np.all(np.isfinite(xy), axis=2)  # (N, V)
    c = np.where(valid, cams, 0)
    Rt = np.transpose(R[c], (0, 1, 3, 2))  # (N, V, 3, 3) cam_R_world
    tc = t[c]  # (N, V, 3)
    P = np.concatenate([Rt, -np.einsum("nvij,nvj->nvi", Rt, tc)[..., None]], axis=3)  # (N, V, 3, 4)
    x = np.nan_to_num(xy)
    ru = x[..., 0, None] * P[:, :, 2, :] - P[:, :, 0, :]
    rv = x[..., 1, None] * P[:, :, 2, :] - P[:, :, 1, :]
    A = np.concatenate([ru, rv], axis=1) * np.concatenate([valid, valid], axis=1)[..., None]  # (N, 2V, 4)
    if A.shape[1] < 4:  # zero rows keep the null space and give the thin SVD its 4 x 4 Vt
        A = np.concatenate([A, np.zeros((N, 4 - A.shape[1], 4))], axis=1)
    # thin: the full U is (N, 2V, 2V), 1.9 GB for a 600 s run's scale check
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Xh = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    z = np.einsum("nvk,nvk->nv", Rt[:, :, 2, :], X[:, None, :] - tc)
    bad = (valid.sum(1) < 2) | ~np.all(np.isfinite(X), axis=1) | np.any(valid & (z <= 0.05), axis=1)
    X[bad] = np.nan
    return X
