"""Re-localisation of a camera that association has lost.

A camera whose estimate is far off (a bad initial guess, a bumped camera) sees people,
but its rays miss everyone else's, so its detections never join a hypothesis and no
cycle can correct it. The other cameras still triangulate the people. In frames where
the network sees exactly one person and the lost camera sees exactly one, its 17 joints
correspond to that person's triangulated joints: a PnP with RANSAC over many such
frames gives the camera's pose, whatever its current estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .associate import Associator
from .config import AssociateConfig
from .geometry import triangulate_views
from .preprocess import Detection


@dataclass(frozen=True)
class Relocalization:
    """A new pose for one camera: R (3, 3) world_R_cam, t (3,) centre."""

    cam: int
    R: np.ndarray
    t: np.ndarray
    inliers: int
    correspondences: int
    frames: int


def frame_correspondences(frames: Sequence[tuple[float, tuple[tuple[Detection, ...], ...]]], cam: int,
                          R: np.ndarray, t: np.ndarray, cfg: AssociateConfig, *, with_camera: int | None = None
                          ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame with one person hypothesis (without camera ``cam``) and one detection in
    ``cam``: the person's triangulated joints (N, 3) and the camera's normalised points
    (N, 2) of the same joints (N >= 6); with ``with_camera``, only hypotheses that camera
    is part of."""
    assoc = Associator(cfg)
    out = []
    for time_, views in frames:
        mine = [d for v in views for d in v if d.cam == cam]
        if len(mine) != 1:
            continue
        others = [tuple(d for d in v if d.cam != cam) for v in views]
        others = [v for v in others if v]
        if len(others) < 2:
            continue
        hyps = assoc(time_, others, R, t, None)
        if len(hyps) != 1 or sum(len(v) for v in others) != len(hyps[0].cams):
            continue  # more than one person (or a stray detection) elsewhere: ambiguous
        h = hyps[0]
        if with_camera is not None and with_camera not in h.cams:
            continue
        X, n = triangulate_views(R, t, h.cams, h.xy)
        ok = np.all(np.isfinite(X), axis=1) & (n >= 2) & np.all(np.isfinite(mine[0].xy), axis=1)
        if ok.sum() < 6:
            continue
        out.append((X[ok], mine[0].xy[ok]))
    return out


def correspondences(frames: Sequence[tuple[float, tuple[tuple[Detection, ...], ...]]], cam: int,
                    R: np.ndarray, t: np.ndarray, cfg: AssociateConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """World points (N, 3) and the lost camera's normalised points (N, 2) from frames
    with one person hypothesis (without camera ``cam``) and one detection in ``cam``
    (``frame_correspondences``, concatenated), and the number of frames."""
    per = frame_correspondences(frames, cam, R, t, cfg)
    if not per:
        return np.zeros((0, 3)), np.zeros((0, 2)), 0
    return np.concatenate([X for X, _ in per]), np.concatenate([x for _, x in per]), len(per)


def relocalize(frames, cam: int, R: np.ndarray, t: np.ndarray, focal: float, cfg: AssociateConfig,
               *, min_inliers: int = 40, reprojection_px: float, seed: int = 0) -> Relocalization | None:
    """PnP + RANSAC pose of camera ``cam`` from the archived frames, or None."""
    import cv2

    X, x, used = correspondences(frames, cam, R, t, cfg)
    if len(X) < min_inliers:
        return None
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X.astype(np.float64), x.astype(np.float64), np.eye(3), None,
        iterationsCount=500, reprojectionError=reprojection_px / focal, confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < min_inliers or len(inl) < 0.3 * len(X):
        return None
    idx = inl.ravel()
    # refine on the inliers (iterative LM from the RANSAC pose)
    ok, rvec, tvec = cv2.solvePnP(X[idx], x[idx], np.eye(3), None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    Rcw, _ = cv2.Rodrigues(rvec)
    R_new, t_new = Rcw.T, (-Rcw.T @ tvec).ravel()
    # Only a pose that explains the correspondences clearly better than the current one
    # replaces it: early on a camera may associate poorly because everyone is still off.
    thr = reprojection_px / focal
    n_new = _inliers(X, x, R_new, t_new, thr)
    n_old = _inliers(X, x, R[cam], t[cam], thr)
    if n_new < max(min_inliers, 2 * n_old):
        return None
    return Relocalization(cam, R_new, t_new, int(n_new), int(len(X)), used)


def _inliers(X: np.ndarray, x: np.ndarray, R: np.ndarray, t: np.ndarray, thr: float) -> int:
    """Correspondences within ``thr`` (normalised units) of the projection with pose R, t."""
    Xc = (X - t) @ R
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(Xc[:, :2] / z[:, None] - x, axis=1)
    return int(np.sum((z > 0) & (e < thr)))
