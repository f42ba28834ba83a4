"""Sensor clock offsets estimated from the data (a sensor whose NTP fails, a bad board clock).

A sensor's stamps are ``capture + offset``. Offsets are relative: the reference clock is
the median of the estimated sensors, and an offset here is how far a sensor's stamps run
ahead of that reference (positive: stamped late; the synchroniser subtracts it).

How (docs/clock_offsets.md has the reasoning and the figures):

1. Tracks, per sensor, on its raw message stream: a person's detections chained from
   message to message (joints moved less than a fraction of the image diagonal per
   second). A sensor far off in time need not join framesets for this.
2. Persons in 3D from the other sensors: each hypothesis the pipeline associates (one
   person at one frameset instant, on the synchronised clock) is triangulated with the
   current pose estimate *without* the sensor under test.
3. For each sensor, block of data time and candidate offset g on a grid, the sensor's
   tracks are interpolated to the raw stamps ``T + g`` and compared with that person
   projected into the sensor (Cauchy-robust reprojection distance, px). With two persons
   in view the track that fits clearly best is the person (ratio test); a fit far worse
   than the sensor's usual one is nobody (gate).
4. The sensor's offset is the minimum of its summed curve over the recent blocks
   (parabola through the best three grid points); its std is the blocks' jackknife
   (blocks are long against the detector's correlated noise). A sensor first searches
   the whole range on a coarse grid, then a fine grid around what it found; a minimum on
   the fine grid's edge (a clock jumped) sends it back to the search.
5. Offsets relative to the median sensor; confident ones are applied by the synchroniser,
   which makes the other sensors' 3D (step 2) better timed in turn.

Reprojection and not the epipolar constraint between pairs of cameras: a pair only sees
motion across its epipolar lines, and people walk mostly along them when the cameras
hang at one height (measured: pairwise estimates 5-30 ms off on noisy detections). This
estimator does not meet its 5 ms bar yet either; it is off by default
(``clock.estimate``); docs/clock_offsets.md has the figures and the next steps.

Synchronous, numpy only; the pipeline feeds it messages and hypotheses and calls
``update`` with the current pose estimate.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from proto import KeypointMessage

from .associate import Hypothesis
from .cameras import Intrinsics, undistort
from .config import ClockConfig
from .geometry import triangulate_batch

log = logging.getLogger(__name__)

# Joints used for timing: the body without the face (five face points move as one and
# would count the head five times).
BODY = np.array([5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16])
_MATCH_DIAG_PER_S = 1.0  # as in sync: persons move less than this many image diagonals per second
_MATCH_MIN_FRAC = 0.03
_FINE_STEP = 0.002  # s, grid step around a found offset
_FINE_HALF = 0.03  # s, half-width of that grid
_RATIO = 0.6  # the best track must fit clearly better than the runner-up (cost per joint)
_STD_FLOOR = 0.0003  # s: the jackknife of few blocks can be optimistic
# Cauchy width in units of the median absolute residual: 2.385 sigma (95 % efficiency
# for Gaussian noise), and the median of |N(0, sigma)| is 0.674 sigma.
_CAUCHY = 2.385 / 0.674


# ------------------------------------------------------------------ results


@dataclass(frozen=True)
class SensorClock:
    """One sensor's clock as estimated.

    offset: s its stamps run ahead of the reference clock (the median sensor), None when
        not estimated yet (nobody seen by it and two others).
    std: s, its standard deviation (jackknife over blocks of data).
    applied: s the synchroniser subtracts from its stamps now.
    blocks: blocks of data (``clock.block`` s each) the estimate rests on.
    drift_warnings: how often its estimate moved by more than ``clock.drift_warning``.
    """

    sensor: str
    offset: float | None
    std: float | None
    applied: float
    blocks: int
    drift_warnings: int

    def to_dict(self) -> dict:
        return {"offset": self.offset, "std": self.std, "applied": self.applied, "blocks": self.blocks,
                "drift_warnings": self.drift_warnings}


# ------------------------------------------------------------------ pure functions


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


def reprojection_curves(proj: np.ndarray, times: np.ndarray, track: tuple[np.ndarray, np.ndarray, np.ndarray],
                        grid: np.ndarray, focal: float, width_px: float, max_gap: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust reprojection cost of persons against one track, per candidate offset.

    proj: (M, J, 2) the persons (from the other sensors) projected into this sensor,
    normalised, NaN = unknown; times: (M,) their instants on the synchronised clock;
    track: (stamps (n,), xy (n, J, 2), ok (n, J)) raw stamps, normalised; grid: (K,) s,
    the track is taken at times + grid. Only joints valid at every candidate count, so
    costs compare across the grid.

    Returns cost (M, K) summed Cauchy cost in px², count (M,) joints, (M,) the median
    distance px at each person's best candidate (NaN when count is 0), the track's
    positions pos (M, K, J, 2) and valid (M, J).
    """
    M, J, _ = proj.shape
    K = len(grid)
    q = times[:, None] + grid[None, :]
    pos, ok = interpolate_track(*track, q, max_gap)  # (M, K, J, 2), (M, K, J)
    valid = ok.all(axis=1) & np.all(np.isfinite(proj), axis=2)  # (M, J)
    count = valid.sum(1)
    d = np.linalg.norm(np.nan_to_num(proj)[:, None] - pos, axis=-1) * focal  # (M, K, J)
    rho = width_px**2 * np.log1p((d / width_px) ** 2)
    cost = np.where(valid[:, None, :], rho, 0.0).sum(-1)
    best = np.argmin(cost, axis=1)
    at_best = d[np.arange(M), best]  # (M, J)
    med = np.full(M, np.nan)
    for m in np.flatnonzero(count):
        med[m] = float(np.median(at_best[m, valid[m]]))
    assert cost.shape == (M, K)
    return cost, count, med, pos, valid


