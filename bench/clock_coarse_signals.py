"""Calibration-free clock offsets from motion signals: an experiment that did NOT work.

Measures how well sensor pairs can be timed against each other without any calibration
by cross-correlating 1D motion signals of their person tracks (docs/clock_offsets.md,
"A calibration-free coarse stage"). Per sensor, persons are tracked on the raw message
stream; each track gives a signal on a common grid of raw time:

- ``speed``: torso centre image speed in torso lengths per second (smoothed 0.15 s);
- ``accel``: its time derivative (starts, stops and slow-downs as sharper events);
- ``gait``: the ankle separation in torso lengths, high-passed (steps).

For every pair of sensors the normalised cross-correlations of their overlapping
tracks (peak above ``--min-corr``) are summed over lags of ±0.5 s, and the peak is that
pair's offset difference; printed: its error against the simulator's truth (median
absolute, share within 10 / 30 ms), and the result of the robust graph solve
(``solve_graph``) per sensor.

    python bench/clock_coarse_signals.py --seconds 60      # seed 1, the bench's recording

Why it fails (measured): the signals are smooth (walking speed changes over ~1 s), a
camera sees only the speed across its line of sight (the looming term that would make
it view-invariant is too noisy), and the gait signal aliases at the step period.
"""


from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from proto import KeypointMessage

# coco17: shoulders and hips
_TORSO = np.array([5, 6, 11, 12])
_MATCH_DIAG_PER_S = 1.0
_MATCH_MIN_FRAC = 0.03


@dataclass(frozen=True)
class CoarseResult:
    """Offsets of every sensor from the motion signals.

    offset: (S,) s relative to the median timed sensor, NaN = not timed.
    std: (S,) s, NaN = not timed.
    pairs: (S,) pairs of sensors whose measurement agrees with the solution.
    """

    offset: np.ndarray
    std: np.ndarray
    pairs: np.ndarray

    def __post_init__(self) -> None:
        S = self.offset.shape[0]
        assert self.offset.shape == (S,) and self.std.shape == (S,) and self.pairs.shape == (S,)


# ------------------------------------------------------------------ pure functions


def motion_signal(stamps: np.ndarray, centre: np.ndarray, size: np.ndarray, grid: np.ndarray,
                  smooth: float, max_gap: float, derivative: bool = False,
                  focal: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """One track's image speed in torso lengths per second on ``grid``.

    stamps (n,) increasing s; centre (n, 2) px; size (n,) px torso length; grid (G,) s
    evenly spaced. Position and size are interpolated onto the grid (gaps wider than
    ``max_gap`` are not bridged), smoothed with a Gaussian of std ``smooth`` s, and
    differentiated. Returns speed (G,) and valid (G,) bool (the smoothing window lies
    inside the track).
    """
    G = len(grid)
    assert centre.shape == (len(stamps), 2) and size.shape == (len(stamps),)
    out, ok = np.zeros(G), np.zeros(G, bool)
    if len(stamps) < 3 or G < 3:
        return out, ok
    dt = float(grid[1] - grid[0])
    i = np.searchsorted(stamps, grid, side="right")
    inside = (i > 0) & (i < len(stamps))
    i1 = np.clip(i, 1, len(stamps) - 1)
    i0 = i1 - 1
    gap = stamps[i1] - stamps[i0]
    inside &= gap <= max_gap
    w = np.clip((grid - stamps[i0]) / np.where(gap > 0, gap, 1.0), 0, 1)
    c = (1 - w)[:, None] * centre[i0] + w[:, None] * centre[i1]
    s = (1 - w) * size[i0] + w * size[i1]
    half = max(1, int(round(3 * smooth / dt)))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * dt / smooth) ** 2)
    k /= k.sum()
    m = inside.astype(float)
    # smoothing window entirely inside the track, else invalid
    full = np.convolve(m, np.ones(2 * half + 1), mode="same") >= 2 * half + 1 - 1e-9
    cs = np.stack([np.convolve(np.where(inside, c[:, d], 0.0), k, mode="same") for d in range(2)], axis=1)
    ss = np.convolve(np.where(inside, s, 0.0), k, mode="same")
    v = np.gradient(cs, dt, axis=0)
    good = full & np.roll(full, 1) & np.roll(full, -1) & (ss > 0)
    good[[0, -1]] = False
    sz = np.where(good, ss, 1.0)
    vv = np.linalg.norm(v, axis=1) / sz
    if focal > 0:  # towards or away from the camera: the torso's image grows or shrinks
        vv = np.hypot(vv, focal / sz * np.gradient(np.log(np.maximum(ss, 1e-9)), dt))
    speed = np.where(good, vv, 0.0)
    if not derivative:
        out[good] = speed[good]
        ok[good] = True
        return out, ok
    acc = np.gradient(speed, dt)
    good2 = good & np.roll(good, 1) & np.roll(good, -1)
    good2[[0, -1]] = False
    out[good2] = acc[good2]
    ok[good2] = True
    return out, ok


