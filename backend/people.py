"""Metric scale from the people in the scene: their size, known or from a population prior.

Keypoints alone fix a camera network up to a similarity: its scale is whatever the
initial estimate (or the bootstrap) made it. People carry a scale with them. Their
bones do not change length while they walk, and stature is nearly proportional to the
chain of bones from the ankle to the shoulder. Segment lengths as fractions of stature H
(Drillis & Contini 1966, as tabulated in D. A. Winter, *Biomechanics and Motor Control of
Human Movement*, 4th ed., 2009, Fig. 4.1):

    shank (knee to ankle)            0.246 H   (knee 0.285 H, ankle 0.039 H above the floor)
    thigh (hip to knee)              0.245 H   (hip 0.530 H)
    torso (mid-hips to mid-shoulders) 0.2924 H (the paper's ratio, ``associate.torso_ratio``;
                                               Drillis & Contini's shoulder 0.818 H - hip 0.530 H
                                               gives 0.288 H, 1.5 % less)

so the chain shank + thigh + torso is 0.7834 H. The chain is measured per person from
triangulated joints, per segment as the median over time (the legs: mean of left and
right), which walking, bending and a swapped left/right in one view do not change.

Individual proportions vary: the relative spread between adults of leg length / stature is
about 2-3 % and of the trunk similar (Bogin & Varela-Silva, "Leg length, body proportion and
health", Int. J. Environ. Res. Public Health 7, 2010); for the sum we take 2 %
(``bootstrap.ratio_std``). That is what a known height can pin the scale to per person.

Without a known height, the population prior: adult stature 1.72 ± 0.10 m (mixed sexes).
Source: German Mikrozensus 2017 (Statistisches Bundesamt, "Körpermaße der Bevölkerung"):
mean height of adult men about 1.79 m, of women about 1.66 m, each with a spread of about
0.07 m (as in other European surveys, e.g. NCD-RisC, eLife 5:e13410, 2016); an equal mix
has mean 1.72 m and std sqrt(0.07² + 0.065²) ≈ 0.096 m. With K distinct persons the
relative uncertainty of the scale is sqrt(0.058² + 0.02²) / sqrt(K) (e.g. 4.4 % for two).
Change the prior (``bootstrap.height_mean``, ``height_std``) for other populations (children,
a basketball team).

Persons are told apart by tracking hypotheses over time and grouping the tracks by their
chain length into as many persons as are seen at once most of the time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .associate import Associator, Hypothesis, triangulate_hypotheses
from .config import AssociateConfig, BootstrapConfig

# COCO-17 joints
L_SHOULDER, R_SHOULDER, L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE = 5, 6, 11, 12, 13, 14, 15, 16
SHANK, THIGH = 0.246, 0.245
ANKLE_HEIGHT = 0.039  # ankle joint above the floor, fraction of H (Drillis & Contini)


def chain_ratio(torso_ratio: float = 0.2924) -> float:
    """Shank + thigh + torso as a fraction of stature."""
    return SHANK + THIGH + torso_ratio


@dataclass(frozen=True, eq=False)
class Segments:
    """Bone lengths of hypotheses, in the units of the camera poses.

    time: (N,) s; com: (N, 3) torso centre; shank, thigh, torso: (N,) lengths, NaN where
    not triangulated (the legs: mean of the sides that are); ankles: (N, 2, 3) ankle
    positions (NaN = missing); up: (N, 3) mid-hips minus mid-ankles (NaN = missing).
    """

    time: np.ndarray
    com: np.ndarray
    shank: np.ndarray
    thigh: np.ndarray
    torso: np.ndarray
    ankles: np.ndarray
    up: np.ndarray

    def __post_init__(self) -> None:
        N = len(self.time)
        assert self.com.shape == (N, 3) and self.ankles.shape == (N, 2, 3) and self.up.shape == (N, 3)
        assert self.shank.shape == self.thigh.shape == self.torso.shape == (N,)


def segments(hyps: Sequence[Hypothesis], R: np.ndarray, t: np.ndarray) -> Segments:
    """Triangulate every hypothesis' joints with poses R (C, 3, 3), t (C, 3) and measure."""
    H = len(hyps)
    if H == 0:
        z = np.zeros(0)
        return Segments(z, np.zeros((0, 3)), z, z, z, np.zeros((0, 2, 3)), np.zeros((0, 3)))
    X = triangulate_hypotheses(hyps, R, t)

    def length(a, b):
        return np.linalg.norm(X[:, a] - X[:, b], axis=1)

    shank = _mean_of_finite(length(L_KNEE, L_ANKLE), length(R_KNEE, R_ANKLE))
    thigh = _mean_of_finite(length(L_HIP, L_KNEE), length(R_HIP, R_KNEE))
    mid_sh = 0.5 * (X[:, L_SHOULDER] + X[:, R_SHOULDER])
    mid_hp = 0.5 * (X[:, L_HIP] + X[:, R_HIP])
    torso = np.linalg.norm(mid_sh - mid_hp, axis=1)
    ankles = X[:, [L_ANKLE, R_ANKLE]]
    up = mid_hp - 0.5 * (ankles[:, 0] + ankles[:, 1])
    return Segments(np.array([h.time for h in hyps]), np.array([h.com for h in hyps]), shank, thigh, torso,
                    ankles, up)


