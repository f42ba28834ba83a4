"""Placing a camera without a pose by resection against the persons the placed cameras see.

The bootstrap places cameras through pairs: frames in which two cameras each see one
person, the same one. A camera that sees people mostly while another person is in the
room, or whose partners are themselves unplaced, gets too few such frames and is left
out. The placed network does not need pairs: wherever two placed cameras see a person
in the same frameset, the association (``backend.associate``, on the placed cameras'
poses) triangulates it. A camera without a pose that sees people in those framesets has
2D-3D correspondences, 17 joints per person, but with two persons in the room it is not
known which of its detections is which person (or whether it sees a person the network
sees at all).

So the pose decides: RANSAC over candidate correspondences (every detection of the camera
with every triangulated person of its frameset), each model from one candidate's joints
(PnP), scored by the frames it explains (a frame agrees when one of its detections lies
within ``resect_px`` of one of the persons' projection, median over joints). The best
model is refined on the agreeing frames (the matching person of each), and the frames
classified again. Because every frame picks its person by the pose, two walkers mixed in
some frames do not mix the pose (the failure of weak pairs, docs/bootstrap.md).

A pose is accepted only when the evidence is broad and consistent (``BootstrapConfig``):
at least ``resect_min_frames`` agreeing frames; among the frames in which the pose puts a
triangulated person in the camera's view (where its detections lie, ``view_box``) while it
sees somebody, at least ``resect_min_share`` agree; the agreeing persons spread over the
room (``resect_min_spread`` m: not one spot, where a pose is poorly determined); and no
clearly different pose explains nearly as many frames (``resect_ambiguity``).

Synchronous numeric core; OpenCV imported lazily.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from .associate import Associator
from .config import AssociateConfig, BootstrapConfig, OptimizeConfig
from .floor import ANKLES, MIN_POINTS, Floor, floor_of_persons
from .geometry import project_so3, rotation_angle_deg, triangulate_views
from .preprocess import Detection

Frame = tuple[float, tuple[tuple[Detection, ...], ...]]
_FLOOR_SIGMA = OptimizeConfig.model_fields["floor_sigma"].default  # m: a lower ankle's height about the floor


@dataclass(frozen=True)
class Persons:
    """The persons the placed cameras triangulate, per frame.

    X: (N, 17, 3) float64 joints in the world (NaN = not triangulated); frame: (N,) int
    index of the frame; com: (N, 3) float64 torso centres.
    """

    X: np.ndarray
    frame: np.ndarray
    com: np.ndarray

    def __post_init__(self) -> None:
        N = len(self.frame)
        assert self.X.shape == (N, 17, 3) and self.com.shape == (N, 3)


def triangulate_persons(frames: Sequence[Frame], R: np.ndarray, t: np.ndarray, placed: np.ndarray,
                        cfg: AssociateConfig) -> Persons:
    """Every person hypothesis of the placed cameras (``placed`` (C,) bool) in each frame,
    triangulated with the poses R (C, 3, 3), t (C, 3)."""
    assoc = Associator(cfg)
    Xs, fis, coms = [], [], []
    for fi, (time_, views) in enumerate(frames):
        vs = [v for v in views if placed[v[0].cam]]
        if len(vs) < 2:
            continue
        for h in assoc(time_, vs, R, t, None):
            X, n = triangulate_views(R, t, h.cams, h.xy)
            if np.sum(np.all(np.isfinite(X), axis=1)) < 6:
                continue
            Xs.append(X)
            fis.append(fi)
            coms.append(h.com)
    if not Xs:
        return Persons(np.zeros((0, 17, 3)), np.zeros(0, np.int64), np.zeros((0, 3)))
    return Persons(np.stack(Xs), np.array(fis, np.int64), np.stack(coms))


@dataclass(frozen=True)
class Resection:
    """The outcome of resecting one camera.

    R: (3, 3) world_R_cam and t: (3,) centre (None when no pose was found); frames:
    agreeing frames; seen: frames in which the pose puts a person in the camera's view
    while it sees somebody; spread: m, the agreeing persons' spread over the floor
    (second principal std of their torso centres); rival: agreeing frames of the best
    clearly different pose; residual_px: median reprojection error of the agreeing
    joints; cov: (6, 6) covariance of (rotation rad, centre m) in the world frame from
    the refinement (per-frame residual blocks, so correlated joints of one detection do
    not count as independent), None without a pose; accepted and reason: the guards'
    verdict. paired: the placed camera whose pair placed it (``place_by_pair``; -1: resected),
    scaled_by: what gave that pair's baseline its length ("floor" or "bones"); its cov is
    then the pair's stated std (``PAIR_TURN_STD_DEG``, ``PAIR_LENGTH_STD``), not a fit's,
    seen and candidates the frames in which each sees one person, spread NaN.
    """

    cam: int
    R: np.ndarray | None
    t: np.ndarray | None
    frames: int
    seen: int
    candidates: int
    spread: float
    rival: int
    residual_px: float
    cov: np.ndarray | None
    accepted: bool
    reason: str
    paired: int = -1
    scaled_by: str = ""
    third: tuple[int, ...] = ()  # the cameras whose pairs refused its pair (``place_by_pair``, ``resect_unplaced``)
    held: int = -1  # agreeing frames of the pose it had (``resect(at=)``), -1: none given

    def summary(self, name: str, names: Sequence[str] = ()) -> str:
        third = ", ".join(names[k] if len(names) > k else f"camera {k}" for k in self.third)
        why = "" if self.accepted else f" ({self.reason}" + (f": {third}" if third else "") + ")"
        if self.R is None:
            return f"{name} not {'placed' if self.paired >= 0 else 'resected'}{why}"
        if self.paired >= 0:
            other = names[self.paired] if len(names) > self.paired else f"camera {self.paired}"
            return (f"{name} {'' if self.accepted else 'not '}placed by its pair with {other}: agrees in "
                    f"{self.frames}/{self.seen} frames in which each sees one person, {self.residual_px:.1f} px, "
                    f"{SCALED_BY[self.scaled_by]}{why}")
        return (f"{name} {'resected' if self.accepted else 'not resected'}: agrees in {self.frames}/{self.seen} frames "
                f"({self.candidates} with candidates), spread {self.spread:.2f} m, rival pose {self.rival} frames, "
                f"{self.residual_px:.1f} px{why}")


def _project(X: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) world points → (..., 2) normalised coordinates and (...,) depth."""
    Xc = (X - t) @ R
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = Xc[..., :2] / z[..., None]
    return u, z


