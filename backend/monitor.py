"""Watching a calibrated camera network for cameras that moved (bumped, re-mounted), and
calibrating a moved camera again.

The evidence is each camera's reprojection of the persons the *other* cameras see: the
joints of every hypothesis are triangulated from the other trusted (watched, not moved)
cameras only, points inconsistent with those views left out, and the camera's own
keypoints are compared with their projection (``correspondences``). At every
``bin_seconds`` of data (a common grid: the cameras are tested together) each watched
camera's correspondences of the bin (several grid steps, up to ``max_bin_seconds``, for a
camera that sees too little to fill one) become its pose as the data alone put it, a robust
resection with the others held fixed (``resect``), with its information; the pose is
carried into the frame the others had when the watch began (the estimate drifting as a
whole is no camera moving). A moved camera shows as a step in this sequence. The test
(``change_test``) is the generalised likelihood ratio test for a step at an unknown time:
for every split in the last ``window_seconds``, the robust mean of the bins after it
against the mean of the camera's own bins before it, χ² with 6 dof against their
covariances. Each bin's covariance is its information's inverse plus the error it does
not show (where the people were, the others' own errors), measured on the camera's own
older bins (``bin_floor``): comparing the camera with its own past, not with the filter's
estimate, a camera whose estimate is a little off, or whose view is biased, does not look
moved; only a change does. A change early in a camera's first watch, with a short
reference, is measured against the scatter of its bins on both sides of it
(``short_reference_bins``). A step must also show with the bias each bin owes to where
its people were in the image and to the lens's error, fitted with it (``where_covariates``,
``lens_covariates``, ``_bias_step``): a lens a little off, or keypoints off the joints,
bias a data-only pose by where the people are and how deep, and people crossing the view
or walking away are no move. It must show without any one of the bins after it, and
without more when the camera's own reference has odd bins often enough that more among
them are likely (``_odd_bins``). A change must also be large (``min_translation`` /
``min_rotation``). A moved camera biases the points the others are tested against, so
they may fail too, and before it does (its own views, now off, join fewer hypotheses):
of the cameras that fail at one evaluation the most significant is taken, and tested
again without each camera its points came from (``_blame``); a step that goes
away without one of them was that camera's, which is flagged instead when its own bins
since the change show it, and otherwise nobody is, yet.

A flagged camera is calibrated again from the data since the change: at every bin, one
resection over all its correspondences since then with the others fixed, until
``recalibrate_seconds`` of data are in (``Recalibration``); the cameras it was a source
of points for start their reference over (their points come without it from then on),
the others drop their bins since the change. The pipeline applies the poses, adjusts
the camera over all its data since the move (the watched cameras held) at
``recalibrate_seconds``, every ``recalibrate_every`` after, up to twice that, and watches
it again once converged.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np
from scipy.stats import binom

from .associate import Hypothesis
from .config import MonitorConfig
from .geometry import pose_local, pose_retract, project_normalised, umeyama


_MAX_PENDING = 5000  # hypotheses held for the next evaluation (none runs while no cycle does)


@dataclass(frozen=True)
class Alarm:
    """A camera found moved: data time of the alarm, camera index, the test's χ², the
    change's size (m, deg) and the data time from which the camera is thought moved."""

    time: float
    cam: int
    chi2: float
    translation: float
    rotation: float
    since: float = float("nan")


@dataclass(frozen=True)
class Correspondences:
    """One camera's joints at one instant against points the others triangulated.

    X: (N, 3) world points; xy: (N, 2) the camera's undistorted normalised keypoints;
    sigma: (N,) their normalised std; view: (N,) int id of the person view (hypothesis);
    Xcov: (N, 3, 3) the points' covariance (m², from the others' rays and keypoint std),
    None: the points taken as exact."""

    time: float
    X: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    view: np.ndarray
    Xcov: np.ndarray | None = None

    def __post_init__(self) -> None:
        N = len(self.X)
        assert self.X.shape == (N, 3) and self.xy.shape == (N, 2) and self.sigma.shape == (N,)
        assert self.view.shape == (N,)
        assert self.Xcov is None or self.Xcov.shape == (N, 3, 3)


@dataclass(frozen=True)
class Resection:
    """A camera pose from correspondences with the others fixed: R (3, 3), t (3,), info
    (6, 6) its information (tangent: rotation rad, translation m; from the Gauss-Newton
    normal equations, Huber-weighted), points and views used, rms_px after the fit; lens
    (6, 4) the pose's first-order change per 1 % of the focal lengths (x, y) and per 1 %
    of the focal length's shift of the principal point (x, y) that the camera's lens has
    and its calibration file does not (``lens_covariates``)."""

    R: np.ndarray
    t: np.ndarray
    info: np.ndarray
    points: int
    views: int
    rms_px: float
    lens: np.ndarray | None = None


@dataclass(frozen=True)
class Recalibration:
    """A moved camera calibrated again from ``seconds`` of data since its move, the
    others fixed: R (3, 3), t (3,), cov (6, 6) (the resection's, plus the error of its
    bins that more of them average out), ``final`` when its recalibration ends here."""

    cam: int
    R: np.ndarray
    t: np.ndarray
    cov: np.ndarray
    seconds: float
    points: int
    final: bool


def resect(R: np.ndarray, t: np.ndarray, data: Sequence[Correspondences], focal: float, *, outlier_px: float,
           huber: float = 2.0, reject: float = 5.0, iterations: int = 8) -> Resection | None:
    """The camera's pose from ``data`` starting at R, t: Gauss-Newton with a Huber
    weight (``huber`` sigmas); then person views whose median residual is far above the
    rest (beyond ``outlier_px`` and 4x the median view; wrong associations), and joints
    beyond ``reject`` sigmas, are dropped and the fit repeated. A residual's covariance is its keypoint's plus its point's
    (``Xcov``) projected into the camera: a person near the camera and far from the
    others, whose points the others place to a few cm, says little about the camera's
    orientation, however large it is in the image. None when too little is left for a pose."""
    if not data:
        return None
    X = np.concatenate([d.X for d in data])
    xy = np.concatenate([d.xy for d in data])
    sig = np.concatenate([d.sigma for d in data])
    view = np.concatenate([d.view for d in data])
    Xcov = np.concatenate([np.zeros((len(d.X), 3, 3)) if d.Xcov is None else d.Xcov for d in data])
    keep = np.ones(len(X), bool)
    for round_ in range(2):
        fit = _gauss_newton(R, t, X[keep], xy[keep], sig[keep], Xcov[keep], huber, iterations)
        if fit is None:
            return None
        R1, t1, info, res, err, lens = fit
        if round_ == 1:
            break
        _, inv = np.unique(view[keep], return_inverse=True)
        res_px = res * focal
        med = np.array([np.median(res_px[inv == k]) for k in range(inv.max() + 1)])
        bad = med > max(outlier_px, 4.0 * float(np.median(med)))
        # ... and single joints far beyond their covariance (a limb's left and right
        # swapped, a joint put on the other person): Huber's weight still lets them pull
        bad_joint = err > reject
        if not bad.any() and not bad_joint.any():
            break
        idx = np.flatnonzero(keep)
        keep[idx[bad[inv] | bad_joint]] = False
        R, t = R1, t1
    n = int(keep.sum())
    return Resection(R1, t1, info, n, int(len(np.unique(view[keep]))), float(np.sqrt(np.mean((res * focal) ** 2))),
                     lens)