def _mean_of_finite(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Element-wise mean of the finite ones of a and b (N,); NaN where neither is."""
    n = np.isfinite(a).astype(np.float64) + np.isfinite(b)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (np.nan_to_num(a) + np.nan_to_num(b)) / n, np.nan)


def tracks(time: np.ndarray, com: np.ndarray, *, max_speed: float = 3.0, slack: float = 0.3,
           max_gap: float = 1.0) -> np.ndarray:
    """(N,) track id of each hypothesis: nearest continuation within ``max_speed`` m/s
    (plus ``slack`` m) of a track's last position, at most ``max_gap`` s ago, one
    hypothesis per track and instant. time (N,), com (N, 3); units of com are metres
    (roughly: the caller's scale), so the limits are generous."""
    N = len(time)
    ids = np.full(N, -1, np.int64)
    last_t: list[float] = []
    last_x: list[np.ndarray] = []
    order = np.argsort(time, kind="stable")
    k = 0
    while k < N:
        j = k
        while j < N and time[order[j]] == time[order[k]]:
            j += 1
        now = order[k:j]
        T = time[now[0]]
        live = [i for i in range(len(last_t)) if T - last_t[i] <= max_gap]
        pairs = []
        for a in now:
            for i in live:
                d = float(np.linalg.norm(com[a] - last_x[i]))
                if d <= max_speed * (T - last_t[i]) + slack:
                    pairs.append((d, int(a), i))
        taken_a, taken_i = set(), set()
        for d, a, i in sorted(pairs):
            if a in taken_a or i in taken_i:
                continue
            ids[a] = i
            taken_a.add(a)
            taken_i.add(i)
        for a in now:
            if ids[a] < 0:
                ids[a] = len(last_t)
                last_t.append(T)
                last_x.append(com[a])
            else:
                last_t[ids[a]] = T
                last_x[ids[a]] = com[a]
        k = j
    return ids


@dataclass(frozen=True)
class Person:
    """One person as measured: chain length (pose units), its standard error (relative),
    hypotheses measured, tracks merged into it."""

    chain: float
    chain_rel_std: float
    hypotheses: int
    tracks: int


@dataclass(frozen=True)
class ScaleEstimate:
    """Metres per unit of the poses it was measured in, with its relative std.

    method: "known height" | "population prior"; heights: (K,) m of the persons after
    scaling (the known ones are reproduced, the prior's are estimates)."""

    factor: float
    rel_std: float
    method: str
    persons: int
    heights: tuple[float, ...]
    note: str = ""

    @property
    def std(self) -> float:
        return self.factor * self.rel_std

    def to_dict(self) -> dict:
        return {"factor": self.factor, "rel_std": self.rel_std, "method": self.method, "persons": self.persons,
                "heights": list(self.heights), "note": self.note}

    def summary(self) -> str:
        hs = ", ".join(f"{h:.2f}" for h in self.heights)
        return (f"scale {self.factor:.4f} ± {100 * self.rel_std:.1f} % from the {self.method} "
                f"({self.persons} person{'s' if self.persons != 1 else ''}: {hs} m)"
                + (f"; {self.note}" if self.note else ""))


IMPLAUSIBLE_RATIO = 1.4  # tallest over shortest person measured: more is not two adults
_MIN_PERSON_SHARE = 0.2  # of the largest group's hypotheses: less is not a person (``_label``)


def label_persons(seg: Segments, *, count: int | None = None, min_track: int = 3,
                  links: np.ndarray | None = None) -> np.ndarray:
    """(N,) person label of each hypothesis (0 .. K-1, -1 = none): tracks (``tracks``),
    each summarised by its median chain (shank + thigh + torso), grouped by chain length
    into ``count`` persons (default: the number of hypotheses seen at one instant in at
    least 10 % of the instants with any). Hypotheses without a full chain, and tracks of
    fewer than ``min_track`` hypotheses, get -1. Labels are in no particular order.
    ``links``: (N,) int the part of the network each hypothesis was seen in (its camera
    pair, in a chain); each part's scale may be off by its own factor, which the grouping
    then estimates along with the persons (``_kmeans_linked``)."""
    return _label(seg, count, min_track, links)[0]


def _label(seg: Segments, count: int | None, min_track: int, links: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) person labels and (N,) track ids (-1 where none) of ``label_persons``."""
    N = len(seg.time)
    labels = np.full(N, -1, np.int64)
    track_of = np.full(N, -1, np.int64)
    ok = np.isfinite(seg.shank) & np.isfinite(seg.thigh) & np.isfinite(seg.torso)
    if not ok.any():
        return labels, track_of
    idx = np.flatnonzero(ok)
    time, com = seg.time[ok], seg.com[ok]
    parts = np.stack([seg.shank[ok], seg.thigh[ok], seg.torso[ok]], axis=1)
    ids = tracks(time, com)
    track_of[idx] = ids
    if count is None:
        _, per_instant = np.unique(time, return_counts=True)
        counts = np.bincount(per_instant)
        share = np.cumsum(counts[::-1])[::-1] / len(per_instant)  # share of instants with >= k
        count = int(max(1, np.flatnonzero(share >= 0.10).max()))
    tr = []
    for i in np.unique(ids):
        m = ids == i
        if m.sum() < min_track:
            continue
        tr.append((float(np.median(parts[m], axis=0).sum()), int(m.sum()), m))
    if not tr:
        return labels, track_of
    chains = np.log([c for c, _, _ in tr])
    w = np.array([n for _, n, _ in tr], dtype=np.float64)
    if links is None:
        tl = np.zeros(len(tr), np.int64)
    else:  # each track's part: the one most of its hypotheses were seen in
        seen_in = links[ok]
        tl = np.array([np.bincount(seen_in[m]).argmax() for _, _, m in tr], dtype=np.int64)
    k = min(count, len(tr))
    cluster = _kmeans_1d(chains, w, k)
    if len(np.unique(tl)) > 1:
        # only when the parts' scales explain most of the spread (a chain's links apart by
        # several percent): where the network has one scale, offsets fitted to parts that
        # saw one person each would only blur the persons
        linked = _kmeans_linked(chains, w, tl, k)
        by_link = _kmeans_1d(linked, w, k)
        if _spread(linked, w, by_link) < 0.5 * _spread(chains, w, cluster):
            chains, cluster = linked, by_link
    # A few tracks far from everyone (hypotheses that joined two persons' views) can take a
    # person's place in the clustering and merge the real persons into one: measured in a
    # 4-camera room, 20 such hypotheses against 400 made two walkers of 1.80 and 1.65 m
    # "1.96 and 1.52 m" and the scale 12 % off. A group with less than a fifth of the
    # largest one's hypotheses is left out and the others are grouped again.
    for _ in range(count):
        size = np.bincount(cluster, weights=w)
        small = size < _MIN_PERSON_SHARE * size.max()
        if not small.any():
            break
        keep = ~small[cluster]
        tr = [x for x, k in zip(tr, keep) if k]
        chains, w = chains[keep], w[keep]
        cluster = _kmeans_1d(chains, w, min(count, len(tr)))
    for (_, _, m), k in zip(tr, cluster):
        labels[idx[m]] = k
    return labels, track_of


def oversized(seg: Segments, person: np.ndarray, ratio: float) -> np.ndarray:
    """(N,) bool: hypotheses whose triangulated body is more than ``ratio`` times the
    size of the largest person (``label_persons``' labels ``person`` (N,)): their views
    met two persons. Size is the chain (shank + thigh + torso) against that person's
    median one, or where a bone is missing the mean of the measured bones' ratios.

    Two cameras that share no floor, with one walker in front of each on the line through
    them, triangulate a giant beyond the far one: its rays cross near the plane of the
    baseline, so the epipolar test cannot see it, and no third camera can. Measured in the
    6-camera corridor (docs/bones.md, Session 33): such hypotheses came out 1.3-3x the
    taller walker, the right ones at most 1.15x with the true poses."""
    N = len(seg.time)
    assert person.shape == (N,)
    labelled = np.unique(person[person >= 0])
    if ratio <= 0 or len(labelled) == 0:
        return np.zeros(N, bool)
    parts = np.stack([seg.shank, seg.thigh, seg.torso], axis=1)
    ref = np.array([np.median(parts[person == k], axis=0) for k in labelled])  # labelled: all three finite
    size = relative_size(seg, ref[np.argmax(ref.sum(axis=1))])
    return np.nan_to_num(size) > ratio


def relative_size(seg: Segments, ref: np.ndarray) -> np.ndarray:
    """(N,) each hypothesis' size against ``ref`` (3,) shank, thigh, torso lengths: its
    chain over ref's, or where a bone is missing the mean of the measured bones' ratios;
    NaN where none is measured."""
    assert ref.shape == (3,)
    parts = np.stack([seg.shank, seg.thigh, seg.torso], axis=1)
    full = np.isfinite(parts).all(axis=1)
    part = np.isfinite(parts).any(axis=1) & ~full
    size = np.full(len(parts), np.nan)
    size[full] = parts[full].sum(axis=1) / ref.sum()
    size[part] = np.nanmean(parts[part] / ref, axis=1)
    return size


def persons(seg: Segments, *, count: int | None = None, min_hypotheses: int = 10) -> list[Person]:
    """Tell persons apart (``label_persons``) and measure each: per-segment medians
    summed into the chain. Persons sorted tallest first."""
    ok = np.isfinite(seg.shank) & np.isfinite(seg.thigh) & np.isfinite(seg.torso)
    if ok.sum() < min_hypotheses:
        return []
    labels, track_of = _label(seg, count, 3)
    parts = np.stack([seg.shank, seg.thigh, seg.torso], axis=1)
    out = []
    for k in np.unique(labels[labels >= 0]):
        m = labels == k
        if m.sum() < min_hypotheses:
            continue
        chain = float(np.median(parts[m], axis=0).sum())
        # standard error of the chain from the spread of the per-hypothesis chains
        c = parts[m].sum(1)
        mad = 1.4826 * np.median(np.abs(c - np.median(c)))
        # neighbouring instants are correlated (10 Hz, the detector's noise over ~0.3 s)
        n_eff = max(1.0, m.sum() / 5.0)
        members = len(np.unique(track_of[m]))
        out.append(Person(chain, float(mad / chain / np.sqrt(n_eff)), int(m.sum()), members))
    return sorted(out, key=lambda p: -p.chain)


def _kmeans_linked(x: np.ndarray, w: np.ndarray, link: np.ndarray, k: int, rounds: int = 10) -> np.ndarray:
    """x (T,) log chains of tracks seen in parts ``link`` (T,) int of the network whose
    scales differ by unknown factors: x less each part's offset, the offsets fitted with
    the k groups in turn (weights w (T,)), the offsets' weighted mean 0. In a corridor
    whose links are scaled a few percent apart, two walkers 9 % apart are otherwise
    grouped by link as much as by walker."""
    # start from each part's own median: every part sees the same people, and its median
    # lies among them whatever its scale (from the raw values a part 1.5x too large was a
    # "person" of its own, and the fit stayed there)
    y = x.copy()
    for lk in np.unique(link):
        m = link == lk
        y[m] -= _weighted_median(x[m], w[m])
    y += _weighted_median(x, w) - np.average(y, weights=w)
    for _ in range(rounds):
        cluster = _kmeans_1d(y, w, k)
        centre = np.array([np.average(y[cluster == c], weights=w[cluster == c]) for c in range(cluster.max() + 1)])
        r = x - centre[cluster]
        off = np.zeros(link.max() + 1)
        for lk in np.unique(link):
            m = link == lk
            off[lk] = np.average(r[m], weights=w[m])
        off -= np.average(off[link], weights=w)
        new = x - off[link]
        if np.allclose(new, y, atol=1e-9):
            break
        y = new
    return y


def _spread(x: np.ndarray, w: np.ndarray, c: np.ndarray) -> float:
    """Weighted within-group sum of squares of x (N,) grouped by c (N,) int."""
    return float(sum(np.sum(w[c == g] * (x[c == g] - np.average(x[c == g], weights=w[c == g])) ** 2)
                     for g in np.unique(c)))


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The value of x (N,) at half the total weight w (N,)."""
    order = np.argsort(x)
    c = np.cumsum(w[order])
    return float(x[order][np.searchsorted(c, 0.5 * c[-1])])


def _kmeans_1d(x: np.ndarray, w: np.ndarray, k: int) -> np.ndarray:
    """Weighted 1D k-means (exact by dynamic programming over the sorted values)."""
    n = len(x)
    if k <= 1 or n <= 1:
        return np.zeros(n, np.int64)
    order = np.argsort(x)
    xs, ws = x[order], w[order]
    cw = np.concatenate([[0], np.cumsum(ws)])
    cx = np.concatenate([[0], np.cumsum(ws * xs)])
    cxx = np.concatenate([[0], np.cumsum(ws * xs * xs)])

    def cost(i, j):  # values i..j-1
        W = cw[j] - cw[i]
        S = cx[j] - cx[i]
        return (cxx[j] - cxx[i]) - S * S / W

    D = np.full((k + 1, n + 1), np.inf)
    B = np.zeros((k + 1, n + 1), np.int64)
    D[0, 0] = 0.0
    for m in range(1, k + 1):
        for j in range(m, n + 1):
            for i in range(m - 1, j):
                v = D[m - 1, i] + cost(i, j)
                if v < D[m, j]:
                    D[m, j], B[m, j] = v, i
    labels_sorted = np.zeros(n, np.int64)
    j = n
    for m in range(k, 0, -1):
        i = B[m, j]
        labels_sorted[i:j] = m - 1
        j = i
    labels = np.zeros(n, np.int64)
    labels[order] = labels_sorted
    return labels


def estimate_scale(people: Sequence[Person], *, heights: Sequence[float] = (), height_mean: float = 1.72,
                   height_std: float = 0.10, ratio_std: float = 0.02, torso_ratio: float = 0.2924) -> ScaleEstimate:
    """Metres per pose unit from the persons' chains.

    ``heights`` known (m): matched to the persons by rank (tallest to tallest) when as many
    are given as persons are seen; otherwise their mean is matched to the persons' mean,
    with the spread of the persons added to the uncertainty. Without heights: the
    population prior N(height_mean, height_std²) per person. In log space each person
    gives log s = log H - log(chain / ratio) with variance ratio_std² (+ the prior's
    relative variance) + the chain's measurement variance; the estimate is their mean."""
    if not people:
        raise ValueError("no person was measured well enough to estimate the scale")
    r = chain_ratio(torso_ratio)
    u = np.array([p.chain / r for p in people])  # heights in pose units
    meas = np.array([p.chain_rel_std for p in people])
    K = len(people)
    note = ""
    if heights:
        H = np.sort(np.asarray(heights, dtype=np.float64))[::-1]
        if len(H) == K:
            logs = np.log(H) - np.log(u)
            var = ratio_std**2 + meas**2
            spread = 0.0
        else:
            note = (f"{len(H)} known height(s) for {K} persons seen: the mean height is matched to the "
                    "persons' mean")
            logs = np.array([np.log(H.mean()) - np.log(np.exp(np.log(u).mean()))])
            spread = float(np.std(np.log(u))) if K > 1 else 0.0
            var = np.array([ratio_std**2 + float(np.mean(meas**2)) + spread**2])
        method = "known height"
    else:
        logs = np.log(height_mean) - np.log(u)
        var = (height_std / height_mean) ** 2 + ratio_std**2 + meas**2
        method = "population prior"
    n = len(logs)
    log_s = float(logs.mean())
    rel = float(np.sqrt(var.sum()) / n)
    s = float(np.exp(log_s))
    if K >= 2 and u.max() > IMPLAUSIBLE_RATIO * u.min():
        # two adults rarely differ by more (1.50 and 2.05 m); the same people measured at
        # different sizes in different parts of the network do: a camera chain whose links
        # are scaled wrongly (two walkers in a corridor, docs/bootstrap.md "Session 19")
        note = "; ".join(x for x in (note, (
            f"the persons measured {u.max() / u.min():.2f} times apart in height: unless a child walked, "
            "the cameras' geometry disagrees with itself (people grow or shrink across it)")) if x)
    return ScaleEstimate(s, rel, method, K, tuple(float(h) for h in s * u), note)


def measure_scale(frames, R: np.ndarray, t: np.ndarray, associate: AssociateConfig, prior: BootstrapConfig, *,
                  heights: Sequence[float] = (), cameras: np.ndarray | None = None
                  ) -> tuple[ScaleEstimate | None, Segments]:
    """The scale of poses R (C, 3, 3), t (C, 3) from the people in ``frames`` (time,
    detections per view): every frame associated with the poses (gated), the persons'
    bones measured and told apart, and the scale estimated (None when no person was
    measured well enough). ``cameras`` (C,) bool: use only these cameras' detections.
    Also returns the measured segments (in the units of t)."""
    assoc = Associator(associate)
    C = len(R)
    gate = np.full(C, associate.gate_pixels)
    keep = np.ones(C, bool) if cameras is None else cameras
    hyps = []
    for time_, views in frames:
        vs = [v for v in views if keep[v[0].cam]]
        if len(vs) >= 2:
            hyps.extend(assoc(time_, vs, R, t, gate))
    seg = segments(hyps, R, t)
    people = persons(seg)
    if not people:
        return None, seg
    return estimate_scale(people, heights=heights, height_mean=prior.height_mean, height_std=prior.height_std,
                          ratio_std=prior.ratio_std, torso_ratio=associate.torso_ratio), seg
