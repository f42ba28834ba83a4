"""Groups of cameras that no camera pair links, joined by the persons each group sees of
the other's.

Two rooms joined by a door: every pair within a room gives a relative pose, no pair across
(where a camera in each room sees one person, it is a different one in each room, and the
essential matrix rightly fails). The bootstrap places one group; each other group is
bootstrapped on its own, in its own floor frame and with the metric scale of its own
people (``bootstrap._join_groups``). Here such a group is joined to the placed one as one
rigid body: a similarity X_placed = s Q X_group + d.

One camera of the group resected against the placed group's persons (``resect.resect``)
rarely has the frames to be trusted alone: through a door it sees a few of them, close
together (measured, two rooms with four walkers, 120 s: 0-39 frames per camera). But each
camera's pose, with the group's own geometry, is a candidate join, and a join is judged by
every camera at once: the frames in which a camera of the group sees a person the placed
cameras triangulate where the join puts it, and a placed camera one of the group's
persons. The best candidate is refined on all those frames (least squares of the
reprojection errors over a turn about z, a shift and a scale) and taken when it agrees in enough frames,
over persons spread enough, and no clearly different join agrees nearly as often.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np

from .config import AssociateConfig, BootstrapConfig
from .geometry import rotation_angle_deg, so3_exp
from .preprocess import Detection
from .resect import Candidates, _project, candidates, resect, triangulate_persons

Frame = tuple[float, tuple[tuple[Detection, ...], ...]]

_MAX_SCALE = 1.4  # the two groups' scales, each from its own people's bones, agree to within this factor
_MAX_TILT = 10.0  # deg: both groups stand on their floor; a join that tilts one more is no join
_REFINE_ROUNDS = 4


@dataclass(frozen=True)
class Join:
    """How a group's frame maps onto the placed cameras': X_placed = s Q X_group + d.
    frames: (camera, frame) agreements over both groups' cameras; cameras: how many
    cameras agree at all; rival: the agreements of the best clearly different join (10°,
    0.5 m at the group's cameras); spread: m, the agreeing persons' spread over the floor
    (2nd principal std of their centres); residual_px: the agreeing joints' median
    reprojection error."""

    accepted: bool
    reason: str
    s: float = 1.0
    Q: np.ndarray | None = None
    d: np.ndarray | None = None
    frames: int = 0
    cameras: int = 0
    rival: int = 0
    spread: float = 0.0
    residual_px: float = float("nan")

    def summary(self) -> str:
        if self.Q is None:
            return f"not joined: {self.reason}"
        return (f"{'joined' if self.accepted else 'not joined'}: its cameras and the others see each other's persons "
                f"in {self.frames} frames ({self.cameras} cameras; a clearly different join {self.rival}), spread "
                f"{self.spread:.2f} m, {self.residual_px:.1f} px, the scales {self.s:.3f} apart"
                + ("" if self.accepted else f"; {self.reason}"))


@dataclass(frozen=True)
class _Side:
    """One direction of the evidence: cameras of one group (poses R (N, 3, 3), t (N, 3)
    in its own frame, focal (N,), the resection's tolerance tol (N,) normalised) and
    their candidates against the other group's persons (in the other's frame);
    into_placed: the group's cameras against the placed persons (else the placed cameras
    against the group's)."""

    R: np.ndarray
    t: np.ndarray
    focal: np.ndarray
    tol: np.ndarray
    cands: tuple[Candidates, ...]
    into_placed: bool


def join(frames: Sequence[Frame], placed: tuple[np.ndarray, np.ndarray, np.ndarray],
         group: tuple[np.ndarray, np.ndarray, np.ndarray], focal: np.ndarray, box: np.ndarray,
         associate: AssociateConfig, cfg: BootstrapConfig, *, seed: int = 0) -> Join:
    """The similarity that maps ``group`` (R (C, 3, 3), t (C, 3), its cameras (C,) bool;
    on its floor, metres) onto ``placed`` (the same; disjoint cameras). ``box`` (C, 2, 2):
    where each camera's detections lie (``bootstrap.view_box``)."""
    Ra, ta, A = placed
    Rb, tb, B = group
    assert not (A & B).any()
    pa = triangulate_persons(frames, Ra, ta, A, associate)
    pb = triangulate_persons(frames, Rb, tb, B, associate)
    ia, ib = np.flatnonzero(A), np.flatnonzero(B)
    tol = cfg.resect_px / focal
    sides = (  # the group's cameras against the placed persons; the placed cameras against the group's
        _Side(Rb[ib], tb[ib], focal[ib], tol[ib], tuple(candidates(frames, pa, int(c)) for c in ib), True),
        _Side(Ra[ia], ta[ia], focal[ia], tol[ia], tuple(candidates(frames, pb, int(c)) for c in ia), False),
    )

    hyps: list[tuple[float, np.ndarray, np.ndarray]] = []
    tilted = 0
    cands = dict(zip(np.r_[ib, ia].tolist(), sides[0].cands + sides[1].cands))
    for c in np.r_[ib, ia]:
        r = resect(frames, pa if B[c] else pb, int(c), float(focal[c]), box[c], cfg, seed=seed, cands=cands[int(c)])
        if r.R is None:
            continue
        # a camera of the group resected in the placed frame; a placed camera resected in
        # the group's frame gives the inverse join
        Q = r.R @ Rb[c].T if B[c] else Ra[c] @ r.R.T
        if _tilt(Q) > _MAX_TILT:
            tilted += 1
            continue
        Q = _turn_z(_yaw(Q))
        hyps.append((1.0, Q, r.t - Q @ tb[c] if B[c] else ta[c] - Q @ r.t))
    if not hyps:
        return Join(False, "no camera of either group sees enough of the other's persons to be resected "
                           f"({cfg.resect_min_frames} frames with candidates)"
                    + (f", or its pose tilts the groups' floors apart ({tilted})" if tilted else ""))
    scored = sorted(((_agreeing(sides, *h), h) for h in hyps), key=lambda x: -x[0])
    best = _refine(sides, *scored[0][1])
    centre = tb[ib].mean(0)

    def different(h) -> bool:
        return (rotation_angle_deg(h[1], best[1]) > 10.0
                or np.linalg.norm(h[0] * h[1] @ centre + h[2] - (best[0] * best[1] @ centre + best[2])) > 0.5)

    rival = 0
    for _, h in scored[1:4]:
        if different(h) and different(h := _refine(sides, *h)):
            rival = max(rival, _agreeing(sides, *h))
    s, Q, d = best
    n, cams, spread, res_px = _evidence(sides, s, Q, d)
    reasons = []
    # one camera's bar twice over: a join moves several cameras at once
    if n < 2 * cfg.resect_min_frames:
        reasons.append(f"{n} agreeing frames, {2 * cfg.resect_min_frames} needed")
    if cams < 2:
        reasons.append("one camera alone agrees")
    if spread < cfg.resect_min_spread:
        reasons.append(f"the persons it agrees with spread {spread:.2f} m, {cfg.resect_min_spread:g} m needed")
    if rival > cfg.resect_ambiguity * n:
        reasons.append(f"a different join agrees in {rival} frames")
    if not 1 / _MAX_SCALE < s < _MAX_SCALE:
        reasons.append(f"the groups' scales {s:.2f} apart")
    return Join(not reasons, "; ".join(reasons), s, Q, d, n, cams, rival, spread, res_px)


def _turn_z(yaw: float) -> np.ndarray:
    return so3_exp(np.array([0.0, 0.0, yaw]))


def _yaw(Q: np.ndarray) -> float:
    return float(np.arctan2(Q[1, 0], Q[0, 0]))


def _tilt(Q: np.ndarray) -> float:
    """deg: how far Q (3, 3) turns z."""
    return float(np.degrees(np.arccos(np.clip(Q[2, 2], -1.0, 1.0))))


def _poses(side: _Side, s: float, Q: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The side's cameras in the other's frame: the group's in the placed frame (the
    join), the placed ones in the group's (its inverse)."""
    if side.into_placed:
        return np.einsum("ij,njk->nik", Q, side.R), s * side.t @ Q.T + d
    return np.einsum("ji,njk->nik", Q, side.R), (side.t - d) @ Q / s


def _agreements(sides: Sequence[_Side], s: float, Q: np.ndarray, d: np.ndarray
                ) -> Iterator[tuple[_Side, int, Candidates, np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera of both sides under the join: (side, camera k, its candidates, the
    agreeing ones (indices, one per agreeing frame), its pose R (3, 3), t (3,))."""
    for side in sides:
        R, t = _poses(side, s, Q, d)
        for k, cand in enumerate(side.cands):
            _, sel = cand.agreeing(R[k], t[k], side.tol[k])
            yield side, k, cand, sel, R[k], t[k]


def _agreeing(sides: Sequence[_Side], s: float, Q: np.ndarray, d: np.ndarray) -> int:
    """Agreeing (camera, frame)s of the join over both sides."""
    return sum(len(sel) for *_, sel, _R, _t in _agreements(sides, s, Q, d))


def _evidence(sides: Sequence[_Side], s: float, Q: np.ndarray, d: np.ndarray) -> tuple[int, int, float, float]:
    """(agreeing (camera, frame)s, cameras that agree, the agreeing persons' spread over
    the floor in m (2nd principal std of their centres, in the placed frame), their
    joints' median reprojection error in px)."""
    total, cams, centres, errs = 0, 0, [], []
    for side, k, cand, sel, R, t in _agreements(sides, s, Q, d):
        if not len(sel):
            continue
        total += len(sel)
        cams += 1
        P = cand.P[sel]
        c = np.nanmean(P, axis=1)
        centres.append(c if side.into_placed else s * c @ Q.T + d)  # the group's persons: into the placed frame
        u, _ = _project(P, R, t)
        errs.append(np.linalg.norm(u - cand.x[sel], axis=-1).ravel() * side.focal[k])
    spread = 0.0
    C = np.concatenate(centres) if centres else np.zeros((0, 3))
    C = C[np.isfinite(C).all(1)]
    if len(C) >= 3:
        spread = float(np.linalg.svd(C[:, :2] - C[:, :2].mean(0), compute_uv=False)[1] / np.sqrt(len(C)))
    e = np.concatenate(errs) if errs else np.zeros(0)
    return total, cams, spread, float(np.nanmedian(e)) if np.isfinite(e).any() else float("nan")


def _refine(sides: Sequence[_Side], s: float, Q: np.ndarray, d: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The join refined on the frames it agrees in (both sides; robust least squares of
    the reprojection errors in px), those frames found again after each round. Only its
    turn about z: both groups stand on their floor, and a door's persons, seen from one
    side, hold a tilt about the door poorly (measured: a join tilted 12° agreed in 62 of
    the 116 frames of the right one)."""
    from scipy.optimize import least_squares

    for _ in range(_REFINE_ROUNDS):
        corr = []  # (side, camera k, joints (M, 3), their detections (M, 2)) of the agreeing frames
        for side, k, cand, sel, _R, _t in _agreements(sides, s, Q, d):
            ok = np.isfinite(cand.P[sel]).all(-1) & np.isfinite(cand.x[sel]).all(-1)
            if ok.any():
                corr.append((side, k, cand.P[sel][ok], cand.x[sel][ok]))
        if sum(len(c[2]) for c in corr) < 12:
            break
        s0, Q0, d0 = s, Q, d

        def residuals(p: np.ndarray) -> np.ndarray:
            si, Qi, di = s0 * np.exp(p[4]), _turn_z(p[0]) @ Q0, d0 + p[1:4]
            out = []
            for side, k, P, x in corr:
                if side.into_placed:  # the group's camera k in the placed frame, the placed persons
                    R, t, X = Qi @ side.R[k], si * Qi @ side.t[k] + di, P
                else:  # the placed camera k, the group's persons mapped into the placed frame
                    R, t, X = side.R[k], side.t[k], si * P @ Qi.T + di
                u, z = _project(X, R, t)
                out.append(np.where(z[:, None] > 0.05, u - x, 1.0).ravel() * side.focal[k])
            return np.concatenate(out)

        sol = least_squares(residuals, np.zeros(5), loss="soft_l1", f_scale=3.0, max_nfev=100)
        s, Q, d = s0 * float(np.exp(sol.x[4])), _turn_z(sol.x[0]) @ Q0, d0 + sol.x[1:4]
    return s, Q, d


def contradicted(frames: Sequence[Frame], R: np.ndarray, t: np.ndarray, located: np.ndarray, cameras: np.ndarray,
                 focal: np.ndarray, box: np.ndarray, associate: AssociateConfig, cfg: BootstrapConfig
                 ) -> dict[int, tuple[int, int]]:
    """The ``cameras`` (C,) bool of the joined network (R (C, 3, 3), t (C, 3), ``located``
    (C,) bool) whose pose the persons the others triangulate contradict: of at least
    ``resect_min_frames`` frames in which such a person lies in its view while it sees
    somebody, fewer than ``resect_min_share`` agree (the resection's guards). A group's
    own bootstrap can misplace one of its cameras that no check of its own caught (a hall
    of 40, seed 1: cam_3 13 m off among 15 cameras joined; the others within 0.07 m but
    one). A pose that looks where nobody walks has nobody in view to contradict it, and
    is kept (the resection's gap too). Returns camera -> (agreeing, in view)."""
    out = {}
    for c in map(int, np.flatnonzero(cameras & located)):
        others = located.copy()
        others[c] = False
        persons = triangulate_persons(frames, R, t, others, associate)
        cand = candidates(frames, persons, c)
        n, _ = cand.agreeing(R[c], t[c], cfg.resect_px / focal[c])
        seen = max(cand.in_view(persons, R[c], t[c], box[c]), n)
        if seen >= cfg.resect_min_frames and n < cfg.resect_min_share * seen:
            out[c] = (n, seen)
    return out