def _gauss_newton(R, t, X, xy, sig, Xcov, huber, iterations):
    if len(X) < 12:
        return None

    def normal_equations(R, t):
        uv, J = project_normalised(R, t, X)
        if not np.all(np.isfinite(uv)):
            return None
        dproj = -J[:, :, 3:]  # (N, 2, 3) d uv / d point in the camera frame
        A = dproj @ np.transpose(R)  # d uv / d world point
        S = np.einsum("nij,njk,nlk->nil", A, Xcov, A) + (sig ** 2)[:, None, None] * np.eye(2)
        Si = np.linalg.inv(S)  # (N, 2, 2)
        r = uv - xy
        e = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, Si, r), 0.0))  # in sigmas
        w = np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12))
        WJ = np.einsum("n,nij,njk->nik", w, Si, J)
        H = np.einsum("nij,nik->jk", J, WJ)
        g = np.einsum("nik,ni->k", WJ, r)
        return uv, H, g, e, WJ

    for _ in range(iterations):
        ne = normal_equations(R, t)
        if ne is None:
            return None
        _, H, g, _, _ = ne
        try:
            dx = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        R, t = pose_retract(R, t, dx)
        if np.linalg.norm(dx) < 1e-7:
            break
    ne = normal_equations(R, t)
    if ne is None:
        return None
    uv, H, _, e, WJ = ne
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e12:
        return None
    # the keypoints' change per 1 % of the lens (focal lengths scale them about the
    # principal point; its shift moves them all), and the fit's answer to it
    G = np.zeros((len(X), 2, 4))
    G[:, 0, 0], G[:, 1, 1], G[:, 0, 2], G[:, 1, 3] = uv[:, 0], uv[:, 1], 1.0, 1.0
    lens = 0.01 * np.linalg.solve(H, np.einsum("nij,nik->jk", WJ, G))
    return R, t, H, np.linalg.norm(uv - xy, axis=1), e, lens


def correspondences(hyps: Sequence[Hypothesis], R: np.ndarray, t: np.ndarray, trusted: np.ndarray,
                    focal: np.ndarray, min_angle_deg: float, max_px: float, first_view: int = 0
                    ) -> dict[int, list[Correspondences]]:
    """Per camera, its joints in ``hyps`` against the points the other trusted cameras
    triangulate (trusted (C,) bool, or (C, C) bool: row c, the cameras camera c's points
    may come from; at least two of them in the hypothesis). Left out:
    points whose rays meet at less than ``min_angle_deg`` (their depth is unknown) and
    points that reproject further than ``max_px`` from a view they were triangulated from
    (a view of another person, a wrong detection: the point is not the person's joint).
    Each point comes with its covariance from its rays and their keypoints' std; its view
    id is ``first_view`` + the hypothesis' index (distinct over calls when the caller counts)."""
    out: dict[int, list[Correspondences]] = {}
    C = len(R)
    trust = np.broadcast_to(trusted, (C, C)) & ~np.eye(C, dtype=bool)
    rows_cams, rows_xy, rows_sig, rows_own, rows_meta = [], [], [], [], []
    for k, h in enumerate(hyps):
        V = len(h.cams)
        for v in range(V):
            ok = trust[h.cams[v]][h.cams]
            if ok.sum() < 2:
                continue
            xy = h.xy.copy()  # (V, 17, 2)
            xy[~ok] = np.nan
            rows_cams.append(np.repeat(h.cams[None], 17, axis=0))
            rows_xy.append(xy.transpose(1, 0, 2))  # (17, V, 2)
            rows_sig.append(h.sigma.T)  # (17, V)
            rows_own.append((h.xy[v], h.sigma[v]))
            rows_meta.append((int(h.cams[v]), h.time, k))
    if not rows_meta:
        return out
    Vmax = max(r.shape[1] for r in rows_cams)
    n = len(rows_meta)
    cams = np.zeros((n, 17, Vmax), np.int64)
    xy = np.full((n, 17, Vmax, 2), np.nan)
    sig = np.full((n, 17, Vmax), np.nan)
    for i, (c, x, sg) in enumerate(zip(rows_cams, rows_xy, rows_sig)):
        cams[i, :, :c.shape[1]] = c
        xy[i, :, :x.shape[1]] = x
        sig[i, :, :sg.shape[1]] = sg
    seen = np.all(np.isfinite(xy), axis=3) & np.isfinite(sig) & (np.nan_to_num(sig) > 0)  # (n, 17, V)
    Xw, rays = _midpoints(R, t, cams, xy, seen)
    # the widest angle between two of a point's rays
    cos = np.einsum("njvk,njwk->njvw", rays, rays)
    both = seen[:, :, :, None] & seen[:, :, None, :]
    min_cos = np.where(both, cos, 1.0).min(axis=(2, 3))
    good = np.all(np.isfinite(Xw), axis=2) & (min_cos <= np.cos(np.radians(min_angle_deg)))
    Rt = np.transpose(R[cams], (0, 1, 2, 4, 3))  # (n, 17, V, 3, 3) cam_R_world
    Xc = np.einsum("njvab,njvb->njva", Rt, Xw[:, :, None, :] - t[cams])
    with np.errstate(divide="ignore", invalid="ignore"):
        px = np.linalg.norm(Xc[..., :2] / Xc[..., 2:3] - xy, axis=3) * focal[cams]
    good &= np.where(seen, px, 0.0).max(axis=2) <= max_px
    # the point's information: each ray pins it across itself to its keypoint's std times
    # the depth
    with np.errstate(divide="ignore", invalid="ignore"):
        wv = np.where(seen & (Xc[..., 2] > 0), 1.0 / (np.nan_to_num(sig, nan=1.0) * Xc[..., 2]) ** 2, 0.0)
    wv = np.nan_to_num(wv, nan=0.0, posinf=0.0)
    info = np.einsum("njv,njvab->njab", wv, np.eye(3) - rays[..., :, None] * rays[..., None, :])
    info[~good] = np.eye(3)
    Xcov = np.linalg.inv(info)
    for i, (c, time, k) in enumerate(rows_meta):
        own_xy, own_sig = rows_own[i]
        m = good[i] & np.all(np.isfinite(own_xy), axis=1) & np.isfinite(own_sig)
        if m.sum() < 4:
            continue
        out.setdefault(c, []).append(Correspondences(time, Xw[i, m], own_xy[m], own_sig[m],
                                                     np.full(int(m.sum()), first_view + k, np.int64), Xcov[i, m]))
    return out