def ncc_curve(a: np.ndarray, oka: np.ndarray, b: np.ndarray, okb: np.ndarray, lags: np.ndarray,
              min_samples: int) -> tuple[np.ndarray, int]:
    """Normalised cross-correlation of a(t) and b(t + k) for k in ``lags`` (grid steps).

    a, b (G,) signals on one grid, oka, okb (G,) validity. Returns (K,) correlation
    (NaN where fewer than ``min_samples`` samples overlap) and the samples at lag 0's
    neighbourhood (the overlap's size)."""
    G = len(a)
    out = np.full(len(lags), np.nan)
    n_max = 0
    for j, k in enumerate(lags):
        k = int(k)
        if k >= 0:
            x, y, m = a[:G - k], b[k:], oka[:G - k] & okb[k:]
        else:
            x, y, m = a[-k:], b[:G + k], oka[-k:] & okb[:G + k]
        n = int(m.sum())
        n_max = max(n_max, n)
        if n < min_samples:
            continue
        xv, yv = x[m] - x[m].mean(), y[m] - y[m].mean()
        den = math.sqrt(float(xv @ xv) * float(yv @ yv))
        if den > 0:
            out[j] = float(xv @ yv) / den
    return out, n_max


def peak(curve: np.ndarray, lags: np.ndarray, step: float) -> float | None:
    """Sub-sample lag (s) of a curve's maximum; None on the edge or without a peak."""
    if not np.isfinite(curve).any():
        return None
    k = int(np.nanargmax(curve))
    if k == 0 or k == len(curve) - 1 or not np.isfinite(curve[k - 1]) or not np.isfinite(curve[k + 1]):
        return None
    c0, c1, c2 = curve[k - 1], curve[k], curve[k + 1]
    den = c0 - 2 * c1 + c2
    shift = 0.5 * (c0 - c2) / den if den < 0 else 0.0
    return float((lags[k] + np.clip(shift, -0.5, 0.5)) * step)