def affine_profile(stats: tuple[np.ndarray, np.ndarray, np.ndarray, float]) -> np.ndarray:
    """(K,) weighted mean squared residual per candidate after the best image-plane
    affine correction (6 parameters) common to all candidates' data: the profile of
    ``Σ w |y_k − D θ|²`` over θ. stats = (M (6, 6) Σ w DᵀD, B (K, 6) Σ w Dᵀy_k,
    C (K,) Σ w |y_k|², W = Σ w)."""
    M, B, C, W = stats
    X = np.linalg.solve(M + 1e-9 * np.trace(M) * np.eye(6), B.T)  # (6, K)
    return (C - np.einsum("kp,pk->k", B, X)) / max(W, 1e-12)


def affine_stats(p: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Sufficient statistics of ``y_k ≈ D(p) θ``: p (N, 2) projected points, y (N, K, 2)
    observed minus projected per candidate, w (N,) weights; D(p) = [[px, py, 0, 0, 1, 0],
    [0, 0, px, py, 0, 1]]."""
    N = len(p)
    D = np.zeros((N, 2, 6))
    D[:, 0, 0:2] = p
    D[:, 1, 2:4] = p
    D[:, 0, 4] = 1.0
    D[:, 1, 5] = 1.0
    M = np.einsum("n,nip,niq->pq", w, D, D)
    B = np.einsum("n,nip,nki->kp", w, D, y)
    C = np.einsum("n,nki->k", w, y * y)
    return M, B, C, float(w.sum())


def curve_minimum(cost: np.ndarray, grid: np.ndarray) -> float | None:
    """Sub-grid minimum of a sampled curve (parabola through the best three points);
    None when the best point lies on the grid's edge (the minimum may be outside)."""
    k = int(np.argmin(cost))
    if k == 0 or k == len(cost) - 1:
        return None
    c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
    den = c0 - 2 * c1 + c2
    shift = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    return float(grid[k] + np.clip(shift, -0.5, 0.5) * (grid[k + 1] - grid[k]))


def _sum_stats(blocks: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    return (sum(b[0] for b in blocks), sum(b[1] for b in blocks), sum(b[2] for b in blocks),
            float(sum(b[3] for b in blocks)))


def jackknife_minimum(blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]], grid: np.ndarray
                      ) -> tuple[float, float] | None:
    """The minimum of the affine profile (``affine_profile``) of all blocks' statistics
    and its jackknife std over blocks. None: fewer than 3 blocks, or a minimum on the
    grid's edge (with all blocks or without one)."""
    B = len(blocks)
    if B < 3:
        return None
    total = _sum_stats(blocks)
    x = curve_minimum(affine_profile(total), grid)
    if x is None:
        return None
    loo = []
    for b in range(B):
        Mb, Bb, Cb, Wb = blocks[b]
        y = curve_minimum(affine_profile((total[0] - Mb, total[1] - Bb, total[2] - Cb, total[3] - Wb)), grid)
        if y is None:
            return None
        loo.append(y)
    a = np.array(loo)
    return x, max(math.sqrt((B - 1) / B * ((a - a.mean()) ** 2).sum()), _STD_FLOOR)


