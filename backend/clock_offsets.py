"""Sensor clock offsets estimated from the data (a sensor whose NTP fails, a bad board clock).

A sensor's stamps are ``capture + offset``. Offsets are relative: the reference clock is
the median of the estimated sensors, and an offset here is how far a sensor's stamps run
ahead of that reference (positive: stamped late; the synchroniser subtracts it).

How (docs/clock_offsets.md has the reasoning and the figures):

1. Tracks, per sensor, on its raw message stream: a person's detections chained from
   message to message. A sensor far off in time need not join framesets for this.
2. The pipeline's hypotheses (one person at one frameset instant T on the synchronised
   clock, associated over the cameras) give each sensor's samples: a hypothesis with the
   sensor in it says which of its tracks is that person (the track through the
   sensor's view at ``T + applied offset``), and the person in 3D comes from the
   *other* views, triangulated with the current pose estimate. Views of sensors whose
   current offset estimate says they were mistimed are left out of that 3D.
3. For a candidate offset g the sensor's tracks are taken at the raw stamps ``T + g``
   and compared with the 3D persons: the sensor's own pose is fitted to them (robust
   Gauss-Newton PnP, Cauchy), because a mistimed camera is also badly calibrated and
   its pose error would swamp the timing signal; the cost left is the profile cost of g.
   A coarse grid over the whole range finds the offset with the pose held (fitted at
   the grid's centre, then once at the best candidate: a pose fitted at every candidate
   of a wide grid mimics a time shift), a fine grid around it (pose fitted at each) and
   a least-squares parabola measure it; its std is the jackknife over blocks of data time.
   At the end of a run (``reestimate``) also the spread over the cameras that triangulate
   the person: the estimate again with each of them left out (``_reference_spread``). An
   error of the others' 3D that every block shares (a lens a little off, a pair of
   cameras that sees the spot) moves every block alike, so the blocks' jackknife cannot
   see it; the reported std is the larger of the two.
   A sensor's tracks that join no hypothesis are identified by projecting the person
   into it, with a gate that grows with its pose's covariance.
4. Offsets relative to the median sensor; confident ones are applied by the
   synchroniser (a first one only when beyond NTP's spread by its tail on two agreeing
   updates), which makes the other sensors' 3D (step 2) better timed in turn. A camera
   never calibrated (or calibrated to its mistimed data) is moved to the pose fitted
   with its offset when that is first applied (``relocation``).

Joint pose and time: walking people move along few directions over a few seconds, so a
pose correction alone could absorb a shift in time; over a window of a minute they walk
every way and the two separate (the std says how well).

Synchronous, numpy only; the pipeline feeds it messages and hypotheses and calls
``update`` with the current pose estimate.
"""

from __future__ import annotations

import copy
import functools
import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np
import scipy.stats

from proto import KeypointMessage

from .associate import Hypothesis
from .cameras import Intrinsics, undistort
from .config import ClockConfig
from .geometry import pose_local, project_normalised, so3_exp, triangulate_batch
from .preprocess import ConfidenceScale, unmeasured

log = logging.getLogger(__name__)

# Joints used for timing: the body without the face (five face points move as one and
# would count the head five times).
BODY = np.array([5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16])
_MATCH_DIAG_PER_S = 1.0  # as in sync: persons move less than this many image diagonals per second
_MATCH_MIN_FRAC = 0.03
_STD_FLOOR = 0.0002  # s: the jackknife of few blocks can be optimistic
_RATIO = 0.5  # a track is the person when it fits at least this much better than any other
_COARSE_SAMPLES = 400  # samples a coarse search uses (spread over the window)
_POSE_ITERS = 2  # Gauss-Newton steps of the pose at each candidate (from the centre's pose)
# Fine grids the search may walk along its minimum. The coarse search holds the pose where
# the cycles put it, and a camera calibrated to mistimed views has absorbed part of the
# shift: seed 3's cam_13 (+119 ms) came out at +70 ms, and the fine search walked +90,
# +110, +126 and was cut off there on every update for 90 s (docs/clock_offsets.md, session 9).
_FINE_WALK = 8
# Cauchy width in units of the median absolute residual: 2.385 sigma (95 % efficiency
# for Gaussian noise), and the median of |N(0, sigma)| is 0.674 sigma (per coordinate;
# for the 2D distance the median is 1.18 sigma).
_CAUCHY = 2.385 / 1.18
_CHI2_6 = float(scipy.stats.chi2.ppf(1 - 0.0027, 6))  # the 3-sigma tail of a 6-dof pose
# A camera is left out of a sensor's reference (``_reference_spread``) when it is in at
# least this share of the sensor's samples: one in a handful moves nothing, and its
# near-zero change would dilute the spread of the ones that matter.
_SPREAD_MIN_SHARE = 0.05


# ------------------------------------------------------------------ results


@dataclass(frozen=True)
class SensorClock:
    """One sensor's clock as estimated.

    offset: s its stamps run ahead of the reference clock (the median sensor), None when
        not estimated yet.
    std: s, its standard deviation: the larger of ``std_blocks`` and ``std_references``.
    std_blocks: s, the jackknife over blocks of data time.
    std_references: s, the jackknife over the cameras whose views place the person it is
        timed against (each left out in turn), measured by the estimate at the end of a
        run; None when not measured (live estimates, too few cameras).
    applied: s the synchroniser subtracts from its stamps now.
    blocks: blocks of data (``clock.block`` s each) the estimate rests on.
    drift_warnings: how often its estimate moved by more than ``clock.drift_warning``.
    note: why the last update left the estimate as it was (None: it was updated), e.g.
        "too few samples": what an operator needs when a sensor stays without one.
    """

    sensor: str
    offset: float | None
    std: float | None
    applied: float
    blocks: int
    drift_warnings: int
    note: str | None = None
    std_blocks: float | None = None
    std_references: float | None = None

    def to_dict(self) -> dict:
        return {"offset": self.offset, "std": self.std, "std_blocks": self.std_blocks,
                "std_references": self.std_references, "applied": self.applied, "blocks": self.blocks,
                "drift_warnings": self.drift_warnings, "note": self.note}


# ------------------------------------------------------------------ pure functions


@functools.lru_cache(maxsize=256)
def _sigmas(blocks: int) -> float:
    """How many jackknife stds from ``blocks`` blocks make the one-sided tail of 3 sigma
    (0.135 %): Student's t on blocks - 1 degrees of freedom (a jackknife std of few
    blocks is itself uncertain)."""
    return float(scipy.stats.t.ppf(1 - 0.00135, max(blocks - 1, 1)))


