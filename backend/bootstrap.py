"""Calibration without an initial estimate: the camera network from people alone.

The online pipeline needs a rough initial estimate (its association cuts rays to depth
intervals in a known world). This module finds one from the preprocessed framesets
(``Detection`` tuples, as ``Pipeline.frames`` archives them), synchronously:

0. Timing. A sensor whose stamps run apart from the others' as they arrive (a clock
   off, or a longer delay: ``stamps_apart``) has its views timed by its lead or as stamped,
   whichever its pairs with the others agree with more (``_timed``).
1. Pairs. In a frame where camera a and camera b each see exactly one person, the 17
   joints are correspondences, if it is the same person. Over time they give an essential
   matrix (MAGSAC on undistorted, normalised coordinates), relative pose b_R_a and the
   direction of the baseline. Frames whose joints agree with it (median Sampson error
   below ``frame_px``) are the pair's correspondences (with two people in the room, a
   and b may each see a different one); the pose is refined on them (robust
   least squares of the Sampson error) and the frames classified again.
2. View graph. Pairs with enough agreeing frames and a baseline the rays can see are
   edges; rotations are chained along the maximum-weight spanning tree, then averaged
   over all edges (iteratively reweighted chordal averaging); pairs that disagree with
   the average are dropped.
3. Scales. A pair's triangulation has its own unknown scale (unit baseline). Two pairs
   that share a camera and triangulate the same person's joints at the same instants see
   them at depths whose ratio is the ratio of their scales; pairs no such relations join
   (a camera chain) are related by the median bone lengths of the people they see. A
   least-squares fit of the log-scales over all relations, then of the camera centres
   from the scaled baselines (pairs without a scale still constrain the direction),
   places every camera.
4. Metric scale from people (``backend.people``): bone lengths of the triangulated
   persons against a known height or a population prior. A rough figure first, so that
   the pipeline's association (which assumes persons of 1.70-2.00 m) works.
5. Bundle adjustment (``optimize.solve``, a 'batch' Problem with weak priors): all frames
   re-associated with the estimate, outlier views dropped, a few rounds. Cameras the view
   graph reached only over bridge pairs (no triangle checked them) are checked against
   the persons the other cameras triangulate without them (``check_bridged``). Cameras no
   pair placed are re-localised by PnP against the persons the others triangulate, and so
   are the cameras that check left unchecked and a group of cameras chained turned, which
   right pairs that disagree with it alike witness (``resect.block_witnesses``; the rest
   of the group follows the ones resected, ``resect.follow_moved``). A group each of whose
   cameras its own pairs hold is found by the pairs across its border that ask one turn
   (``resect.turned_blocks``) and moved as one where its cameras agree with the others'
   persons in the most 5 s windows (``resect.move_block``).
6. The scale from people again (now with multi-view persons, told apart by tracking) and
   the world frame from the floor: the plane of the ankles over time, z up, origin under
   the first camera, x towards the second.
7. Groups. Cameras no pair links to the placed ones (two rooms joined by a door: where a
   camera in each room sees one person, it is a different one) are bootstrapped on their
   own (steps 1-6) and joined to the placed ones as one body, by the persons each group
   sees of the other's (``backend.groups``). Each keeps its own adjustment (one over both
   sides of a wall associates people through it); step 6 runs again over all.

The result goes to the online pipeline as its initial estimate, with an honest, large
uncertainty (``handover``).
"""

from __future__ import annotations

import time as _time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from proto import KeypointMessage

from .associate import Hypothesis, torso_centre
from .cameras import CameraSet, Extrinsics, Intrinsics, Pose, natural_key
from .config import BootstrapConfig, EngineConfig, FloorFrame
from .floor import median_up, plane_of_ankles, world_frame
from .geometry import hat, pose_std, project_so3, rotation_angle_deg, so3_exp, triangulate_batch
from .optimize import BONE_NAMES, BONES
from .people import ANKLE_HEIGHT, ScaleEstimate, Segments, measure_scale, segments
from .preprocess import Detection, Preprocessor
from .stamp_watch import StampWatch
from .sync import Synchronizer

Frame = tuple[float, tuple[tuple[Detection, ...], ...]]
Progress = Callable[[str], None]


class BootstrapError(RuntimeError):
    """The data do not determine the cameras (too few people seen by pairs of cameras)."""


# ------------------------------------------------------------------ front end


def collect_frames(names: Sequence[str], intrinsics: Mapping[str, Intrinsics], config: EngineConfig,
                   messages: Iterable[KeypointMessage], *, max_seconds: float = 0.0,
                   progress: Progress | None = None, stamps: StampWatch | None = None) -> list[Frame]:
    """The pipeline's front end (sync, preprocess) on messages in arrival order: the
    preprocessed framesets with >= 2 views, up to ``max_seconds`` of data (0: all).
    ``stamps``: watches the accepted messages' stamps as the pipeline does (its
    ``leads()`` then say which sensors' clocks run apart, ``stamps_apart``).

    The clock is the newest plausible stamp, found as the pipeline finds it: the first
    messages are held back and their median decides which stamps are absurd."""
    config = config.for_images(intrinsics[n].resolution for n in names)
    sync = Synchronizer(config.sync, tuple(names))
    pre = Preprocessor(config.preprocess, tuple(names), intrinsics)
    frames: list[Frame] = []
    pending: list[KeypointMessage] = []
    clock: float | None = None
    first: float | None = None
    last_report = 0.0

    def take(now: float) -> bool:
        nonlocal first, last_report
        for fs in sync.pop_ready(now):
            dets = pre(fs)
            if len(dets) < 2:
                continue
            frames.append((fs.time, tuple(tuple(v) for v in dets)))
            first = fs.time if first is None else first
            if max_seconds and fs.time - first > max_seconds:
                frames.pop()
                return True
            if progress is not None and fs.time - first - last_report >= 10.0:
                last_report = fs.time - first
                progress(f"reading: {last_report:.0f} s of data, {len(frames)} framesets")
        return False

    def push(m: KeypointMessage) -> None:
        nonlocal clock
        if sync.push(m, clock) is None:
            if clock is None or m.stamp > clock:
                clock = m.stamp
            if stamps is not None:
                stamps.observe(m.sensor, m.stamp)
                stamps.sample(clock)

    for m in messages:
        if clock is None:
            pending.append(m)
            if len(pending) < 16:
                continue
            med = float(np.median([p.stamp for p in pending]))
            ok = [p.stamp for p in pending if abs(p.stamp - med) <= config.sync.max_stamp_future]
            clock = max(ok) if ok else med
            for p in sorted(pending, key=lambda p: p.stamp):
                push(p)
            pending = []
        else:
            push(m)
        if take(clock):
            return frames
    if pending:
        clock = float(np.median([p.stamp for p in pending]))
        for p in sorted(pending, key=lambda p: p.stamp):
            push(p)
    if clock is not None:
        take(clock + config.sync.wait + 1.0 / config.sync.rate)
    return frames


# ------------------------------------------------------------------ pairs


@dataclass(frozen=True, eq=False)
class PairPose:
    """Relative pose of camera b to camera a from one person's joints over time.

    R: (3, 3) b_R_a; t: (3,) unit vector; X_b = R X_a + s t for an unknown s > 0.
    frames: (F,) int indices (into the frames given) of the frames whose joints agree.
    depths: {camera: (N,) float64} depth of each triangulated joint in that camera for
    s = 1, keyed by ``keys`` (N,) int = frame index * 17 + joint.
    bones: (len(BONE_NAMES),) float64 the median length of each bone over the agreeing
    frames for s = 1, NaN = seen too rarely (``pair_bones``).
    size_spread: how much the person's size varies from frame to frame (``pair_size_spread``).
    """

    a: int
    b: int
    R: np.ndarray
    t: np.ndarray
    frames: np.ndarray
    candidates: int
    inliers: int
    residual_px: float
    angle_deg: float
    keys: np.ndarray = field(repr=False)
    depths: Mapping[int, np.ndarray] = field(repr=False)
    bones: np.ndarray = field(default_factory=lambda: np.full(len(BONE_NAMES), np.nan), repr=False)
    size_spread: float = float("nan")  # ``pair_size_spread``

    def __post_init__(self) -> None:
        assert self.R.shape == (3, 3) and self.t.shape == (3,)
        assert all(d.shape == self.keys.shape for d in self.depths.values())
        assert self.bones.shape == (len(BONE_NAMES),)


def single_whole(view: Sequence[Detection]) -> Detection | None:
    """A camera's view's one person seen with the whole torso, or None (nobody, or more
    than one: nothing tells which is which)."""
    whole = [d for d in view if d.whole_torso]
    return whole[0] if len(whole) == 1 else None


def single_views(frames: Sequence[Frame]) -> list[dict[int, Detection]]:
    """Per frame: camera → its detection, for the cameras that see exactly one person
    with the whole torso; persons seen in profile (``preprocess.partial_torso``) are not
    looked at, as the paper's preprocessing drops them. Geometry from scratch made of
    them doubled the wrong pairs of a hall of 30 cameras that mostly see different
    walkers; counted as persons that make a view ambiguous, they halved the pairs of a
    corridor where one walker hides behind the other (Session 47)."""
    return [{d.cam: d for d in map(single_whole, views) if d is not None} for _, views in frames]


def sampson_px(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, focal: float) -> np.ndarray:
    """(N,) signed Sampson error in px of correspondences xa, xb (N, 2) normalised under
    X_b = R X_a + s t."""
    E = hat(t) @ R
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    Ex = ha @ E.T
    Etx = hb @ E
    num = np.sum(hb * Ex, axis=1)
    den = np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)
    return num / np.maximum(den, 1e-15) * focal


