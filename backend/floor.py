"""The floor the people walk on, as the adjustments see it (``optimize.floor``).

A walker has a foot on the floor at nearly every instant, so each hypothesis' lower ankle
lies a few centimetres above one plane. Projections alone leave a chain of cameras that
see people only in pairs free to bend and twist a little at every link (pitch and roll
add up along it); the plane does not bend. The adjustments that hold the people's bones
(``optimize.bones``; not the bootstrap's) also hold the lower ankles to one plane, a variable of the solve
(backend/optimize.py's ``_add_floor``) under a robust kernel that lets a foot on a step, a
jump or a wrong ankle go. This module finds where that plane starts and which ankles it
holds: fitted to the previous round's own landmarks, not to points triangulated again (a
two-view DLT spreads an ankle along its rays, which along a chain of cameras pitched down
tilts the noisy points' plane by degrees), and the same fit gives the bootstrap's world
frame its floor (``plane_of_ankles``).

Pure numpy: the factors themselves are built in backend/optimize.py.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

ANKLES = (15, 16)  # COCO-17 l_ankle, r_ankle
_TOP = (5, 6, 11, 12)  # shoulders and hips: what is above the ankles of an upright body
MIN_POINTS = 30  # lower ankles a plane needs
MAX_TILT_DEG = 30.0  # the ankles' plane against the bodies' up: a floor is level to people
GATE = 6.0  # spreads, and at least GATE_M: a lower ankle further from the plane is on another
GATE_M = 1.0  # floor (a gallery, a stage), not on this one in a bent chain
MIN_WIDTH = 0.25  # m: std of the ankles across their main direction below which the
# plane's roll about that direction is the bodies' up (people walking one line)


@dataclass(frozen=True)
class Floor:
    """n (3,) unit normal, upwards; d: the plane is n·X = d (the lower ankles' level, not
    the floor's: the ankle joint's height above the floor is in d); spread: m, the robust
    std of the lower ankles' distances to it (feet in the air, noise), at least the sigma
    it was fitted with; points: how many lower ankles it was fitted to."""

    n: np.ndarray
    d: float
    spread: float
    points: int

    def gate(self) -> float:
        """m: a lower ankle further from the plane is not on this floor."""
        return max(GATE * self.spread, GATE_M)


def lower_ankles(landmarks: np.ndarray, lm_hyp: np.ndarray, lm_joint: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per hypothesis with both ankles and a shoulder or hip triangulated: (ankle landmark
    indices (H', 2) int, up (H', 3) unit vectors from the ankles' midpoint to the shoulders'
    and hips' mean). landmarks (L, 3); lm_hyp, lm_joint (L,) int. Also returns the
    hypotheses' indices (H',)."""
    assert landmarks.shape == (len(lm_hyp), 3) and lm_joint.shape == lm_hyp.shape
    H = int(lm_hyp.max()) + 1 if len(lm_hyp) else 0
    lm_of = np.full((H, 17), -1, np.int64)
    lm_of[lm_hyp, lm_joint] = np.arange(len(lm_hyp))
    ank = lm_of[:, ANKLES]
    top = lm_of[:, _TOP]
    has_top = (top >= 0).any(1)
    ok = (ank >= 0).all(1) & has_top
    hyp = np.flatnonzero(ok)
    ank, top = ank[ok], top[ok]
    T = np.where((top >= 0)[..., None], landmarks[np.maximum(top, 0)], np.nan)
    up = np.nanmean(T, axis=1) - landmarks[ank].mean(1)
    norm = np.linalg.norm(up, axis=1, keepdims=True)
    return ank, up / np.where(norm > 0, norm, 1.0), hyp


def median_up(up: np.ndarray) -> np.ndarray | None:
    """(3,) the unit median of bodies' up vectors (N, 3) (finite rows, any length), or None
    when there is none."""
    up = up[np.isfinite(up).all(axis=1)]
    norm = np.linalg.norm(up, axis=1, keepdims=True)
    u = np.median(up / np.where(norm > 0, norm, 1.0), axis=0) if len(up) else np.zeros(3)
    return u / np.linalg.norm(u) if np.linalg.norm(u) > 0 else None


def fit_floor(landmarks: np.ndarray, lm_hyp: np.ndarray, lm_joint: np.ndarray, sigma: float) -> Floor | None:
    """``plane_of_ankles`` of a graph's landmarks (L, 3) with their hypotheses and joints
    (L,) int."""
    ank, up, _ = lower_ankles(landmarks, lm_hyp, lm_joint)
    return plane_of_ankles(landmarks[ank], up, sigma)