def _midpoints(R: np.ndarray, t: np.ndarray, cams: np.ndarray, xy: np.ndarray, seen: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Points nearest to their rays (cams (..., V), xy (..., V, 2), seen (..., V)):
    (..., 3) points (NaN with < 2 rays or behind a camera) and (..., V, 3) unit rays.
    A 3x3 solve per point: many times faster than the DLT's SVD, and as good for
    telling a joint's position to a few pixels (the outliers are checked after)."""
    x = np.where(seen[..., None], xy, 0.0)
    d = np.einsum("...vab,...vb->...va", R[cams], np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    proj = np.eye(3) - d[..., :, None] * d[..., None, :]  # (..., V, 3, 3)
    proj = proj * seen[..., None, None]
    A = proj.sum(-3)
    b = np.einsum("...vab,...vb->...a", proj, t[cams])
    ok = seen.sum(-1) >= 2
    A[~ok] = np.eye(3)
    with np.errstate(invalid="ignore"):
        X = np.linalg.solve(A, b[..., None])[..., 0]
    depth = np.einsum("...va,...va->...v", d, X[..., None, :] - t[cams])
    ok &= np.all(~seen | (depth > 0.05), axis=-1)
    X[~ok] = np.nan
    return X, d


@dataclass
class _Camera:
    """The monitor's record of one camera."""

    data: deque = field(default_factory=deque)  # Correspondences, oldest first
    bin_start: float | None = None
    # closed bins: (start, end, z (6,) the resection's tangent offset from the anchor,
    # in the frame of the others, info (6, 6) its information, where (2,) its points'
    # mean in the image, lens (6, 4) ``Resection.lens``)
    bins: list = field(default_factory=list)
    anchor: tuple[np.ndarray, np.ndarray] | None = None  # the camera's estimate when its watch began
    # the cameras its points come from: those trusted when its watch began (one joining
    # later would change the points, and look like this camera moving)
    trust: np.ndarray | None = None
    since: float | None = None  # being calibrated again with the data from this time on
    # its first watch of the session: a change early in it is tested on a short reference
    # (``MonitorConfig.short_reference_bins``); not after an alarm started it over
    first_watch: bool = True


class Monitor:
    """Per camera: correspondences (``add``), bins of resections and the change test for
    watched cameras, recalibration of flagged ones (``evaluate``)."""

    def __init__(self, cfg: MonitorConfig, focal: np.ndarray, *, outlier_px: float = 15.0,
                 min_angle_deg: float = 2.0):
        self.cfg = cfg
        self.focal = focal
        self.outlier_px = outlier_px
        self.min_angle = min_angle_deg
        self.cams = [_Camera() for _ in range(len(focal))]
        self.alarms: list[Alarm] = []
        self.pending: list[Hypothesis] = []  # hypotheses not yet turned into correspondences
        # the hypotheses of the test's window, for testing a camera again without another
        self.recent: deque[Hypothesis] = deque()
        self._views = 0  # person views numbered so far
        r = np.radians(cfg.model_std_rotation)
        self.floor = np.diag([r * r] * 3 + [cfg.model_std_translation ** 2] * 3)
        r = np.radians(cfg.bin_std_rotation)
        self.bin_floor = np.diag([r * r] * 3 + [cfg.bin_std_translation ** 2] * 3)
        self._full_reference = cfg.model_copy(update={"short_reference_bins": cfg.min_reference_bins})

    def recalibrating(self) -> np.ndarray:
        """(C,) bool cameras being calibrated again after an alarm."""
        return np.array([k.since is not None for k in self.cams])

    def add(self, hyps: Sequence[Hypothesis]) -> None:
        """New hypotheses, turned into correspondences at the next ``evaluate`` (many at
        once: the triangulation is vectorised)."""
        if self.cfg.enabled:
            self.pending.extend(hyps)
            del self.pending[:-_MAX_PENDING]

    def _correspond(self, R: np.ndarray, t: np.ndarray, watched: np.ndarray) -> None:
        hyps, self.pending = self.pending, []
        self.recent.extend(hyps)
        trusted = watched & ~self.recalibrating()
        if not hyps or trusted.sum() < 2:
            return
        trust = np.zeros((len(R), len(R)), bool)
        for c, k in enumerate(self.cams):
            if k.since is not None:  # being calibrated again: against every trusted camera
                trust[c] = trusted
            elif watched[c]:
                trust[c] = trusted if k.trust is None else trusted & k.trust
        # view ids distinct over calls: a bin's resection drops wrong person views by their
        # median residual, and two views with one id would be judged as one
        found = correspondences(hyps, R, t, trust, self.focal, self.min_angle, self.outlier_px, self._views)
        self._views += len(hyps)
        for c, items in found.items():
            self.cams[c].data.extend(items)

    def evaluate(self, now: float, watched: np.ndarray, R: np.ndarray, t: np.ndarray
                 ) -> tuple[list[Alarm], list[Recalibration]]:
        """Close the bins due at data time ``now``, test the watched (C,) bool cameras,
        recalibrate the flagged ones. Returns (new alarms, new poses of cameras being
        calibrated again); the one marked ``final`` ends a camera's recalibration."""
        cfg = self.cfg
        if not cfg.enabled:
            return [], []
        # each camera's joints against what the others it can trust triangulate
        self._correspond(R, t, watched)
        recalibrating = self.recalibrating()
        results: list[Recalibration] = []
        candidates: list[tuple[float, Alarm]] = []
        keep_from = now - (cfg.window_seconds + 2 * cfg.bin_seconds)
        for c, k in enumerate(self.cams):
            if k.since is not None:
                if k.bin_start is None or now - k.bin_start >= cfg.bin_seconds:
                    k.bin_start = now
                    r = resect(R[c], t[c], [d for d in k.data if d.time >= k.since], float(self.focal[c]),
                               outlier_px=self.outlier_px)
                    seconds = now - k.since
                    final = seconds >= cfg.recalibrate_seconds
                    if r is not None:
                        cov = np.linalg.inv(r.info) + self.bin_floor * cfg.bin_seconds / max(seconds, cfg.bin_seconds)
                        results.append(Recalibration(c, r.R, r.t, cov, seconds, r.points, final))
                    if final:
                        self._reset(k)
                continue
            if not watched[c]:
                self._reset(k)
            else:
                if k.anchor is None:
                    k.anchor = (R[c].copy(), t[c].copy())
                    k.trust = watched & ~recalibrating
                    k.trust[c] = False
                if k.bin_start is None:
                    k.bin_start = now
                    k.data.clear()  # what came before the camera was watched is not its reference
                elif np.floor(now / cfg.bin_seconds) > np.floor(k.bin_start / cfg.bin_seconds):
                    # bins end on a common grid: the cameras are tested together
                    self._close_bin(c, k, now, R, t)
                    a = self._test(c, k, now)
                    if a is not None:
                        # a test on a full reference before one on a short reference: the
                        # short one is the fallback for a camera no other test covers (the west
                        # room: cam_16's short test, χ² 42.3, outranked cam_15's full one, 41.0,
                        # whose blame found cam_14 moved; cam_16's found cam_15)
                        full = sum(b[0] < a.since for b in k.bins) >= self.cfg.min_reference_bins
                        candidates.append(((full, a.chi2), a))
            while k.data and k.data[0].time < keep_from:
                k.data.popleft()
        while self.recent and self.recent[0].time < keep_from:
            self.recent.popleft()
        alarms = []
        # Of the cameras that fail, the most significant is flagged (a moved camera biases
        # the points the others are tested against, so they may fail too; the bins are on
        # a common grid, so they all have as many bins after the move) unless its step is
        # another camera's (``_blame``). A single odd bin does not fail a test
        # (``change_test`` leaves each one out).
        top = max(candidates, key=lambda x: x[0]) if candidates else None
        a = None if top is None else self._blame(top[1], now, watched, R, t)
        if a is not None:
            alarms.append(a)
            self.alarms.append(a)
            k = self.cams[a.cam]
            # calibrated again from the end of the first bin after the change: the move
            # happened in that bin, and its older data would drag the camera back
            since = next((b[1] for b in k.bins if b[0] == a.since), a.since + cfg.bin_seconds)
            data = [d for d in k.data if d.time >= since]
            self._reset(k)
            k.since = since
            k.data.extend(data)
            k.first_watch = False
            # The others' evidence since the change was triangulated with the moved camera;
            # and from now on their points come without it (it is not trusted while it is
            # calibrated again): a camera it was a source of starts its reference over, or
            # losing that source would look like a step of its own (one alarm cascading).
            shared = {int(c) for h in self.recent if a.cam in h.cams for c in h.cams}
            for c, o in enumerate(self.cams):
                if c == a.cam or o.since is not None:
                    continue
                if c in shared and (o.trust is None or o.trust[a.cam]):
                    self._reset(o)
                    o.first_watch = False
                else:
                    o.bins = [b for b in o.bins if b[1] <= a.since]
                    while o.data and o.data[-1].time >= a.since:
                        o.data.pop()
        return alarms, results

    def _blame(self, a: Alarm, now: float, watched: np.ndarray, R: np.ndarray, t: np.ndarray) -> Alarm | None:
        """The alarm to raise for camera ``a.cam``'s failed test: its own, unless the step
        goes away when its bins since the change are made again without one of the cameras
        its points came from (that camera moved and biased them): gone is no longer large
        (``min_translation`` / ``min_rotation``), or a quarter as significant as the
        threshold, or no longer significant and a quarter as significant as it was; less
        data alone leave a real step as large. Then ``_explained``. When no camera explains it
        and some could not be left out (too little left without them), one of those whose
        own bins show a more significant step at the same time is the moved one (the step
        a move induces in another is smaller)."""
        cfg = self.cfg
        explaining, undecided = [], []
        for j in self._suspects(a, watched):
            bins = self._bins_without(a, j, R, t)
            step = None if bins is None else _step_at(bins, a.since, now, cfg, self.floor)
            if step is None:
                undecided.append(j)  # too little left without j to tell
                continue
            chi2, trans, rot, _ = step
            # gone: a quarter of the threshold, or no longer significant and a quarter of what
            # it was (lenses 1 % off leave a little step of their own in every camera: cam_8
            # turned 2°, cam_9's step without it fell from χ² 108.6 to 10.4, and cam_9 was
            # flagged and calibrated again against the moved camera)
            if chi2 < cfg.chi2 / 4 or (chi2 < cfg.chi2 and chi2 < a.chi2 / 4) \
                    or (trans <= cfg.min_translation and rot <= cfg.min_rotation):
                explaining.append(j)
        # A camera too new to judge (too few bins since the change to show a step of its
        # own), one of several that explain the step or, when none does, one that could not
        # be left out, may be the moved one, and the steps of the others (this one too) its
        # move: wait for its bins rather than calibrate another camera again against it
        # (the west room mid-session, cam_14 turned 3°: cam_15 failed 22 s later, and
        # cam_11, whose own step was larger, was flagged; calibrated again against cam_14,
        # the others moved 9 cm). One camera alone explaining it is ``_explained``'s to judge.
        maybe_moved = explaining if explaining else undecided
        if (len(maybe_moved) > 1 or not explaining) and any(self._unjudged(j, a) for j in maybe_moved):
            return None
        if explaining:
            return self._explained(a, now, explaining)
        # measured alike: the failing camera's own step at the same split, all its bins
        mine = self._own_step(a.cam, a, now)
        bar = max(a.chi2, mine[0] if mine is not None else 0.0)
        steps = [(own[0], j, own) for j in undecided
                 if (own := self._own_step(j, a, now)) is not None and self._flags(own) and own[0] > bar]
        if steps:
            _, j, own = max(steps)
            return Alarm(now, j, *own)
        return a

    def _unjudged(self, j: int, a: Alarm) -> bool:
        """Camera j is watched but has fewer than ``min_change_bins`` + 1 bins since
        ``a.since`` (its own step cannot be measured yet)."""
        k = self.cams[j]
        return (k.since is None and k.anchor is not None
                and sum(b[0] >= a.since for b in k.bins) <= self.cfg.min_change_bins)

    def _explained(self, a: Alarm, now: float, explaining: list[int]) -> Alarm | None:
        """Camera ``a.cam``'s step goes away without each of ``explaining``: the alarm of
        the one whose own bins since the change show a step already (the most
        significant); else, when one camera alone explains it and its own reference is too
        short to tell (it sees little, or its watch began about the change), that camera's;
        else none yet: its own test will tell."""
        best = None
        untested = []
        for j in explaining:
            k = self.cams[j]
            if k.since is not None or k.anchor is None:
                continue  # not watched: not flagged
            own = self._own_step(j, a, now)
            if own is not None and self._flags(own):
                if best is None or own[0] > best.chi2:
                    best = Alarm(now, j, *own)
            elif own is None or sum(b[0] < a.since for b in k.bins) < self.cfg.min_reference_bins:
                untested.append(j)
        if best is not None or len(explaining) > 1 or untested != explaining:
            return best
        # The step is this camera's by the others' evidence alone: its reference cannot show
        # it (bumped while converging, its filter follows only slowly; or seeing little).
        # Its size: its bins since the change against its anchor, which may already hold
        # part of the move.
        j = untested[0]
        after = [b for b in self.cams[j].bins if b[0] >= a.since]
        d = _mean(np.array([b[2] for b in after]), np.array([b[3] for b in after]))[0] if after else np.zeros(6)
        return Alarm(now, j, a.chi2, float(np.linalg.norm(d[3:])), float(np.degrees(np.linalg.norm(d[:3]))), a.since)

    def _own_step(self, j: int, a: Alarm, now: float) -> tuple[float, float, float, float] | None:
        """Camera j's own step at ``a.since`` (``_step_at``; 3 reference bins are enough: its
        reference may be short, its bins since the change were the other's evidence), or
        None when it is not watched or has too few bins."""
        k = self.cams[j]
        if k.since is not None or k.anchor is None:
            return None
        return _step_at(k.bins, a.since, now, self.cfg, self.floor, min_after=self.cfg.min_change_bins, min_before=3)

    def _flags(self, step: tuple[float, float, float, float]) -> bool:
        """A step significant and large enough to flag a camera."""
        chi2, trans, rot, _ = step
        return chi2 > self.cfg.chi2 and (trans > self.cfg.min_translation or rot > self.cfg.min_rotation)

    def _suspects(self, a: Alarm, watched: np.ndarray) -> list[int]:
        """The cameras camera ``a.cam``'s points since the change came from, most views first."""
        k = self.cams[a.cam]
        trust = (watched & ~self.recalibrating()) if k.trust is None else k.trust & watched
        seen: dict[int, int] = {}
        for h in self.recent:
            if h.time >= a.since and a.cam in h.cams:
                for c in h.cams:
                    if c != a.cam and trust[c]:
                        seen[int(c)] = seen.get(int(c), 0) + 1
        return sorted(seen, key=lambda c: -seen[c])

    def _bins_without(self, a: Alarm, j: int, R: np.ndarray, t: np.ndarray) -> list | None:
        """Camera ``a.cam``'s bins with those since the change made again from points
        camera j had no part in; None when fewer than ``min_change_bins`` + 1 are left."""
        c, k = a.cam, self.cams[a.cam]
        C = len(R)
        trust = np.zeros((C, C), bool)
        trust[c] = (k.trust if k.trust is not None else np.ones(C, bool)) & (np.arange(C) != j)
        hyps = [h for h in self.recent if h.time >= a.since and c in h.cams]
        data = correspondences(hyps, R, t, trust, self.focal, self.min_angle, self.outlier_px).get(c, [])
        after = [b for b in (self._bin(c, start, end, data, R, t) for start, end, *_ in k.bins if start >= a.since)
                 if b is not None]
        if len(after) < self.cfg.min_change_bins + 1:
            return None
        return [b for b in k.bins if b[0] < a.since] + after

    def _reset(self, k: _Camera) -> None:
        k.bins.clear()
        k.bin_start = None
        k.anchor = None
        k.trust = None
        k.since = None
        k.data.clear()

    def _in_anchor_frame(self, c: int, R: np.ndarray, t: np.ndarray, Rs: np.ndarray, ts: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Camera c's pose R, t found against the others' current estimates Rs, ts (C, ...),
        carried into the frame the others had when their watch began (a similarity fit of
        their centres): the estimate drifting as a whole (its gauge) is no camera moving,
        nor is the filter pulling the moved camera along with its data."""
        trust = self.cams[c].trust
        others = [d for d, o in enumerate(self.cams)
                  if d != c and o.anchor is not None and o.since is None and (trust is None or trust[d])]
        if len(others) < 3:
            return R, t
        src = ts[others]
        dst = np.array([self.cams[d].anchor[1] for d in others])
        s, Rg, tg = umeyama(src, dst, with_scale=True)
        return Rg @ R, s * Rg @ t + tg

    def _bin(self, c: int, start: float, end: float, data: Sequence[Correspondences], Rs: np.ndarray, ts: np.ndarray
             ) -> tuple | None:
        """Camera c's bin [start, end) of ``data``: (start, end, z, info, where, lens), its
        resection in the anchor's frame, where in the image its points were (2,) (their
        mean, normalised) and the resection's answer to a lens error; None when too
        little was seen (the bin says nothing; its data still count for a
        recalibration) or no pose came of it."""
        in_bin = [d for d in data if start <= d.time < end]
        if sum(len(d.X) for d in in_bin) < self.cfg.min_points:
            return None
        r = resect(Rs[c], ts[c], in_bin, float(self.focal[c]), outlier_px=self.outlier_px)
        if r is None:
            return None
        where = np.concatenate([d.xy for d in in_bin]).mean(axis=0)
        z = pose_local(*self.cams[c].anchor, *self._in_anchor_frame(c, r.R, r.t, Rs, ts))
        # r.lens is in the resection's tangent; the carry into the anchor frame is a small
        # similarity, which leaves it as it is to first order
        return start, end, z, r.info, where, r.lens

    def _close_bin(self, c: int, k: _Camera, now: float, Rs: np.ndarray, ts: np.ndarray) -> None:
        """End camera c's bin at ``now`` (a grid step) and keep its pose, unless it has fewer
        than ``min_points`` joints: then it stays open for the next grid step, its oldest
        data dropped beyond ``max_bin_seconds``. A camera that sees a few joints a second
        gets a bin every 10-20 s instead of almost none: with a short reference of 3 bins it
        was never tested (the west room's cam_14 mid-session: 20-90 joints per 5 s)."""
        start = k.bin_start
        in_bin = [d for d in k.data if start <= d.time < now]
        if sum(len(d.X) for d in in_bin) < self.cfg.min_points:
            k.bin_start = max(start, now - max(self.cfg.max_bin_seconds, self.cfg.bin_seconds) + self.cfg.bin_seconds)
            return
        k.bin_start = now
        b = self._bin(c, start, now, in_bin, Rs, ts)
        if b is None:
            return
        k.bins.append(b)
        horizon = now - self.cfg.reference_seconds - self.cfg.window_seconds
        while k.bins and k.bins[0][1] < horizon:
            k.bins.pop(0)

    def _test(self, c: int, k: _Camera, now: float) -> Alarm | None:
        """The change test over the camera's bins."""
        if len(k.bins) < self.cfg.min_reference_bins:
            return None
        z = np.array([b[2] for b in k.bins])
        W = np.array([b[3] for b in k.bins])
        # After an alarm a camera's reference starts over (the camera moved, or lost one of
        # its points' sources), and its first minute differs from the next by what that did
        # (the recalibration's fit; the sources left), more likely than by a second move:
        # lab seed 218 (a live session's protocol) flagged cam_10 again 90 s into its second
        # watch, 12 cm / 0.65°, on a reference of 8 bins
        cfg = self.cfg if k.first_watch else self._full_reference
        found = change_test(z, W, np.array([b[0] for b in k.bins]), now, cfg, self.floor, where=_where(k.bins),
                            lens=_lens(k.bins))
        if found is None:
            return None
        chi2, trans, rot, since = found
        return Alarm(now, c, chi2, trans, rot, since)


def change_test(z: np.ndarray, W: np.ndarray, start: np.ndarray, now: float, cfg: MonitorConfig, floor: np.ndarray,
                *, leave_one_out: bool = True, where: np.ndarray | None = None, lens: np.ndarray | None = None,
                window_bins: int | None = None) -> tuple[float, float, float, float] | None:
    """The generalised likelihood ratio test for a step in a camera's data-only poses z
    (n, 6) (tangent at a fixed pose) with informations W (n, 6, 6), of bins starting at
    ``start`` (n,) data time: for every split of the last ``window_seconds`` (or of the
    last ``window_bins`` bins, window_seconds / bin_seconds unless given, if that reaches
    further back) leaving at
    least ``min_change_bins`` after it and ``min_reference_bins`` before, the robust mean
    after vs before, χ² against their covariances plus ``floor`` (6, 6). Each bin's
    covariance is its information's inverse plus the error it does not show
    (``bin_floor``, measured on the bins before the window). A split with fewer bins
    before it (down to ``short_reference_bins``: the camera was moved early in its
    watch) is tested once there are ``min_reference_bins`` in all, that error measured on
    the bins of both sides about their own means (``_split_scatter``). Returns the most
    significant split (by its χ² over all its bins) that passes ``chi2`` and the size
    thresholds, also without any one of the bins after it (so at least
    ``min_change_bins`` + 1 of them) that the others after it do not agree with
    (``agrees``), without more of them, agreeing or not, when the reference's odd bins
    make more than one odd bin there likely (``_odd_bins``), and, given ``where`` (n, 2)
    (where in the image each bin's points were) and ``where_covariates``, or ``lens``
    (n, 6, 4) (each bin's answer to a lens error, ``Resection.lens``) and
    ``lens_covariates``, with the bias they explain (``_bias_step``), as (χ², m, deg,
    data time of the change; the χ² and size the least of those), or None."""
    n = len(z)
    # the window in data time, or in bins for a camera whose bins are longer (it sees
    # little): a step at the start of its first watch had left a 60 s window before it
    # had the bins to be tested (the west room's cam_14, 3 cm mid-session: never flagged)
    bins = round(cfg.window_seconds / cfg.bin_seconds) if window_bins is None else window_bins
    first = next((j for j in range(n) if now - start[j] <= cfg.window_seconds or n - j <= bins), n)
    full = max(first, cfg.min_reference_bins)
    lo = max(first, min(cfg.short_reference_bins, full)) if n >= cfg.min_reference_bins else full
    if lo >= n - cfg.min_change_bins:
        return None
    C = np.linalg.inv(W)
    where = where if cfg.where_covariates else None
    lens = lens if cfg.lens_covariates else None
    bias = None if where is None and lens is None else _bias_columns(n, where, lens, cfg.lens_std)
    # split: (W (n, 6, 6) with the floor, overdispersion, share of odd bins)
    scatter: dict[int, tuple[np.ndarray, float, float]] = {}

    def calibrated(j: int) -> tuple[np.ndarray, float, float]:
        if j < full:  # a short reference: the scatter of both sides
            if j not in scatter:
                scatter[j] = _split_scatter(z, C, j, cfg)
            return scatter[j]
        if full not in scatter:
            Wf = np.linalg.inv(C + bin_floor(z[:full], C[:full], cfg))
            m, _, kappa, _ = _mean(z[:full], Wf[:full])
            r = z[:full] - m
            chi = np.einsum("ni,nij,nj->n", r, Wf[:full], r) / kappa
            scatter[full] = (Wf, kappa, _odd_share(chi))
        return scatter[full]

    best = None
    reference: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # split: the mean before it (once per split)

    def step(j: int, after: np.ndarray) -> _Step | None:
        Wj, kappa, _ = calibrated(j)
        if j not in reference:
            reference[j] = _mean(z[:j], Wj[:j], kappa)[:2]
        zr, Sr = reference[j]
        zn, Sn, _, kept = _mean(z[after], Wj[after], kappa)
        if kept < cfg.min_change_bins:
            return None  # bins after the split that disagree among themselves are no step
        d = zn - zr
        try:
            chi2 = float(d @ np.linalg.solve(kappa * (Sr + Sn) + floor, d))
        except np.linalg.LinAlgError:
            return None
        # NaN (no reference bin kept: infinite covariance) passes no "<=" threshold
        return _Step(chi2, d, zn, Sn) if np.isfinite(chi2) else None

    def agrees(j: int, i: int, rest: _Step) -> bool:
        """Bin i is where the other bins after split j put the camera (their mean ``rest``),
        and they show the step on their own at half the threshold's χ²."""
        Wj, kappa, _ = calibrated(j)
        r = z[i] - rest.after
        try:
            chi2 = float(r @ np.linalg.solve(kappa * (np.linalg.inv(Wj[i]) + rest.after_cov), r))
        except np.linalg.LinAlgError:
            return False
        return chi2 <= _CHI2_6_Q99 and rest.chi2 > cfg.chi2 / 2

    for j in range(lo, n - cfg.min_change_bins):
        found = step(j, np.arange(j, n))
        if found is None or found.chi2 <= cfg.chi2:
            continue
        full_chi2 = found.chi2
        # ... and still without any one of the bins after it: one bin far off (a person
        # the camera sees oddly for a few seconds) is no step. A bin where the others put
        # the camera is no odd one, however much it weighs: the bar's seed 1 (cam_8 moved
        # 3 cm) had χ² 56 from 15 s after the move, 29 without its one bin of 671 joints
        # (the others had 150-190), which agreed with them (χ² 2.0); it waited 50 s
        # for another bin as strong. Without more than one, when the camera's own bins
        # are often odd (``_odd_bins``; lenses 1 % off and keypoints on the outline: lab
        # seed 304's cam_19 failed on two odd bins of nine, at χ² 128 and 53 to the
        # reference, the other seven within it; 3 of the 33 bins before its window were
        # odd): the bins left out one at a time, each time the one whose leaving lowers
        # the χ² most
        after = np.arange(j, n)
        rounds = _odd_bins(n - j, calibrated(j)[2], cfg.odd_bin_level) if leave_one_out else 0
        # A bin that agrees with the rest is kept only while one odd bin is all the camera's
        # reference makes likely: when more are, the rest may hold odd ones too, and odd
        # bins that happen to agree are no step (lab seed 263, quiet: cam_10 flagged at
        # χ² 42.3 on six bins, three of them odd, each agreeing with the other five at χ²
        # 11-17; its reference had 3 of 33 bins odd)
        trust_agreement = rounds == 1
        for _ in range(rounds):
            rest = found
            for leave in after:
                without = step(j, after[after != leave])
                if without is not None and (without.chi2 >= found.chi2 or trust_agreement and agrees(j, leave, without)):
                    continue
                found, left = without, leave
                if found is None or found.chi2 <= cfg.chi2:
                    break
            if found is None or found.chi2 <= cfg.chi2 or found is rest:
                break  # no step, or no bin left that is odd
            after = after[after != left]
        if found is None or found.chi2 <= cfg.chi2:
            continue
        chi2, d = found.chi2, found.step
        if bias is not None:
            chi2 = min(chi2, _bias_step(z, *calibrated(j)[:2], floor, j, *bias))
            if chi2 <= cfg.chi2:
                continue
        rot = float(np.degrees(np.linalg.norm(d[:3])))
        trans = float(np.linalg.norm(d[3:]))
        # the split is the likeliest one (all its bins; the least of the leave-one-out
        # χ² favours splits with more bins, before the change too)
        if (trans > cfg.min_translation or rot > cfg.min_rotation) and (best is None or full_chi2 > best[0]):
            best = (full_chi2, (chi2, trans, rot, float(start[j])))
    return None if best is None else best[1]


class _Step(NamedTuple):
    """A split's step in ``change_test``: its χ², the step (6,), and the robust mean of the
    bins after the split (6,) with its covariance (6, 6)."""

    chi2: float
    step: np.ndarray
    after: np.ndarray
    after_cov: np.ndarray


def _where(bins: list) -> np.ndarray | None:
    """(n, 2) where in the image the points of each of ``bins`` were, or None when a bin
    does not say (made by hand)."""
    if not bins or any(len(b) < 5 or b[4] is None for b in bins):
        return None
    return np.array([b[4] for b in bins])


def _lens(bins: list) -> np.ndarray | None:
    """(n, 6, 4) each of ``bins``' pose change per 1 % of a lens error
    (``Resection.lens``), or None when a bin does not say (made by hand)."""
    if not bins or any(len(b) < 6 or b[5] is None for b in bins):
        return None
    return np.array([b[5] for b in bins])


def _bias_columns(n: int, where: np.ndarray | None, lens: np.ndarray | None, lens_std: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The bias terms of ``_bias_step`` for n bins: columns G (n, 6, p) and the prior
    information of their coefficients (p,). Where (n, 2): B (6, 2) linear in where the
    bin's points were in the image (12 coefficients, centred; a weak prior, 1 rad / 1 m
    per unit of the normalised image, only keeps a bias the people's places cannot show
    at zero). Lens (n, 6, 4): λ (4), the lens's error in % (prior std ``lens_std``, a
    fraction)."""
    cols, prior = [np.zeros((n, 6, 0))], [np.zeros(0)]
    if where is not None:
        w = where - where.mean(axis=0)
        eye = np.eye(6)
        cols += [w[:, 0, None, None] * eye, w[:, 1, None, None] * eye]
        prior.append(np.ones(12))
    if lens is not None:
        cols.append(lens)
        prior.append(np.full(4, (0.01 / lens_std) ** 2))
    return np.concatenate(cols, axis=2), np.concatenate(prior)


def _bias_step(z: np.ndarray, W: np.ndarray, kappa: float, floor: np.ndarray, j: int, G: np.ndarray,
               prior: np.ndarray, *, huber: float = 3.5, reject: float = 10.0) -> float:
    """χ² of the step at bin j of poses z (n, 6) (informations W (n, 6, 6) with the floor,
    overdispersion ``kappa``) when each bin's pose may also be biased by terms that
    depend on what the bin saw, G (n, 6, p) with coefficients of prior information
    ``prior`` (p,) (``_bias_columns``): z_i = a + d·[i >= j] + G_i·β + e_i, β fitted
    with the step (robustly, as ``_mean``). A lens a little off its calibration or
    keypoints off the joints bias a camera's data-only pose by where the people are in
    its view and how deep: people walking to another part of it are not the camera
    moving. A move shifts every bin, wherever its people; when the people changed places
    with the step, it cannot be told from their bias and waits for them to come back.
    Returns d's χ² against its covariance plus ``floor``."""
    n, p = len(z), G.shape[2]
    D = np.zeros((n, 6, 12 + p))  # the parameters: a (6), d (6), β (p)
    eye = np.eye(6)
    D[:, :, :6] = eye
    D[j:, :, 6:12] = eye
    D[:, :, 12:] = G
    P = np.diag(np.r_[np.zeros(12), prior])
    wt = np.ones(n)
    chi2 = float("inf")  # no fit: nothing explained
    for _ in range(5):
        A = np.einsum("n,nia,nij,njb->ab", wt, D, W, D) + P
        try:
            Ainv = np.linalg.inv(A)
            theta = Ainv @ np.einsum("n,nia,nij,nj->a", wt, D, W, z)
            cov = kappa * Ainv[6:12, 6:12]
            d = theta[6:12]
            chi2 = float(d @ np.linalg.solve(cov + floor, d))
        except np.linalg.LinAlgError:
            break
        r = z - np.einsum("nia,a->ni", D, theta)
        m = np.sqrt(np.einsum("ni,nij,nj->n", r, W, r) / kappa)
        wt = np.where(m > reject, 0.0, np.minimum(1.0, huber / np.maximum(m, 1e-12)))
        if not wt[:j].any() or not wt[j:].any():
            break  # a side left out whole: the last fit stands
    return chi2


def _split_scatter(z: np.ndarray, C: np.ndarray, j: int, cfg: MonitorConfig) -> tuple[np.ndarray, float, float]:
    """For a split at bin j with a short reference: the bins' informations with the
    floor (``bin_floor``) and the overdispersion, both measured on the bins of each side
    about that side's own mean (a step between them is not scatter). A side's χ² about
    its own mean are scaled by n / (n - 1): four bins' mean takes a quarter of their
    scatter. Returns (W (n, 6, 6), overdispersion, share of odd bins: ``_odd_share``)."""
    sides = (slice(0, j), slice(j, len(z)))
    F = bin_floor(z, C, cfg, sides=sides)
    W = np.linalg.inv(C + F)
    chi = np.concatenate([_chi_about_mean(z[s], W[s]) for s in sides])
    kappa = max(float(np.median(chi)) / _CHI2_6_MEDIAN, _KAPPA_MIN)
    return W, kappa, _odd_share(chi / kappa)


def _odd_share(chi: np.ndarray) -> float:
    """The share of a camera's bins that are odd, from the χ² (n,) of its reference bins
    about their mean (scaled by the overdispersion): those beyond the χ² distribution's
    99th percentile, with half an odd and half a not counted in (Jeffreys's prior: a
    reference of a dozen bins none of which is odd says only that odd ones are rare)."""
    return (float(np.count_nonzero(chi > _CHI2_6_Q99)) + 0.5) / (len(chi) + 1.0)


def _odd_bins(after: int, share: float, level: float) -> int:
    """How many of ``after`` bins a step must pass without: one, or more when bins odd
    at the rate ``share`` leave more than that many odd among them with a probability
    above ``level`` (binomial)."""
    k = 1
    while k < after and binom.sf(k, after, share) > level:  # P(more than k odd)
        k += 1
    return k


def _chi_about_mean(z: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) the χ² of bins z (n, 6) about their robust mean (informations W), scaled by
    n / (n - 1) for the degrees of freedom the mean takes."""
    r = z - _mean(z, W, 1.0)[0]
    return np.einsum("ni,nij,nj->n", r, W, r) * len(z) / max(len(z) - 1, 1)


def _step_at(bins: list, since: float, now: float, cfg: MonitorConfig, floor: np.ndarray, min_after: int = 1,
             min_before: int | None = None) -> tuple[float, float, float, float] | None:
    """The step of a camera's ``bins`` (start, end, z, info) at the one split ``since``,
    unthresholded and without leaving bins out, as ``change_test`` measures it: (χ², m,
    deg, since), or None without ``min_before`` (``min_reference_bins``) bins before it
    (``short_reference_bins`` when there are ``min_before`` in all, as ``change_test``
    has it) and ``min_after`` after."""
    n_after = sum(b[0] >= since for b in bins)
    min_before = cfg.min_reference_bins if min_before is None else min_before
    # a short reference is measured as ``change_test`` measures it, with min_before bins in all
    short = min(min_before, cfg.short_reference_bins) if len(bins) >= min_before else min_before
    if n_after < max(min_after, 1) or len(bins) - n_after < short:
        return None
    one = cfg.model_copy(update={"window_seconds": now - since + 1e-6, "min_change_bins": n_after - 1,
                                 "min_reference_bins": min_before, "short_reference_bins": short,
                                 "chi2": 0.0, "min_translation": -1.0, "min_rotation": -1.0})
    return change_test(np.array([b[2] for b in bins]), np.array([b[3] for b in bins]),
                       np.array([b[0] for b in bins]), now, one, floor, leave_one_out=False, where=_where(bins),
                       lens=_lens(bins), window_bins=0)


def bin_floor(z: np.ndarray, C: np.ndarray, cfg: MonitorConfig, *, sides: tuple[slice, ...] | None = None
              ) -> np.ndarray:
    """(6, 6) the error of one bin that its covariance C (n, 6, 6) does not show (where
    the people were and what the others' own errors made of that), measured on the
    camera's bins z (n, 6): α² diag(``bin_std_*``²) with the least α in [0, 1] for
    which the bins' χ² around their robust mean have the χ² distribution's upper quartile
    (not the median: the bins' errors have heavy tails)
    (α = 1 when even that is not enough; the overdispersion of ``_mean`` takes the rest).
    ``sides``: the bins' χ² about each side's own mean instead (``_chi_about_mean``).
    Without it one bin that claims too much outweighs several; a fixed value would be
    wrong for a network calibrated better or worse than the one it was measured on."""
    rb = np.radians(cfg.bin_std_rotation)
    F0 = np.diag([rb * rb] * 3 + [cfg.bin_std_translation ** 2] * 3)

    def median_chi(a: float) -> float:
        W = np.linalg.inv(C + a * a * F0)
        if sides is not None:
            return float(np.quantile(np.concatenate([_chi_about_mean(z[s], W[s]) for s in sides]), 0.75))
        m, _, _, _ = _mean(z, W, 1.0)
        r = z - m
        return float(np.quantile(np.einsum("ni,nij,nj->n", r, W, r), 0.75))

    if median_chi(0.0) <= _CHI2_6_Q75:
        return 0.0 * F0
    if median_chi(1.0) >= _CHI2_6_Q75:
        return F0
    lo, hi = 0.0, 1.0
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if median_chi(mid) > _CHI2_6_Q75 else (lo, mid)
    return hi * hi * F0


_CHI2_6_MEDIAN = 5.348  # median of the χ² distribution with 6 dof
# least overdispersion: bins that scatter less than their covariances say do not make the
# test more sensitive. A dozen reference bins of people walking the same spots scatter
# less than bins of people elsewhere do (their errors are correlated over time), and a
# median of a dozen χ² is itself uncertain: lab seed 107 raised a false alarm (cam_12,
# 751 s) on a reference that scattered a third of what its covariances said
_KAPPA_MIN = 1.0
_CHI2_6_Q75 = 7.841  # its upper quartile
_CHI2_6_Q99 = 16.81  # its 99th percentile


def _mean(z: np.ndarray, W: np.ndarray, kappa: float | None = None, *, huber: float = 3.5, reject: float = 10.0
          ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Robust information-weighted mean of poses z (n, 6) with informations W (n, 6, 6):
    (mean, its covariance, overdispersion, bins kept). The overdispersion, unless given, is the bins'
    median χ² around the mean over the χ² distribution's median (what the solver's
    information overstates or, below 1, understates; at least ``_KAPPA_MIN``). A bin further than ``huber`` (Mahalanobis, scaled by
    the overdispersion) from the mean is down-weighted: one bin of wrong associations
    must not make a change; one beyond ``reject`` is left out."""
    k = 1.0 if kappa is None else kappa
    # the start: the bin nearest the others (least median χ² to them, each in the other's
    # information), not a mean, which a far-off bin drags, nor the coordinate-wise median,
    # which with a bin's strongly correlated rotation and translation can lie far from
    # every bin, so that all would be rejected
    r = z[:, None, :] - z[None, :, :]
    m = z[int(np.argmin(np.median(np.einsum("inj,njk,ink->in", r, W, r), axis=1)))]
    for _ in range(5):
        r = z - m
        chi = np.einsum("ni,nij,nj->n", r, W, r)
        if kappa is None and len(z) >= 3:
            k = max(float(np.median(chi)) / _CHI2_6_MEDIAN, _KAPPA_MIN)
        dist = np.sqrt(chi / k)
        w = np.where(dist <= huber, 1.0, huber / np.maximum(dist, 1e-12)) * (dist <= reject)
        if not w.any():
            return m, np.full((6, 6), np.inf), k, 0
        Wsum = np.einsum("n,nij->ij", w, W)
        cov = np.linalg.inv(Wsum)
        m = cov @ np.einsum("n,nij,nj->i", w, W, z)
    return m, cov, k, int(np.count_nonzero(w))