def _refine(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, focal: float,
            scale_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust (Huber) least squares of the Sampson error over R and the baseline direction."""
    from scipy.optimize import least_squares

    # the direction on its tangent plane: two coordinates
    u = np.cross(t, [1.0, 0, 0] if abs(t[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(t, u)

    def pose(p):
        tn = t + p[3] * u + p[4] * v
        return so3_exp(p[:3]) @ R, tn / np.linalg.norm(tn)

    def res(p):
        return sampson_px(*pose(p), xa, xb, focal)

    r = least_squares(res, np.zeros(5), loss="huber", f_scale=scale_px, max_nfev=50)
    return pose(r.x)


def _triangulate_pair(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of a pair with unit baseline: depth in a, depth in b, ray angle (deg), each (N,)."""
    C = len(xa)
    Rs = np.stack([np.eye(3), R.T])  # world = camera a: world_R_cam
    ts = np.stack([np.zeros(3), -R.T @ t])  # centre of b in a's frame
    X = triangulate_batch(Rs, ts, np.tile([0, 1], (C, 1)), np.stack([xa, xb], axis=1))
    za = X[:, 2]
    zb = (X @ R.T + t)[:, 2]
    ra = X / np.linalg.norm(X, axis=1, keepdims=True)
    rb = X - ts[1]
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1, 1)))
    return za, zb, ang


def relative_pose(xa: np.ndarray, xb: np.ndarray, fid: np.ndarray, focal: float, cfg: BootstrapConfig,
                  *, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Relative pose from correspondences xa, xb (N, 2) normalised, grouped by frame id
    fid (N,). Returns (R (3, 3), t (3,), agreeing frame ids (F,), inlier mask (N,)) or
    None. A frame agrees when its joints' median Sampson error is below ``frame_px``; a
    joint is an inlier of an agreeing frame within 3 ``frame_px`` (left/right swaps and
    stray joints are not)."""
    import cv2

    if len(xa) < 8:
        return None
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.999,
                                   threshold=cfg.ransac_px / focal, maxIters=2000)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    _, R, t, _ = cv2.recoverPose(E, xa, xb, np.eye(3), mask=mask.copy())
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).ravel()
    uf, inv = np.unique(fid, return_inverse=True)
    good = np.zeros(0, np.int64)
    sel = np.zeros(len(xa), bool)
    for _round in range(3):
        e = np.abs(sampson_px(R, t, xa, xb, focal))
        med = np.array([np.median(e[inv == k]) for k in range(len(uf))])
        ok_frame = med < cfg.frame_px
        sel = ok_frame[inv] & (e < 3 * cfg.frame_px)
        if ok_frame.sum() < 2 or sel.sum() < 8:
            return None
        new_good = uf[ok_frame]
        if np.array_equal(new_good, good):
            break
        good = new_good
        R, t = _refine(R, t, xa[sel], xb[sel], focal, cfg.ransac_px)
    # cheirality: the person is in front of both cameras
    za, zb, _ = _triangulate_pair(R, t, xa[sel], xb[sel])
    front = np.mean((za > 0) & (zb > 0))
    if front < 0.5:  # the twisted pair: the other solution of the decomposition
        return None
    return R, t, good, sel


def pair_poses(frames: Sequence[Frame], cameras: int, focal: np.ndarray, cfg: BootstrapConfig, *,
               seed: int = 0, progress: Progress | None = None, only: int | None = None) -> tuple[list[PairPose], int]:
    """Every camera pair's relative pose from frames where both see one person (``only``:
    the pairs of that camera).

    Returns the accepted pairs and the number of pairs tried."""
    single = single_views(frames)
    by_pair: dict[tuple[int, int], list[int]] = defaultdict(list)
    for fi, s in enumerate(single):
        cs = sorted(s)
        for i in range(len(cs)):
            for j in range(i + 1, len(cs)):
                if only is None or only in (cs[i], cs[j]):
                    by_pair[(cs[i], cs[j])].append(fi)
    tried = [(k, v) for k, v in sorted(by_pair.items()) if len(v) >= cfg.min_pair_frames]
    out = []
    last = _time.perf_counter()
    for n, ((a, b), fis) in enumerate(tried):
        if progress is not None and _time.perf_counter() - last > 2.0:
            last = _time.perf_counter()
            progress(f"pairs: {n}/{len(tried)} tried, {len(out)} accepted")
        xa, xb, fid, jid = [], [], [], []
        for fi in fis:
            da, db = single[fi][a], single[fi][b]
            ok = np.all(np.isfinite(da.xy), 1) & np.all(np.isfinite(db.xy), 1)
            xa.append(da.xy[ok])
            xb.append(db.xy[ok])
            fid.append(np.full(int(ok.sum()), fi))
            jid.append(np.flatnonzero(ok))
        xa, xb = np.concatenate(xa), np.concatenate(xb)
        fid, jid = np.concatenate(fid), np.concatenate(jid)
        f = float(np.sqrt(focal[a] * focal[b]))
        r = relative_pose(xa, xb, fid, f, cfg, seed=seed + 7919 * a + b)
        if r is None:
            continue
        R, t, good, sel = r
        if len(good) < cfg.min_pair_frames or len(good) < cfg.min_consistent_ratio * len(fis):
            continue
        if len(_moving(single, (a, b), good, cfg.pair_motion)) < cfg.pair_min_moving:
            continue  # its agreeing frames are a few still spells: the same few points again and again
        za, zb, ang = _triangulate_pair(R, t, xa[sel], xb[sel])
        fine = (za > 0) & (zb > 0) & np.isfinite(za) & np.isfinite(zb)
        angle = float(np.median(ang[fine])) if fine.any() else 0.0
        if angle < cfg.min_triangulation_angle:
            continue
        keys = (fid[sel] * 17 + jid[sel])[fine]
        res = float(np.median(np.abs(sampson_px(R, t, xa[sel], xb[sel], f))))
        points = za[fine, None] * np.c_[xa[sel][fine], np.ones(int(fine.sum()))]
        bones = pair_bones(keys, points)
        out.append(PairPose(a, b, R, t, good, len(fis), int(sel.sum()), res, angle, keys,
                            {a: za[fine], b: zb[fine]}, bones, pair_size_spread(keys, points, bones)))
    return out, len(tried)


def _moving(single: Sequence[Mapping[int, Detection]], pair: tuple[int, int], fis: Sequence[int],
            min_motion: float) -> list[int]:
    """The frames ``fis`` (in time order) of a camera pair in which its person moved since
    the last one taken, in either view, by at least ``min_motion`` times its size there:
    the median of its joints' displacements over the median distance of its joints from
    their centre. A person who stands still gives the same few points frame after frame:
    no new correspondence, and where each of two cameras sees another person standing
    still, an essential matrix fits both skeletons in every such frame (two slow walkers
    who paused along a corridor: pairs of cameras that share no view, 59-171° off, agreed
    in 48-58 frames, of which 7-9 moved; where people walk, right pairs' agreeing frames
    moved in 27 and more, where they mostly stood in 12 and more; docs/bootstrap.md,
    Session 36)."""
    out: list[int] = []
    last: list[np.ndarray] = []
    for fi in fis:
        cur = [single[fi][c].xy for c in pair]
        if out:
            for now, before in zip(cur, last):
                ok = np.all(np.isfinite(now), 1) & np.all(np.isfinite(before), 1)
                if ok.sum() < 3:  # other joints seen: not the same points
                    break
                size = np.median(np.linalg.norm(now[ok] - now[ok].mean(0), axis=1))
                if np.median(np.linalg.norm(now[ok] - before[ok], axis=1)) >= min_motion * size:
                    break
            else:
                continue
        out.append(fi)
        last = cur
    return out


def _frame_bones(keys: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(F, len(BONES)) each bone's length in each frame of ``keys`` (NaN = a joint missing)."""
    frame, joint = np.divmod(keys, 17)
    uf, row = np.unique(frame, return_inverse=True)
    P = np.full((len(uf), 17, 3), np.nan)
    P[row, joint] = points
    return np.linalg.norm(P[:, BONES[:, 1]] - P[:, BONES[:, 2]], axis=2)


def pair_size_spread(keys: np.ndarray, points: np.ndarray, bones: np.ndarray) -> float:
    """How much one pair's person changes size from frame to frame: the robust std (1.4826
    MAD) of each frame's median bone length relative to ``bones`` (the pair's medians,
    ``pair_bones``); NaN without a measured bone. One person keeps its size: in the
    simulated corridors and the lab, pairs that saw one person spread 0.01-0.09 (a few
    noisy ones to 0.16); pairs whose two cameras saw two different people that moved alike
    (phantoms that survived the essential matrix) 0.15 and far more (docs/bones.md,
    Session 33). Keys and points as ``pair_bones``."""
    if not len(keys) or not np.isfinite(bones).any():
        return float("nan")
    L = _frame_bones(keys, points)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = L / bones[BONES[:, 0]]
    fin = np.isfinite(r).any(axis=1)
    if not fin.any():
        return float("nan")
    per_frame = np.nanmedian(r[fin], axis=1)
    return float(1.4826 * np.median(np.abs(per_frame - 1.0)))


def pair_bones(keys: np.ndarray, points: np.ndarray, *, min_frames: int = 10) -> np.ndarray:
    """(len(BONE_NAMES),) median length of each bone (left and right together) over the
    frames in which both its joints were triangulated, NaN when fewer than ``min_frames``.
    keys: (N,) int frame index * 17 + joint; points: (N, 3) float64 the joints."""
    assert keys.shape == (len(points),) and points.shape[1:] == (3,)
    out = np.full(len(BONE_NAMES), np.nan)
    if not len(keys):
        return out
    L = _frame_bones(keys, points)
    for k in range(len(BONE_NAMES)):
        v = L[:, BONES[:, 0] == k].ravel()
        v = v[np.isfinite(v)]
        if len(v) >= min_frames:
            out[k] = float(np.median(v))
    return out


# ------------------------------------------------------------------ view graph


def spanning_tree(cameras: int, edges: Sequence[tuple[int, int, float]]) -> list[int]:
    """Indices of the edges (a, b, weight) of a maximum-weight spanning forest (Kruskal)."""
    parent = list(range(cameras))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    out = []
    for k in sorted(range(len(edges)), key=lambda k: -edges[k][2]):
        a, b, _ = edges[k]
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
            out.append(k)
    return out