def floor_of_persons(X: np.ndarray, sigma: float) -> Floor | None:
    """``plane_of_ankles`` of whole triangulated persons X (N, 17, 3), NaN = missing (a
    person without an ankle or anything above them is not counted)."""
    assert X.ndim == 3 and X.shape[1:] == (17, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nobody's shoulders or hips: NaN
        up = np.nanmean(X[:, _TOP], axis=1) - X[:, ANKLES].mean(axis=1)
    return plane_of_ankles(X[:, ANKLES], up, sigma)


def plane_of_ankles(ankles: np.ndarray, up: np.ndarray, sigma: float, rounds: int = 10) -> Floor | None:
    """The plane of the hypotheses' lower ankles; ankles (N, 2, 3), up (N, 3) each body's
    up (from the ankles to the hips or shoulders), NaN = missing. The lower ankle is the
    one lower along the bodies' median up; the plane is fitted with Cauchy weights of width
    max(sigma, the robust spread). None when fewer than MIN_POINTS bodies have both ankles
    and an up, or the plane leans more than MAX_TILT_DEG from the bodies' up (no one floor:
    a ramp, stairs, or too few people upright). Where the ankles lie along one line, the
    plane's turn about it is taken from the bodies' up."""
    assert ankles.ndim == 3 and ankles.shape[1:] == (2, 3) and up.shape == (len(ankles), 3)
    ok = np.isfinite(ankles).all(axis=(1, 2)) & np.isfinite(up).all(axis=1)
    ankles, up = ankles[ok], up[ok]
    if len(ankles) < MIN_POINTS:
        return None
    u = median_up(up)
    if u is None:
        return None
    P = ankles[np.arange(len(ankles)), np.argmin(ankles @ u, axis=1)]
    n, d = u, float(np.median(P @ u))
    spread = sigma
    for _ in range(rounds):
        r = P @ n - d
        spread = max(sigma, 1.4826 * float(np.median(np.abs(r - np.median(r)))))
        w = 1.0 / (1.0 + (r / spread) ** 2)
        mu = w @ P / w.sum()
        Q = (P - mu) * np.sqrt(w)[:, None]
        evals, evecs = np.linalg.eigh(Q.T @ Q / w.sum())
        m = evecs[:, 0]
        if evals[1] < MIN_WIDTH**2:  # one line of ankles: its roll is the bodies'
            a = evecs[:, 2]
            m = u - (u @ a) * a
            m /= np.linalg.norm(m)
        n = m if m @ u >= 0 else -m
        d = float(n @ mu)
    if np.degrees(np.arccos(np.clip(n @ u, -1.0, 1.0))) > MAX_TILT_DEG:
        return None
    return Floor(n, d, spread, len(P))


def world_frame(n: np.ndarray, level: float, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The floor's world frame: (F (3, 3), o (3,), k) with new coordinates X' = F (X - o):
    z along n (3,) (unit, up), the floor the plane n·X = level, origin on it under
    centres[0], x towards the floor point under centres[k], the first of centres (K, 3)
    whose floor point is more than 0.1 m from the origin's. None when there is none."""
    assert n.shape == (3,) and centres.ndim == 2 and centres.shape[1] == 3 and len(centres)
    proj = centres - np.outer(centres @ n - level, n)
    o = proj[0]
    for k in range(1, len(proj)):
        v = proj[k] - o
        if np.linalg.norm(v) > 0.1:
            x = v / np.linalg.norm(v)
            return np.stack([x, np.cross(n, x), n]), o, k
    return None


def held_ankles(landmarks: np.ndarray, lm_hyp: np.ndarray, lm_joint: np.ndarray, floor: Floor) -> np.ndarray:
    """(K,) int the landmark of each hypothesis' lower ankle (lower along the floor's
    normal) within ``floor.gate()`` of it: the ankles an adjustment holds to it."""
    ank, _, _ = lower_ankles(landmarks, lm_hyp, lm_joint)
    if not len(ank):
        return np.zeros(0, np.int64)
    low = ank[np.arange(len(ank)), np.argmin(landmarks[ank] @ floor.n, axis=1)]
    return low[np.abs(landmarks[low] @ floor.n - floor.d) <= floor.gate()]
