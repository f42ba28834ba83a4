"""Filters and undistortion of one frameset's views (the paper's preprocessing).

Joints outside the image (or where its lens model folds back) and below the confidence
threshold are dropped; a person detected twice in one image keeps its better detection; a
person needs both hips and both shoulders; persons too close to
another person in the same image are dropped (their keypoints mix); crowded views are
dropped (detections with no joint at the threshold do not count towards a crowd). What
remains is undistorted to normalised image coordinates with a per-joint standard deviation
in pixels.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .cameras import Intrinsics, undistort
from .config import PreprocessConfig
from .sync import Frameset, View

L_SHOULDER, R_SHOULDER, L_HIP, R_HIP = 5, 6, 11, 12
TORSO = (L_SHOULDER, R_SHOULDER, L_HIP, R_HIP)
OUTSIDE_TOLERANCE = 1.0  # px beyond the image border a joint may lie (pixel-centre conventions differ)
# Relative keypoint noise per COCO joint: detectors place the face and shoulders best,
# hips (under clothing) and the extremities worst. Ordered like proto.COCO17.
JOINT_NOISE = np.array([1.0, 1.0, 1.0, 1.2, 1.2, 1.2, 1.2, 1.5, 1.5, 2.0, 2.0, 1.4, 1.4, 1.6, 1.6, 2.0, 2.0])


def unmeasured(kp: np.ndarray, size: tuple[int, int], intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Detected joints (confidence > 0) that are no measurement: outside the image, and
    inside it where the lens model folds back (``Intrinsics.fold_radius``).

    kp: (..., 3) float64 pixels and confidence at ``size`` (w, h); intr at that size.
    Returns two (...,) bool masks. A detector may place a joint it guesses beyond the
    image border (top-down models do, from a crop that extends past it): no pixel saw
    it, and the lens model is not valid there."""
    W, H = size
    u, w = kp[..., 0], kp[..., 1]
    seen = kp[..., 2] > 0
    tol = OUTSIDE_TOLERANCE
    outside = seen & ~((u >= -tol) & (u <= W + tol) & (w >= -tol) & (w <= H + tol))
    folded = np.zeros_like(outside)
    if np.isfinite(intr.fold_radius):
        folded = seen & ~outside & (np.hypot((u - intr.cx) / intr.fx, (w - intr.cy) / intr.fy) >= intr.fold_radius)
    return outside, folded


@dataclass(frozen=True, eq=False)
class Detection:
    """One person in one camera, ready for association.

    xy: (17, 2) float64 undistorted normalised coordinates, NaN = missing.
    sigma: (17,) float64 pixel standard deviation per joint, NaN = missing.
    """

    cam: int
    xy: np.ndarray
    sigma: np.ndarray
    focal: float  # mean focal length in px: sigma / focal is the normalised std
    seq: int = -1  # provenance: message seq and position in its persons (for evaluation)
    index: int = -1

    def __post_init__(self) -> None:
        assert self.xy.shape == (17, 2) and self.sigma.shape == (17,)

    @property
    def whole_torso(self) -> bool:
        """Both shoulders and both hips seen (else one side is hidden: a profile view)."""
        return bool(np.isfinite(self.xy[list(TORSO), 0]).all())


class ConfidenceScale:
    """Per sensor, the factor that brings its detector's confidences to the scale that
    ``min_confidence`` is stated for: ``reference`` over the 90th percentile of its
    detected torso-joint confidences, between 1 and ``MAX_FACTOR``. Until a sensor has
    sent ``MIN_JOINTS`` such joints, the factor of all sensors' joints together (one
    detector on every sensor is the rule; a sensor that sees little would otherwise
    lose its first minutes). The 90th percentile is what the detector says of a clearly
    seen joint: occlusion, distance and the border lower the rest, not it (the
    simulator's sensors: 0.93-0.98, also those with half their torso joints below 0.6)."""

    BINS = 200
    MIN_JOINTS = 200
    MAX_FACTOR = 3.0
    QUANTILE = 0.9
    _ALL = ""  # the key of all sensors' joints together

    def __init__(self, reference: float | None):
        self.reference = reference
        self.hist: dict[str, np.ndarray] = {}  # sensor (and _ALL) -> (BINS,) counts of confidences in (0, 1]
        self._factor: dict[str, float] = {}

    def observe(self, sensor: str, conf: np.ndarray) -> None:
        """conf: (N,) detected (> 0) torso-joint confidences of one view, as sent."""
        if self.reference is None or not len(conf):
            return
        counts = np.bincount(np.minimum((np.clip(conf, 0, 1) * self.BINS).astype(np.int64), self.BINS - 1),
                             minlength=self.BINS)
        for key in (sensor, self._ALL):
            h = self.hist.get(key)
            if h is None:
                h = self.hist[key] = np.zeros(self.BINS, np.int64)
            h += counts
            n = int(h.sum())
            if n >= self.MIN_JOINTS:
                q = (int(np.searchsorted(np.cumsum(h), self.QUANTILE * n)) + 1) / self.BINS  # the bin's upper edge
                self._factor[key] = float(np.clip(self.reference / q, 1.0, self.MAX_FACTOR))

    def factor(self, sensor: str) -> float:
        k = self._factor.get(sensor)
        return self._factor.get(self._ALL, 1.0) if k is None else k

    def take(self, other: "ConfidenceScale") -> None:
        """Go on with another's scales, in place (other stages hold this one)."""
        self.hist, self._factor = {k: h.copy() for k, h in other.hist.items()}, dict(other._factor)

    def apply(self, sensor: str, conf: np.ndarray) -> np.ndarray:
        """conf (...,) scaled, at most 1 (a new array unless the factor is 1)."""
        k = self.factor(sensor)
        return conf if k == 1.0 else np.minimum(conf * k, 1.0)