def triangle_check(pairs: Sequence[PairPose], tol_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Cycle consistency of the relative rotations: for every triangle of pairs (a, b),
    (b, c), (a, c), R_ac must equal R_bc R_ab. Returns (consistent, inconsistent) (P,)
    int counts of each pair's triangles. A pair whose triangles all disagree is wrong (its
    frames mixed two people, or RANSAC took a wrong model); one without triangles cannot
    be checked here (the bundle adjustment is its check)."""
    index = {(p.a, p.b): k for k, p in enumerate(pairs)}
    nbr: dict[int, set[int]] = defaultdict(set)
    for p in pairs:
        nbr[p.a].add(p.b)
        nbr[p.b].add(p.a)
    good = np.zeros(len(pairs), np.int64)
    bad = np.zeros(len(pairs), np.int64)
    for (a, b), kab in index.items():
        for c in nbr[a] & nbr[b]:
            if c <= b:
                continue  # each triangle once, a < b < c
            kbc, kac = index[(b, c)], index.get((a, c))
            if kac is None:
                continue
            err = rotation_angle_deg(pairs[kbc].R @ pairs[kab].R, pairs[kac].R)
            for k in (kab, kbc, kac):
                if err <= tol_deg:
                    good[k] += 1
                else:
                    bad[k] += 1
    return good, bad


def average_rotations(cameras: int, pairs: Sequence[PairPose], *, root: int | None = None,
                      sigma_deg: float = 2.0, sweeps: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World_R_cam (C, 3, 3) of the cameras connected to ``root`` (default: the camera
    with the most inliers), with R_root = I: chained along the maximum-inlier spanning
    tree, then iteratively reweighted chordal averaging over every pair (Cauchy weights of
    width ``sigma_deg``). Returns (R, connected (C,) bool, residual deg per pair)."""
    C = cameras
    w = np.array([float(p.inliers) for p in pairs])
    if root is None:
        load = np.zeros(C)
        for p, wi in zip(pairs, w):
            load[p.a] += wi
            load[p.b] += wi
        root = int(np.argmax(load))
    R = np.repeat(np.eye(3)[None], C, axis=0)
    known = np.zeros(C, bool)
    known[root] = True
    tree = [pairs[k] for k in spanning_tree(C, [(p.a, p.b, float(p.inliers)) for p in pairs])]
    changed = True
    while changed:  # chain along the tree from the root: R_a = R_b R_ab, R_b = R_a R_ab^T
        changed = False
        for p in tree:
            if known[p.a] and not known[p.b]:
                R[p.b] = R[p.a] @ p.R.T
                known[p.b] = changed = True
            elif known[p.b] and not known[p.a]:
                R[p.a] = R[p.b] @ p.R
                known[p.a] = changed = True
    use = [k for k, p in enumerate(pairs) if known[p.a] and known[p.b]]

    def residuals():
        return np.array([rotation_angle_deg(R[p.b].T @ R[p.a], p.R) for p in pairs])

    for _ in range(sweeps):
        r = residuals()
        rw = w / (1.0 + (r / sigma_deg) ** 2)
        M = np.zeros((C, 3, 3))
        for k in use:
            p = pairs[k]
            M[p.a] += rw[k] * (R[p.b] @ p.R)
            M[p.b] += rw[k] * (R[p.a] @ p.R.T)
        for c in np.flatnonzero(known):
            if c != root and np.any(M[c]):
                R[c] = project_so3(M[c])
    return R, known, residuals()


def pair_scales(pairs: Sequence[PairPose], cfg: BootstrapConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Relative scale of each pair's unit-baseline triangulation (the baseline length in
    a common unit), from the depths at which two pairs sharing a camera see the same
    joints. Pairs that no such chain of shared joints relates (a corridor: no camera
    triple sees one instant) are related by their people's bones instead
    (``bootstrap.bone_scales``): the same people walk past both, so their median bones
    are the same length in metres. Returns (log scale (P,), known (P,) bool, number of
    bone relations used): the largest connected group of related pairs, its best pair at
    log scale 0."""
    P = len(pairs)
    rel = []  # (e, f, log(s_e / s_f), weight)
    incident: dict[int, list[int]] = defaultdict(list)
    for k, p in enumerate(pairs):
        incident[p.a].append(k)
        incident[p.b].append(k)
    sharing = [(cam, ks[i], ks[j]) for cam, ks in incident.items() for i in range(len(ks)) for j in range(i + 1, len(ks))]
    for cam, ke, kf in sharing:
        e, f = pairs[ke], pairs[kf]
        common, ie, if_ = np.intersect1d(e.keys, f.keys, return_indices=True)
        if len(common) < cfg.min_shared_points:
            continue
        ze, zf = e.depths[cam][ie], f.depths[cam][if_]
        ok = (ze > 0) & (zf > 0)
        if ok.sum() < cfg.min_shared_points:
            continue
        ratios = np.log(zf[ok] / ze[ok])
        rel.append((ke, kf, float(np.median(ratios)), float(np.sqrt(min(ok.sum(), 400)))))
    known = np.zeros(P, bool)
    logs = np.zeros(P)
    if P == 0:
        return logs, known, 0
    label = _related(P, rel)
    n_bones, shared = 0, len(rel)
    if cfg.bone_scales:
        for _cam, ke, kf in sharing:
            if label[ke] == label[kf]:
                continue  # shared joints relate them better
            v = np.log(pairs[kf].bones / pairs[ke].bones)
            v = v[np.isfinite(v)]
            # every bone scales alike; a spread says one pair's geometry is wrong
            if len(v) >= 3 and np.median(np.abs(v - np.median(v))) <= 0.1:
                rel.append((ke, kf, float(np.median(v)), 1.0))  # people differ: weak against shared joints
                n_bones += 1
        if n_bones:
            label = _related(P, rel)
    groups = [np.flatnonzero(label == g).tolist() for g in range(label.max() + 1)]
    best = max(groups, key=lambda g: (len(g), sum(pairs[k].inliers for k in g)))
    anchor = max(best, key=lambda k: pairs[k].inliers)
    if len(best) < 2:
        known[anchor] = True
        return logs, known, 0
    idx = {k: i for i, k in enumerate(best)}
    rows = [(idx[e], idx[f], v, w) for e, f, v, w in rel if e in idx and f in idx]
    n = len(best)
    wr = np.ones(len(rows))
    x = np.zeros(n)
    for _ in range(10):  # IRLS, Huber on the log residuals (width 0.02)
        A = np.zeros((len(rows) + 1, n))
        b = np.zeros(len(rows) + 1)
        for r, (i, j, v, w) in enumerate(rows):
            s = w * wr[r]
            A[r, i], A[r, j], b[r] = s, -s, s * v
        A[-1, idx[anchor]] = b[-1] = 0.0
        A[-1, idx[anchor]] = 1e3
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        res = np.array([abs(x[i] - x[j] - v) for i, j, v, _ in rows])
        wr = np.where(res > 0.02, 0.02 / np.maximum(res, 1e-12), 1.0)
    for k in best:
        logs[k] = x[idx[k]]
        known[k] = True
    return logs, known, sum(1 for e, _f, _v, _w in rel[shared:] if e in idx)


def _related(P: int, rel: Sequence[tuple[int, int, float, float]]) -> np.ndarray:
    """(P,) label of each pair's connected group over the relations (labelled in the
    order of their first pair)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ef = np.array([(e, f) for e, f, _, _ in rel], dtype=np.int64).reshape(-1, 2)
    _, label = connected_components(coo_matrix((np.ones(len(ef)), (ef[:, 0], ef[:, 1])), shape=(P, P)),
                                    directed=False)
    return label


def _busiest(cameras: int, pairs: Sequence[PairPose], use: np.ndarray) -> int | None:
    """The camera with the most inliers over the pairs ``use`` (P,) bool; None if none."""
    if not np.any(use):
        return None
    load = np.zeros(cameras)
    for p, u in zip(pairs, use):
        if u:
            load[p.a] += p.inliers
            load[p.b] += p.inliers
    return int(np.argmax(load))