def _frame_errors(P: np.ndarray, x: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K,) median reprojection error (normalised) of candidates: persons P (K, 17, 3)
    against detections x (K, 17, 2); inf where fewer than 6 joints are in front."""
    u, z = _project(P, R, t)
    e = np.linalg.norm(u - x, axis=-1)
    ok = np.isfinite(e) & (z > 0.1)
    enough = ok.sum(1) >= 6
    med = np.full(len(e), np.inf)
    if enough.any():
        with warnings.catch_warnings():  # rows of NaN are not possible here, but stay quiet
            warnings.simplefilter("ignore", RuntimeWarning)
            med[enough] = np.nanmedian(np.where(ok[enough], e[enough], np.nan), axis=1)
    return med


def _pnp(X: np.ndarray, x: np.ndarray, R0: np.ndarray | None = None, t0: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray] | None:
    """world_R_cam, centre from world points X (N, 3) and normalised points x (N, 2)."""
    import cv2

    ok = np.all(np.isfinite(X), 1) & np.all(np.isfinite(x), 1)
    X, x = X[ok].astype(np.float64), x[ok].astype(np.float64)
    if len(X) < 6:
        return None
    try:
        if R0 is None:
            good, rvec, tvec = cv2.solvePnP(X, x, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        else:
            Rcw = R0.T
            rvec0, _ = cv2.Rodrigues(Rcw)
            tvec0 = (-Rcw @ t0).reshape(3, 1)
            good, rvec, tvec = cv2.solvePnP(X, x, np.eye(3), None, rvec0, tvec0, useExtrinsicGuess=True,
                                            flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not good:
        return None
    Rcw, _ = cv2.Rodrigues(rvec)
    return Rcw.T, (-Rcw.T @ np.asarray(tvec).ravel())


def _covariance(X: np.ndarray, x: np.ndarray, frame: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of (world rotation rad, centre m) of the pose R, t fitted to X
    (N, 3), x (N, 2), from the Jacobian of the reprojection residuals, with the noise
    level of the residuals and the residuals of one frame (one detection) taken as one
    correlated block: the sandwich estimate over frames, so 17 joints of one detection
    are not 17 independent measurements."""
    from .geometry import so3_exp

    def resid(p):
        Rp = so3_exp(p[:3]) @ R
        tp = t + p[3:]
        u, _ = _project(X, Rp, tp)
        return (u - x)

    eps = 1e-6
    r0 = resid(np.zeros(6))
    J = np.zeros((len(X), 2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        J[:, :, k] = (resid(d) - r0) / eps
    J = J.reshape(-1, 6)
    r = r0.reshape(-1)
    fr = np.repeat(frame, 2)
    H = J.T @ J
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
    meat = np.zeros((6, 6))
    for f in np.unique(fr):
        g = J[fr == f].T @ r[fr == f]
        meat += np.outer(g, g)
    return Hi @ meat @ Hi


@dataclass(frozen=True)
class Candidates:
    """What one camera could see of the persons others triangulate: every (person,
    detection) of one frame with >= 6 joints in both. P: (K, 17, 3) the persons' joints;
    x: (K, 17, 2) the detections (normalised); frame: (K,) frame index; detections: the
    camera's detections per frame index (all, candidates or not)."""

    P: np.ndarray
    x: np.ndarray
    frame: np.ndarray
    detections: Mapping[int, list[np.ndarray]]

    def __post_init__(self) -> None:
        K = len(self.frame)
        assert self.P.shape == (K, 17, 3) and self.x.shape == (K, 17, 2)

    @property
    def frames(self) -> int:
        """Frames with a candidate."""
        return len(np.unique(self.frame))

    @functools.cached_property
    def _inv(self) -> np.ndarray:
        return np.unique(self.frame, return_inverse=True)[1]

    def agreeing(self, R: np.ndarray, t: np.ndarray, tol: float) -> tuple[int, np.ndarray]:
        """(frames in which the camera at R (3, 3), t (3,) sees one of the persons within
        ``tol`` (normalised, the joints' median), each such frame's best candidate)."""
        if not len(self.frame):
            return 0, np.zeros(0, np.int64)
        inv = self._inv
        e = _frame_errors(self.P, self.x, R, t)
        order = np.lexsort((e, inv))  # by frame, then error: each frame's best candidate first
        first = np.r_[True, inv[order][1:] != inv[order][:-1]]
        arg = order[first]
        agree = e[arg] < tol
        return int(agree.sum()), arg[agree]

    def in_view(self, persons: Persons, R: np.ndarray, t: np.ndarray, box: np.ndarray) -> int:
        """Frames in which the camera at R (3, 3), t (3,) has one of ``persons`` in its
        view (half its joints in front and inside ``box`` (2, 2), where its detections
        lie) while it sees somebody."""
        u, z = _project(persons.X, R, t)
        inside = (z > 0.1) & np.all((u >= box[0]) & (u <= box[1]), axis=-1)
        in_view = np.mean(inside, axis=1) >= 0.5
        return len(set(persons.frame[in_view].tolist()) & set(self.detections))


def candidates(frames: Sequence[Frame], persons: Persons, cam: int) -> Candidates:
    """Camera ``cam``'s candidates against ``persons`` (triangulated in ``frames``)."""
    cand_P, cand_x, cand_f = [], [], []
    dets_by_frame: dict[int, list[np.ndarray]] = {}
    for fi, (_, views) in enumerate(frames):
        mine = [d.xy for v in views for d in v if d.cam == cam]
        if mine:
            dets_by_frame[fi] = mine
    for k in range(len(persons.frame)):
        fi = int(persons.frame[k])
        for xy in dets_by_frame.get(fi, ()):
            ok = np.all(np.isfinite(persons.X[k]), 1) & np.all(np.isfinite(xy), 1)
            if ok.sum() >= 6:
                cand_P.append(persons.X[k])
                cand_x.append(xy)
                cand_f.append(fi)
    if not cand_f:
        return Candidates(np.zeros((0, 17, 3)), np.zeros((0, 17, 2)), np.zeros(0, np.int64), dets_by_frame)
    return Candidates(np.stack(cand_P), np.stack(cand_x), np.array(cand_f, np.int64), dets_by_frame)


def resect(frames: Sequence[Frame], persons: Persons, cam: int, focal: float, box: np.ndarray,
           cfg: BootstrapConfig, *, seed: int = 0, iterations: int = 200,
           at: tuple[np.ndarray, np.ndarray] | None = None, cands: Candidates | None = None) -> Resection:
    """The pose of camera ``cam`` from the persons the placed cameras triangulate
    (``triangulate_persons``) and its own detections in the same frames; ``box`` (2, 2):
    where its detections lie in its image (``bootstrap.view_box``); ``at``: a pose it has
    (R (3, 3), t (3,)) whose agreeing frames are counted too (``Resection.held``);
    ``cands``: its ``candidates`` against ``persons``, when the caller has them. See the
    module doc."""
    tol = cfg.resect_px / focal
    cands = candidates(frames, persons, cam) if cands is None else cands
    nf = cands.frames

    def empty(reason: str) -> Resection:
        return Resection(cam, None, None, 0, 0, nf, 0.0, 0, float("nan"), None, False, reason)

    if nf < cfg.resect_min_frames:
        return empty(f"{nf} frames with candidates, {cfg.resect_min_frames} needed")
    P, x = cands.P, cands.x

    def score(R, t):
        return cands.agreeing(R, t, tol)

    rng = np.random.default_rng(seed)
    models = []  # (agreeing frames, R, t)
    for k in rng.choice(len(P), size=min(iterations, len(P)), replace=False):
        m = _pnp(P[k], x[k])
        if m is None:
            continue
        n, _ = score(*m)
        models.append((n, m[0], m[1]))
    if not models:
        return empty("no PnP model")
    models.sort(key=lambda m: -m[0])

    def refine(R, t):
        for _round in range(4):
            n, sel = score(R, t)
            if n < 2:
                break
            m = _pnp(P[sel].reshape(-1, 3), x[sel].reshape(-1, 2), R, t)
            if m is None:
                break
            R, t = m
        return R, t

    def different(Ra, ta, Rb, tb):
        return rotation_angle_deg(Ra, Rb) > 10.0 or np.linalg.norm(ta - tb) > 0.5

    R, t = refine(models[0][1], models[0][2])
    n, sel = score(R, t)
    # the best clearly different pose after its own refinement (a single detection's PnP
    # can be far from the pose its frames then refine to: that is no rival)
    rival, tries = 0, 0
    for nm, Rm, tm in models:
        if nm <= rival or tries >= 3:
            break
        if not different(Rm, tm, R, t):
            continue
        tries += 1
        Rm, tm = refine(Rm, tm)
        if different(Rm, tm, R, t):
            rival = max(rival, score(Rm, tm)[0])
    seen = max(cands.in_view(persons, R, t, box), n)
    coms = np.nanmean(P[sel], axis=1) if len(sel) else np.zeros((0, 3))
    spread = 0.0
    if len(coms) >= 3:
        sv = np.linalg.svd(coms - coms.mean(0), compute_uv=False) / np.sqrt(len(coms))
        spread = float(sv[1])
    e = np.linalg.norm(_project(P[sel], R, t)[0] - x[sel], axis=-1) if len(sel) else np.zeros((0, 17))
    res_px = float(np.nanmedian(e) * focal) if np.isfinite(e).any() else float("nan")
    Xs, xs = P[sel].reshape(-1, 3), x[sel].reshape(-1, 2)
    fs = np.repeat(np.arange(len(sel)), 17)
    ok = np.all(np.isfinite(Xs), 1) & np.all(np.isfinite(xs), 1)
    ok[ok] &= np.linalg.norm(_project(Xs[ok], R, t)[0] - xs[ok], axis=1) < 3 * tol
    cov = _covariance(Xs[ok], xs[ok], fs[ok], R, t) if ok.sum() >= 12 else None
    reasons = []
    if n < cfg.resect_min_frames:
        reasons.append(f"{n} agreeing frames, {cfg.resect_min_frames} needed")
    if n < cfg.resect_min_share * seen:
        reasons.append(f"agrees in {n} of {seen} frames with a person in view, {cfg.resect_min_share:.0%} needed")
    if spread < cfg.resect_min_spread:
        reasons.append(f"the persons it agrees with spread {spread:.2f} m, {cfg.resect_min_spread:g} m needed")
    if rival > cfg.resect_ambiguity * n:
        reasons.append(f"a different pose agrees in {rival} frames")
    held = score(*at)[0] if at is not None else -1
    return Resection(cam, R, t, n, seen, nf, spread, rival, res_px, cov, not reasons, "; ".join(reasons), held=held)


def resect_unplaced(frames: Sequence[Frame], R: np.ndarray, t: np.ndarray, located: np.ndarray, focal: np.ndarray,
                    boxes: np.ndarray, assoc: AssociateConfig, cfg: BootstrapConfig, *, seed: int = 0,
                    pairs: bool = False, floor_frames: Sequence[Frame] = (), provisional: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Resection]]:
    """Resect the cameras not ``located`` (C,) bool, one at a time, best evidence first:
    a camera placed joins the network the next ones are resected against (a room that
    two placed cameras see rarely is reached through the first camera placed in it).
    ``pairs``: a camera the resection does not place may be placed by its pair with a
    placed camera (``place_by_pair``), its baseline's length from the floor of the persons
    the located cameras triangulate in ``frames`` and ``floor_frames`` (more of the
    network's framesets: ``frames`` may hold only those in which the camera sees
    somebody). The cameras placed by pairs must hold together: when a camera outside the
    network given (placed here or not) has a pair with one placed here and a pair, about
    as strong, with the network that turn it apart (``_apart``), every camera placed from
    the first pair placement on is taken back (a wrong pair turns its camera round, and
    the cameras chained to it with it, docs/bootstrap.md, Session 44), and the pass runs
    again without pairs (the cameras the persons place alone stay). ``provisional``
    (C,) bool: located cameras nothing verified (reached over pairs that no triangle and
    no check confirmed): resected as if not located, against the others' persons only,
    and kept where they were where the resection does not place them, unless the persons
    in their view agree with another pose (in ``resect_min_frames`` frames) and with
    theirs in fewer: then not placed. Returns copies of
    (R (C, 3, 3), t (C, 3), located (C,)) and each camera's last Resection."""
    keep = np.zeros_like(located) if provisional is None else provisional & located
    R, t, located = R.copy(), t.copy(), located & ~keep
    R0, t0, placed0 = R.copy(), t.copy(), located.copy()
    last: dict[int, Resection] = {}
    first: Persons | None = None  # the persons of the cameras located from the start

    @functools.cache
    def pairs_of(c: int) -> tuple:
        """Camera c's pairs with every camera (placed or not: they do not depend on the poses)."""
        return tuple(camera_pairs(frames, c, focal, cfg, seed=seed))

    @functools.cache
    def floor() -> Floor | None:
        """The located cameras' floor, fitted once, when a pair needs it."""
        more = (triangulate_persons(floor_frames, R0, t0, placed0, assoc).X if len(floor_frames)
                else np.zeros((0, 17, 3)))
        return floor_of_persons(np.concatenate([first.X, more]), _FLOOR_SIGMA)

    def place(use_pairs: bool) -> list[int]:
        """Resect (and with ``use_pairs`` pair) the cameras not located into R, t,
        located, best evidence first; the cameras placed, in turn."""
        nonlocal first
        placed: list[int] = []
        while True:
            todo = [int(c) for c in np.flatnonzero(~located)]
            if not todo or located.sum() < 2:
                break
            persons = triangulate_persons(frames, R, t, located, assoc)
            if first is None:
                first = persons
            found = [resect(frames, persons, c, float(focal[c]), boxes[c], cfg, seed=seed + c,
                            at=(R0[c], t0[c]) if keep[c] else None) for c in todo]
            if use_pairs:
                # the network's bones from the cameras located from the start: the ones placed
                # by pairs since then triangulate with their pair's std, which shows in the bones
                found = [r if r.accepted else (place_by_pair(frames, first, r.cam, R, t, located, focal, cfg, seed=seed,
                                                             network_floor=floor, pairs_of=pairs_of) or r)
                         for r in found]
            for r in found:
                last[r.cam] = r
            ok = [r for r in found if r.accepted]
            if not ok:
                break
            best = max(ok, key=lambda r: r.frames)
            R[best.cam], t[best.cam], located[best.cam] = best.R, best.t, True
            placed.append(best.cam)
        return placed

    order = place(pairs)
    start = next((k for k, c in enumerate(order) if last[c].paired >= 0), None)  # the first pair placement
    split = _apart(set(order[start:]), R, located, placed0, pairs_of, cfg) if start is not None else []
    if split:
        for c in order[start:]:
            R[c], t[c], located[c] = R0[c], t0[c], False
            last[c] = replace(last[c], accepted=False, third=tuple(split),
                              reason="taken back: the cameras placed by pairs do not hold together, the pairs of these "
                                     "with the cameras placed turn them apart")
        # Again without pairs: a camera resected after the first pair placement may
        # have leant on it, but one the persons place without it stands on its own (a
        # hall of 40 took back 12 cameras that agreed with them in 125-356 frames,
        # spread 1-3 m, for two pairs that disagreed: docs/bootstrap.md, Session 49)
        taken_back = {c: last[c] for c in order[start:]}
        placed_again = set(place(False))
        last.update({c: r for c, r in taken_back.items() if c not in placed_again})
    for c in map(int, np.flatnonzero(keep & ~located)):  # not resected: where their pairs put them (R0, t0)
        r = last.get(c)
        if (r is not None and r.R is not None and r.frames >= cfg.resect_min_frames
                and r.held < r.frames and rotation_angle_deg(r.R, R0[c]) > PAIR_SPLIT_DEG):
            # the persons in its view agree with another pose more than with its pairs':
            # nothing verified those, and a wrong pair's pose, which sees nobody where it
            # looks (a camera seen little), or sees a walker or two at one spot, is what
            # such data leave. Not placed now, the late join decides on more data: a hall
            # of 40 kept cam_24 11.7 m / 15° off, its pose agreeing in 17 frames, another
            # in 26 (docs/bootstrap.md, Session 49)
            last[c] = replace(r, reason=f"{r.reason}; the pose its pairs gave agrees in {r.held} frames: not placed")
            continue
        located[c] = True
    return R, t, located, [last[c] for c in sorted(last)]


def _apart(new: set[int], R: np.ndarray, located: np.ndarray, network: np.ndarray,
           pairs_of: Callable[[int], Sequence], cfg: BootstrapConfig) -> list[int]:
    """The cameras outside the ``network`` (C,) bool, placed or not, whose best pair with a
    camera ``new`` and whose best pair with the network, about as strong (``split_ratio``),
    turn them more than PAIR_SPLIT_DEG apart (``resect_unplaced``)."""
    out = []
    for c in map(int, np.flatnonzero(~network)):
        ps = [p for p in pairs_of(c) if located[_partner(p, c)]]
        a = max((p for p in ps if _partner(p, c) in new), key=lambda p: len(p.frames), default=None)
        b = max((p for p in ps if network[_partner(p, c)]), key=lambda p: len(p.frames), default=None)
        if a is None or b is None:
            continue
        fa, fb = len(a.frames), len(b.frames)
        if min(fa, fb) >= cfg.split_ratio * max(fa, fb) and rotation_angle_deg(_turn(a, c, R),
                                                                               _turn(b, c, R)) > PAIR_SPLIT_DEG:
            out.append(c)
    return out


SCALED_BY = {"floor": "its baseline's length from the floor both sides' people stand on",
             "bones": "its baseline's length from the people's bones"}
PAIR_SCALES_AGREE = 0.2  # the floor's and the bones' scale of a pair: further apart, its geometry is wrong
# A pair-placed camera's std: its turn and its baseline's direction from a pair are good to
# 0.1-1.5 degrees (docs/bootstrap.md, Method 1; 1.1-1.3 in tests/backend/test_resect.py);
# its baseline's length to a few per cent from the floor (ankles are not all at one height
# above it), to some ten from the bones (people differ in size)
PAIR_TURN_STD_DEG = 1.5
PAIR_SPLIT_DEG = 10.0  # two pairs that turn the camera further apart disagree (2x the bootstrap's rotation_outlier)
PAIR_LENGTH_STD = {"floor": 0.03, "bones": 0.10}
FLOOR_REACH_M = 2.0  # m along the floor: where the network's people walked, its floor is known


def place_by_pair(frames: Sequence[Frame], persons: Persons, cam: int, R: np.ndarray, t: np.ndarray,
                  located: np.ndarray, focal: np.ndarray, cfg: BootstrapConfig, *, seed: int = 0,
                  network_floor: Callable[[], Floor | None] | None = None,
                  pairs_of: Callable[[int], Sequence] | None = None) -> Resection | None:
    """Camera ``cam`` placed by its relative pose to a placed camera, or None (or a
    refused Resection that says why, when a third camera's pairs decided).
    ``network_floor``: gives the network's floor when a pair is found (else it is fitted
    to ``persons``, the placed cameras' in ``frames``); ``pairs_of``: a camera's pairs
    (``camera_pairs``; a caller placing several cameras keeps them).

    A resection needs persons that two placed cameras triangulate in the camera's view. At
    the end of a camera chain (a corridor) only its one neighbour sees where it sees, so
    only a pair can place it: found as the bootstrap finds its pairs (``pair_poses``, with
    its guards, on every frame given; the bootstrap's pairs had only its first
    ``max_seconds``), and as a bridge of the view graph it must keep one person's size
    (``bridge_spread``). The pair fixes the camera's turn and the direction of its
    baseline; the baseline's length is where the pair's people stand on the floor the
    placed network's people stand on (the lower ankles of both on one plane: camera
    heights, not people's sizes). Without a floor on both sides, the people's bones give
    it (the same people walk past the pair and the network; walkers of different sizes
    make that a few per cent off). With both, they must agree within PAIR_SCALES_AGREE,
    and the bones must agree among themselves as the bootstrap's bone relations must.
    The best-supported pair that passes wins, unless another with ``split_ratio`` of its
    frames turns the camera elsewhere (a split camera: none wins).

    A pair of cameras that share no view can fit one too: two walkers on one line, each
    seen by one camera, fit the camera turned round, looking back (a 12-camera corridor,
    docs/bootstrap.md, Session 44); nothing in the pair gives it away. A third camera can:
    where the camera also pairs with a camera not yet placed, the triangle of the three
    pairs checks the turn (PAIR_SPLIT_DEG). A pair that is the weakest of a triangle that
    disagrees places nothing."""
    from .bootstrap import pair_bones, single_views  # it imports this module

    if not len(persons.frame):
        return None
    if pairs_of is None:
        def pairs_of(c: int) -> list:
            return camera_pairs(frames, c, focal, cfg, seed=seed)

    mine = pairs_of(cam)
    found = sorted((p for p in mine if located[_partner(p, cam)]), key=lambda p: -len(p.frames))
    # the turns first: a far weaker pair that turns the camera elsewhere is dropped before
    # the guards of the baseline's length (those may drop the stronger, right one); one
    # about as strong is left to the guards, then to ``one_pose``
    turns = [_turn(p, cam, R) for p in found]
    found = [p for p, turn in zip(found, turns) if rotation_angle_deg(turn, turns[0]) <= PAIR_SPLIT_DEG
             or len(p.frames) >= cfg.split_ratio * len(found[0].frames)]
    if not found:
        return None
    kept, others = _third_camera(cam, found, mine, located, pairs_of)
    if not kept:
        best = max(found, key=lambda p: len(p.frames))
        return Resection(cam, None, None, len(best.frames), best.candidates, best.candidates, float("nan"), 0,
                         best.residual_px, None, False, "its pairs with placed cameras are the weakest of triangles "
                         "that disagree, through cameras not placed", paired=_partner(best, cam), third=tuple(others))
    found = kept
    sub = [(time_, tuple(v for v in views if located[v[0].cam] or v[0].cam == cam)) for time_, views in frames]
    # the network's bones in metres, measured as the pair's are (each person a "frame")
    rows, joints = np.nonzero(np.isfinite(persons.X).all(axis=2))
    ref = pair_bones(rows * 17 + joints, persons.X[rows, joints])
    floor = network_floor() if network_floor is not None else floor_of_persons(persons.X, _FLOOR_SIGMA)
    walked = persons.X[:, list(ANKLES)].reshape(-1, 3)
    walked = walked[np.isfinite(walked).all(axis=1)]
    single = single_views(sub)
    placed: list[Resection] = []
    for p in found:
        v = np.log(ref / p.bones)
        v = v[np.isfinite(v)]
        if len(v) < 3 or np.median(np.abs(v - np.median(v))) > 0.1:
            continue  # the bones disagree on the scale: the pair's geometry is wrong
        s, by = float(np.exp(np.median(v))), "bones"
        o, Rc = _partner(p, cam), _turn(p, cam, R)
        # x_b = R x_a + t: b's centre in a's frame is at -R.T t; the camera's centre from
        # o's for a unit baseline
        step = -R[o] @ p.R.T @ p.t if cam == p.b else R[o] @ p.t
        if floor is not None:
            s_floor, near = _floor_scale(single, p.frames, cam, o, R, t, Rc, step, floor, walked)
            if s_floor is not None and abs(np.log(s_floor / s)) <= PAIR_SCALES_AGREE:
                s, by = s_floor, "floor"
            elif s_floor is not None and near >= 0.5:
                continue  # on the floor the network's people walked, the bones disagree: the geometry is wrong
            # else the pair's people stand beyond where the network's walked: a floor
            # fitted there tilts a few degrees, tens of cm some metres on (a 12-camera
            # corridor: 4 degrees, 25 % on the baseline 6 m on, docs/bootstrap.md,
            # Session 44); the bones are the same people's
        turn = np.radians(PAIR_TURN_STD_DEG)
        length = s * float(np.linalg.norm(step))
        cov = np.diag([turn**2] * 3 + [length**2 * (PAIR_LENGTH_STD[by] ** 2 + turn**2)] * 3)
        placed.append(Resection(cam, Rc, t[o] + s * step, len(p.frames), p.candidates, p.candidates, float("nan"), 0,
                                p.residual_px, cov, True, "", paired=o, scaled_by=by))
    return one_pose(placed, cfg.split_ratio)


def one_pose(placed: Sequence[Resection], ratio: float) -> Resection | None:
    """The first of a camera's pair placements (best supported first), or None when
    another with at least ``ratio`` of its frames turns the camera more than
    PAIR_SPLIT_DEG elsewhere: two walkers who moved alike (as the bootstrap's split
    cameras, ``split_ratio``), not a pose to pick by the count of frames."""
    if not placed:
        return None
    best = placed[0]
    for r in placed[1:]:
        if rotation_angle_deg(r.R, best.R) > PAIR_SPLIT_DEG and r.frames >= ratio * best.frames:
            return None
    return best


def _turn(p, cam: int, R: np.ndarray) -> np.ndarray:
    """(3, 3) camera ``cam``'s orientation by its pair ``p`` with a placed camera (``R`` (C, 3, 3))."""
    o = _partner(p, cam)
    return R[o] @ _rel(p, cam, o)


def _partner(p, cam: int) -> int:
    """The other camera of pair ``p``."""
    return p.b if p.a == cam else p.a


def _third_camera(cam: int, found: list, mine: Sequence, located: np.ndarray, pairs_of: Callable[[int], Sequence]
                  ) -> tuple[list, list[int]]:
    """The triangles through camera ``cam``'s unplaced partners (its pairs: ``mine``) on
    its pairs with placed cameras (``found``): returns those a triangle confirms or none
    blames (a triangle that disagrees blames its weakest pair), and the unplaced partners
    (``place_by_pair``)."""
    mine_by = {_partner(p, cam): p for p in mine}
    others = sorted(c for c in mine_by if not located[c])
    if not others:
        return found, []
    placed_by = {y: {_partner(q, y): q for q in pairs_of(y) if located[_partner(q, y)]} for y in others}
    kept = []
    for p in found:
        o, good, bad = _partner(p, cam), 0, 0
        for y in others:  # y's pair with o closes the triangle cam-o-y
            q = placed_by[y].get(o)
            if q is None:
                continue
            py = mine_by[y]
            err = rotation_angle_deg(_rel(p, o, cam), _rel(py, y, cam) @ _rel(q, o, y))
            if err <= PAIR_SPLIT_DEG:
                good += 1
            elif len(p.frames) < min(len(py.frames), len(q.frames)):
                bad += 1  # the weakest of a triangle that disagrees is the likeliest wrong
        if good or not bad:
            kept.append(p)
    return kept, others


def _rel(p, src: int, dst: int) -> np.ndarray:
    """(3, 3) pair ``p``'s rotation from camera ``src``'s frame to ``dst``'s (x_b = R x_a)."""
    return p.R if (p.a, p.b) == (src, dst) else p.R.T


def camera_pairs(frames: Sequence[Frame], cam: int, focal: np.ndarray, cfg: BootstrapConfig, *, seed: int = 0
                 ) -> list:
    """Camera ``cam``'s pairs with every camera in ``frames`` (``bootstrap.pair_poses``,
    one seed per camera) whose person keeps one size as a bridge pair's must
    (``bridge_spread``)."""
    from .bootstrap import pair_poses  # it imports this module

    C = len(focal)
    found, _ = pair_poses(frames, C, focal, cfg, seed=seed + 104729 * cam, only=cam)
    return [p for p in found if p.size_spread <= cfg.bridge_spread]


def _floor_scale(single: Sequence[dict[int, Detection]], agreeing: np.ndarray, cam: int, o: int, R: np.ndarray,
                 t: np.ndarray, Rc: np.ndarray, step: np.ndarray, floor: Floor, walked: np.ndarray
                 ) -> tuple[float | None, float]:
    """The baseline length that puts the pair's lower ankles on ``floor``: triangulated
    with a unit baseline, the pair's points scale about camera o's centre, so each lower
    ankle P gives s = (d - n.C_o) / n.(P - C_o). Their median (None from fewer than
    MIN_POINTS // 3), and the share of the ankles it puts there within FLOOR_REACH_M along
    the floor of one of ``walked`` (N, 3), the network's people's ankles."""
    Rs = np.stack([R[o], Rc])
    ts = np.stack([t[o], t[o] + step])
    low = []
    for fi in agreeing:
        xy = np.stack([single[fi][o].xy, single[fi][cam].xy])
        P, _ = triangulate_views(Rs, ts, np.array([0, 1]), xy)
        a = P[list(ANKLES)]
        a = a[np.all(np.isfinite(a), axis=1)]
        if len(a):
            low.append(a[np.argmin(a @ floor.n)])
    if len(low) < MIN_POINTS // 3:
        return None, 0.0
    den = (np.array(low) - t[o]) @ floor.n
    num = floor.d - float(t[o] @ floor.n)
    ok = np.abs(den) > 1e-9
    s = num / den[ok]
    good = s > 0
    if good.sum() < MIN_POINTS // 3:
        return None, 0.0
    scale = float(np.median(s[good]))
    if not len(walked):
        return scale, 0.0
    from scipy.spatial import cKDTree

    flat = np.eye(3) - np.outer(floor.n, floor.n)  # distances along the floor
    P = t[o] + scale * (np.array(low)[ok][good] - t[o])
    near, _ = cKDTree(walked @ flat).query(P @ flat, distance_upper_bound=FLOOR_REACH_M)
    return scale, float(np.mean(np.isfinite(near)))


def block_witnesses(pairs: Sequence, R: np.ndarray, located: np.ndarray, cfg: BootstrapConfig) -> np.ndarray:
    """(C,) bool: the located cameras of pairs that say a block of the network was chained
    turned, and the cameras that witness it. A camera c whose pairs with two or more
    located cameras agree with each other on c's turn, disagree with its pose by more than
    PAIR_SPLIT_DEG, and are about as strong (``split_ratio``) as its pairs that agree with
    it: either those pairs are wrong, or their cameras are placed turned as a group
    (two walkers crossing a hall the opposite ways, each seen by other cameras, give
    pairs that turn one side of the network round alike; docs/bootstrap.md, Session 45).
    The resection against the others' persons tells which."""
    C = len(located)
    out = np.zeros(C, bool)
    by_cam: dict[int, list] = {}
    for p in pairs:
        if located[p.a] and located[p.b]:
            by_cam.setdefault(p.a, []).append(p)
            by_cam.setdefault(p.b, []).append(p)
    for c, ps in by_cam.items():
        agree = sum(len(p.frames) for p in ps if rotation_angle_deg(_turn(p, c, R), R[c]) <= PAIR_SPLIT_DEG)
        off = [p for p in ps if rotation_angle_deg(_turn(p, c, R), R[c]) > PAIR_SPLIT_DEG]
        best: list = []
        for p in off:  # the largest group of disagreeing pairs that agree on one turn
            group = [q for q in off if rotation_angle_deg(_turn(q, c, R), _turn(p, c, R)) <= PAIR_SPLIT_DEG]
            if sum(len(q.frames) for q in group) > sum(len(q.frames) for q in best):
                best = group
        if len(best) >= 2 and sum(len(q.frames) for q in best) >= cfg.split_ratio * agree:
            out[c] = True
            for q in best:
                out[_partner(q, c)] = True
    return out


def follow_moved(pairs: Sequence, R: np.ndarray, t: np.ndarray, located: np.ndarray,
                 before: dict[int, tuple[np.ndarray, np.ndarray]]) -> list[int]:
    """The rest of a block the resection moved part of (``block_witnesses``): the cameras
    ``before`` (camera -> its (R (3, 3), t (3,)) before the move) moved as one rigid
    motion; a group of located cameras that the pairs agreeing with the poses hold
    together, apart from the largest group, whose pairs with the others agree best on a
    turn, and on the motion's turn, is moved by it too (the chain of cameras beyond the
    ones resected: their own pairs held them to the moved ones). R, t (C, 3, 3), (C, 3)
    are changed in place; returns the cameras moved."""
    if not before:
        return []
    motion = {c: (R[c] @ Ro.T, t[c] - R[c] @ Ro.T @ to) for c, (Ro, to) in before.items()}
    group = max(([k for k in motion if rotation_angle_deg(motion[k][0], motion[c][0]) <= PAIR_SPLIT_DEG]
                 for c in motion), key=len)
    Q = project_so3(sum(motion[c][0] for c in group))
    d = np.median([motion[c][1] for c in group], axis=0)
    agreeing = [p for p in pairs if located[p.a] and located[p.b]
                and rotation_angle_deg(_turn(p, p.b, R), R[p.b]) <= PAIR_SPLIT_DEG]
    parent = list(range(len(located)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for p in agreeing:
        parent[root(p.a)] = root(p.b)
    comps: dict[int, list[int]] = {}
    for c in map(int, np.flatnonzero(located)):
        comps.setdefault(root(c), []).append(c)
    main = max(comps.values(), key=len)
    moved: list[int] = []
    for comp in comps.values():
        if comp is main:
            continue
        inside = set(comp)
        # each pair with a camera outside the group: the turn it asks of the group
        turns = [(_turn(p, k, R) @ R[k].T, len(p.frames)) for p in pairs
                 for k in (p.a, p.b) if k in inside and located[_partner(p, k)] and _partner(p, k) not in inside]
        if len(turns) < 2:
            continue
        best = max(([(Qp, n) for Qp, n in turns if rotation_angle_deg(Qp, Qc) <= PAIR_SPLIT_DEG] for Qc, _ in turns),
                   key=lambda g: sum(n for _, n in g))
        if len(best) < 2 or rotation_angle_deg(project_so3(sum(Qp * n for Qp, n in best)), Q) > PAIR_SPLIT_DEG:
            continue
        for k in comp:
            R[k], t[k] = Q @ R[k], Q @ t[k] + d
            moved.append(k)
    return sorted(moved)


def turned_blocks(pairs: Sequence, R: np.ndarray, located: np.ndarray, *, limit: int = 3
                  ) -> list[tuple[np.ndarray, list, np.ndarray]]:
    """Groups of located cameras that the pairs disagreeing with the placement say are
    turned as one against the rest, where each camera's own pairs hold it (so no camera
    witnesses it, ``block_witnesses``). A pair that disagrees asks one of its cameras to
    turn by Q (world frame) against the other; the pairs that ask one turn (Q or Q^T:
    which side turns a turn near 180° does not say; two pairs at least) are the edges
    the group's border should cross. The border: the split of the located cameras that
    parts the fewest agreeing pair frames and the most of those pairs' frames (two-sided
    correlation clustering, ``_two_sides``; near ties are common, so the few cheapest
    splits), where it parts most of them: the wrong pairs may well have more frames
    than the right ones (that is how they won). The agreeing pairs it parts are the
    wrong ones that chained the group so: two walkers crossing a hall the opposite ways
    at one time, each seen by cameras of one side, give many (docs/bootstrap.md, Session
    46). Up to ``limit`` groups, the turn most disagreeing frames ask first, each
    (the smaller side (C,) bool, the agreeing pairs across its border, the turn (3, 3)
    or its inverse). Which is right ``move_block`` tells."""
    from scipy.sparse import csr_array
    from scipy.sparse.csgraph import shortest_path

    C = len(located)
    agree, votes = [], []
    for p in pairs:
        if located[p.a] and located[p.b]:
            Q = _turn(p, p.b, R) @ R[p.b].T
            (agree if rotation_angle_deg(Q, np.eye(3)) <= PAIR_SPLIT_DEG else votes).append((p, Q))
    idx = np.flatnonzero(located)
    pos = {c: k for k, c in enumerate(idx)}
    n = len(idx)
    W = np.zeros((n, n))  # agreeing frames: keep together
    for p, _ in agree:
        W[pos[p.a], pos[p.b]] += len(p.frames)
    W = W + W.T
    hops = shortest_path(csr_array(W), unweighted=True)
    out: list[tuple[np.ndarray, list, np.ndarray]] = []
    while len(out) < limit and len(votes) >= 2:
        best: list = []
        turn = np.eye(3)
        for _, Q in votes:
            group = [(p, Qb) for p, Qb in votes
                     if min(rotation_angle_deg(Qb, Q), rotation_angle_deg(Qb.T, Q)) <= PAIR_SPLIT_DEG]
            if sum(len(p.frames) for p, _ in group) > sum(len(p.frames) for p, _ in best):
                best, turn = group, Q
        if len(best) < 2:
            break
        votes = [v for v in votes if not any(v[0] is p for p, _ in best)]
        N = np.zeros((n, n))  # the group's frames: part
        for p, _ in best:
            N[pos[p.a], pos[p.b]] += len(p.frames)
        N = N + N.T
        # starts: each camera on the side of the group pair's end it is nearer to
        starts = [hops[pos[p.a]] < hops[pos[p.b]] for p, _ in best]
        for _, x in _two_sides(W, N, starts)[:limit - len(out)]:
            side = np.zeros(C, bool)
            side[idx[x]] = True
            cut = [p for p, _ in agree if side[p.a] != side[p.b]]
            out.append(((side if x.sum() <= n - x.sum() else located & ~side), cut, turn))
    return out


def _two_sides(W: np.ndarray, N: np.ndarray, starts: Sequence[np.ndarray] = ()) -> list[tuple[float, np.ndarray]]:
    """Splits (cost, (n,) bool) of n nodes that cut little of W and keep little of N within
    a side (both (n, n) symmetric, >= 0), that part most of N, cheapest first: single
    nodes moved across while that helps, from the signed graph Laplacian's split and
    from ``starts`` (the optimum is hard to find; near ties go to ``move_block``)."""
    S = W - N
    L = np.diag(np.abs(S).sum(1)) - S

    def cost(x: np.ndarray) -> float:
        same = x[:, None] == x[None, :]
        return 0.5 * float((W * ~same).sum() + (N * same).sum())

    out: list[tuple[float, np.ndarray]] = []
    for x in [np.linalg.eigh(L)[1][:, 0] >= 0, *starts]:
        x = x.copy()
        c = cost(x)
        while True:
            trials = [cost(np.where(np.arange(len(x)) == k, ~x, x)) for k in range(len(x))]
            k = int(np.argmin(trials))
            if trials[k] >= c:
                break
            x[k], c = ~x[k], trials[k]
        kept = float((N * (x[:, None] == x[None, :])).sum())
        seen = any(np.array_equal(x, y) or np.array_equal(x, ~y) for _, y in out)
        if kept < 0.5 * N.sum() and x.any() and not x.all() and not seen:
            out.append((c, x))
    return sorted(out, key=lambda cx: cx[0])


EVENT_S = 5.0  # s: the agreement of a group's pose is counted in windows this long


@dataclass(frozen=True)
class BlockMove:
    """A rigid motion of a group of cameras (``move_block``): R' = Q R, t' = Q t + d.

    windows / frames: the EVENT_S windows and frames in which a camera of the group agrees
    with the others' persons after the motion; held_windows / held_frames: before it."""

    Q: np.ndarray
    d: np.ndarray
    windows: int
    frames: int
    held_windows: int
    held_frames: int
    accepted: bool


def move_block(frames: Sequence[Frame], R: np.ndarray, t: np.ndarray, located: np.ndarray, block: np.ndarray,
               turn: np.ndarray, focal: np.ndarray, assoc: AssociateConfig, cfg: BootstrapConfig, *,
               seed: int = 0, iterations: int = 300) -> BlockMove | None:
    """Where a group of cameras (``block`` (C,) bool, from ``turned_blocks``) belongs if it
    is turned by ``turn`` (3, 3) or its inverse against the rest: the persons the other
    located cameras triangulate against the group's detections, with each camera's
    orientation fixed by the turn, so that only the group's shift d (3,) is sought (RANSAC,
    one candidate's joints a model). A pose is scored by the EVENT_S windows in which one
    of the group's cameras agrees with those persons, not by frames: pairs that chained a
    group wrong (two walkers crossing a hall the opposite ways, each seen by one side)
    make the persons agree with the wrong pose in many frames of one crossing, the right
    pose agrees whenever somebody walks where both sides see (docs/bootstrap.md, Session
    46). Accepted when the moved group agrees in ``resect_min_frames`` frames and the pose
    it has in fewer than ``resect_ambiguity`` times its windows. None: no candidates."""
    persons = triangulate_persons(frames, R, t, located & ~block, assoc)
    times = np.array([f[0] for f in frames])
    mine: dict[int, list[tuple[int, np.ndarray]]] = {}  # frame -> the group's (camera, detection)
    for fi, (_, views) in enumerate(frames):
        for v in views:
            for det in v:
                if block[det.cam]:
                    mine.setdefault(fi, []).append((det.cam, det.xy))
    cams, P, x, fr = [], [], [], []
    for k in range(len(persons.frame)):
        fi = int(persons.frame[k])
        for c, xy in mine.get(fi, ()):
            if (np.all(np.isfinite(persons.X[k]), 1) & np.all(np.isfinite(xy), 1)).sum() >= 6:
                cams.append(c)
                P.append(persons.X[k])
                x.append(xy)
                fr.append(fi)
    if len(P) < cfg.resect_min_frames:
        return None
    order = np.argsort(cams, kind="stable")  # camera by camera: the RANSAC's draws depend on the order
    cams_a, P_a, x_a, fr_a = np.array(cams)[order], np.stack(P)[order], np.stack(x)[order], np.array(fr)[order]
    tol = cfg.resect_px / focal[cams_a]
    per_cam = [(c, cams_a == c) for c in np.unique(cams_a)]

    def score(Q: np.ndarray, d: np.ndarray) -> tuple[int, int]:
        f = np.unique(fr_a[agreeing(Q, d)])
        return len(np.unique(np.floor((times[f] - times[0]) / EVENT_S))), len(f)

    def shift(Q: np.ndarray, ks: np.ndarray) -> np.ndarray | None:
        """d that puts candidates ``ks``' detections on their persons (the orientation
        known: linear in each camera's centre, one d for all)."""
        rows, rhs = [], []
        for k in ks:
            c = cams_a[k]
            ok = np.all(np.isfinite(P_a[k]), 1) & np.all(np.isfinite(x_a[k]), 1)
            b = np.c_[x_a[k][ok], np.ones(ok.sum())] @ (Q @ R[c]).T  # bearings in the world
            z = np.zeros(len(b))
            bx = np.stack([np.stack([z, -b[:, 2], b[:, 1]], 1), np.stack([b[:, 2], z, -b[:, 0]], 1),
                           np.stack([-b[:, 1], b[:, 0], z], 1)], 1)  # (N, 3, 3) [b]x
            # [b]x (Q t_c + d) = [b]x X: the centre on each joint's ray
            rows.append(bx.reshape(-1, 3))
            rhs.append((np.cross(b, P_a[k][ok]) - np.cross(b, Q @ t[c])).reshape(-1))
        d, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
        return d if np.all(np.isfinite(d)) else None

    def agreeing(Q: np.ndarray, d: np.ndarray) -> np.ndarray:
        ok = np.zeros(len(P_a), bool)
        for c, m in per_cam:
            ok[m] = _frame_errors(P_a[m], x_a[m], Q @ R[c], Q @ t[c] + d) < tol[m]
        return np.flatnonzero(ok)

    held = score(np.eye(3), np.zeros(3))
    turns = [turn] + ([turn.T] if rotation_angle_deg(turn, turn.T) > PAIR_SPLIT_DEG else [])
    rng = np.random.default_rng(seed)
    best = (-1, -1, np.eye(3), np.zeros(3))
    for k in rng.choice(len(P_a), size=min(iterations, len(P_a)), replace=False):
        for Q in turns:
            d = shift(Q, np.array([k]))
            if d is not None:
                w, n = score(Q, d)
                if (w, n) > best[:2]:
                    best = (w, n, Q, d)
    w, n, Q, d = best
    if w < 0:
        return None
    for _round in range(3):  # on every agreeing candidate
        sel = agreeing(Q, d)
        d1 = shift(Q, sel) if len(sel) else None
        if d1 is None:
            break
        w1, n1 = score(Q, d1)
        if (w1, n1) < (w, n):
            break
        d, w, n = d1, w1, n1
    ok = n >= cfg.resect_min_frames and held[0] < cfg.resect_ambiguity * w
    return BlockMove(Q, d, w, n, held[0], held[1], bool(ok))