def solve_graph(S: int, edges: list[tuple[int, int, float, float]], scale: float, min_pairs: int
                ) -> CoarseResult:
    """Per-sensor offsets o from pair measurements (a, b, d ≈ o_b − o_a, weight w).

    Cauchy-weighted least squares (width ``scale`` s) over the largest connected set of
    sensors, iterated; a sensor with fewer than ``min_pairs`` agreeing measurements (or
    none) is not timed. Offsets relative to the median of the timed sensors."""
    off, std, npairs = np.full(S, np.nan), np.full(S, np.nan), np.zeros(S, np.int64)
    if not edges:
        return CoarseResult(off, std, npairs)
    A = np.array([[a, b] for a, b, _, _ in edges], np.int64)
    d = np.array([e[2] for e in edges])
    w0 = np.array([e[3] for e in edges])
    # components: the offsets of sensors not linked to each other are unrelated
    parent = list(range(S))

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in A:
        parent[find(int(a))] = find(int(b))
    roots = [find(int(a)) for a in A[:, 0]]
    main = max(set(roots), key=roots.count)
    keep = np.array([r == main for r in roots])
    A, d, w0 = A[keep], d[keep], w0[keep]
    nodes = np.unique(A)
    idx = {int(n): i for i, n in enumerate(nodes)}
    N = len(nodes)
    J = np.zeros((len(d), N))
    for e, (a, b) in enumerate(A):
        J[e, idx[int(a)]] -= 1.0
        J[e, idx[int(b)]] += 1.0
    w = w0.copy()
    o = np.zeros(N)
    for _ in range(20):
        H = J.T @ (w[:, None] * J) + 1e-6 * np.eye(N)
        o_new = np.linalg.solve(H, J.T @ (w * d))
        o_new -= np.median(o_new)
        r = d - J @ o_new
        w = w0 / (1.0 + (r / scale) ** 2)
        if np.max(np.abs(o_new - o)) < 1e-6:
            o = o_new
            break
        o = o_new
    r = d - J @ o
    good = np.abs(r) < 3 * scale
    cnt = np.zeros(N, np.int64)
    for (a, b), g in zip(A, good):
        if g:
            cnt[idx[int(a)]] += 1
            cnt[idx[int(b)]] += 1
    # std: residual scatter of the agreeing measurements through the normal equations
    wg = np.where(good, w0, 0.0)
    dof = max(int(good.sum()) - (N - 1), 1)
    sigma2 = float((wg * r * r).sum()) / dof
    H = J.T @ (wg[:, None] * J) + 1e-9 * np.eye(N)
    # gauge: fix the mean (the median shift is a constant)
    P = np.eye(N) - 1.0 / N
    cov = P @ np.linalg.pinv(H) @ P * max(sigma2, 1e-8)
    timed = cnt >= min_pairs
    if timed.sum() >= 2:
        o = o - np.median(o[timed])
    for n, i in idx.items():
        npairs[n] = cnt[i]
        if timed[i]:
            off[n] = o[i]
            std[n] = math.sqrt(max(cov[i, i], 0.0))
    return CoarseResult(off, std, npairs)


# ------------------------------------------------------------------ the estimator


class _Tracks:
    """One sensor's person tracks: (stamp, torso centre px, torso length px)."""

    def __init__(self) -> None:
        self.tracks: list[list[tuple[float, float, float, float]]] = []
        self.last: float | None = None

    def push(self, msg: KeypointMessage, min_conf: float, max_gap: float) -> None:
        t = msg.stamp
        if self.last is not None and t <= self.last:
            return
        self.last = t
        kp = msg.keypoints()
        if not len(kp):
            return
        torso = kp[:, _TORSO]
        ok = (torso[:, :, 2] >= min_conf).all(1)
        if not ok.any():
            return
        torso = torso[ok]
        centre = torso[:, :, :2].mean(1)  # (P, 2)
        length = np.linalg.norm(torso[:, :2, :2].mean(1) - torso[:, 2:, :2].mean(1), axis=1)
        diag = float(np.hypot(*msg.size))
        open_ = [tr for tr in self.tracks if t - tr[-1][0] <= max_gap]
        taken: set[int] = set()
        used: set[int] = set()
        if open_:
            prev = np.array([tr[-1][1:3] for tr in open_])
            dts = np.array([t - tr[-1][0] for tr in open_])
            dist = np.linalg.norm(prev[:, None] - centre[None], axis=-1)
            limit = diag * np.maximum(_MATCH_MIN_FRAC, _MATCH_DIAG_PER_S * dts)
            for flat in np.argsort(dist, axis=None):
                i, j = divmod(int(flat), dist.shape[1])
                if i in used or j in taken or dist[i, j] > limit[i]:
                    continue
                open_[i].append((t, float(centre[j, 0]), float(centre[j, 1]), float(length[j])))
                used.add(i)
                taken.add(j)
        for j in range(len(centre)):
            if j not in taken and length[j] > 0:
                self.tracks.append([(t, float(centre[j, 0]), float(centre[j, 1]), float(length[j]))])

    def prune(self, before: float) -> None:
        self.tracks = [tr for tr in self.tracks if tr[-1][0] >= before]