def place_cameras(cameras: int, R: np.ndarray, pairs: Sequence[PairPose], logs: np.ndarray,
                  scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (C, 3) from the rotations and the pairs' baselines: c_b - c_a =
    s·(-R_b t_ab) for pairs with a scale, (c_b - c_a) ∥ -R_b t_ab for the others
    (robust least squares). Returns (centres, located (C,) bool)."""
    C = cameras
    located = np.zeros(C, bool)
    for k, p in enumerate(pairs):
        if scaled[k]:
            located[p.a] = located[p.b] = True
    if not located.any():
        return np.zeros((C, 3)), located
    # cameras with direction-only pairs to >= 2 placed cameras in different directions
    changed = True
    while changed:
        changed = False
        for c in np.flatnonzero(~located):
            dirs = []
            for p in pairs:
                other = p.b if p.a == c else p.a if p.b == c else None
                if other is not None and located[other]:
                    dirs.append(-R[p.b] @ p.t)
            if len(dirs) >= 2:
                D = np.array(dirs)
                if np.linalg.svd(D, compute_uv=False)[1] > np.sin(np.radians(10)):
                    located[c] = changed = True
    idx = np.flatnonzero(located)
    col = {c: i for i, c in enumerate(idx)}
    use = [k for k, p in enumerate(pairs) if located[p.a] and located[p.b]]
    root = idx[0]
    wr = np.ones(len(use))
    x = np.zeros(3 * len(idx))
    for _ in range(10):
        rows_A, rows_b = [], []
        for r, k in enumerate(use):
            p = pairs[k]
            d = -R[p.b] @ p.t
            w = np.sqrt(p.inliers) * wr[r]
            blk = np.zeros((3, 3 * len(idx)))
            blk[:, 3 * col[p.b]:3 * col[p.b] + 3] = np.eye(3)
            blk[:, 3 * col[p.a]:3 * col[p.a] + 3] = -np.eye(3)
            if scaled[k]:
                rows_A.append(w * blk)
                rows_b.append(w * np.exp(logs[k]) * d)
            else:
                rows_A.append(w * hat(d) @ blk)
                rows_b.append(np.zeros(3))
        anchor = np.zeros((3, 3 * len(idx)))
        anchor[:, 3 * col[root]:3 * col[root] + 3] = 1e3 * np.eye(3)
        A = np.concatenate(rows_A + [anchor])
        b = np.concatenate(rows_b + [np.zeros(3)])
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        res = np.array([np.linalg.norm((A[3 * r:3 * r + 3] @ x - b[3 * r:3 * r + 3])) / (np.sqrt(pairs[k].inliers) * wr[r])
                        for r, k in enumerate(use)])
        med = float(np.median(res)) if len(res) else 0.0
        lim = max(3.0 * med, 1e-6)
        wr = np.where(res > lim, lim / np.maximum(res, 1e-12), 1.0)
    t = np.zeros((C, 3))
    t[idx] = x.reshape(-1, 3)
    return t, located


# ------------------------------------------------------------------ bridges


def _groups(cameras: int, ab: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(C,) label of each camera's connected group over the edges ab (E, 2) that ``keep``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(int(keep.sum())), (ab[keep, 0], ab[keep, 1])), shape=(cameras, cameras))
    return connected_components(g, directed=False)[1]


def bridges(cameras: int, edges: Sequence[tuple[int, int]]) -> np.ndarray:
    """(E,) bool: the edges (a, b) whose removal disconnects their cameras (bridges of the
    view graph: a pair no cycle of pairs checks)."""
    E = len(edges)
    out = np.zeros(E, bool)
    if E == 0:
        return out
    ab = np.array(edges, dtype=np.int64).reshape(-1, 2)
    every = np.ones(E, bool)
    for k in range(E):
        every[k] = False
        lab = _groups(cameras, ab, every)
        out[k] = lab[ab[k, 0]] != lab[ab[k, 1]]
        every[k] = True
    return out


# A person's size varying by less is noise, not two people: right bridges spread up to 0.10
# (the corridors, the lab, the west room's live bootstrap at 30-40 s of data, where the
# limit sat at 0.10 with a bridge at 0.094-0.10), the corridor's phantom 0.161.
_MIN_PHANTOM_SPREAD = 0.13


def split_cameras(cameras: int, pairs: Sequence[PairPose], kept: np.ndarray, ratio: float) -> np.ndarray:
    """(C,) bool: cameras whose pairs the rotation averaging dropped (``kept`` (P,) False)
    agree in at least ``ratio`` times the frames of its kept pairs. Two walkers who moved
    alike for a while give a camera consistent wrong pairs with the cameras that saw the
    other one; where they are as many as its right pairs, the averaging picks a side by
    their count: measured in the lab (seed 2, the first 60 s), cam_16 and cam_17 kept
    their wrong pairs (100 degrees off, 187 and 77 frames against 133 and 93 dropped) and
    the bootstrap put them metres off. 0: none."""
    assert kept.shape == (len(pairs),)
    out = np.zeros(cameras, bool)
    if ratio <= 0:
        return out
    frames_kept, frames_dropped = np.zeros(cameras), np.zeros(cameras)
    for p, k in zip(pairs, kept):
        for c in (p.a, p.b):
            (frames_kept if k else frames_dropped)[c] += len(p.frames)
    return (frames_dropped > 0) & (frames_dropped >= ratio * frames_kept)


def _without_phantom_bridges(cameras: int, pairs: list[PairPose], ratio: float
                             ) -> tuple[list[PairPose], list[PairPose]]:
    """(kept, dropped): bridge pairs (``bridges``) whose ``size_spread`` exceeds ``ratio``
    times the median over ``pairs`` and ``_MIN_PHANTOM_SPREAD`` are dropped. A bridge has
    no cycle to check it, and in a corridor with several walkers two cameras that share no
    floor each see one of two people who move alike often enough for an essential matrix;
    measured, such a pair spread 0.16 (2.8x the median) and chained the corridor 1.7 m
    off, the right bridges 0.6-1.2x (docs/bones.md, Session 33). 0: off."""
    if ratio <= 0 or len(pairs) < 3:
        return pairs, []
    spread = np.array([p.size_spread for p in pairs])
    if not np.isfinite(spread).any():
        return pairs, []
    high = np.nan_to_num(spread) > max(ratio * float(np.nanmedian(spread)), _MIN_PHANTOM_SPREAD)
    if not high.any():  # the bridges (a graph search per pair) only when some pair could go
        return pairs, []
    drop = bridges(cameras, [(p.a, p.b) for p in pairs]) & high
    return [p for p, d in zip(pairs, drop) if not d], [p for p, d in zip(pairs, drop) if d]


def core_cameras(cameras: int, edges: Sequence[tuple[int, int]]) -> np.ndarray:
    """(C,) bool: the largest group of cameras that stays connected without the bridges
    (the largest 2-edge-connected component: every camera in it is reached by two
    independent chains of pairs); all False when no group has 3 cameras (a corridor,
    where every pair is a bridge)."""
    core = np.zeros(cameras, bool)
    if not edges:
        return core
    ab = np.array(edges, dtype=np.int64).reshape(-1, 2)
    keep = ~bridges(cameras, edges)
    if not keep.any():
        return core
    lab = _groups(cameras, ab, keep)
    in_edge = np.zeros(cameras, bool)
    in_edge[ab[keep].ravel()] = True
    sizes = np.bincount(lab[in_edge], minlength=lab.max() + 1)
    best = int(np.argmax(sizes))
    if sizes[best] >= 3:
        core = in_edge & (lab == best)
    return core


@dataclass(frozen=True)
class BridgeCheck:
    """The check of a camera reached in the view graph only over bridge pairs.

    frames: frames (outside its pairs' own) in which the persons the verified cameras
    triangulate lie in its view (where its detections lie, ``view_box``) while it sees one
    person; agree: in how many its detection is that person by its pose (median
    reprojection error within ``check_px``); outcome: "verified", "re-localised" (by PnP
    against those persons), "dropped" (the evidence is against its pose and PnP found
    none) or "unchecked" (too few such frames: kept as the view graph placed it).
    """

    cam: int
    frames: int
    agree: int
    outcome: str


def view_box(frames: Sequence[Frame], cameras: int) -> np.ndarray:
    """(C, 2, 2) per camera the 1 % and 99 % quantiles of its detections' normalised
    coordinates (where people appear in its image; NaN without detections)."""
    out = np.full((cameras, 2, 2), np.nan)
    pts: dict[int, list[np.ndarray]] = defaultdict(list)
    for _, views in frames:
        for v in views:
            for d in v:
                pts[d.cam].append(d.xy[np.all(np.isfinite(d.xy), axis=1)])
    for c, ps in pts.items():
        P = np.concatenate(ps)
        if len(P):
            out[c] = np.percentile(P, [1, 99], axis=0)
    return out


def _agreement(per: Sequence[tuple[np.ndarray, np.ndarray]], R: np.ndarray, t: np.ndarray, box: np.ndarray,
               tol: float) -> tuple[int, int]:
    """(frames whose person lies in the view box of the pose R (3, 3), t (3,), frames
    among them whose detection is within ``tol`` (normalised, median over joints))."""
    seen = agree = 0
    for X, x in per:
        Xc = (X - t) @ R
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = Xc[:, :2] / z[:, None]
        inside = (z > 0) & np.all((u >= box[0]) & (u <= box[1]), axis=1)
        if inside.mean() < 0.5:
            continue
        seen += 1
        agree += bool(np.median(np.linalg.norm(u[inside] - x[inside], axis=1)) < tol)
    return seen, agree


def check_bridged(frames: Sequence[Frame], pairs: Sequence[PairPose], R: np.ndarray, t: np.ndarray,
                  located: np.ndarray, focal: np.ndarray, config: EngineConfig, *, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[BridgeCheck]]:
    """Check the located cameras the view graph reached only over bridge pairs (pairs no
    triangle of pairs checks: a pair whose frames mixed two walkers who happened to move
    alike places its camera anywhere, 160° off in one measured case, and the bundle
    adjustment keeps it with wrong associations) against the persons the cameras of the
    core (``core_cameras``) triangulate without them, in frames outside the camera's own
    pairs' frames (independent evidence): where such a person lies in the camera's view
    and it sees one person, that must be the person (``_agreement``). A camera agreeing
    in at least ``check_min_agree`` of at least ``check_min_frames`` such frames is
    verified and joins the cameras the next ones are checked against; one agreeing less
    is re-localised by PnP against the same persons (``relocalize``) or, failing that,
    not placed; one with fewer frames (a corridor, where no camera triangulates what it
    sees without it; a room behind the others) is kept unchecked. Nothing is checked
    when no core of 3 cameras exists.

    Returns (R, t, located, checks); R, t, located are copies."""
    from .relocalize import frame_correspondences, relocalize

    R, t, located = R.copy(), t.copy(), located.copy()
    cfg = config.bootstrap
    edges = [(p.a, p.b) for p in pairs if located[p.a] and located[p.b]]
    verified = core_cameras(len(located), edges) & located
    checks: list[BridgeCheck] = []
    if not verified.any():
        return R, t, located, checks
    boxes = view_box(frames, len(located))
    todo = [int(c) for c in np.flatnonzero(located & ~verified)]
    changed = True
    while changed and todo:
        changed = False
        for c in list(todo):
            keep = verified.copy()
            keep[c] = True
            own = set()
            for p in pairs:
                if c in (p.a, p.b):
                    own.update(p.frames.tolist())
            fr = _without([f for i, f in enumerate(frames) if i not in own], keep)
            per = frame_correspondences(fr, c, R, t, config.associate)
            seen, agree = _agreement(per, R[c], t[c], boxes[c], cfg.check_px / focal[c])
            if seen < cfg.check_min_frames:
                continue  # perhaps after more cameras are verified
            todo.remove(c)
            changed = True
            if agree >= cfg.check_min_agree * seen:
                verified[c] = True
                checks.append(BridgeCheck(c, seen, agree, "verified"))
                continue
            rl = relocalize(_without(frames, keep), c, R, t, float(focal[c]), config.associate,
                            reprojection_px=cfg.check_px, seed=seed)
            if rl is not None:
                R[c], t[c] = rl.R, rl.t
                verified[c] = True
                checks.append(BridgeCheck(c, seen, agree, "re-localised"))
            else:
                located[c] = False
                checks.append(BridgeCheck(c, seen, agree, "dropped"))
    checks += [BridgeCheck(c, 0, 0, "unchecked") for c in todo]
    return R, t, located, checks


# ------------------------------------------------------------------ result


@dataclass(frozen=True, eq=False)
class BootstrapResult:
    """Camera poses found without an initial estimate.

    R: (C, 3, 3) world_R_cam; t: (C, 3) centres, metres by ``scale``; located: (C,) bool
    (the others keep R = I, t = 0 and must not be used); std_translation (C,) m and
    std_rotation (C,) deg: the bundle adjustment's shape std (NaN where unknown);
    residual_px (C,) and observations (C,): each camera's median reprojection error and
    number of joint observations in the last bundle adjustment (how well the data hold
    it there; None when not recorded); depth (C,) m: the median distance of the points
    each camera saw there (NaN where unknown; None when not recorded).
    """

    names: tuple[str, ...]
    R: np.ndarray
    t: np.ndarray
    located: np.ndarray
    std_translation: np.ndarray
    std_rotation: np.ndarray
    scale: ScaleEstimate | None
    frame: str
    pairs: int
    pairs_tried: int
    frames: int
    data_seconds: float
    seconds: float
    stages: Mapping[str, float] = field(default_factory=dict)
    checks: tuple[str, ...] = ()  # the cameras reached only over bridge pairs and their check ("cam_1 dropped ...")
    resections: tuple[str, ...] = ()  # the cameras no pair placed and their resection (backend/resect.py)
    residual_px: np.ndarray | None = None
    observations: np.ndarray | None = None
    floor: FloorFrame | None = None  # how ``frame`` was made: the final batch levels it again on its floor
    # sensors whose stamps ran apart from the others' (``stamps_apart``): name -> the shift (s) its
    # views were timed by here (its lead, or 0 where its stamps fitted its pairs better)
    mistimed: Mapping[str, float] = field(default_factory=dict)
    depth: np.ndarray | None = None
    joins: tuple[str, ...] = ()  # the groups of cameras no pair linked to the others, and how each was joined (or not)

    def __post_init__(self) -> None:
        C = len(self.names)
        assert self.R.shape == (C, 3, 3) and self.t.shape == (C, 3) and self.located.shape == (C,)
        assert self.std_translation.shape == (C,) and self.std_rotation.shape == (C,)

    def poses(self) -> dict[str, Pose]:
        return {n: Pose(self.R[c].copy(), self.t[c].copy()) for c, n in enumerate(self.names) if self.located[c]}

    def extrinsics(self, resolutions: Mapping[str, tuple[int, int]]) -> dict[str, Extrinsics]:
        """Every camera (unlocated ones at R = I, t = 0, std unknown), for a CameraSet."""
        out = {}
        for c, n in enumerate(self.names):
            st, sr = self.std_translation[c], self.std_rotation[c]
            out[n] = Extrinsics(Pose(self.R[c].copy(), self.t[c].copy()), resolutions[n],
                                float(st) if np.isfinite(st) else None, float(sr) if np.isfinite(sr) else None)
        return out

    def to_dict(self) -> dict:
        """The metadata, with the placed cameras' poses (``poses``: name → translation,
        rotation quaternion x, y, z, w, as in the extrinsics YAML; the bootstrap's own
        estimate, before any online pipeline)."""
        from .geometry import R_to_quat

        return {
            "frame": self.frame,
            "poses": {n: {"translation": self.t[c].tolist(), "rotation": R_to_quat(self.R[c]).tolist()}
                      for c, n in enumerate(self.names) if self.located[c]},
            "scale": self.scale.to_dict() if self.scale else None,
            "located": [n for c, n in enumerate(self.names) if self.located[c]],
            "not_located": [n for c, n in enumerate(self.names) if not self.located[c]],
            "pairs": self.pairs, "pairs_tried": self.pairs_tried, "frames": self.frames,
            "data_seconds": self.data_seconds, "seconds": self.seconds, "stages": dict(self.stages),
            "bridge_checks": list(self.checks),
            "resections": list(self.resections),
            "mistimed": dict(self.mistimed),
            "joined_groups": list(self.joins),
        }


def handover(cfg: EngineConfig, result: BootstrapResult) -> EngineConfig:
    """The engine config for the online pipeline that starts from ``result``: its initial
    std is honest and large, 3x the worst bootstrap std or the ``handover_*`` floor; the
    final batch runs from the result as well and is kept from there when it explains the
    data better (``Pipeline._batch_from_start``), and its floor levels the world frame
    again (``bootstrap.level_final``: the bootstrap's floor may be one pair's people's)."""
    b = cfg.bootstrap
    st = result.std_translation[result.located]
    sr = result.std_rotation[result.located]
    worst_t = float(np.nanmax(st)) if np.any(np.isfinite(st)) else 0.0
    worst_r = float(np.nanmax(sr)) if np.any(np.isfinite(sr)) else 0.0
    std_t, std_r = b.handover_std(worst_t, worst_r)
    refine = cfg.refine.model_copy(update={
        "initial_std_translation": std_t,
        "initial_std_rotation": std_r,
        # the bootstrap saw all its data at once: a final batch from it too, kept when better
        "final_batch_from_start": True,
        "floor_frame": result.floor if b.level_final else None,
    })
    return cfg.model_copy(update={"refine": refine})


def camera_set(intrinsics: Mapping[str, Intrinsics], result: BootstrapResult) -> CameraSet:
    """The CameraSet the online pipeline starts from: the cameras the bootstrap placed (a
    camera without a pose would only feed wrong associations; its messages are counted
    as from an unknown sensor)."""
    names = [n for c, n in enumerate(result.names) if result.located[c]]
    ext = result.extrinsics({n: intrinsics[n].resolution for n in result.names})
    return CameraSet.combine({n: intrinsics[n] for n in names}, {n: ext[n] for n in names})


# ------------------------------------------------------------------ the whole bootstrap


def _without(frames: Sequence[Frame], keep: np.ndarray) -> list[Frame]:
    """Frames with the detections of cameras not in ``keep`` (C,) bool removed."""
    out = []
    for time_, views in frames:
        vs = tuple(v for v in views if keep[v[0].cam])
        if len(vs) >= 2:
            out.append((time_, vs))
    return out


def retimed(frames: Sequence[Frame], cam: int, delta: float, *, max_gap: float = 0.25) -> list[Frame]:
    """``frames`` with camera ``cam``'s views those it had ``delta`` s later, interpolated
    between its two nearest frames (at most ``max_gap`` s apart) in which it saw one
    person with the whole torso, as ``single_views`` (with several persons nothing tells
    which is which: such views are dropped, as are frames left with < 2 views). Its sigma
    is the larger of the two."""
    own = [(T, d) for T, views in frames for v in views
           if v and v[0].cam == cam and (d := single_whole(v)) is not None]
    times = np.array([T for T, _ in own])
    out: list[Frame] = []
    for T, views in frames:
        others = tuple(v for v in views if v and v[0].cam != cam)
        target = T + delta
        j = int(np.searchsorted(times, target))
        d = None
        if j < len(times) and times[j] == target:
            d = own[j][1]
        elif 0 < j < len(times) and times[j] - times[j - 1] <= max_gap:
            (t0, d0), (t1, d1) = own[j - 1], own[j]
            w = (target - t0) / (t1 - t0)
            d = replace(d0, xy=(1 - w) * d0.xy + w * d1.xy, sigma=np.maximum(d0.sigma, d1.sigma))  # NaN: either missing
        if d is not None:
            others = tuple(sorted(others + ((d,),), key=lambda v: v[0].cam))
        if len(others) >= 2:
            out.append((T, others))
    return out


def _timed(frames: list[Frame], names: Sequence[str], focal: np.ndarray, cfg: BootstrapConfig,
           mistimed: Mapping[str, float], *, seed: int) -> tuple[list[Frame], dict[str, float]]:
    """The frames with each sensor of ``mistimed`` (name -> lead, s) timed as its pairs
    with the others (not mistimed) agree best: by its lead (a clock that runs ahead or
    behind) or as stamped (a longer delay than the others', the stamps right). The
    stamps alone cannot tell the two apart (backend/stamp_watch.py); a view a fifth of a
    second off shows a walker 0.26 m from where the others see him, and the lab's seed 2
    with five sensors -200 ... +200 ms off put cam_2 14 m off (docs/bootstrap.md,
    Session 41). Judged by the frames its pairs agree in (``_timing_agreement``); no
    pair either way: as stamped, and left out of the shifts returned (not judged: a
    camera placed later is timed then, backend/late_join.py). The pipeline estimates
    the offsets from then on."""
    idx = {n: c for c, n in enumerate(names)}
    reference = np.array([n not in mistimed for n in names])
    out, shifts = frames, {}
    for n, lead in mistimed.items():
        c = idx[n]
        keep = reference.copy()
        keep[c] = True
        as_stamped, by_lead = _timing_agreement(_without(frames, keep), c, lead, focal, cfg, seed=seed)
        if as_stamped or by_lead:  # no pair either way (a camera that saw nobody yet): not judged
            shifts[n] = lead if by_lead > as_stamped else 0.0
    for n, d in shifts.items():
        if d:
            out = retimed(out, idx[n], d)
    return out, shifts


def _timing_agreement(frames: list[Frame], cam: int, lead: float, focal: np.ndarray, cfg: BootstrapConfig, *,
                      seed: int) -> tuple[int, int]:
    """The frames in which camera ``cam``'s pairs agree, its views as stamped and its
    lead later. Retimed views are interpolated between two single-person views, so there
    are fewer of them: the lead must win on fewer frames, and the stamps are kept unless
    the data say otherwise (seed 1's cam_17, +200 ms: 494 of 727 frames agree as stamped,
    483 of 589 timed; it was placed later, by its pair). The share of agreeing frames,
    or the counts at the instants with a view both ways, decided no better: cameras that
    see little tie (the west room's cam_13 in 60 s: no pair at the common instants)."""
    out = []
    for F in (frames, retimed(frames, cam, lead)):
        pairs, _ = pair_poses(F, len(focal), focal, cfg, seed=seed, only=cam)
        out.append(sum(len(p.frames) for p in pairs))
    return out[0], out[1]


def _pair_hypotheses(frames: Sequence[Frame], pairs: Sequence[PairPose], use: np.ndarray,
                     R: np.ndarray, t: np.ndarray) -> list[Hypothesis]:
    """Two-view hypotheses of the pairs' agreeing frames (the rough scale's material)."""
    single = single_views(frames)
    hyps = []
    for k in np.flatnonzero(use):
        p = pairs[k]
        for fi in p.frames:
            da, db = single[fi][p.a], single[fi][p.b]
            cams = np.array([p.a, p.b])
            xy = np.stack([da.xy, db.xy])
            c = triangulate_batch(R, t, cams[None], np.stack([torso_centre(da.xy), torso_centre(db.xy)])[None])[0]
            if not np.all(np.isfinite(c)):
                continue
            hyps.append(Hypothesis(frames[fi][0], cams, xy, np.stack([da.sigma / da.focal, db.sigma / db.focal]), c))
    return hyps


def _rough_scale(seg: Segments, cfg: BootstrapConfig, torso_ratio: float, heights: Sequence[float]) -> float:
    """Metres per unit from the pooled median chain of every two-view hypothesis."""
    from .people import chain_ratio

    ok = np.isfinite(seg.shank) & np.isfinite(seg.thigh) & np.isfinite(seg.torso)
    if ok.sum() < 10:
        raise BootstrapError("too few persons triangulated by camera pairs to find the scale")
    chain = float(np.median(seg.shank[ok]) + np.median(seg.thigh[ok]) + np.median(seg.torso[ok]))
    H = float(np.mean(heights)) if heights else cfg.height_mean
    return H / (chain / chain_ratio(torso_ratio))


def _place_by_bones(R: np.ndarray, t: np.ndarray, located: np.ndarray, R_bones: np.ndarray, t_bones: np.ndarray,
                    located_bones: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cameras of the bones' placement (``R_bones``, ``t_bones``, ``located_bones``: the
    averaged rotations and the centres with the bones' scale relations) that ``located``
    lacks, moved onto (R, t) by the similarity of the cameras both placed (the rotation
    from their orientations: two cameras of a corridor fix no rotation by their centres).
    Returns (R, t, added (C,) bool)."""
    common = located & located_bones
    added = located_bones & ~located
    if common.sum() < 2 or not added.any():
        return R, t, np.zeros(len(R), bool)
    Rw = project_so3(np.einsum("cij,ckj->ik", R[common], R_bones[common]))
    a = t_bones[common] @ Rw.T
    b = t[common]
    da, db = a - a.mean(0), b - b.mean(0)
    s = float(np.sum(da * db) / np.sum(da * da))
    if not (np.isfinite(s) and s > 0):
        return R, t, np.zeros(len(R), bool)
    R, t = R.copy(), t.copy()
    R[added] = np.einsum("ij,cjk->cik", Rw, R_bones[added])
    t[added] = s * t_bones[added] @ Rw.T + (b.mean(0) - s * a.mean(0))
    return R, t, added


def floor_frame(seg: Segments, t: np.ndarray, located: np.ndarray, height: float,
                names: Sequence[str], sigma: float = 0.05) -> tuple[np.ndarray, np.ndarray, str, FloorFrame]:
    """The world frame of the floor the people walk on: (F (3, 3), o (3,), note, its
    definition for levelling it again on the final floor) with new coordinates
    X' = F (X - o). The floor is the plane of each hypothesis' lower ankle
    (``floor.plane_of_ankles``: robust, its turn about a line of ankles from the bodies' up;
    where no plane is found, level to the bodies' median up), lowered by the ankle's height
    above the floor in a stance (0.039 x the persons' height); z up (towards the hips),
    origin under the first located camera, x towards the next one's floor point;
    ``sigma``: m, a lower ankle's height about the plane (``optimize.floor_sigma``).

    Not every ankle's least-squares plane: along a corridor two or three walkers' wrong
    pairs put ankles metres off, and their plane stood 60-78° from level (session 34)."""
    P = seg.ankles.reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 50:
        raise BootstrapError("too few ankles triangulated to find the floor")
    plane = plane_of_ankles(seg.ankles, seg.up, sigma)
    if plane is not None:
        n, stance, how = plane.n, plane.d, f"the plane of the people's lower ankles (fit over {plane.points})"
    else:
        n = median_up(seg.up)
        if n is None:
            raise BootstrapError("no person triangulated upright: no floor to define the frame by")
        stance = float(np.percentile(P @ n, 10))
        how = "the people's median up (their ankles fit no one plane)"
    idx = np.flatnonzero(located)
    found = world_frame(n, stance - ANKLE_HEIGHT * height, t[idx])
    if found is None:
        raise BootstrapError("the cameras' floor points coincide: no x axis")
    F, o, k = found
    first, second = names[idx[0]], names[idx[k]]
    note = (f"floor frame: z up, normal to {how}, the floor {ANKLE_HEIGHT * height:.3f} m below the ankles' "
            f"stance level; origin on the floor under {first}, x towards the floor point under {second}")
    return F, o, note, FloorFrame(first=first, second=second, ankle_height=ANKLE_HEIGHT * height)


def bootstrap(frames: Sequence[Frame], names: Sequence[str], focal: np.ndarray, config: EngineConfig, *,
              heights: Sequence[float] = (), seed: int = 0, progress: Progress | None = None,
              mistimed: Mapping[str, float] | None = None) -> BootstrapResult:
    """Camera poses from ``frames`` alone (see the module doc). ``heights``: known heights
    of the walkers (m); without them the population prior sets the scale. ``config``: in
    the cameras' pixels (``EngineConfig.for_images``, as ``bootstrap_messages`` and the
    pipelines make it). ``mistimed``: sensors whose stamps run apart from the others'
    (``stamps_apart``; name -> lead, s): their views timed by their lead or as stamped,
    whichever their pairs agree with more (``_timed``). Raises BootstrapError when fewer
    than 2 cameras can be placed."""
    cfg = config.bootstrap
    say = progress or (lambda _m: None)
    t_start = _time.perf_counter()
    stages: dict[str, float] = {}
    C = len(names)
    focal = np.asarray(focal, dtype=np.float64)
    assert focal.shape == (C,)
    frames = list(frames)
    timed: dict[str, float] = {}
    if mistimed:
        frames, timed = _timed(frames, names, focal, cfg, {n: float(v) for n, v in mistimed.items() if n in names},
                               seed=seed)
        if timed:  # none when every such sensor is unjudged (no pair either way)
            say(mistimed_summary(timed))
    if len(frames) < cfg.min_pair_frames:
        raise BootstrapError(f"{len(frames)} framesets with >= 2 views: too few to start "
                             f"(a pair needs {cfg.min_pair_frames})")
    data_seconds = frames[-1][0] - frames[0][0]
    g = _place(frames, names, focal, config, heights, seed=seed, say=say, stages=stages)
    t0 = _time.perf_counter()
    g, scale, note, spec = _on_floor(frames, g, names, config, heights, say)
    stages["people"] = _time.perf_counter() - t0
    joins: list[str] = []
    if cfg.join_groups:
        t0 = _time.perf_counter()
        g, scale, note, spec, joins = _join_groups(frames, g, (scale, note, spec), names, focal, config, heights,
                                                   seed=seed, say=say)
        stages["groups"] = _time.perf_counter() - t0
    located = g.located
    R, t = g.R.copy(), g.t.copy()
    R[~located], t[~located] = np.eye(3), 0.0
    std_t, std_r = np.where(located, g.std_t, np.nan), np.where(located, g.std_r, np.nan)
    residual_px = np.where(located, g.residual_px, np.nan)
    observations = np.where(located, g.observations, 0)
    depth = np.where(located, g.depth, np.nan)
    return BootstrapResult(tuple(names), R, t, located, std_t, std_r, scale, note, g.pairs, g.tried, len(frames),
                           float(data_seconds), _time.perf_counter() - t_start, stages, g.checks, g.resections,
                           residual_px, observations, spec, timed, depth, tuple(joins))


@dataclass(frozen=True)
class _Placed:
    """One group of cameras placed by steps 1-5 (in the units of its rough scale until
    ``_on_floor``). R (C, 3, 3), t (C, 3), located (C,) bool; std_t (C,) m, std_r (C,) deg,
    residual_px (C,), observations (C,), depth (C,) m from the last adjustment (NaN, 0
    where unknown); pairs: the view graph's pairs; tried: pairs tried; checks,
    resections: as BootstrapResult's."""

    R: np.ndarray
    t: np.ndarray
    located: np.ndarray
    std_t: np.ndarray
    std_r: np.ndarray
    residual_px: np.ndarray
    observations: np.ndarray
    depth: np.ndarray
    pairs: int
    tried: int
    checks: tuple[str, ...]
    resections: tuple[str, ...]


def _place(frames: list[Frame], names: Sequence[str], focal: np.ndarray, config: EngineConfig,
           heights: Sequence[float], *, seed: int, say: Progress, stages: dict[str, float]) -> _Placed:
    """Steps 1-5 of the module doc on ``frames``: the cameras of the group the busiest
    pairs reach. Raises BootstrapError when fewer than 2 can be placed."""
    from .optimize import Problem, solve
    from .relocalize import relocalize
    from .resect import EVENT_S, PAIR_SPLIT_DEG, block_witnesses, follow_moved, move_block, resect_unplaced, turned_blocks

    cfg = config.bootstrap
    C = len(names)

    # 1. pairs
    t0 = _time.perf_counter()
    pairs, tried = pair_poses(frames, C, focal, cfg, seed=seed, progress=say)
    stages["pairs"] = _time.perf_counter() - t0
    say(f"pairs: {len(pairs)} of {tried} camera pairs agree on one person's joints")
    if not pairs:
        raise BootstrapError(f"no camera pair saw one person in {cfg.min_pair_frames} frames consistently "
                             f"({tried} pairs tried)")

    # 2. rotations, 3. scales and centres
    t0 = _time.perf_counter()
    ok_tri, bad_tri = triangle_check(pairs, 2 * cfg.rotation_outlier)
    # the pairs the triangles refuse are kept for ``turned_blocks``: where wrong pairs
    # chained a group turned, its right pairs with the rest are the ones refused
    every_pair, pairs = pairs, [p for p, g, b in zip(pairs, ok_tri, bad_tri) if g > 0 or b == 0]
    R, connected, rres = average_rotations(C, pairs, sigma_deg=cfg.rotation_outlier / 2)
    inl = rres <= cfg.rotation_outlier
    good = [p for p, ok in zip(pairs, inl) if ok]
    split = split_cameras(C, pairs, inl, cfg.split_ratio)
    if split.any():
        good = [p for p in good if not (split[p.a] or split[p.b])]
        say("cameras whose pairs disagree on their turn, left to the resection: "
            + ", ".join(names[c] for c in np.flatnonzero(split)))
    good, phantoms = _without_phantom_bridges(C, good, cfg.bridge_spread)
    if phantoms:
        say("bridge pairs whose person changed size as two people would, dropped: "
            + ", ".join(f"{names[p.a]}-{names[p.b]} (spread {p.size_spread:.2f})" for p in phantoms))
    logs, scaled, _ = pair_scales(good, cfg.model_copy(update={"bone_scales": False}))
    blogs, bscaled, n_bones = pair_scales(good, cfg) if cfg.bone_scales else (logs, scaled, 0)
    # The rotations are rooted where the scales are: a hall whose view graph falls apart
    # had its most-seen camera in a part no scale reached, and placed none of its 30
    # cameras (grid30 seed 1, Session 47).
    R, connected, _ = average_rotations(C, good, root=_busiest(C, good, scaled if scaled.any() else bscaled),
                                        sigma_deg=cfg.rotation_outlier / 2)
    # Geometry first, the people's bones last. A bone relation takes the person two pairs
    # see for one, and two walkers of 1.85 and 1.60 m put a group of cameras 15 % off
    # (the HD lab's seed 0: cam_4 and cam_7 1.4 m off, stated 0.013 m; the lab's seed 0 at
    # 110 s: 12 of 19 cameras within the bars, 19 with the group left to the resection).
    # Cameras only bones can place (a corridor: no camera triple, no resection) are placed
    # by them after the resection (``_place_by_bones``).
    t, located = place_cameras(C, R, good, logs, scaled)
    located &= connected
    bones_at = None  # (R, t, located) of the placement with the bones' relations, for after the resection
    bone_links = 0  # the bones' relations the placement took as it is
    if cfg.bone_scales:
        tb, lb = place_cameras(C, R, good, blogs, bscaled)
        lb &= connected
        if located.sum() < 2:  # nothing to place the rest on: the bones' placement as it is
            t, located, bone_links = tb, lb, n_bones
        elif (lb & ~located).any():
            bones_at = (R.copy(), tb, lb)
    stages["graph"] = _time.perf_counter() - t0
    say(f"view graph: {len(good)} pairs after rotation averaging, {int(scaled.sum())} with a scale"
        + (f" ({bone_links} of their relations by the people's bones)" if bone_links else "")
        + f", {int(located.sum())}/{C} cameras placed"
        + (f" ({int((bones_at[2] & ~located).sum())} more by the people's bones, unless the resection places "
           "them)" if bones_at is not None else ""))
    if located.sum() < 2:
        raise BootstrapError("fewer than 2 cameras could be placed: too few pairs share a person")

    # 4. rough metric scale from the pairs' persons
    use = np.array([scaled[k] and located[p.a] and located[p.b] for k, p in enumerate(good)])
    seg = segments(_pair_hypotheses(frames, good, use, R, t), R, t)
    s = _rough_scale(seg, cfg, config.associate.torso_ratio, heights)
    t = t * s
    say(f"rough scale from the persons' bones: {s:.4g} m per unit")

    # 5. bundle adjustment rounds
    t0 = _time.perf_counter()
    std_t = np.full(C, np.nan)
    std_r = np.full(C, np.nan)
    prior = np.diag([np.radians(cfg.prior_std_rotation) ** 2] * 3 + [cfg.prior_std_translation**2] * 3)
    opt = config.optimize.model_copy(update={"max_iterations": max(config.optimize.max_iterations, 100)})
    bones_auto = opt.bones == "auto"
    if bones_auto:  # a scale carried by bones needs them to hold it in the adjustment too
        opt = opt.model_copy(update={"bones": "batch" if bone_links else "off"})
    # not the floor: the bootstrap's first adjustments start from poses the pairs chained,
    # and in the lab (one relation by bones, seed 0 at 110 s) holding its ankles to one
    # plane bent the network (0.012 -> 0.048 m); the final batch of a chain holds it
    opt = opt.model_copy(update={"floor": False})
    rng = np.random.default_rng(seed)
    tried_reloc = False
    check_notes: tuple[str, ...] = ()
    resect_notes: tuple[str, ...] = ()
    residual_px, observations, depth = np.full(C, np.nan), np.zeros(C, np.int64), np.full(C, np.nan)
    rounds = cfg.batch_rounds
    r = 0
    while r < rounds:
        r += 1
        last = r == rounds
        fr = _without(frames, located)
        p = Problem(cycle=r, R=R.copy(), t=t.copy(), prior_R=R.copy(), prior_t=t.copy(),
                    prior_cov=np.repeat(prior[None], C, axis=0), focal=focal, config=opt, frames=tuple(fr),
                    associate=config.associate, gate_px=None, max_hypotheses=cfg.batch_hypotheses,
                    spacing=config.select.min_spacing / 2, seed=int(rng.integers(2**31)), marginals=last,
                    kind="batch", bones_from_start=True)
        sol = solve(p)
        if not sol.ok and not last:
            say(f"bundle adjustment {r}: {sol.reason}")
            continue
        if not sol.ok:  # the last round failed: keep the previous round's poses
            say(f"bundle adjustment {r}: {sol.reason}; the previous estimate is kept")
            break
        R, t = sol.R.copy(), sol.t.copy()
        located &= sol.active  # a camera the adjustment could not constrain is not placed
        say(f"bundle adjustment {r}/{rounds}: {sol.hypotheses} hypotheses, {int(sol.active.sum())} cameras, "
            f"median reprojection {np.median(sol.residual_px) if len(sol.residual_px) else float('nan'):.2f} px"
            + (f", {sol.phantoms} far larger than anyone dropped" if sol.phantoms else ""))
        if last and sol.ok:
            residual_px, observations = sol.residual_cam_px.copy(), sol.obs_per_camera.copy()
            depth = sol.depth_cam.copy()
            for c in np.flatnonzero(sol.active):
                P = sol.cov_shape[c]
                if np.all(np.isfinite(P)):
                    std_t[c], sr = pose_std(P)
                    std_r[c] = np.degrees(sr)
        if last and not tried_reloc:
            tried_reloc = True
            R, t, located, checks = check_bridged(frames, good, R, t, located, focal, config, seed=seed)
            bridged = sum(ch.outcome in ("re-localised", "dropped") for ch in checks)
            check_notes = tuple(f"{names[ch.cam]} {ch.outcome}" + (f" (agrees in {ch.agree}/{ch.frames} frames)"
                                                                   if ch.frames else "") for ch in checks)
            if checks:
                say("cameras reached only over bridge pairs, checked against the others' persons: "
                    + ", ".join(check_notes))
            found = 0
            refused = np.zeros(C, bool)  # located cameras the resection took out
            if cfg.resect:
                # A camera no triangle and no check verified stands on its bridge pairs
                # alone, and two wrong pairs can agree: in a hall of 40 cameras and 4
                # walkers two pairs, each of two people seen one by each camera, turned
                # cam_30 round alike, and the check saw nobody in the view they gave it
                # (docs/bootstrap.md, Session 45). The resection against the others'
                # persons decides where it can; where it cannot, the pairs' pose stays.
                unchecked = np.zeros(C, bool)
                unchecked[[ch.cam for ch in checks if ch.outcome == "unchecked"]] = True
                R_pairs, t_pairs = R, t
                R, t, now_located, resections = resect_unplaced(frames, R, t, located, focal, view_box(frames, C),
                                                                config.associate, cfg, seed=seed, provisional=unchecked)
                moved = [f"{names[r.cam]} {np.linalg.norm(t[r.cam] - t_pairs[r.cam]):.2f} m / "
                         f"{rotation_angle_deg(R[r.cam], R_pairs[r.cam]):.1f}°"
                         for r in resections if r.accepted and unchecked[r.cam]]
                refused = located & ~now_located
                found = int(now_located.sum() - located.sum()) + len(moved)
                located = now_located
                kept = unchecked & now_located
                resect_notes = tuple(r.summary(names[r.cam], names)
                                     + ("; kept where its bridge pairs put it" if kept[r.cam] and not r.accepted else "")
                                     for r in resections)
                if resections:
                    say("cameras not placed or only over unchecked bridge pairs, resected against the others' persons: "
                        + "; ".join(resect_notes))
                if moved:
                    say("moved from where their bridge pairs put them: " + ", ".join(moved))
                for _ in range(3):
                    witnessed = block_witnesses(pairs, R, located, cfg)
                    far: list[int] = []
                    if witnessed.any():
                        R1, t1, _, again = resect_unplaced(frames, R, t, located, focal, view_box(frames, C),
                                                           config.associate, cfg, seed=seed, provisional=witnessed)
                        # a camera the resection puts about where it was keeps the adjustment's pose
                        far = [r.cam for r in again if r.accepted and witnessed[r.cam]
                               and rotation_angle_deg(R1[r.cam], R[r.cam]) > PAIR_SPLIT_DEG]
                    if far:
                        block = ("pairs that turn a group of cameras alike; resected against the others' persons, "
                                 "moved: " + ", ".join(f"{names[c]} {np.linalg.norm(t1[c] - t[c]):.2f} m / "
                                                       f"{rotation_angle_deg(R1[c], R[c]):.1f}°" for c in far))
                        say(block)
                        resect_notes += (block,)
                        before = {c: (R[c].copy(), t[c].copy()) for c in far}
                        for c in far:
                            R[c], t[c] = R1[c], t1[c]
                        found += len(far)
                        rest = follow_moved(pairs, R, t, located, before)
                        if rest:
                            block = ("moved with them, as their pairs hold them together: "
                                     + ", ".join(names[c] for c in rest))
                            say(block)
                            resect_notes += (block,)
                            found += len(rest)
                        continue
                    # no camera witnesses it: a group each of whose cameras its own pairs
                    # hold, turned as one, found by the pairs across its border
                    for group, cut, turn in turned_blocks(every_pair, R, located):
                        mv = move_block(frames, R, t, located, group, turn, focal, config.associate, cfg, seed=seed)
                        if mv is not None and mv.accepted:
                            break
                    else:
                        break
                    block = (f"a group of cameras turned as one against the others (the pairs across its border "
                             f"{', '.join(f'{names[p.a]}-{names[p.b]}' for p in cut)} wrong): moved "
                             f"{rotation_angle_deg(mv.Q, np.eye(3)):.0f}°, its cameras agree with the others' "
                             f"persons in {mv.windows} windows of {EVENT_S:g} s ({mv.held_windows} before): "
                             + ", ".join(names[c] for c in np.flatnonzero(group)))
                    say(block)
                    resect_notes += (block,)
                    for c in np.flatnonzero(group):
                        R[c], t[c] = mv.Q @ R[c], mv.Q @ t[c] + mv.d
                    found += int(group.sum())
            else:
                for c in np.flatnonzero(~located):
                    rl = relocalize(frames, int(c), R, t, float(focal[c]), config.associate,
                                    reprojection_px=config.associate.relocalize_px, seed=seed)
                    if rl is not None:
                        R[c], t[c], located[c] = rl.R, rl.t, True
                        found += 1
                if found:
                    say(f"re-localised {found} camera(s) by PnP")
            added = np.zeros(C, bool)
            if bones_at is not None:
                # not a camera whose pairs' pose the persons in its view refused: the bones
                # place it by the same pairs
                R, t, added = _place_by_bones(R, t, located, bones_at[0], bones_at[1], bones_at[2] & ~refused)
            if added.any():
                located |= added
                if bones_auto:
                    opt = opt.model_copy(update={"bones": "batch"})
                say("placed by the people's bones (no camera triple and no resection placed them): "
                    + ", ".join(names[c] for c in np.flatnonzero(added)) + f"; {cfg.batch_rounds} more bundle adjustments")
                rounds += cfg.batch_rounds
            elif found or bridged:
                say("one more bundle adjustment")
                rounds += 1
    stages["bundle"] = _time.perf_counter() - t0
    return _Placed(R, t, located, std_t, std_r, residual_px, observations, depth, len(good), tried, check_notes,
                   resect_notes)


def _on_floor(frames: Sequence[Frame], g: _Placed, names: Sequence[str], config: EngineConfig,
              heights: Sequence[float], say: Progress) -> tuple[_Placed, ScaleEstimate | None, str, FloorFrame]:
    """Step 6 of the module doc: ``g`` in metres by its people and in the frame of their
    floor; with the scale, the frame's note and its definition."""
    cfg = config.bootstrap
    R, t, std_t, depth, located = g.R, g.t, g.std_t, g.depth, g.located
    scale, seg = measure_scale(frames, R, t, config.associate, cfg, heights=heights, cameras=located)
    if scale is not None:
        t = t * scale.factor
        std_t = std_t * scale.factor
        depth = depth * scale.factor
        seg = Segments(seg.time, seg.com * scale.factor, seg.shank * scale.factor, seg.thigh * scale.factor,
                       seg.torso * scale.factor, seg.ankles * scale.factor, seg.up * scale.factor)
        say(scale.summary())
    else:
        say("no person measured well enough for the scale: the rough scale is kept")
    mean_h = float(np.mean(scale.heights)) if scale else cfg.height_mean
    F, o, note, spec = floor_frame(seg, t, located, mean_h, names, config.optimize.floor_sigma)
    R = np.einsum("ij,cjk->cik", F, R)
    t = (t - o) @ F.T
    return replace(g, R=R, t=t, std_t=std_t, depth=depth), scale, note, spec


def _join_groups(frames: list[Frame], g: _Placed, floor: tuple[ScaleEstimate | None, str, FloorFrame],
                 names: Sequence[str], focal: np.ndarray, config: EngineConfig, heights: Sequence[float], *,
                 seed: int, say: Progress) -> tuple[_Placed, ScaleEstimate | None, str, FloorFrame, list[str]]:
    """The cameras ``g`` left unplaced, bootstrapped on their own and joined to it by the
    persons each group sees of the other's (``backend.groups``), as long as a group of
    >= 2 is placed and joined; then put on their floor again. Returns ``g`` (as given when
    nothing joined) with its floor and a note per group tried."""
    from .groups import contradicted, join

    cfg = config.bootstrap
    scale, note, spec = floor
    notes: list[str] = []
    attempted: list[np.ndarray] = []
    box = view_box(frames, len(names))  # where each camera's detections lie: the same frames every round
    while (rest := ~g.located).sum() >= 2 and not any((rest == r).all() for r in attempted):
        attempted.append(rest)
        part = _without(frames, rest)
        if len(part) < cfg.min_pair_frames:
            break
        names_rest = ", ".join(names[c] for c in np.flatnonzero(rest))
        say(f"not placed: {names_rest}; bootstrapped on their own, to be joined by the persons each group sees "
            "of the other's")
        try:
            h = _place(part, names, focal, config, heights, seed=seed, say=lambda m: say("  " + m), stages={})
            h, _, _, _ = _on_floor(part, h, names, config, heights, lambda m: say("  " + m))
        except BootstrapError as e:
            notes.append(f"{names_rest}: not placed on their own ({e})")
            say(notes[-1])
            break
        group = h.located & rest
        j = join(frames, (g.R, g.t, g.located), (h.R, h.t, group), focal, box, config.associate, cfg, seed=seed)
        notes.append(f"{', '.join(names[c] for c in np.flatnonzero(group))}: {j.summary()}")
        say(notes[-1])
        if not j.accepted:
            break
        # No adjustment of the groups together: its association, over cameras on both sides
        # of a wall, joins a person in one room to another behind the wall where their
        # images happen to line up. Measured (two rooms, four walkers, 90 s): each group's
        # own adjustment and the join 0.016 m / 0.42° (shape), three adjustments together
        # from there 0.17 m / 2.0°, and from the true poses too (0.16 m). The online
        # pipeline's depth gates and the final batch take it from here.
        Rg, tg = np.einsum("ij,cjk->cik", j.Q, h.R), j.s * h.t @ j.Q.T + j.d  # the group in the placed frame
        bad = contradicted(frames, np.where(group[:, None, None], Rg, g.R), np.where(group[:, None], tg, g.t),
                           g.located | group, group, focal, box, config.associate, cfg)
        if bad:
            notes.append("left out of the join, the others' persons in their view contradict them: "
                         + ", ".join(f"{names[c]} (agrees in {n} of {k} frames)" for c, (n, k) in bad.items()))
            say(notes[-1])
            group = group.copy()
            group[list(bad)] = False

        def put(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # a, with the joined cameras' rows of b
            return np.where(group.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)

        joined = _Placed(put(g.R, Rg), put(g.t, tg), g.located | group, put(g.std_t, j.s * h.std_t),
                         put(g.std_r, h.std_r), put(g.residual_px, h.residual_px), put(g.observations, h.observations),
                         put(g.depth, j.s * h.depth), g.pairs + h.pairs, g.tried, g.checks + h.checks,
                         g.resections + h.resections)
        try:
            g, scale, note, spec = _on_floor(frames, joined, names, config, heights, say)
        except BootstrapError as e:  # the placed group keeps the floor it had
            notes.append(f"the joined groups found no floor ({e}): the group is left out")
            say(notes[-1])
            break
    return g, scale, note, spec, notes


def mistimed_summary(timed: Mapping[str, float]) -> str:
    """A line for a result's header: how the bootstrap timed the sensors whose stamps ran
    apart (``BootstrapResult.mistimed``: name -> shift, s); "" for none."""
    if not timed:
        return ""
    return ("bootstrap: sensors whose stamps ran apart from the others' as they arrived, timed by what their "
            "pairs agree on: " + ", ".join(f"{n} {f'{1000 * v:+.0f} ms (its clock)' if v else 'as stamped (its delay)'}"
                                           for n, v in sorted(timed.items(), key=lambda kv: natural_key(kv[0]))))


def stamps_apart(stamps: StampWatch, config: EngineConfig, cameras: int) -> dict[str, float]:
    """Sensors whose stamps run more than ``clock.auto_lead`` apart from the others' as
    they arrive (name -> median lead, s), as the pipeline's ``clock.estimate = "auto"``
    finds them; empty when the clocks are not estimated (``clock.estimate = false``: the
    user vouches for them) or when they are half of the ``cameras`` or more (then the
    others' stamps are no reference). The bootstrap times them (``_timed``)."""
    if config.clock.estimate is False:
        return {}
    far = {n: v for n, v in stamps.leads().items() if abs(v) > config.clock.auto_lead}
    return far if 2 * len(far) < cameras else {}


def bootstrap_messages(intrinsics: Mapping[str, Intrinsics], config: EngineConfig, messages: Iterable[KeypointMessage],
                       *, heights: Sequence[float] = (), seed: int = 0, progress: Progress | None = None
                       ) -> BootstrapResult:
    """``bootstrap`` on the first ``bootstrap.max_seconds`` of ``messages`` (all of them
    when 0), for the cameras of ``intrinsics`` in their natural order. Raises
    BootstrapError as ``bootstrap``."""
    names = tuple(sorted(intrinsics, key=natural_key))
    config = config.for_images(i.resolution for i in intrinsics.values())
    stamps = StampWatch(config.clock.auto_lead)
    frames = collect_frames(names, intrinsics, config, messages, max_seconds=config.bootstrap.max_seconds,
                            progress=progress, stamps=stamps)
    focal = np.array([0.5 * (intrinsics[n].fx + intrinsics[n].fy) for n in names])
    return bootstrap(frames, names, focal, config, heights=heights, seed=seed, progress=progress,
                     mistimed=stamps_apart(stamps, config, len(names)))