def duplicates(kp: np.ndarray, max_distance: float, max_candidates: int | None = None) -> np.ndarray:
    """(P,) True for the detections that are another's person detected again: of the joints
    both detected (confidence > 0; at least 3 and half of the smaller skeleton's), 80 % lie
    within ``max_distance`` times the smaller one's size (its joints' extent) of the
    other's. Of such a pair the detection with more joints (then the larger confidence
    sum) is kept; pairs are settled best first, so a person sent three times keeps one.
    Why not the median: a person half hidden behind another gets a skeleton that mixes
    the two (some joints on the one in front, others its own); that is no copy of either,
    and both stay to the min_box_distance check.

    ``max_candidates``: with more detections of 3 joints or more, none is tested (the
    pairwise test's (P, P, 17) arrays are for views that can still be used).

    kp: (P, 17, 3) float64 pixels and confidence, 0 = not detected."""
    assert kp.ndim == 3 and kp.shape[1:] == (17, 3)
    P = len(kp)
    out = np.zeros(P, bool)
    seen = kp[..., 2] > 0
    n = seen.sum(1)
    if P < 2 or max_distance <= 0 or (max_candidates is not None and int((n >= 3).sum()) > max_candidates):
        return out
    lo = np.where(seen[..., None], kp[..., :2], np.inf).min(1)
    hi = np.where(seen[..., None], kp[..., :2], -np.inf).max(1)
    size = np.where(n >= 2, np.max(hi - lo, axis=1), 0.0)  # (P,)
    # all pairs at once (a message may hold up to proto's 256 persons): the 80 % quantile
    # (numpy's linear one) of each pair's distances over the joints both have
    both = seen[:, None, :] & seen[None, :, :]  # (P, P, 17)
    k = both.sum(-1)
    d = np.sort(np.where(both, np.linalg.norm(kp[:, None, :, :2] - kp[None, :, :, :2], axis=-1), np.inf), -1)
    pos = 0.8 * np.maximum(k - 1, 0)
    i0 = np.floor(pos).astype(np.int64)[..., None]
    i1 = np.ceil(pos).astype(np.int64)[..., None]
    d0, d1 = np.take_along_axis(d, i0, -1)[..., 0], np.take_along_axis(d, i1, -1)[..., 0]
    small = np.minimum(n[:, None], n[None, :])
    pair = (k >= 3) & (k >= 0.5 * small)
    with np.errstate(invalid="ignore"):
        q = np.where(pair, d0 + (pos - np.floor(pos)) * (d1 - d0), np.inf)
    same = pair & (q < max_distance * np.minimum(size[:, None], size[None, :]))
    np.fill_diagonal(same, False)
    order = np.lexsort((-kp[..., 2].sum(1), -n))  # best first
    rank = np.empty(P, np.int64)
    rank[order] = np.arange(P)
    for a in order:  # ``same`` holds only pairs of 3 joints or more
        if not out[a]:
            out |= same[a] & (rank > rank[a])
    return out