def _row_nanmedian(a: np.ndarray) -> np.ndarray:
    """(N, J) -> (N,) the median of each row's non-NaN values (every row has one), as
    ``np.nanmedian(a, axis=1)`` gives it, without its per-call cost."""
    s = np.sort(a, axis=1)  # NaN sort last
    n = np.count_nonzero(~np.isnan(a), axis=1)
    assert n.min(initial=1) >= 1
    i = np.arange(len(a))
    return 0.5 * (s[i, (n - 1) // 2] + s[i, n // 2])


def interpolate_track(stamps: np.ndarray, xy: np.ndarray, ok: np.ndarray, q: np.ndarray,
                      max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """A track (stamps (n,) increasing, n >= 2, xy (n, J, 2), ok (n, J) bool) at query
    times q (...,): (..., J, 2) positions and (..., J) validity (both bracketing joints
    there, the bracket within the track and at most ``max_gap`` wide)."""
    n = len(stamps)
    assert n >= 2 and xy.shape[0] == n and ok.shape == xy.shape[:2]
    i = np.searchsorted(stamps, q, side="right")
    exact = (i > 0) & (stamps[np.clip(i - 1, 0, n - 1)] == q)
    inside = (i > 0) & (i < n)
    i1 = np.clip(i, 1, n - 1)
    i0 = i1 - 1
    t0, t1 = stamps[i0], stamps[i1]
    gap = t1 - t0
    w = np.clip((q - t0) / gap, 0.0, 1.0)[..., None, None]
    out = (1 - w) * xy[i0] + w * xy[i1]
    good = ((inside & (gap <= max_gap)) | exact)[..., None] & ok[i0] & ok[i1]
    return out, good


def smooth_track(stamps: np.ndarray, xy: np.ndarray, ok: np.ndarray, q: np.ndarray, max_gap: float,
                 bandwidth: float) -> tuple[np.ndarray, np.ndarray]:
    """Like ``interpolate_track`` (same validity) but the positions are a local linear
    fit (Gaussian kernel, ``bandwidth`` s) at q (K,). Plain interpolation between noisy
    detections has half the noise variance halfway between two of them and all of it
    at one: when the query times share a phase against the sensor's frames (a 30 Hz
    camera, framesets at 10 Hz) that variance pattern shifts the cost's minimum."""
    lin, good = interpolate_track(stamps, xy, ok, q, max_gap)
    lo, hi = np.searchsorted(stamps, [q.min() - 3 * bandwidth, q.max() + 3 * bandwidth])
    lo, hi = max(lo - 1, 0), min(hi + 1, len(stamps))
    dt = stamps[None, lo:hi] - q[:, None]  # (K, n)
    w = np.exp(-0.5 * (dt / bandwidth) ** 2)[:, :, None] * ok[None, lo:hi]  # (K, n, J)
    dt = dt[:, :, None]
    s0, s1, s2 = w.sum(1), (w * dt).sum(1), (w * dt * dt).sum(1)  # (K, J)
    x = np.nan_to_num(xy[lo:hi])[None]  # (1, n, J, 2)
    t0 = (w[..., None] * x).sum(1)  # (K, J, 2)
    t1 = (w[..., None] * dt[..., None] * x).sum(1)
    det = s0 * s2 - s1 * s1
    fine = det > 1e-6 * np.maximum(s0, 1e-12) * bandwidth**2 * np.maximum(s0, 1e-12)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = (s2[..., None] * t0 - s1[..., None] * t1) / det[..., None]
    return np.where(fine[..., None], a, lin), good


def fit_pose(X: np.ndarray, x: np.ndarray, R: np.ndarray, t: np.ndarray, width: float, iters: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust (Cauchy, ``width`` normalised units) Gauss-Newton fit of a camera pose to
    world points X (N, 3) seen at normalised coordinates x (N, 2), from R (3, 3), t (3,)
    (world_R_cam, optical centre). Returns R, t and the (N,) distances (normalised) at
    the result (inf behind the camera)."""
    assert X.shape[1:] == (3,) and x.shape == (len(X), 2)
    for _ in range(iters + 1):
        front = ((X - t) @ R)[:, 2] > 0.05  # cam_R_world (X - t): in front of the camera
        u = np.zeros((len(X), 2))
        J = np.zeros((len(X), 2, 6))  # behind the camera: weight 0, no Jacobian
        u[front], J[front] = project_normalised(R, t, X[front])
        r = x - u
        d = np.where(front, np.linalg.norm(r, axis=1), np.inf)
        if _ == iters:
            return R, t, d
        w = np.where(front, 1.0 / (1.0 + (np.where(front, d, 0.0) / width) ** 2), 0.0)
        Jm = J.reshape(-1, 6)  # (2N, 6); the step below is R' = R exp([w]), t' = t + R v
        Jw = Jm * np.repeat(w, 2)[:, None]
        H = Jw.T @ Jm
        g = Jw.T @ r.reshape(-1)
        H += (1e-6 * np.trace(H) + 1e-12) * np.eye(6)
        step = np.linalg.solve(H, g)
        t = t + R @ step[3:]
        R = R @ so3_exp(step[:3])
    raise AssertionError("unreachable")


def cauchy(d: np.ndarray, width: float) -> np.ndarray:
    """Cauchy cost of distances d (any shape), ``width``: same units; inf stays inf-free
    (a point behind the camera costs as a far outlier)."""
    return width**2 * np.log1p((np.minimum(d, 1e3 * width) / width) ** 2)


def parabola_minimum(cost: np.ndarray, grid: np.ndarray, half: int = 2) -> float | None:
    """Minimum of a sampled curve: least-squares parabola through the 2·half+1 points
    around the best one. None when the best point lies within ``half`` of the grid's
    edge (the minimum may be outside) or the parabola opens downwards."""
    k = int(np.argmin(cost))
    if k < half or k >= len(cost) - half:
        return None
    sl = slice(k - half, k + half + 1)
    x = grid[sl] - grid[k]
    a, b, _ = np.polyfit(x, cost[sl] - cost[k], 2)
    if a <= 0:
        return None
    m = -b / (2 * a)
    span = grid[k + half] - grid[k]
    return float(grid[k] + np.clip(m, -span, span))


def jackknife_minimum(block_cost: np.ndarray, grid: np.ndarray) -> tuple[float, float] | None:
    """The minimum (``parabola_minimum``) of the summed per-block curves block_cost
    (B, K) and its jackknife std over the blocks; None with fewer than 3 blocks or when
    a minimum is not found (with all blocks or without one)."""
    B = block_cost.shape[0]
    if B < 3:
        return None
    total = block_cost.sum(0)
    x = parabola_minimum(total, grid)
    if x is None:
        return None
    loo = []
    for b in range(B):
        y = parabola_minimum(total - block_cost[b], grid)
        if y is None:
            return None
        loo.append(y)
    a = np.array(loo)
    return x, max(math.sqrt((B - 1) / B * ((a - a.mean()) ** 2).sum()), _STD_FLOOR)


@dataclass(frozen=True)
class Samples:
    """One sensor's samples: persons in 3D from the other sensors and its own track.

    X: (N, J, 3) world joints from the others (NaN = unknown).
    times: (N,) s frameset instants on the synchronised clock.
    tracks: N tracks of the sensor (stamps (n,), xy (n, J, 2) normalised, ok (n, J)),
        raw stamps.
    memo: N dicts where ``profile`` keeps the tracks taken at a grid (they do not change).
    """

    X: np.ndarray
    times: np.ndarray
    tracks: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]
    memo: tuple[dict, ...] | None = None

    def __post_init__(self) -> None:
        N = len(self.times)
        assert self.X.shape == (N, len(BODY), 3) and len(self.tracks) == N
        assert self.memo is None or len(self.memo) == N


def profile(samples: Samples, grid: np.ndarray, R: np.ndarray, t: np.ndarray, max_gap: float, block: float,
            focal: float, min_scale_px: float, anneal: bool = True, bandwidth: float = 0.05,
            nuisance: str = "pose") -> tuple[np.ndarray, np.ndarray, float, int] | None:
    """Profile cost of candidate offsets: the samples' 3D joints against the sensor's
    tracks at ``times + g`` (``smooth_track``) for each g in grid (K,), with the sensor's
    pose handled by ``nuisance``:

    - "pose": fitted at each g (``fit_pose``, from the pose fitted at the grid's centre;
      ``anneal``: the start pose may be far off, begin with a wide Cauchy). Right over a
      narrow grid around the offset; over a wide one a pose shift can mimic a time shift
      (people walking one way through a view) and the profile flattens.
    - "fixed": the pose fitted at the grid's centre (as above) and held over the grid,
      then fitted once at the best candidate and held again (``_profile_fixed``): the
      search over the whole range. The robust scale is taken at the best candidate.

    Only joints valid at every candidate count, so costs compare across the grid.

    Returns block_cost (B, K) (Cauchy px², per block of ``block`` s of data time), the
    block ids' count B, the robust scale used (px, median distance at the centre, or at
    the best candidate with "fixed"), the number of joints and the pose (R, t) fitted at
    the centre (at the best candidate with "fixed"); None without joints.
    """
    assert nuisance in ("pose", "fixed")
    K = len(grid)
    pos, val = [], []
    key = (round(float(grid[0]), 6), round(float(grid[-1]), 6), K)
    for m, tr in enumerate(samples.tracks):
        memo = samples.memo[m] if samples.memo is not None else None
        if memo is not None and key in memo:
            p, ok = memo[key]
        else:
            p, ok = smooth_track(*tr, samples.times[m] + grid, max_gap, bandwidth)  # (K, J, 2), (K, J)
            if memo is not None:
                memo[key] = (p, ok)
        pos.append(p)
        val.append(ok.all(0) & np.isfinite(samples.X[m]).all(-1))
    valid = np.stack(val)  # (N, J)
    if valid.sum() < 12:
        return None
    obs = np.stack(pos)[np.nonzero(valid)[0], :, np.nonzero(valid)[1]]  # (P, K, 2)
    X = samples.X[valid]  # (P, 3)
    blk = np.floor(np.repeat(samples.times[:, None], valid.shape[1], 1)[valid] / block).astype(np.int64)
    _, blk = np.unique(blk, return_inverse=True)
    B = int(blk.max()) + 1
    c = K // 2
    # the pose at the centre, annealed from a wide Cauchy (the pose may be far off)
    Rc, tc = R, t
    for w_px in (50.0, 20.0) if anneal else (20.0,):
        Rc, tc, d = fit_pose(X, obs[:, c], Rc, tc, w_px / focal, 4 if anneal else 2)
    scale = max(min_scale_px, float(np.median(d[np.isfinite(d)])) * focal if np.isfinite(d).any() else np.inf)
    width = _CAUCHY * scale / focal
    Rc, tc, _ = fit_pose(X, obs[:, c], Rc, tc, width, 3)
    if nuisance == "fixed":
        return _profile_fixed(X, obs, blk, B, Rc, tc, c, focal, min_scale_px)
    out = np.zeros((B, K))
    for k in range(K):
        _, _, d = fit_pose(X, obs[:, k], Rc, tc, width, _POSE_ITERS)
        out[:, k] = np.bincount(blk, cauchy(d * focal, _CAUCHY * scale), minlength=B)
    return out, B, scale, len(X), (Rc, tc)


def _profile_fixed(X: np.ndarray, obs: np.ndarray, blk: np.ndarray, B: int, R: np.ndarray, t: np.ndarray, k: int,
                   focal: float, min_scale_px: float) -> tuple | None:
    """``profile`` with the pose held: X (P, 3) joints, obs (P, K, 2) the track at each
    candidate, blk (P,) block ids, (R, t) the pose fitted at candidate k. The profile
    with that pose held finds the best candidate; the pose is fitted once more there
    and the profile taken again with it held (a sensor far off in time: the pose
    fitted at the centre absorbed part of the shift). The Cauchy width from the median
    distance at the best candidate."""
    K = obs.shape[1]
    for rnd in range(2):
        front = ((X - t) @ R)[:, 2] > 0.05
        if front.sum() < 12:
            return None
        d = np.full((len(X), K), np.inf)
        u, _ = project_normalised(R, t, X[front])
        d[front] = np.linalg.norm(obs[front] - u[:, None, :], axis=-1) * focal  # (P, K) px
        scale = max(min_scale_px, float(np.median(d[front, k])))
        cost = cauchy(d, _CAUCHY * scale)  # (P, K)
        k = int(np.argmin(cost.sum(0)))
        scale = max(min_scale_px, float(np.median(d[front, k])))
        if rnd == 0:
            R, t, _ = fit_pose(X, obs[:, k], R, t, _CAUCHY * scale / focal, 3)
    cost = cauchy(d, _CAUCHY * scale)
    out = np.stack([np.bincount(blk, cost[:, j], minlength=B) for j in range(K)], axis=1)
    return out, B, scale, len(X), (R, t)


# ------------------------------------------------------------------ per-sensor tracks


class _Track:
    __slots__ = ("stamps", "xy", "ok", "px", "_arrays")

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.xy: list[np.ndarray] = []
        self.ok: list[np.ndarray] = []
        self.px: np.ndarray | None = None  # last detection (17, 3) pixels + confidence, for matching
        self._arrays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def add(self, stamp: float, xy: np.ndarray, ok: np.ndarray, px: np.ndarray) -> None:
        self.stamps.append(stamp)
        self.xy.append(xy)
        self.ok.append(ok)
        self.px = px
        self._arrays = None

    def trim(self, before: float) -> None:
        k = 0
        while k < len(self.stamps) - 1 and self.stamps[k + 1] < before:
            k += 1
        if k:
            del self.stamps[:k], self.xy[:k], self.ok[:k]
            self._arrays = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """stamps (n,), xy (n, J, 2) normalised, ok (n, J) over the BODY joints."""
        if self._arrays is None:
            self._arrays = (np.array(self.stamps), np.stack(self.xy), np.stack(self.ok))
        return self._arrays

    def frozen(self) -> "_Track":
        """A copy that later ``add`` calls on this one do not change (the lists are
        copied; their items are never changed in place)."""
        c = _Track()
        c.stamps, c.xy, c.ok, c.px, c._arrays = list(self.stamps), list(self.xy), list(self.ok), self.px, self._arrays
        return c


class _SensorTracks:
    def __init__(self, intr: Intrinsics, min_confidence: float, max_gap: float):
        self.intr = intr
        self.min_conf = min_confidence
        self.max_gap = max_gap
        self.tracks: list[_Track] = []
        self.last_stamp: float | None = None
        self.out_of_order = 0

    def push(self, msg: KeypointMessage, intr: Intrinsics, confidence_scale: float = 1.0) -> None:
        t = msg.stamp
        if self.last_stamp is not None and t <= self.last_stamp:
            self.out_of_order += 1
            return
        self.last_stamp = t
        kp = msg.keypoints()
        if not len(kp):
            return
        outside, folded = unmeasured(kp, msg.size, intr)
        kp[outside | folded, 2] = 0.0
        if confidence_scale != 1.0:
            kp[:, :, 2] = np.minimum(kp[:, :, 2] * confidence_scale, 1.0)
        conf = kp[:, BODY, 2] >= self.min_conf
        keep = conf.sum(1) >= 4
        kp, conf = kp[keep], conf[keep]
        if not len(kp):
            return
        uv = kp[:, BODY, :2].reshape(-1, 2)
        xy = undistort(uv, intr).reshape(len(kp), len(BODY), 2)
        open_ = [tr for tr in self.tracks if tr.stamps and t - tr.stamps[-1] <= self.max_gap]
        diag = float(np.hypot(*msg.size))
        taken: set[int] = set()
        used_tr: set[int] = set()
        if open_:
            prev = np.stack([tr.px for tr in open_])  # (T, 17, 3)
            dts = np.array([t - tr.stamps[-1] for tr in open_])
            both = (prev[:, None, BODY, 2] >= self.min_conf) & conf[None]
            dist = np.linalg.norm(prev[:, None, BODY, :2] - kp[None, :, BODY, :2], axis=-1)
            n = both.sum(-1)
            cost = np.where(n >= 4, np.where(both, dist, 0).sum(-1) / np.maximum(n, 1), np.inf)
            limit = diag * np.maximum(_MATCH_MIN_FRAC, _MATCH_DIAG_PER_S * dts)
            for flat in np.argsort(cost, axis=None):
                i, j = divmod(int(flat), cost.shape[1])
                if not np.isfinite(cost[i, j]):
                    break
                if i in used_tr or j in taken or cost[i, j] > limit[i]:
                    continue
                open_[i].add(t, xy[j], conf[j], kp[j])
                used_tr.add(i)
                taken.add(j)
        for j in range(len(kp)):
            if j not in taken:
                tr = _Track()
                tr.add(t, xy[j], conf[j], kp[j])
                self.tracks.append(tr)

    def frozen(self) -> "_SensorTracks":
        """A copy of the tracks as they are now (for a ``ClockJob`` in another thread)."""
        c = copy.copy(self)
        c.tracks = [tr.frozen() for tr in self.tracks]
        return c

    def prune(self, before: float) -> None:
        self.tracks = [tr for tr in self.tracks if tr.stamps and tr.stamps[-1] >= before]
        for tr in self.tracks:
            tr.trim(before)

    def find(self, q: float, xy: np.ndarray, tol: float, lo: float, hi: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The track through detection xy (J, 2) normalised at raw stamp q (median joint
        distance below tol), cut to [lo, hi]; None when no track passes there."""
        best, best_d = None, tol
        for tr in self.tracks:
            if len(tr.stamps) < 2 or tr.stamps[0] > q or tr.stamps[-1] < q:
                continue
            st, txy, tok = tr.arrays()
            p, ok = interpolate_track(st, txy, tok, np.array(q), 2 * self.max_gap)
            both = ok & np.isfinite(xy).all(-1)
            if both.sum() < 4:
                continue
            d = float(np.median(np.linalg.norm(p[both] - xy[both], axis=-1)))
            if d < best_d:
                best, best_d = (st, txy, tok), d
        if best is None:
            return None
        st, txy, tok = best
        i0 = max(int(np.searchsorted(st, lo, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(st, hi, side="left")) + 1, len(st))
        if i1 - i0 < 2:
            return None
        return st[i0:i1].copy(), txy[i0:i1].copy(), tok[i0:i1].copy()


# ------------------------------------------------------------------ the estimator


def _triangulate_rows(rows: list[tuple[_Record, np.ndarray]], R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, J, 3) the BODY joints of each record from its views where the mask says."""
    N, J = len(rows), len(BODY)
    V = max(int(o.sum()) for _, o in rows)
    cams = np.zeros((N, V), np.int64)
    xy = np.full((N, V, J, 2), np.nan)
    for n, (r, o) in enumerate(rows):
        k = int(o.sum())
        cams[n, :k] = r.cams[o]
        xy[n, :k] = r.xy[o]
    pts = np.transpose(xy, (0, 2, 1, 3)).reshape(N * J, V, 2)
    return triangulate_batch(R, t, np.repeat(cams[:, None, :], J, axis=1).reshape(N * J, V), pts).reshape(N, J, 3)


@dataclass
class _Record:
    """A hypothesis as the estimator keeps it: time, cameras (V,), BODY joints
    (V, J, 2) normalised, the offsets applied when it was made (S,), and per view the
    sensor's track around it (None: not found / not looked up yet); ``free``: for
    sensors not in it, their track identified as this person by projection."""

    time: float
    cams: np.ndarray
    xy: np.ndarray
    applied: np.ndarray
    tracks: list | None = None
    free: dict = field(default_factory=dict)  # sensor not in it -> its track identified by projection, or None
    memo: dict = field(default_factory=dict)  # sensor -> its track taken at grids (``profile``)


@dataclass(frozen=True)
class ClockResult:
    """What a ``ClockJob`` found: per sensor (S,) the estimate on the synchronised clock
    (s, NaN = none), its std (s, the blocks' jackknife), the residual scale (px), the
    blocks it rests on, where the next fine grid is centred (s, NaN = search the whole
    range), the pose fitted with the offset ((R (3, 3), t (3,)) or None), why a sensor's
    estimate was not updated (None: it was), and the spread over the reference cameras
    (s, NaN = not measured; ``_reference_spread``)."""

    raw: np.ndarray
    std: np.ndarray
    scale: np.ndarray
    nblocks: np.ndarray
    center: np.ndarray
    pose: tuple
    note: tuple[str | None, ...]
    ref_std: np.ndarray | None = None


@dataclass
class ClockJob:
    """The heavy part of an estimator update (seconds of numpy), made to run in another
    thread while the caller's loop goes on: ``ClockOffsetEstimator.begin`` takes it (on
    the caller's thread), ``run`` computes (any thread; it reads only the job's copies
    and writes only the caches of the records it holds, which nothing else touches
    while it runs), ``ClockOffsetEstimator.finish`` takes the result (caller's thread).

    now: data time of the estimate. R (C, 3, 3), t (C, 3): the poses it uses (copies).
    records: the records in the window. work: the estimator's copy it runs on.
    cancelled: set from any thread to end ``run`` early (between sensors; it returns None).
    spread: also measure each estimate's spread over its reference cameras (costly: a
    fine search per camera left out; ``reestimate``).
    """

    now: float
    flush: bool
    R: np.ndarray
    t: np.ndarray
    records: list
    work: "ClockOffsetEstimator"
    cancelled: bool = False
    spread: bool = False

    def run(self) -> ClockResult | None:
        return self.work._compute(self)

    def cancel(self) -> None:
        self.cancelled = True


class ClockOffsetEstimator:
    """Online estimate of every sensor's clock offset (see the module's docstring).

    ``push`` every accepted message (raw stamps); ``add`` the pipeline's hypotheses;
    ``update(now, R, t)`` when ``due`` with the current pose estimate; ``clocks()`` the
    per-sensor result; ``applied`` (S,) the offsets to subtract from stamps.
    """

    def __init__(self, config: ClockConfig, names: tuple[str, ...], intrinsics: Mapping[str, Intrinsics],
                 min_confidence: float, confidence: ConfidenceScale | None = None):
        """``confidence``: the sensors' confidence scales (the preprocessing's), applied
        before ``min_confidence``."""
        self.cfg = config
        self.confidence = confidence or ConfidenceScale(None)
        self.names = tuple(names)
        S = len(self.names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.intrinsics = dict(intrinsics)
        self._scaled: dict[tuple[str, tuple[int, int]], Intrinsics | None] = {}
        self.tracks = [_SensorTracks(self.intrinsics[n], min_confidence, config.track_gap) for n in self.names]
        self.focal = np.array([0.5 * (self.intrinsics[n].fx + self.intrinsics[n].fy) for n in self.names])
        self.records: deque[_Record] = deque()
        self.last_update: float | None = None
        self.raw = np.full(S, np.nan)  # estimates on the synchronised clock (what a raw stamp is ahead of it)
        self.offset = np.full(S, np.nan)  # ... relative to the median sensor
        self.std = np.full(S, np.nan)  # the blocks' jackknife
        self.ref_std = np.full(S, np.nan)  # the spread over reference cameras (``_reference_spread``), NaN: not measured
        self.scale = np.full(S, np.nan)  # px: the robust residual scale of the sensor's last fit
        self.nblocks = np.zeros(S, np.int64)
        self.pose: list[tuple[np.ndarray, np.ndarray] | None] = [None] * S  # the sensor's pose fitted with its offset
        self.center = np.full(S, np.nan)  # where the fine grid is centred (NaN: search the whole range)
        self.applied = np.zeros(S)
        self.anchor = np.full(S, np.nan)  # estimate at the last drift check point
        self.anchor_std = np.full(S, np.nan)
        self.drift_candidate = np.full(S, np.nan)  # a fresh estimate beyond the anchor, to be confirmed by the next
        self.drift_candidate_std = np.full(S, np.nan)
        self.drift_warnings = np.zeros(S, np.int64)
        self.candidate = np.full(S, np.nan)  # the last fresh estimate that passed the test to be applied (``_first``)
        self.candidate_std = np.full(S, np.nan)
        self.note: list[str | None] = ["no update yet"] * S
        # a synchronised sensor whose fresh estimates agree is estimated less often (``_settle``)
        self.every = np.full(S, config.interval)  # s between its estimates
        self.next_due = np.full(S, -np.inf)  # data time of its next estimate
        self.settle_ref = np.full(S, np.nan)  # its last fresh estimate, and std
        self.settle_ref_std = np.full(S, np.nan)
        self._job: ClockJob | None = None  # the update in flight (``begin`` .. ``finish``)
        self.pose_cov: np.ndarray | None = None  # (S, 6, 6) of the poses of the update in flight (``begin``)
        self._tri: dict[tuple[int, bytes], np.ndarray] = {}  # a job's triangulations (``_triangulate``)

    @property
    def _margin(self) -> float:
        """s of data time after a hypothesis until its sensors' tracks around it are complete."""
        return self.cfg.max_offset + 2 * self.cfg.track_gap + 0.5

    # -------------------------------------------------------------- input

    def _intr(self, sensor: str, size: tuple[int, int]) -> Intrinsics | None:
        key = (sensor, tuple(size))
        if key not in self._scaled:
            self._scaled[key] = self.intrinsics[sensor].at(size)
        return self._scaled[key]

    def push(self, msg: KeypointMessage) -> None:
        """One message of a known sensor, with its raw stamp."""
        c = self.index.get(msg.sensor)
        if c is None:
            return
        intr = self._intr(msg.sensor, msg.size)
        if intr is None:
            return
        self.tracks[c].push(msg, intr, self.confidence.factor(msg.sensor))

    def add(self, hyps: Iterable[Hypothesis]) -> None:
        """Hypotheses of one frameset (time on the synchronised clock, timed with the
        offsets applied now)."""
        for h in hyps:
            if len(h.cams) >= 3:  # a sensor's sample needs two other views
                self.records.append(_Record(h.time, h.cams.copy(), h.xy[:, BODY].copy(), self.applied.copy()))

    # -------------------------------------------------------------- estimation

    def due(self, now: float | None) -> bool:
        return (self.cfg.estimate and now is not None and bool(self.records) and self._job is None
                and (self.last_update is None or now - self.last_update >= self.cfg.interval))

    def _attach_tracks(self, records: Iterable[_Record], now: float, flush: bool) -> None:
        half = self.cfg.max_offset + self.cfg.track_gap
        for rec in records:
            if rec.tracks is not None:
                continue
            if not flush and rec.time + self._margin > now:
                break
            rec.tracks = []
            for v, c in enumerate(rec.cams):
                q = rec.time + rec.applied[c]
                tol = self.cfg.view_match_px / self.focal[c]
                rec.tracks.append(self.tracks[c].find(q, rec.xy[v], tol, rec.time - half, rec.time + half))

    def update(self, now: float, R: np.ndarray, t: np.ndarray, *, flush: bool = False,
               P: np.ndarray | None = None) -> list[str]:
        """Estimate from the data up to ``now`` (all of it with ``flush``) with the
        poses R (C, 3, 3), t (C, 3) (and their covariance P (C, 6, 6), see ``begin``),
        in this thread (``begin`` + ``ClockJob.run`` + ``finish``); returns the sensors
        whose applied offset changed."""
        job = self.begin(now, R, t, flush=flush, P=P)
        return self.finish(job, job.run())

    def begin(self, now: float, R: np.ndarray, t: np.ndarray, *, flush: bool = False,
              P: np.ndarray | None = None, spread: bool = False) -> "ClockJob":
        """The cheap part of an update, on the caller's thread: drop records and track
        points that left the window, and take a ``ClockJob`` with copies of what the
        estimate reads (the per-sensor state, the tracks as they are now, the records in
        the window). ``push`` and ``add`` may go on while the job runs elsewhere; ``due``
        says False until ``finish`` (a ``flush`` job replaces one in flight).
        P (C, 6, 6): the poses' covariance (rotation, translation; right perturbation):
        a sensor's gate for identifying its tracks grows with it (None: the fixed gate).
        spread: the job also measures ``_reference_spread``."""
        S = len(self.names)
        assert R.shape == (S, 3, 3) and t.shape == (S, 3) and (P is None or P.shape == (S, 6, 6))
        self.last_update = now
        cfg = self.cfg
        while self.records and self.records[0].time < now - cfg.window:
            self.records.popleft()
        horizon = (self.records[0].time if self.records else now) - cfg.max_offset - 2 * cfg.track_gap - 1.0
        for st in self.tracks:
            st.prune(horizon)
        work = copy.copy(self)  # shares the config and the constant tables; the state below is copied
        work.tracks = [st.frozen() for st in self.tracks]
        work.records = deque()
        for k in ("raw", "offset", "std", "scale", "nblocks", "center", "applied", "anchor", "anchor_std",
                  "drift_candidate", "drift_candidate_std",
                  "drift_warnings", "next_due"):
            setattr(work, k, getattr(self, k).copy())
        work.pose, work.note = list(self.pose), list(self.note)
        work._job = None
        work.pose_cov = None if P is None else P.copy()
        job = ClockJob(now, flush, R.copy(), t.copy(), list(self.records), work, spread=spread)
        self._job = job
        return job

    def finish(self, job: "ClockJob", result: "ClockResult | None") -> list[str]:
        """The cheap part after a job: take its estimates (None: it failed or was
        cancelled) and decide the offsets to apply; returns the sensors whose applied
        offset changed. A job that is no longer the one in flight changes nothing."""
        if job is not self._job:
            return []
        self._job = None
        if result is None:
            return []
        self._take(result)
        self._settle(job.now)
        for live, done in zip(self.tracks, job.work.tracks):  # keep the arrays the job built
            for a, b in zip(live.tracks, done.tracks):
                if a._arrays is None and b._arrays is not None and len(a.stamps) == len(b.stamps):
                    a._arrays = b._arrays
        return self._apply(job.now)

    def reestimate(self, now: float, R: np.ndarray, t: np.ndarray, P: np.ndarray | None = None) -> None:
        """Estimate once more from all the data in the window with the poses R (C, 3, 3),
        t (C, 3) (covariance P as for ``begin``), without changing what is applied: the
        last step of a run, after its final adjustment. A sensor's samples are its
        tracks against the persons triangulated from the others, so the estimate is only
        as good as those poses: the poses of the online filter, before the final batch,
        biased the offset of one sensor on seed 1 of the bench by 5 ms (+7.6 ms error with
        them, +2.5 ms with the batch's, +2.3 ms with the true ones: docs/clock_offsets.md).
        Offsets applied stay as they were (the batch used them); what changes is what is
        reported (``clocks``) and where the next fine grids are centred, for every sensor
        whose re-estimate is at least as certain as its estimate before. With
        ``clock.reference_spread`` it also measures each estimate's spread over its
        reference cameras (``_reference_spread``; the std reported is then the larger)."""
        job = self.begin(now, R, t, flush=True, P=P, spread=self.cfg.reference_spread)
        self._job = None
        result = job.run()
        if result is None:
            return
        # a sensor whose re-estimate is less certain than the estimate it would replace keeps
        # that one: the final poses remove a bias, they do not make weak data stronger (seed 5
        # of the bench: cam_13's +123.7 +- 2.7 ms, 5 ms off, would have become +132.8 +- 9.2)
        # (the spread over the reference cameras measured now stays with a kept estimate: it
        # is the same window's, and the cameras are the same)
        before = [(self.raw[s], self.std[s], self.scale[s], self.nblocks[s], self.center[s], self.pose[s],
                   self.note[s]) for s in range(len(self.names))]
        self._take(result)
        for s, (raw, std, scale, nb, center, pose, note) in enumerate(before):
            if np.isfinite(raw) and np.isfinite(std) and not self.std[s] <= std:
                self.raw[s], self.std[s], self.scale[s], self.nblocks[s], self.center[s] = raw, std, scale, nb, center
                self.pose[s], self.note[s] = pose, note
        self._relative()

    def _take(self, result: "ClockResult") -> None:
        """A job's estimates become this estimator's."""
        self.raw, self.std, self.scale = result.raw.copy(), result.std.copy(), result.scale.copy()
        self.ref_std = np.full(len(self.raw), np.nan) if result.ref_std is None else result.ref_std.copy()
        self.nblocks, self.center, self.pose = result.nblocks.copy(), result.center.copy(), list(result.pose)
        self.note = list(result.note)

    def _settle(self, now: float) -> None:
        """When each sensor is estimated next. A synchronised sensor (nothing applied, its
        estimate within half of ``clock.min_apply`` of the median) whose fresh estimate
        agrees with its last fresh one (within 2.5 combined std or ``clock.min_change``,
        its std within ``clock.max_std``) doubles its interval, up to
        ``clock.settled_interval``; any other fresh estimate sets it back to
        ``clock.interval``. Most of the estimator's CPU went into sensors whose clocks
        are fine; a sensor with an offset is refined at every update (the calibration
        uses its timing), and a synchronised one that starts to drift is seen within a
        settled interval."""
        cfg = self.cfg
        self._relative()
        for s in range(len(self.names)):
            if self.note[s] is not None:  # not estimated this time (skipped, or no estimate)
                continue
            o, e = self.raw[s], self.std[s]
            ref, ref_e = self.settle_ref[s], self.settle_ref_std[s]
            agree = (np.isfinite(ref) and e <= cfg.max_std and self.applied[s] == 0.0
                     and abs(self.offset[s]) < cfg.min_apply / 2
                     and abs(o - ref) <= max(cfg.min_change, 2.5 * math.hypot(e, ref_e)))
            self.every[s] = min(2 * self.every[s], max(cfg.settled_interval, cfg.interval)) if agree else cfg.interval
            self.next_due[s] = now + self.every[s] - 0.5 * cfg.interval  # due at the update nearest to that
            self.settle_ref[s], self.settle_ref_std[s] = o, e

    def _relative(self) -> None:
        """The offsets relative to the sensors' median (the network's own clock)."""
        est = np.isfinite(self.raw)
        self.offset = self.raw - np.median(self.raw[est]) if est.any() else self.raw.copy()

    def cancel(self) -> None:
        """Ask the job in flight (if any) to end early."""
        if self._job is not None:
            self._job.cancel()

    def _compute(self, job: "ClockJob") -> "ClockResult | None":
        """The heavy part, on the job's copies (``self`` is ``job.work``)."""
        # the persons the other views triangulate are the same for every sensor not in a
        # record, and one of V leave-one-out sets for those in it: made once per job
        self._tri: dict[tuple[int, bytes], np.ndarray] = {}
        self.ref_std = np.full(len(self.names), np.nan)  # this job's measure, or none
        self._attach_tracks(job.records, job.now, job.flush)
        recs = [r for r in job.records if r.tracks is not None]
        if not recs:
            self.note = ["no samples: no person seen by three cameras in the window yet"] * len(self.names)
        else:
            R, t, S = job.R, job.t, len(self.names)
            todo = [s for s in range(S) if job.flush or self.next_due[s] <= job.now]
            for s in set(range(S)) - set(todo):
                self.note[s] = (f"settled: synchronised, estimated every {self.every[s]:g} s of data "
                                f"(next in {self.next_due[s] - job.now:.0f} s)")
            trusted = self._trusted(recs)
            for s in todo:
                if job.cancelled:
                    return None
                self._estimate_sensor(s, recs, trusted[0], R, t)
            again = self._trusted(recs)
            if not np.array_equal(again[1], trusted[1]):  # views found mistimed that were used: once more without them
                for s in todo:
                    if job.cancelled:
                        return None
                    self._estimate_sensor(s, recs, again[0], R, t)
            if job.spread:
                for s in todo:
                    if job.cancelled:
                        return None
                    if self.note[s] is None:
                        self.ref_std[s] = self._reference_spread(s, recs, again[0], R, t)
        return ClockResult(self.raw, self.std, self.scale, self.nblocks, self.center, tuple(self.pose),
                           tuple(self.note), self.ref_std.copy())

    def _trusted(self, recs: list[_Record]) -> tuple[list[np.ndarray], np.ndarray]:
        """Per record (V,) bool: views timed right as far as the current estimates know
        (a sensor's view made with an offset applied that its estimate now contradicts
        is left out of the others' 3D); and a fingerprint of that choice. Estimates are
        compared relative to the median sensor, as offsets are applied: the raw ones
        share the synchronised clock's own lag (seed 2 of the bench: about -10 ms on
        every sensor), which would otherwise mark every view of a synchronised sensor
        as mistimed. With fewer than 3 estimates the median is no reference (one of them
        may be the mistimed one): the raw estimates then."""
        tol = max(self.cfg.retime_tolerance, 0.0)
        fin = np.isfinite(self.raw)
        rel = self.raw - (np.median(self.raw[fin]) if fin.sum() >= 3 else 0.0)
        out = []
        for r in recs:
            est, applied = rel[r.cams], r.applied[r.cams]
            # a view made with nothing applied is as timed as NTP keeps it while its estimate
            # is within NTP's spread: that is not applied either (``_apply``)
            ok = ~np.isfinite(est) | (np.abs(est - applied) <= np.where(applied == 0.0, max(tol, self.cfg.min_apply),
                                                                         tol))
            out.append(ok)
        return out, np.concatenate(out) if out else np.zeros(0, bool)

    def _samples(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray, t: np.ndarray,
                 keep: int | None = None) -> Samples | None:
        """Sensor s's samples: records with s in them (its track known from its view, the
        person from the other views) and records without it whose person one of its
        tracks clearly is (``_identify``); at most ``keep`` of them, spread in time."""
        rows, trs = self._rows(s, recs, trusted, R, t)
        if keep is not None and len(rows) > keep:
            idx = np.linspace(0, len(rows) - 1, keep).round().astype(int)
            rows, trs = [rows[i] for i in idx], [trs[i] for i in idx]
        if not rows:
            return None
        return Samples(self._triangulate(rows, R, t), np.array([r.time for r, _ in rows]), tuple(trs),
                       tuple(r.memo.setdefault(s, {}) for r, _ in rows))

    def _rows(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray, t: np.ndarray
              ) -> tuple[list[tuple[_Record, np.ndarray]], list]:
        """Sensor s's samples as (record, mask (V,) of the views that place the person)
        and its track in each (``_samples``)."""
        self._identify(s, recs, trusted, R, t)
        rows, trs = [], []
        for i, r in enumerate(recs):
            hit = np.flatnonzero(r.cams == s)
            if len(hit):
                tr = r.tracks[hit[0]]
                others = trusted[i] & (r.cams != s)
            else:
                tr = r.free.get(s)
                others = trusted[i]
            if tr is None or others.sum() < 2:
                continue
            rows.append((r, others))
            trs.append(tr)
        return rows, trs

    def _reference_spread(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray,
                          t: np.ndarray) -> float:
        """s: how far sensor s's estimate moves with the cameras that place its persons:
        the estimate again (the fine grid around it, the pose fitted at each candidate)
        with each camera in at least ``_SPREAD_MIN_SHARE`` of its samples left out of the
        others' 3D, and the jackknife std of those estimates; NaN with fewer than 2 (two
        are a crude spread, but a sensor whose persons two cameras place depends on
        them most).

        The blocks' jackknife cannot see an error of the others' 3D that stays with the
        cameras (a lens a little off its file, the few pairs that see a spot): it moves
        every block alike. bench/clock_offsets.py, seeds 1-5: the errors of the 100
        sensors were 1.3-2.0 of the blocks' std (rms per seed; 17 beyond 2 std), 0.8-1.2
        of the larger of the two (4 beyond 2 std; docs/clock_offsets.md, Session 51)."""
        cfg = self.cfg
        rows, _ = self._rows(s, recs, trusted, R, t)
        if not rows or not np.isfinite(self.raw[s]):
            return float("nan")
        counts = np.bincount(np.concatenate([r.cams[m] for r, m in rows]), minlength=len(self.names))
        grid = (round(self.raw[s] / cfg.fine_step) * cfg.fine_step
                + np.arange(-cfg.fine_half, cfg.fine_half + 1e-9, cfg.fine_step))
        found = []
        for c in np.flatnonzero(counts >= _SPREAD_MIN_SHARE * len(rows)):
            smp = self._samples(s, recs, [m & (r.cams != c) for r, m in zip(recs, trusted)], R, t)
            if smp is None:
                continue
            res = profile(smp, grid, *self._start(s, R, t), cfg.track_gap, cfg.block, float(self.focal[s]),
                          cfg.min_scale_px, anneal=False)
            if self._unfit(res) is not None:
                continue
            m = parabola_minimum(res[0].sum(0), grid)
            if m is not None:
                found.append(m)
        G = len(found)
        if G < 2:
            return float("nan")
        a = np.array(found)
        return math.sqrt((G - 1) / G * float(((a - a.mean()) ** 2).sum()))

    def _triangulate(self, rows: list[tuple[_Record, np.ndarray]], R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, J, 3) the BODY joints of each record of ``rows`` (N >= 1) from its views where
        the mask says, each (record, mask) triangulated once per job (R, t are the job's
        throughout)."""
        keys = [(id(r), o.tobytes()) for r, o in rows]
        todo = {k: row for k, row in zip(keys, rows) if k not in self._tri}
        if todo:
            X = _triangulate_rows(list(todo.values()), R, t)
            self._tri.update(zip(todo, X))
        return np.stack([self._tri[k] for k in keys])

    def _identify(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray, t: np.ndarray) -> None:
        """For records without sensor s (it missed the frameset or was not associated):
        which of its tracks is that person. The person from the
        other views is projected into s (its fitted pose when there is one); a track is
        the person when, at its best offset within the range searched, it fits clearly
        better than any other track (ratio test) and within the gate."""
        cfg = self.cfg
        # decided once per record, but a sensor still without an estimate looks again at
        # the records where it found nobody (its pose and gate have changed since)
        retry = not np.isfinite(self.raw[s])
        todo = [i for i, r in enumerate(recs) if (s not in r.free or (retry and r.free[s] is None))
                and not (r.cams == s).any() and trusted[i].sum() >= 2]
        if not todo:
            return
        Rs, ts = self.pose[s] if self.pose[s] is not None else (R[s], t[s])
        c = self.center[s]
        grid = (np.arange(-cfg.max_offset, cfg.max_offset + 1e-9, 2 * cfg.coarse_step) if not np.isfinite(c)
                else c + np.arange(-2 * cfg.fine_half, 2 * cfg.fine_half + 1e-9, cfg.fine_step))
        X = self._triangulate([(recs[i], trusted[i]) for i in todo], R, t)
        Xc = (X - ts) @ Rs
        with np.errstate(invalid="ignore", divide="ignore"):
            proj = np.where((Xc[..., 2] > 0.1)[..., None], Xc[..., :2] / Xc[..., 2:3], np.nan)  # (N, J, 2)
        live = [tr for tr in self.tracks[s].tracks if len(tr.stamps) >= 2]
        spans = np.array([(tr.stamps[0], tr.stamps[-1]) for tr in live]).reshape(-1, 2)
        half = cfg.max_offset + cfg.track_gap
        gates = self._gates(s, proj, Rs, ts, X)
        for n, i in enumerate(todo):
            r = recs[i]
            r.free[s] = None
            vis = np.isfinite(proj[n]).all(-1)
            if vis.sum() < 4 or not len(live):
                continue
            q = r.time + grid
            cand = np.flatnonzero((spans[:, 0] <= q[-1]) & (spans[:, 1] >= q[0]))
            dist, owner = [], []
            for j in cand:
                pos, ok = interpolate_track(*live[j].arrays(), q, cfg.track_gap)  # (K, J, 2), (K, J)
                ok = ok & vis
                enough = ok.sum(1) >= 4
                if not enough.any():
                    continue
                dist.append(np.where(ok[enough], np.linalg.norm(pos[enough] - np.nan_to_num(proj[n]), axis=-1), np.nan))
                owner.append(j)
            if not dist:
                continue
            # one median over every candidate's grid rows (per-call overhead was a sixth of the estimate)
            med = _row_nanmedian(np.concatenate(dist))
            first = np.cumsum([0] + [len(d) for d in dist[:-1]])
            best = sorted(zip(np.minimum.reduceat(med, first).tolist(), owner))
            if best[0][0] > gates[n] or (len(best) > 1 and best[0][0] > _RATIO * best[1][0]):
                continue
            st, txy, tok = live[best[0][1]].arrays()
            i0 = max(int(np.searchsorted(st, r.time - half, side="right")) - 1, 0)
            i1 = min(int(np.searchsorted(st, r.time + half, side="left")) + 1, len(st))
            if i1 - i0 >= 2:
                r.free[s] = (st[i0:i1].copy(), txy[i0:i1].copy(), tok[i0:i1].copy())

    def _gates(self, s: int, proj: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """(N,) normalised: how close a track of sensor s must come to each person X
        (N, J, 3) projected into it (proj (N, J, 2), NaN behind it)
        to be that person: ``clock.match_px`` widened by ``clock.match_sigmas`` times
        the projection's std under the pose's covariance (median over the person's
        joints, the larger axis of each joint's 2x2), at most ``clock.match_max_px``.
        A camera whose mistimed data left it badly calibrated is also an uncertain one:
        a fixed gate misses its persons, and with them the samples that would time it."""
        cfg = self.cfg
        f = float(self.focal[s])
        base = np.full(len(X), cfg.match_px / f)
        if self.pose_cov is None or cfg.match_sigmas <= 0:
            return base
        vis = np.isfinite(proj).all(-1)  # (N, J)
        if not vis.any():
            return base
        _, Jac = project_normalised(R, t, X[vis])  # (M, 2, 6)
        C = Jac @ self.pose_cov[s] @ np.swapaxes(Jac, 1, 2)  # (M, 2, 2)
        a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
        sig = np.full(vis.shape, np.nan)
        sig[vis] = np.sqrt(np.maximum(0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b), 0.0))
        med = np.zeros(len(X))
        rows = vis.any(1)
        med[rows] = np.nanmedian(sig[rows], axis=1)
        return np.minimum(np.hypot(base, cfg.match_sigmas * med), max(cfg.match_max_px, cfg.match_px) / f)

    def _start(self, s: int, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.pose[s] if self.pose[s] is not None else (R[s], t[s])

    def _estimate_sensor(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray,
                         t: np.ndarray) -> None:
        self.note[s] = self._estimate_sensor_why(s, recs, trusted, R, t)

    def _unfit(self, res: tuple | None, scale: bool = True) -> str | None:
        """Why a profile cannot be used, or None (``scale``: also when its residuals say
        the pose is too far off; not for the search with the pose held, whose residuals
        include the pose's error, which the fine search then fits)."""
        if res is None:
            return "too few joints seen by it and two other cameras"
        if res[1] < self.cfg.min_blocks:
            return f"data in {res[1]} blocks of {self.cfg.block:g} s (needs {self.cfg.min_blocks})"
        if scale and res[2] > self.cfg.max_scale_px:
            return f"its residuals are {res[2]:.1f} px (at most {self.cfg.max_scale_px:g}): its pose is too far off"
        return None

    def _estimate_sensor_why(self, s: int, recs: list[_Record], trusted: list[np.ndarray], R: np.ndarray,
                             t: np.ndarray) -> str | None:
        cfg = self.cfg
        f = float(self.focal[s])
        fine = np.arange(-cfg.fine_half, cfg.fine_half + 1e-9, cfg.fine_step)
        center = self.center[s]
        if not np.isfinite(center):  # search the whole range on a subsample
            smp = self._samples(s, recs, trusted, R, t, keep=_COARSE_SAMPLES)
            if smp is None:
                return "no samples: no person seen by it and two other cameras timed right"
            grid = np.arange(-cfg.max_offset, cfg.max_offset + 1e-9, cfg.coarse_step)
            # the pose held (its fit at every candidate would let a pose shift mimic a
            # time shift over the whole range); the fine search around the minimum fits it
            res = profile(smp, grid, *self._start(s, R, t), cfg.track_gap, cfg.block, f, cfg.min_scale_px,
                          nuisance=cfg.coarse_nuisance)
            if (why := self._unfit(res, scale=cfg.coarse_nuisance == "pose")) is not None:
                return "coarse search: " + why
            k = int(np.argmin(res[0].sum(0)))
            if k == 0 or k == len(grid) - 1:
                return f"coarse search: the best offset is at the edge of ±{cfg.max_offset * 1000:.0f} ms"
            center = float(grid[k])
        smp = self._samples(s, recs, trusted, R, t)
        if smp is None:
            return "no samples: no person seen by it and two other cameras timed right"
        for _ in range(_FINE_WALK):  # the fine grid follows its minimum when it lies near its edge
            res = profile(smp, center + fine, *self._start(s, R, t), cfg.track_gap, cfg.block, f, cfg.min_scale_px,
                          anneal=self.pose[s] is None)
            if (why := self._unfit(res)) is not None:
                return "fine search: " + why
            total = res[0].sum(0)
            k = int(np.argmin(total))
            if 2 <= k < len(fine) - 2:
                break
            center = float(center + fine[k])
            if abs(center) > cfg.max_offset:
                self.center[s] = np.nan
                return f"fine search: the minimum runs beyond ±{cfg.max_offset * 1000:.0f} ms"
        else:
            self.center[s] = np.nan  # it keeps running away: search again next time
            return "fine search: the minimum keeps moving to the grid's edge (searched again next time)"
        r = jackknife_minimum(res[0], center + fine)
        if r is None:
            return "no clear minimum (jackknife)"
        self.raw[s], self.std[s] = r
        self.scale[s], self.nblocks[s] = res[2], res[1]
        self.pose[s] = res[4]
        self.center[s] = round(r[0] / cfg.fine_step) * cfg.fine_step if r[1] < cfg.fine_half / 2 else np.nan
        return None

    def _apply(self, now: float) -> list[str]:
        cfg = self.cfg
        self._relative()
        changed = []
        for s, n in enumerate(self.names):
            o, e = self.offset[s], self.std[s]
            if not np.isfinite(o) or e > cfg.max_std:
                if self.note[s] is None:  # a fresh estimate too uncertain: no candidate to confirm
                    self.candidate[s] = self.candidate_std[s] = np.nan
                continue
            self._check_drift(s, o, e, now)
            # an offset within NTP's spread is left alone (min_apply, ``_first``); once
            # applied it is kept (and followed) until it falls below half of that
            # (hysteresis). "3 std" with the std from few blocks: Student's t on
            # blocks - 1 degrees of freedom (8 blocks: 4.5 std; 24: 3.4)
            k = _sigmas(int(self.nblocks[s]))
            if self.applied[s] == 0.0:
                if self._first(s, o, e, k):
                    self.applied[s] = o
                    changed.append(n)
                continue
            target = o if abs(o) >= max(cfg.min_apply / 2, k * e) else 0.0
            step = cfg.min_change
            # refining an applied offset: 2.5 std (the t factor is for "is there one";
            # measured: with it here too, seed 1 with offsets ended 0.038 m off, not 0.014)
            refine = target != 0.0 and self.applied[s] != 0.0
            if abs(target - self.applied[s]) > max(step, (2.5 if refine else 2.5 / 3 * k) * e):
                self.applied[s] = target
                changed.append(n)
        return changed

    def _first(self, s: int, o: float, e: float, k: float) -> bool:
        """Whether sensor s's estimate o (std e, tail factor k) is applied while nothing
        is: the offset itself (not only the estimate) is beyond NTP's spread, |o| - k e
        >= ``clock.min_apply``, on two successive fresh estimates of the sensor that
        agree within k times their combined std. A single estimate from few blocks can
        pass its own jackknife's test and be wrong (a synchronised sensor, +3.9 ms true,
        estimated +16.5 ms from 11 blocks and applied); a real offset is found again
        ten seconds later. A stale estimate (this update left the sensor as it was)
        counts once."""
        if self.note[s] is not None:
            return False
        passes = abs(o) - k * e >= self.cfg.min_apply
        prev, prev_std = self.candidate[s], self.candidate_std[s]
        self.candidate[s], self.candidate_std[s] = (o, e) if passes else (np.nan, np.nan)
        return bool(passes and np.isfinite(prev) and abs(o - prev) <= k * math.hypot(e, prev_std))

    def relocation(self, c: int, R: np.ndarray, t: np.ndarray, P: np.ndarray, calibrated: bool
                   ) -> tuple[np.ndarray, np.ndarray] | None:
        """Where to put camera c when its first offset is applied: the pose the estimate
        fitted with that offset (a robust PnP of its tracks against the others' 3D,
        timed right) when the current one, R (3, 3), t (3,) with covariance P (6, 6), is
        not calibrated yet or lies beyond the 3-sigma tail of P from it (chi² with 6 dof,
        0.27 %); None: keep it. A mistimed sensor's views join no hypothesis (its person
        is 14-28 cm elsewhere), so its camera stays at the initial estimate, or gets
        calibrated to its mistimed data; once the offset is applied its new views
        would have to be associated with that pose."""
        pose = self.pose[c]
        if pose is None:
            return None
        if not calibrated:
            return pose
        v = pose_local(R, t, *pose)
        try:
            d2 = float(v @ np.linalg.solve(P, v))
        except np.linalg.LinAlgError:
            return None
        return pose if d2 > _CHI2_6 else None

    def _check_drift(self, c: int, o: float, s: float, now: float) -> None:
        """Warn when sensor c's estimate o (std s) moved from the last anchor by more than
        ``clock.drift_warning`` and 3 stds, on two successive fresh estimates that agree
        (as a first offset is applied, ``_first``): under a noisy detector single
        estimates wander by tens of ms with stds that do not say so (docs/clock_offsets.md,
        session 9: 11 warnings on synchronised sensors, seed 1), a real change stays."""
        if not np.isfinite(self.anchor[c]):
            self.anchor[c], self.anchor_std[c] = o, s
            return
        if self.note[c] is not None:  # a stale estimate confirms nothing
            return
        moved = o - self.anchor[c]
        beyond = abs(moved) > self.cfg.drift_warning and abs(moved) > 3 * math.hypot(s, self.anchor_std[c])
        if beyond and self.applied[c] == 0.0 and abs(o) < self.cfg.min_apply:
            # back within NTP's spread with nothing applied: an early estimate was wrong, the
            # clock is fine (the bench's synchronised sensors: 10 of 13 warnings were these)
            self.anchor[c], self.anchor_std[c] = o, s
            self.drift_candidate[c] = self.drift_candidate_std[c] = np.nan
            return
        prev, prev_std = self.drift_candidate[c], self.drift_candidate_std[c]
        self.drift_candidate[c], self.drift_candidate_std[c] = (o, s) if beyond else (np.nan, np.nan)
        if beyond and np.isfinite(prev) and abs(o - prev) <= 3 * math.hypot(s, prev_std):
            self.drift_candidate[c] = self.drift_candidate_std[c] = np.nan
            self.drift_warnings[c] += 1
            log.warning("sensor %s: clock offset moved by %+.1f ms to %+.1f ms (data time %.1f)",
                        self.names[c], 1000 * moved, 1000 * o, now,
                        extra={"sensor": self.names[c], "clock_offset": o, "clock_drift": moved})
            self.anchor[c], self.anchor_std[c] = o, s

    # -------------------------------------------------------------- output

    def clocks(self) -> tuple[SensorClock, ...]:
        out = []
        for c, n in enumerate(self.names):
            o, s, ref = self.offset[c], self.std[c], self.ref_std[c]
            if not np.isfinite(o):
                out.append(SensorClock(n, None, None, float(self.applied[c]), int(self.nblocks[c]),
                                       int(self.drift_warnings[c]), self.note[c]))
                continue
            ref = float(ref) if np.isfinite(ref) else None
            out.append(SensorClock(n, float(o), max(float(s), ref or 0.0), float(self.applied[c]), int(self.nblocks[c]),
                                   int(self.drift_warnings[c]), self.note[c], float(s), ref))
        return tuple(out)

    def set_applied(self, applied: Mapping[str, float]) -> None:
        """Restore applied offsets (a resumed session)."""
        for n, v in applied.items():
            if n in self.index and math.isfinite(float(v)):
                self.applied[self.index[n]] = float(v)