class CoarseClock:
    """Coarse offsets of all sensors from their raw message streams (module docstring).

    ``push`` every message (raw stamp); ``solve(now)`` the offsets from the last
    ``window`` s of data.
    """

    def __init__(self, names: tuple[str, ...], *, max_offset: float, min_confidence: float,
                 step: float = 0.02, smooth: float = 0.15, window: float = 60.0, track_gap: float = 0.3,
                 min_overlap: float = 4.0, min_corr: float = 0.6, scale: float = 0.015, min_pairs: int = 2,
                 derivative: bool = True, focal: dict | None = None, looming: float = 1.0):
        self.names = tuple(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.max_offset = max_offset
        self.min_conf = min_confidence
        self.step = step
        self.smooth = smooth
        self.window = window
        self.track_gap = track_gap
        self.min_overlap = min_overlap
        self.min_corr = min_corr
        self.scale = scale
        self.min_pairs = min_pairs
        self.derivative = derivative
        self.focal = [looming * (focal or {}).get(n, 0.0) for n in self.names]
        self.tracks = [_Tracks() for _ in self.names]
        self.first: float | None = None
        self.latest: float | None = None

    def push(self, msg: KeypointMessage) -> None:
        c = self.index.get(msg.sensor)
        if c is None:
            return
        self.tracks[c].push(msg, self.min_conf, self.track_gap)
        if self.first is None or msg.stamp < self.first:
            self.first = msg.stamp
        if self.latest is None or msg.stamp > self.latest:
            self.latest = msg.stamp

    def signals(self, t0: float, t1: float) -> tuple[np.ndarray, list[list[tuple[np.ndarray, np.ndarray]]]]:
        """The grid over [t0, t1] and per sensor its tracks' (speed, valid) on it."""
        grid = np.arange(math.floor(t0 / self.step) * self.step, t1, self.step)
        min_len = self.min_overlap / 2
        out = []
        for s, st in enumerate(self.tracks):
            sig = []
            for tr in st.tracks:
                if tr[-1][0] < t0 or tr[0][0] > t1 or tr[-1][0] - tr[0][0] < min_len:
                    continue
                a = np.array(tr)
                v, ok = motion_signal(a[:, 0], a[:, 1:3], a[:, 3], grid, self.smooth, self.track_gap,
                                      self.derivative, self.focal[s])
                if ok.sum() * self.step >= min_len and np.ptp(v[ok]) > 0:
                    sig.append((v, ok))
            out.append(sig)
        return grid, out

    def measurements(self, now: float) -> list[tuple[int, int, float, float]]:
        """Pair measurements (a, b, o_b − o_a s, weight) from the last ``window`` s."""
        t0 = max(self.first if self.first is not None else now, now - self.window)
        grid, sig = self.signals(t0 - 1.0, now)
        if len(grid) < 3:
            return []
        L = int(math.ceil(2 * self.max_offset / self.step)) + 1
        lags = np.arange(-L, L + 1)
        min_samples = int(self.min_overlap / self.step)
        edges = []
        S = len(self.names)
        for a in range(S):
            for b in range(a + 1, S):
                if not sig[a] or not sig[b]:
                    continue
                total = np.zeros(len(lags))
                weight = 0.0
                for va, oa in sig[a]:
                    for vb, ob in sig[b]:
                        if not (oa & ob).any() and not (oa[:-L] & ob[L:]).any() and not (oa[L:] & ob[:-L]).any():
                            continue
                        curve, n = ncc_curve(va, oa, vb, ob, lags, min_samples)
                        if not np.isfinite(curve).any() or np.nanmax(curve) < self.min_corr:
                            continue
                        total += n * np.nan_to_num(curve, nan=0.0)
                        weight += n
                if weight == 0:
                    continue
                lag = peak(total / weight, lags, self.step)
                if lag is None:
                    continue
                edges.append((a, b, lag, weight * self.step))
        return edges

    def solve(self, now: float) -> CoarseResult:
        return solve_graph(len(self.names), self.measurements(now), self.scale, self.min_pairs)

    def prune(self, now: float) -> None:
        for st in self.tracks:
            st.prune(now - self.window - 2.0)


def gait_signal(track: list[tuple[float, float, float, float, float]], grid: np.ndarray, max_gap: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Ankle separation (torso lengths) high-passed: a Gaussian of 0.03 s minus one of 0.25 s."""
    a = np.array(track)
    step = float(grid[1] - grid[0])
    n = len(a)
    i = np.searchsorted(a[:, 0], grid, side="right")
    ins = (i > 0) & (i < n)
    i1 = np.clip(i, 1, n - 1)
    i0 = i1 - 1
    gap = a[i1, 0] - a[i0, 0]
    w = np.clip((grid - a[i0, 0]) / np.maximum(gap, 1e-9), 0, 1)
    v = (1 - w) * a[i0, 4] + w * a[i1, 4]
    ok = ins & (gap <= max_gap) & np.isfinite(v)
    v = np.nan_to_num(v)

    def smooth(sig: float) -> tuple[np.ndarray, np.ndarray]:
        h = int(3 * sig / step)
        k = np.exp(-0.5 * (np.arange(-h, h + 1) * step / sig) ** 2)
        num = np.convolve(np.where(ok, v, 0.0), k, "same")
        den = np.convolve(ok.astype(float), k, "same")
        return num / np.maximum(den, 1e-9), den > 0.9 * k.sum()

    lo, ok1 = smooth(0.03)
    bg, ok2 = smooth(0.25)
    return lo - bg, ok & ok1 & ok2


class _GaitTracks(_Tracks):
    """Tracks that also keep the ankle separation (torso lengths, NaN = ankles unseen)."""

    def push(self, msg: KeypointMessage, min_conf: float, max_gap: float) -> None:
        n_before = {id(tr): len(tr) for tr in self.tracks}
        super().push(msg, min_conf, max_gap)
        kp = msg.keypoints()
        for tr in self.tracks:
            if len(tr) > n_before.get(id(tr), 0) and len(tr[-1]) == 4:
                t, cx, cy, L = tr[-1]
                # the person of this track: the detection whose torso centre is this one
                sep = np.nan
                for p in kp:
                    if (p[_TORSO, 2] >= min_conf).all() and np.allclose(p[_TORSO, :2].mean(0), (cx, cy)):
                        if (p[[15, 16], 2] >= min_conf).all() and L > 0:
                            sep = float(np.linalg.norm(p[15, :2] - p[16, :2]) / L)
                        break
                tr[-1] = (t, cx, cy, L, sep)


def main() -> None:
    repo = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(repo))
    from bench.accuracy import simulate
    from bench.clock_offsets import DEFAULT_OFFSETS
    from edge_clients.sim import Truth
    from proto import read_recording

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=60.0, help="s of data from the start")
    ap.add_argument("--min-corr", type=float, default=0.5)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    a = ap.parse_args()
    rec = simulate(2, 180.0, a.seed, a.cache, {"clock_offsets": DEFAULT_OFFSETS})
    truth = Truth.load(Truth.sidecar_path(rec))
    names = tuple(truth.sensors)
    true = truth.clock_offset
    print(f"Calibration-free pair timing, 20-camera lab, 2 persons, first {a.seconds:g} s, seed {a.seed}")
    print("| signal | pairs | median abs error (ms) | within 10 ms | within 30 ms | sensors timed | max sensor error (ms) |")
    print("|---|---|---|---|---|---|---|")
    for variant in ("speed", "accel", "gait"):
        cc = CoarseClock(names, max_offset=0.25, min_confidence=0.3, derivative=variant == "accel",
                         min_corr=a.min_corr, step=0.01 if variant == "gait" else 0.02)
        if variant == "gait":
            cc.tracks = [_GaitTracks() for _ in names]
        first = None
        for m in read_recording(rec):
            if first is None:
                first = m.stamp
            if m.stamp - first > a.seconds:
                break
            cc.push(m)
        now = first + a.seconds
        if variant == "gait":
            grid = np.arange(first, now, cc.step)
            sig = [[gait_signal(tr, grid, 0.15) for tr in st.tracks if tr[-1][0] - tr[0][0] > 3] for st in cc.tracks]
            cc.signals = lambda t0, t1, _g=grid, _s=sig: (_g, _s)  # noqa: E731
        edges = cc.measurements(now)
        err = np.array([1000 * (d - (true[b] - true[a_])) for a_, b, d, _ in edges])
        r = solve_graph(len(names), edges, cc.scale, cc.min_pairs)
        est = np.isfinite(r.offset)
        rel = true - np.median(true[est]) if est.any() else true
        se = np.abs(1000 * (r.offset - rel))[est]
        ae = np.abs(err)
        print(f"| {variant} | {len(edges)} | {np.median(ae):.0f} | {np.mean(ae < 10):.0%} | {np.mean(ae < 30):.0%} | "
              f"{int(est.sum())}/{len(names)} | {se.max() if len(se) else float('nan'):.0f} |")


if __name__ == "__main__":
    main()