def triangulate_without(R: np.ndarray, t: np.ndarray, hyps: list[Hypothesis]) -> tuple[np.ndarray, np.ndarray]:
    """Every hypothesis' BODY joints triangulated from all its views, and from all but
    each one of them.

    Returns X (M, J, 3) and X_without (M, Vmax, J, 3) world points (NaN where fewer than
    two views remain or a point lies behind a camera); X_without[m, v] leaves out view v
    of hypothesis m (cams[v])."""
    M, J = len(hyps), len(BODY)
    Vmax = max((len(h.cams) for h in hyps), default=0)
    X_all = np.full((M, J, 3), np.nan)
    X_wo = np.full((M, max(Vmax, 1), J, 3), np.nan)
    if M == 0:
        return X_all, X_wo
    # one batch: rows (m, leave-out v or -1, joint), columns = views (padding NaN)
    cams = np.zeros((M, Vmax + 1, Vmax), np.int64)
    xy = np.full((M, Vmax + 1, Vmax, J, 2), np.nan)
    for m, h in enumerate(hyps):
        V = len(h.cams)
        body = h.xy[:, BODY]  # (V, J, 2)
        for r in range(V + 1):  # r = V: all views
            keep = [v for v in range(V) if v != r]
            cams[m, r, :len(keep)] = h.cams[keep]
            xy[m, r, :len(keep)] = body[keep]
    pts_xy = np.transpose(xy, (0, 1, 3, 2, 4)).reshape(-1, Vmax, 2)  # (M*(Vmax+1)*J, Vmax, 2)
    pts_cams = np.repeat(cams[:, :, None, :], J, axis=2).reshape(-1, Vmax)
    X = triangulate_batch(R, t, pts_cams, pts_xy).reshape(M, Vmax + 1, J, 3)
    for m, h in enumerate(hyps):
        V = len(h.cams)
        X_all[m] = X[m, V]
        X_wo[m, :V] = X[m, :V]
    return X_all, X_wo


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