class Preprocessor:
    def __init__(self, config: PreprocessConfig, names: tuple[str, ...], intrinsics: Mapping[str, Intrinsics],
                 confidence: ConfidenceScale | None = None):
        """``confidence``: the sensors' confidence scales, shared with another stage that
        learnt them (a new one learns from this one's views)."""
        self.cfg = config
        self.confidence = confidence or ConfidenceScale(config.confidence_reference)
        self.index = {n: i for i, n in enumerate(names)}
        self.intrinsics = dict(intrinsics)
        self._scaled: dict[tuple[str, tuple[int, int]], Intrinsics | None] = {}
        self.rejected: Counter = Counter()
        self.accepted = 0
        # per sensor: torso keypoints detected (confidence > 0) and those of them below the
        # threshold; a detector whose confidences run lower than the threshold shows here
        self.torso_seen: Counter = Counter()
        self.torso_low: Counter = Counter()
        # per sensor: joints detected and those of them outside the message's image; a
        # sensor whose `size` is not its keypoints' pixel frame shows here
        self.joints_seen: Counter = Counter()
        self.joints_outside: Counter = Counter()
        # ... and those where the lens model folds back (Intrinsics.fold_radius)
        self.joints_folded: Counter = Counter()

    def take_counts(self, other: "Preprocessor") -> None:
        """Go on with another preprocessor's counts (a pipeline rebuilt mid-session)."""
        for k in ("accepted", "rejected", "torso_seen", "torso_low", "joints_seen", "joints_outside", "joints_folded"):
            setattr(self, k, getattr(other, k))
        self.confidence.take(other.confidence)

    def intrinsics_for(self, sensor: str, size: tuple[int, int]) -> Intrinsics | None:
        """The sensor's intrinsics at a message's resolution; None if the aspect differs."""
        key = (sensor, tuple(size))
        if key not in self._scaled:
            self._scaled[key] = self.intrinsics[sensor].at(size)
        return self._scaled[key]

    def __call__(self, fs: Frameset) -> list[list[Detection]]:
        """Detections per view of the frameset (views with none are left out)."""
        out = []
        for v in fs.views:
            dets = self.view(v)
            if dets:
                out.append(dets)
        return out

    def view(self, v: View) -> list[Detection]:
        intr = self.intrinsics_for(v.sensor, v.size)
        P = len(v.kp)
        if P == 0:
            return []
        if intr is None:
            self.rejected["resolution_mismatch"] += P
            return []
        kp = v.kp.copy()
        seen = kp[..., 2] > 0
        outside, folded = unmeasured(kp, v.size, intr)
        self.joints_seen[v.sensor] += int(seen.sum())
        self.joints_outside[v.sensor] += int(outside.sum())
        self.joints_folded[v.sensor] += int(folded.sum())
        kp[outside | folded, 2] = 0.0
        torso = kp[:, TORSO, 2]
        detected = torso > 0
        self.confidence.observe(v.sensor, torso[detected])
        kp[..., 2] = self.confidence.apply(v.sensor, kp[..., 2])
        torso = kp[:, TORSO, 2]
        confident = detected & (torso >= self.cfg.min_confidence)
        self.torso_seen[v.sensor] += int(detected.sum())
        self.torso_low[v.sensor] += int((detected & ~confident).sum())
        kp[kp[..., 2] < self.cfg.min_confidence, 2] = 0.0
        # more than three times max_persons detections are a crowd however many are copies
        dup = duplicates(kp, self.cfg.duplicate_distance, 3 * self.cfg.max_persons)
        self.rejected["duplicate"] += int(dup.sum())
        # A detection with no joint at the threshold is no one the calibration sees: real
        # detectors send such low-score boxes by the dozen, and counted as persons they
        # would make a whole view "crowded". It still counts as a neighbour that is too
        # close: most are people half hidden behind the one in front, whose keypoints mix
        # (counted out, the two-walker corridor's seed 2 ended 0.078 m off, not 0.047).
        if ((kp[..., 2] > 0).any(axis=1) & ~dup).sum() > self.cfg.max_persons:
            self.rejected["crowded_view"] += P - int(dup.sum())  # each detection counted once
            return []
        if self.cfg.partial_torso:  # TORSO is (L_SHOULDER, R_SHOULDER, L_HIP, R_HIP)
            keep = confident[:, :2].any(axis=1) & confident[:, 2:].any(axis=1)
        else:
            keep = np.all(confident, axis=1)
        self.rejected["no_torso"] += int((~keep & ~dup).sum())
        keep &= ~dup
        close = self._too_close(kp, v.boxes, v.size, ~dup) & keep
        self.rejected["too_close"] += int(close.sum())
        keep &= ~close
        if not keep.any():
            return []
        idx = np.flatnonzero(keep)
        kp = kp[idx]
        valid = kp[..., 2] > 0
        uv = kp[..., :2][valid]
        xy = np.full((len(idx), 17, 2), np.nan)
        xy[valid] = undistort(uv, intr)
        sigma = self._sigma(kp, v, idx, valid)
        f = 0.5 * (intr.fx + intr.fy)
        cam = self.index[v.sensor]
        self.accepted += len(idx)
        src = v.index[idx] if v.index is not None else np.full(len(idx), -1)
        return [Detection(cam, xy[k], sigma[k], f, v.seq, int(src[k])) for k in range(len(idx))]

    def confidence_report(self, min_joints: int = 200, warn_share: float = 0.5,
                          warn_outside: float = 0.2) -> dict[str, dict]:
        """Per sensor: torso keypoints seen, the share of them below ``min_confidence``,
        the shares of all its joints outside the image and beyond its lens model, and a
        warning when more than ``warn_share`` resp. ``warn_outside`` of at least
        ``min_joints`` are."""
        out = {}
        for sensor in self.joints_seen:
            n = self.torso_seen[sensor]
            share = self.torso_low[sensor] / n if n else 0.0
            m = self.joints_seen[sensor]
            outside = self.joints_outside[sensor] / m if m else 0.0
            warn = []
            if m >= min_joints and outside > warn_outside:
                warn.append(f"{100 * outside:.0f} % of its keypoints lie outside its images' size and are dropped: "
                            "the messages' `size` is not the pixel frame of their keypoints (a detector run at "
                            "another resolution than it reports?)")
            if n >= min_joints and share > warn_share:
                k = self.confidence.factor(sensor)
                warn.append(f"{100 * share:.0f} % of its torso keypoints are below preprocess.min_confidence "
                            f"({self.cfg.min_confidence:g}"
                            + (f", its confidences scaled x{k:.2f}" if k != 1.0 else "")
                            + ") and dropped: few of its detections reach the calibration "
                            "(people far, occluded or cut off by the image border; or a detector whose confidences run "
                            "lower, which needs a lower threshold)")
            folded = self.joints_folded[sensor] / m if m else 0.0
            if m >= min_joints and folded > warn_outside:
                warn.append(f"{100 * folded:.0f} % of its keypoints lie where its lens model folds back (its "
                            "distortion polynomial stops growing towards the image border) and are dropped: "
                            "distortion coefficients fitted to the image's centre only?")
            out[sensor] = {"torso_keypoints": n, "below_confidence": round(share, 4),
                           "confidence_scale": round(self.confidence.factor(sensor), 4),
                           "outside_image": round(outside, 4), "beyond_lens_model": round(folded, 4),
                           "warning": "; ".join(warn) or None}
        return out

    def _too_close(self, kp: np.ndarray, boxes: np.ndarray, size: tuple[int, int], present: np.ndarray
                   ) -> np.ndarray:
        """(P,) True for persons whose box is within the distance limit of another's
        (of the ``present`` (P,) ones: a dropped duplicate is no neighbour)."""
        P = len(kp)
        if P < 2 or self.cfg.min_box_distance <= 0:
            return np.zeros(P, bool)
        b = boxes.copy()
        for i in range(P):  # boxes from the keypoints where the sensor sent none
            if not np.all(np.isfinite(b[i])):
                ok = kp[i, :, 2] > 0
                pts = kp[i, ok, :2] if ok.any() else kp[i, :, :2]
                b[i] = [*pts.min(0), *pts.max(0)]
        # gap between axis-aligned boxes (0 when they overlap)
        gx = np.maximum(0, np.maximum(b[:, None, 0], b[None, :, 0]) - np.minimum(b[:, None, 2], b[None, :, 2]))
        gy = np.maximum(0, np.maximum(b[:, None, 1], b[None, :, 1]) - np.minimum(b[:, None, 3], b[None, :, 3]))
        gap = np.hypot(gx, gy)
        np.fill_diagonal(gap, np.inf)
        gap[:, ~present] = np.inf
        return gap.min(1) < self.cfg.min_box_distance * float(np.hypot(*size))

    def _sigma(self, kp: np.ndarray, v: View, idx: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(P, 17) px std: the sensor's covariance if sent, else a confidence model;
        widened by the motion over the time offset of a non-interpolated view."""
        if v.cov is not None:
            c = v.cov[idx]
            var = np.maximum(0.5 * (c[..., 0] + c[..., 2]), self.cfg.min_pixel_sigma**2)
        else:
            conf = np.clip(kp[..., 2], 0.3, 1.0)
            var = (self.cfg.pixel_sigma * JOINT_NOISE[None, :] / conf) ** 2
        var = var + (v.speed[idx] * v.offset) ** 2
        return np.where(valid, np.sqrt(var), np.nan)