class _SensorTracks:
    def __init__(self, intr: Intrinsics, min_confidence: float, max_gap: float):
        self.intr = intr
        self.min_conf = min_confidence
        self.max_gap = max_gap
        self.tracks: list[_Track] = []
        self.last_stamp: float | None = None
        self.first_stamp: float | None = None
        self.count = 0
        self.out_of_order = 0

    def rate(self) -> float:
        if self.count < 2 or self.last_stamp is None or self.first_stamp is None or self.last_stamp <= self.first_stamp:
            return 0.0
        return (self.count - 1) / (self.last_stamp - self.first_stamp)

    def push(self, msg: KeypointMessage, intr: Intrinsics) -> None:
        t = msg.stamp
        if self.last_stamp is not None and t <= self.last_stamp:
            self.out_of_order += 1
            return
        self.first_stamp = t if self.first_stamp is None else self.first_stamp
        self.last_stamp = t
        self.count += 1
        kp = msg.keypoints()
        if not len(kp):
            return
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

    def prune(self, before: float) -> None:
        self.tracks = [tr for tr in self.tracks if tr.stamps and tr.stamps[-1] >= before]
        for tr in self.tracks:
            tr.trim(before)

    def overlapping(self, t0: float, t1: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        out = []
        for tr in self.tracks:
            if len(tr.stamps) >= 2 and tr.stamps[0] <= t1 and tr.stamps[-1] >= t0:
                out.append(tr.arrays())
        return out


# ------------------------------------------------------------------ the estimator


class _Fit:
    """One sensor's accumulated curves on its current grid of candidate offsets."""

    def __init__(self, half: float, step: float):
        self.center = 0.0
        self.fine = False
        self.grid = np.arange(-half, half + 1e-9, step)
        self.blocks: deque[tuple[float, tuple, int]] = deque()  # (time, affine_stats, joints)
        self.scales: deque[float] = deque(maxlen=200)  # median distance px of accepted fits
        self.coarse: tuple[float, float, int] | None = None  # the search's result (offset, std, blocks)

    def scale(self, floor: float, common: float, pose_px: float) -> float:
        """px: the median reprojection distance of this sensor's fits; until it has its
        own, the common one. Capped at a few times the common one or what its pose's
        uncertainty allows: a sensor whose first fits were the wrong person must not
        learn a scale that lets every wrong fit in."""
        if len(self.scales) < 10:
            return max(common, pose_px)
        return min(max(floor, float(np.median(self.scales))), max(4 * common, pose_px))

    def refocus(self, center: float) -> None:
        self.center = round(center / _FINE_STEP) * _FINE_STEP
        self.fine = True
        self.grid = self.center + np.arange(-_FINE_HALF, _FINE_HALF + 1e-9, _FINE_STEP)
        self.blocks.clear()


class ClockOffsetEstimator:
    """Online estimate of every sensor's clock offset (see the module's docstring).

    ``push`` every accepted message (raw stamps); ``add`` the pipeline's hypotheses;
    ``update(now, R, t)`` when ``due`` with the current pose estimate; ``clocks()`` the
    per-sensor result; ``applied`` (S,) the offsets to subtract from stamps.
    """

    def __init__(self, config: ClockConfig, names: tuple[str, ...], intrinsics: Mapping[str, Intrinsics],
                 min_confidence: float):
        self.cfg = config
        self.names = tuple(names)
        S = len(self.names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.intrinsics = dict(intrinsics)
        self._scaled: dict[tuple[str, tuple[int, int]], Intrinsics | None] = {}
        self.tracks = [_SensorTracks(self.intrinsics[n], min_confidence, config.track_gap) for n in self.names]
        self.focal = np.array([0.5 * (self.intrinsics[n].fx + self.intrinsics[n].fy) for n in self.names])
        self.fits = [_Fit(self._search, config.coarse_step) for _ in range(S)]
        self.hyps: deque[Hypothesis] = deque()
        self.next_block: float | None = None
        self.last_update: float | None = None
        self.offset = np.full(S, np.nan)
        self.std = np.full(S, np.nan)
        self.nblocks = np.zeros(S, np.int64)
        self.applied = np.zeros(S)
        self.anchor = np.full(S, np.nan)  # estimate at the last drift check point
        self.anchor_std = np.full(S, np.nan)
        self.drift_warnings = np.zeros(S, np.int64)
        self.ambiguous = 0  # fits left out: two tracks fit about as well
        self.gated = 0  # fits left out: far worse than the sensor's usual fit
        self._scales: deque[float] = deque(maxlen=1000)  # accepted fits' median distance px, all sensors

    @property
    def _search(self) -> float:
        return self.cfg.max_offset + 2 * self.cfg.coarse_step

    def _common_scale(self) -> float:
        if len(self._scales) < 30:
            return self.cfg.initial_scale_px
        return max(self.cfg.min_scale_px, float(np.median(self._scales)))

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
        self.tracks[c].push(msg, intr)

    def add(self, hyps: Iterable[Hypothesis]) -> None:
        """Hypotheses of one frameset (time on the synchronised clock)."""
        for h in hyps:
            if len(h.cams) >= 2:
                self.hyps.append(h)
                if self.next_block is None:
                    L = self.cfg.block
                    self.next_block = math.floor(h.time / L) * L + L

    # -------------------------------------------------------------- estimation

    def due(self, now: float | None) -> bool:
        return (self.cfg.estimate and now is not None and self.next_block is not None
                and (self.last_update is None or now - self.last_update >= self.cfg.interval))

    def update(self, now: float, R: np.ndarray, t: np.ndarray, pose_px: np.ndarray | None = None, *,
               flush: bool = False) -> list[str]:
        """Process every block complete by ``now`` (all of them with ``flush``) with the
        poses R (C, 3, 3), t (C, 3) and pose_px (C,) the reprojection error their
        uncertainty allows (px, 0 = none); returns the sensors whose applied offset changed."""
        S = len(self.names)
        assert R.shape == (S, 3, 3) and t.shape == (S, 3)
        pose_px = np.zeros(S) if pose_px is None else pose_px
        assert pose_px.shape == (S,)
        self.last_update = now
        if self.next_block is None:
            return []
        L = self.cfg.block
        margin = self._search + self.cfg.track_gap + 1.0
        last = self.hyps[-1].time if self.hyps else -math.inf
        while self.next_block + margin <= now or (flush and self.next_block - L <= last):
            t0, t1 = self.next_block - L, self.next_block
            block = []
            while self.hyps and self.hyps[0].time < t1:
                h = self.hyps.popleft()
                if h.time >= t0:
                    block.append(h)
            if block:
                self._block(t0, t1, block, R, t, pose_px)
            self.next_block += L
        horizon = self.next_block - L - self._search - 2 * self.cfg.track_gap - 1.0
        for st in self.tracks:
            st.prune(horizon)
        return self._estimate(now)

    def _block(self, t0: float, t1: float, hyps: list[Hypothesis], R: np.ndarray, t: np.ndarray,
               pose_px: np.ndarray) -> None:
        cfg = self.cfg
        times = np.array([h.time for h in hyps])
        X_all, X_wo = triangulate_without(R, t, hyps)
        common = self._common_scale()
        for s, fit in enumerate(self.fits):
            # persons from the others: without this sensor's own view, which would pull
            # the fit to the offset applied when the frameset was made
            X = X_all.copy()
            for m, h in enumerate(hyps):
                hit = np.flatnonzero(h.cams == s)
                if len(hit):
                    X[m] = X_wo[m, hit[0]] if len(h.cams) >= 3 else np.nan
            Xc = (X - t[s]) @ R[s]  # camera frame: R^T (X - t)
            with np.errstate(invalid="ignore"):
                front = Xc[..., 2] > 0.1
            proj = np.where(front[..., None], Xc[..., :2] / np.where(front, Xc[..., 2], 1.0)[..., None], np.nan)
            use = np.flatnonzero(np.isfinite(proj).all(-1).sum(-1) >= cfg.min_joints)
            if not len(use):
                continue
            lo, hi = t0 + fit.grid[0] - cfg.track_gap, t1 + fit.grid[-1] + cfg.track_gap
            tracks = self.tracks[s].overlapping(lo, hi)
            if not tracks:
                continue
            scale = fit.scale(cfg.min_scale_px, common, float(pose_px[s]))
            res = [reprojection_curves(proj[use], times[use], tr, fit.grid, self.focal[s], _CAUCHY * scale,
                                       cfg.track_gap) for tr in tracks]
            cost = np.stack([r[0] for r in res])  # (Tr, M, K)
            count = np.stack([r[1] for r in res])  # (Tr, M)
            med = np.stack([r[2] for r in res])
            per_joint = np.where(count >= cfg.min_joints, cost.min(-1) / np.maximum(count, 1), np.inf)  # (Tr, M)
            order = np.argsort(per_joint, axis=0)
            P, Y, Wt = [], [], []
            width = _CAUCHY * scale / self.focal[s]  # normalised units
            joints = 0
            for m in range(len(use)):
                b = order[0, m]
                if not np.isfinite(per_joint[b, m]):
                    continue
                if len(tracks) > 1 and per_joint[b, m] > _RATIO * per_joint[order[1, m], m]:
                    self.ambiguous += 1
                    continue
                if len(fit.scales) >= 10 and med[b, m] > cfg.gate * scale:
                    self.gated += 1
                    continue
                fit.scales.append(float(med[b, m]))
                self._scales.append(float(med[b, m]))
                pos, valid = res[b][3][m], res[b][4][m]  # (K, J, 2), (J,)
                p = proj[use[m]][valid]  # (n, 2)
                y = np.transpose(pos[:, valid], (1, 0, 2)) - p[:, None, :]  # (n, K, 2)
                kb = int(np.argmin(cost[b, m]))
                e = np.linalg.norm(y[:, kb], axis=-1)
                P.append(p)
                Y.append(y)
                Wt.append(1.0 / (1.0 + (e / width) ** 2))  # Cauchy weights at the person's best candidate
                joints += int(valid.sum())
            if joints:
                st = affine_stats(np.concatenate(P), np.concatenate(Y), np.concatenate(Wt))
                fit.blocks.append((t1, st, joints))
            while fit.blocks and fit.blocks[0][0] < t1 - cfg.window:
                fit.blocks.popleft()

    def _estimate(self, now: float) -> list[str]:
        cfg = self.cfg
        S = len(self.names)
        g = np.full(S, np.nan)
        sd = np.full(S, np.nan)
        nb = np.zeros(S, np.int64)
        for s, fit in enumerate(self.fits):
            r = None
            if len(fit.blocks) >= cfg.min_blocks:
                stats = [st for _, st, _ in fit.blocks]
                r = jackknife_minimum(stats, fit.grid)
                if r is None and fit.fine and int(np.argmin(affine_profile(_sum_stats(stats)))) in (0, len(fit.grid) - 1):
                    self.fits[s] = _Fit(self._search, cfg.coarse_step)  # the offset left the fine grid: search again
                    continue
                if r is not None and not fit.fine and r[1] < cfg.coarse_step:
                    fit.coarse = (r[0], r[1], len(fit.blocks))
                    fit.refocus(r[0])
            if r is None and fit.fine and fit.coarse is not None:
                r = fit.coarse[:2]  # the fine grid is still filling: the search's result stands
                nb[s] = fit.coarse[2]
            elif r is not None:
                nb[s] = len(fit.blocks)
            if r is not None and (fit.fine or r[1] < cfg.coarse_step):
                g[s], sd[s] = r
        est = np.isfinite(g)
        self.offset = g - np.median(g[est]) if est.any() else g
        self.std, self.nblocks = sd, nb
        changed = []
        for s, n in enumerate(self.names):
            o, e = self.offset[s], self.std[s]
            if not np.isfinite(o) or e > cfg.max_std:
                continue
            self._check_drift(s, o, e, now)
            target = o if abs(o) >= max(cfg.min_apply, 3 * e) else 0.0
            if abs(target - self.applied[s]) > max(cfg.min_apply, 2 * e):
                self.applied[s] = target
                changed.append(n)
        return changed

    def _check_drift(self, c: int, o: float, s: float, now: float) -> None:
        if not np.isfinite(self.anchor[c]):
            self.anchor[c], self.anchor_std[c] = o, s
            return
        moved = o - self.anchor[c]
        if abs(moved) > self.cfg.drift_warning and abs(moved) > 3 * math.hypot(s, self.anchor_std[c]):
            self.drift_warnings[c] += 1
            log.warning("sensor %s: clock offset moved by %+.1f ms to %+.1f ms (data time %.1f)",
                        self.names[c], 1000 * moved, 1000 * o, now,
                        extra={"sensor": self.names[c], "clock_offset": o, "clock_drift": moved})
            self.anchor[c], self.anchor_std[c] = o, s

    # -------------------------------------------------------------- output

    def clocks(self) -> tuple[SensorClock, ...]:
        out = []
        for c, n in enumerate(self.names):
            o, s = self.offset[c], self.std[c]
            est = bool(np.isfinite(o))
            out.append(SensorClock(n, float(o) if est else None, float(s) if est else None, float(self.applied[c]),
                                   int(self.nblocks[c]), int(self.drift_warnings[c])))
        return tuple(out)

    def set_applied(self, applied: Mapping[str, float]) -> None:
        """Restore applied offsets (a resumed session)."""
        for n, v in applied.items():
            if n in self.index and math.isfinite(float(v)):
                self.applied[self.index[n]] = float(v)
