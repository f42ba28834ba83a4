"""The initial estimate against the data: keep its frame and scale, take the data's shape.

From a rough initial estimate (0.75 m / 20° per camera) the online pipeline's first
associations are wrong often enough to drag cameras off for good: the association cuts
rays to depth intervals in a world that is metres and degrees wrong. The bootstrap
(``backend.bootstrap``) finds the network's shape from the people alone, up to a
similarity, and is far more precise than any rough estimate (0.01-0.02 m). Aligned onto
the initial estimate by a trimmed similarity on the camera centres (the protocol of
``Refiner.keep_scale``, ``geometry.trimmed_similarity``), it keeps the user's world frame
and scale and brings the data's shape. The online pipeline starts there, the initial
estimate with its stated uncertainty still its prior, frame and scale: its first
adjustment fixes the gauge by those priors as it would have, from a start whose
associations are right.

Per camera, the two are compared after the alignment:

- *agrees*: within ``bootstrap.agree_translation`` / ``agree_rotation`` (or 3x the
  bootstrap's own std): the initial estimate already has the data's shape there;
- *refused*: further than ``bootstrap.refuse_sigma`` times the initial estimate's stated
  std (``refine.initial_std_*``), or times the cameras' lower quartile distance when that
  is larger (an estimate off everywhere by more than it states singles out no camera): one
  of the two is grossly wrong (a pair chained wrongly in the bootstrap, a camera swapped
  in the floor plan); that camera starts from the initial estimate and the pipeline's
  association and re-localisation decide;
- *overruled*: refused, but the data hold the bootstrap's pose (its last bundle
  adjustment has as many observations of the camera and reprojects them as well as the
  others'), and only a few cameras are refused (two, or a quarter; at least as many and
  three left to align on): the initial estimate is what is wrong
  there (two cameras swapped, one moved since the floor plan), so the camera starts from
  the data's pose whatever the mode but 'never'. Left at its initial pose such a camera
  is never calibrated: its views join nobody, and re-localisation refuses poses that far
  from the initial estimate.
- *block*: three or more overruled cameras that one similarity of their own puts within
  the refusal limits of the initial estimate (``_block``): the two agree on them and
  disagree on how they hang on the rest, which the bootstrap gets wrong when it chains a
  room through one bad pair (slow, pausing walkers). Not overruled: they start from the
  initial estimate. (An initial estimate with a whole room misplaced, the other way round,
  is then not put right by the data; its cameras stay refused, the summary names them.)

``bootstrap.with_initial``: 'never' (the paper's way), 'always' (start from the aligned
bootstrap for every camera it placed and did not refuse), 'auto' (the same, but only when
the initial estimate is further off the data than it states (``auto_sigma``) or than the
paper's first adjustments cope with (``auto_translation`` / ``auto_rotation``): an initial
estimate the data confirm is left exactly as it is).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Iterable, Mapping, Sequence

import numpy as np

from proto import KeypointMessage

from .bootstrap import BootstrapError, BootstrapResult, Progress, bootstrap_messages
from .cameras import CameraSet, Intrinsics, Pose
from .config import EngineConfig
from .geometry import align_poses, within_std
from .refine import handover_covariance, initial_covariance


@dataclass(frozen=True, eq=False)
class Reconciled:
    """The initial estimate compared with the bootstrap's shape aligned onto it.

    names: the initial estimate's cameras (C,); R (C, 3, 3), t (C, 3): where the online
    pipeline starts (the aligned bootstrap where ``from_bootstrap``, else the initial
    estimate); translation (C,) m, rotation (C,) deg: the initial estimate's distance
    from the aligned bootstrap (NaN where the bootstrap did not place the camera);
    agrees, refused, from_bootstrap, aligned, overruled (C,) bool (aligned: the camera took
    part in the alignment, not trimmed; overruled: refused, started from the data anyway);
    scale: initial-estimate units per bootstrap unit;
    std_translation (C,) m, std_rotation (C,) deg: the bootstrap's own std in those units
    (NaN where it did not place the camera)."""

    names: tuple[str, ...]
    R: np.ndarray
    t: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    agrees: np.ndarray
    refused: np.ndarray
    from_bootstrap: np.ndarray
    aligned: np.ndarray
    scale: float
    mode: str
    std_translation: np.ndarray
    std_rotation: np.ndarray
    overruled: np.ndarray
    block: np.ndarray  # (C,) bool: refused cameras the initial estimate holds as one block (``_block``), not overruled
    nowhere: bool = False  # every camera refused: the data's shape used for all, in the centres' frame
    # m: how far the initial estimate's errors typically move what a camera sees, at the
    # distance of its persons (``_reach``; NaN: not known)
    displacement: float = float("nan")
    # (C, 3, 3), (C, 3): the bootstrap aligned onto the initial estimate, where it placed a
    # camera it was not refused for (NaN elsewhere); None: not kept
    R_data: np.ndarray | None = field(default=None, repr=False)
    t_data: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        C = len(self.names)
        assert self.R.shape == (C, 3, 3) and self.t.shape == (C, 3)
        for a in (self.translation, self.rotation, self.agrees, self.refused, self.from_bootstrap, self.aligned,
                  self.std_translation, self.std_rotation, self.overruled, self.block):
            assert a.shape == (C,)
        assert (self.R_data is None) == (self.t_data is None)
        assert self.R_data is None or (self.R_data.shape == (C, 3, 3) and self.t_data.shape == (C, 3))

    @property
    def used(self) -> bool:
        return bool(self.from_bootstrap.any())

    def start(self, config: EngineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(R, t, P (C, 6, 6)) for ``Pipeline(start=...)``, or None when the initial estimate
        is kept. ``config``: the run's (``self.config(...)``). A camera started from the
        data's shape is anchored there with the bootstrap's honest std (as without an initial
        estimate, ``bootstrap.handover``); one started from the initial estimate keeps its
        std. Anchoring every camera to the rough initial estimate instead pulled the online
        estimate's shape from 0.012-0.019 m at the start to 0.12-0.14 m after 30-90 s of
        data in the lab from 0.75 m / 20° (the final batch put it right)."""
        if not self.used:
            return None
        P = np.repeat(initial_covariance(config.refine)[None], len(self.names), axis=0)
        for c in np.flatnonzero(self.from_bootstrap):
            P[c] = handover_covariance(config.bootstrap, self.std_translation[c], self.std_rotation[c])
        return self.R.copy(), self.t.copy(), P

    def data_shape(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(R (C, 3, 3), t (C, 3), std (C, 2) m and deg; NaN rows where the bootstrap did
        not place a camera or was refused for it) for ``Pipeline(data_shape=...)``: where
        the data's shape puts the cameras when the run starts from the initial estimate,
        for its final batch to try too (``EndOfRun._batch_from_data``); None when the run
        starts from the data's shape already, or it holds fewer than 3 cameras."""
        if self.used or self.R_data is None:
            return None
        placed = np.isfinite(self.t_data).all(axis=1)
        if placed.sum() < 3:
            return None
        std = np.stack([self.std_translation, self.std_rotation], axis=1)
        std[~placed] = np.nan
        return self.R_data.copy(), self.t_data.copy(), std

    def applied(self, config: EngineConfig, cameras: CameraSet
                ) -> tuple[EngineConfig, CameraSet, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """What a run takes from this reconciliation: its config (``config``), its cameras
        (``cameras``) and its start (``start``, with that config)."""
        config = self.config(config)
        return config, self.cameras(cameras), self.start(config)

    def cameras(self, cameras: CameraSet) -> CameraSet:
        """``cameras`` with the overruled cameras' initial poses replaced by the data's
        (aligned into the initial estimate's frame and scale): the run's frame and scale
        are fitted to the initial estimate's centres (``Refiner.keep_scale``), and a pose
        known to be wrong (a swapped camera metres away) would pull them."""
        if not self.overruled.any():
            return cameras
        ext = dict(cameras.extrinsics)
        for c in np.flatnonzero(self.overruled):
            n = self.names[c]
            ext[n] = replace(ext[n], pose=Pose(self.R[c].copy(), self.t[c].copy()))
        return CameraSet(cameras.names, cameras.intrinsics, ext)

    def observed_std(self) -> tuple[float, float]:
        """(m, deg) how far the initial estimate is off the data's shape: the RMS distance
        over the cameras the alignment kept (the convention of ``refine.initial_std_*``:
        0.25 m for cameras 0.25 m off)."""
        k = self.aligned & ~self.refused & np.isfinite(self.translation)  # not the gross errors
        if self.nowhere:  # all of them are
            k = self.aligned & np.isfinite(self.translation)
        if not k.any():
            return 0.0, 0.0
        return (float(np.sqrt(np.mean(self.translation[k] ** 2))), float(np.sqrt(np.mean(self.rotation[k] ** 2))))

    def config(self, config: EngineConfig) -> EngineConfig:
        """The engine config to run from this start: when starting from the data's shape and
        the initial estimate is further off than its stated std, the stated std is raised to
        what the data show (the initial estimate stays the prior; a prior that claims 0.25 m
        when the cameras are 0.75 m off pulls the first adjustments' shape towards its
        errors: measured, 0.012 m -> 0.22 m shape error in the lab from 0.75 m / 20°)."""
        if not self.used:
            return config
        st, sr = self.observed_std()
        rc = config.refine
        if st <= rc.initial_std_translation and sr <= rc.initial_std_rotation:
            return config
        return config.model_copy(update={"refine": rc.model_copy(update={
            "initial_std_translation": max(rc.initial_std_translation, st),
            "initial_std_rotation": max(rc.initial_std_rotation, sr)})})

    def summary(self) -> str:
        placed = np.isfinite(self.translation)
        n = int(placed.sum())
        if n == 0:
            return "the bootstrap placed none of the initial estimate's cameras: the initial estimate is used as it is"
        dt = np.nanmedian(self.translation)
        dr = np.nanmedian(self.rotation)
        head = (f"the initial estimate vs the data's shape (bootstrap, {n} cameras, aligned on "
                f"{int(self.aligned.sum())}): median {dt:.3f} m / {dr:.2f}°, max {np.nanmax(self.translation):.3f} m / "
                f"{np.nanmax(self.rotation):.2f}°"
                + (f", typically {self.displacement:.2f} m at its persons" if np.isfinite(self.displacement)
                   else "")
                + f"; {int(self.agrees.sum())}/{n} agree")
        refused = [m for m, r, o, k in zip(self.names, self.refused, self.overruled, self.block)
                   if r and not o and not k]
        tail = f"; refused (too far from the initial estimate): {', '.join(refused)}" if refused else ""
        over = [f"{m} ({d:.2f} m / {a:.0f}° away)" for m, o, d, a in
                zip(self.names, self.overruled, self.translation, self.rotation) if o]
        if over:
            tail += (f"; the data place {', '.join(over)} far from the initial estimate (swapped or moved?): "
                     "started from the data's pose")
        if self.block.any():
            tail += (f"; the data place {', '.join(m for m, k in zip(self.names, self.block) if k)} far from the "
                     "initial estimate as one block, each where the initial estimate has it relative to the others: "
                     "the bootstrap (or the estimate) linked the block to the rest wrongly; started from the "
                     "initial estimate")
        if self.nowhere:
            tail += ("; the initial estimate singles out no camera, it is off everywhere: its frame and scale "
                     "are only as good as its centres")
        if self.used:
            return f"{head}{tail}; starting from the data's shape for {int(self.from_bootstrap.sum())} cameras"
        return f"{head}{tail}; the initial estimate is used as it is ({self.mode})"

    def to_dict(self) -> dict:
        fin = np.isfinite(self.translation)
        return {
            "mode": self.mode, "used": self.used, "scale": self.scale,
            "from_bootstrap": [n for n, u in zip(self.names, self.from_bootstrap) if u],
            "refused": [n for n, r in zip(self.names, self.refused) if r],
            "overruled": [n for n, o in zip(self.names, self.overruled) if o],
            "block": [n for n, k in zip(self.names, self.block) if k],
            "nowhere": self.nowhere,
            "displacement": round(self.displacement, 4) if np.isfinite(self.displacement) else None,
            "disagree": [n for n, a, f in zip(self.names, self.agrees, fin) if f and not a],
            "translation": {n: round(float(d), 5) for n, d, f in zip(self.names, self.translation, fin) if f},
            "rotation": {n: round(float(d), 4) for n, d, f in zip(self.names, self.rotation, fin) if f},
        }


def reconcile(boot: BootstrapResult, names: Sequence[str], R0: np.ndarray, t0: np.ndarray,
              config: EngineConfig, mode: str | None = None) -> Reconciled | None:
    """Align the bootstrap's cameras onto the initial estimate R0 (C, 3, 3), t0 (C, 3) of
    ``names`` and decide per camera where the online pipeline starts (module doc).
    None when fewer than 3 cameras are in both (no frame to align)."""
    b = config.bootstrap
    mode = mode or b.with_initial
    C = len(names)
    assert R0.shape == (C, 3, 3) and t0.shape == (C, 3)
    index = {n: k for k, n in enumerate(boot.names)}
    both = np.array([n in index and bool(boot.located[index[n]]) for n in names])
    idx = np.flatnonzero(both)
    if len(idx) < 3:
        return None
    bi = np.array([index[names[c]] for c in idx])  # the bootstrap's index of each camera in both
    rc = config.refine

    def compare(use: np.ndarray | None):
        al = align_poses(boot.R[bi], boot.t[bi], R0[idx], t0[idx], use, orientations=True)
        if al is None:
            return None
        dt, dr, st, sr = (np.full(C, np.nan) for _ in range(4))
        dt[idx], dr[idx] = al.dt, al.dr
        # the bootstrap's own std, in the initial estimate's units
        st[idx] = al.s * boot.std_translation[bi]
        sr[idx] = boot.std_rotation[bi]
        agrees = both & within_std(dt, dr, st, sr, b.agree_translation, b.agree_rotation)
        # gross against the initial estimate's stated std, or against how far its cameras
        # are off the data typically when that is more (the lower quartile: the better
        # cameras' error, which gross errors of up to three quarters of them do not raise):
        # an estimate whose every camera is 1.5 m / 45° off (stated 0.25 m / 10°) cannot
        # single out a camera the bootstrap got wrong, and refusing half of them by its std
        # left them there (the lab: 0.40 m shape, 11 of 20 refused; from 3 m / 90° every
        # camera was refused and the run failed)
        lim_t, lim_r = b.refuse_sigma * rc.initial_std_translation, b.refuse_sigma * rc.initial_std_rotation
        typical_t, typical_r = float(np.quantile(al.dt, 0.25)), float(np.quantile(al.dr, 0.25))
        # ... but only when the alignment is sound: its centres fit within the stated std,
        # or the initial estimate's orientations scatter about the aligned bootstrap's,
        # their mean turn less than the typical one (the lab 1.5 m / 45° and 3 m / 90°
        # off: 5-13° and 14-32°). A frame fitted to centres of which most are wrong
        # (cameras swapped) turns them all alike (175° against 121°), and there a gross
        # error is the alignment's, not the estimate's. (Centres that fit with every
        # orientation turned alike are an estimate with one orientation error, a
        # convention mixed up: sound.)
        if typical_t <= rc.initial_std_translation or _frame_angle(R0[idx], al.R) < typical_r:
            lim_t = max(lim_t, b.refuse_sigma * typical_t)
            lim_r = max(lim_r, b.refuse_sigma * typical_r)
        refused = both & ((np.nan_to_num(dt) > lim_t) | (np.nan_to_num(dr) > lim_r))
        return al, dt, dr, st, sr, agrees, refused

    out = compare(None)
    if out is None:
        return None
    refused = out[-1]
    if refused.any() and (both & ~refused).sum() >= 3:
        # a refused camera is a gross error of one of the two: it must not pull the frame
        # the others are compared in (a swapped pair 0.5 m apart is not trimmed)
        again = compare(~refused[idx])
        if again is not None:
            out = again[:-1] + (again[-1] | refused,)
    al, dt, dr, st, sr, agrees, refused = out
    s, keep, Ra, ta = al.s, al.keep, al.R, al.t
    aligned = np.zeros(C, bool)
    aligned[idx] = keep
    overruled = np.zeros(C, bool)
    if mode != "never":
        overruled[idx] = refused[idx] & _held_by_data(boot, bi)
    block = _block(boot, bi, idx, overruled, R0, t0, b.refuse_sigma * rc.initial_std_translation,
                   b.refuse_sigma * rc.initial_std_rotation)
    overruled &= ~block
    if refused.sum() > max(2, 0.25 * both.sum()) or (aligned & ~refused).sum() < max(3, refused.sum()):
        # many cameras refused, or few left to align on: the alignment is in doubt, not a camera
        overruled[:] = False
    usable = both & ~refused
    # 'auto' starts from the data's shape only when the initial estimate is further off than
    # it claims: the case where the first adjustment, which trusts the stated std, loses
    # cameras; or further off than that adjustment copes with at all. An estimate within
    # its std is left alone (the paper's way reaches the limit from it, and a bootstrap
    # mistake cannot spoil it).
    # Over the better three quarters of the cameras: whether the estimate as a whole is rougher
    # than it states is no one camera's say. A camera grossly off is judged on its own (refused,
    # overruled), and one the bootstrap chained 1.36 m wrong (stated 0.013 m; HD lab, seed 0)
    # made a 0.25 m / 10° estimate look "off" by the plain RMS and came in with its shape.
    k = both & ~refused
    rms_t, rms_r = _typical_rms(dt[k]), _typical_rms(dr[k])
    off = rms_t > b.auto_sigma * rc.initial_std_translation or rms_r > b.auto_sigma * rc.initial_std_rotation
    # ... or further off than the paper's way copes with, however honestly its std is stated
    off = off or rms_t > b.auto_translation or rms_r > b.auto_rotation
    # ... or than it copes with where the people are far: its association's segments miss
    # each other by the error at the persons (the turn times their distance), not by the
    # angle. The lab's persons are 4-14 m from their cameras (median 6.7 m), a warehouse's
    # 9-16 m (14 m): from 0.25 m / 10° the paper's way holds the lab and put a warehouse
    # camera 5.3 m off (0.030 m from the data's shape)
    reach = _reach(boot, bi, al.s, dt[idx], dr[idx])
    k_reach = k[idx] & np.isfinite(reach)
    displacement = _typical_rms(reach[k_reach]) if k_reach.any() else float("nan")
    off = off or displacement > b.auto_displacement
    # every camera refused: the estimate singles out none, it is off everywhere (each camera
    # of a 4 m room 3 m / 90° off, most of them swapped). The data's shape then, in the
    # frame its centres give, however rough: kept as it is, it was never calibrated (the
    # steep room from 3 m / 90°: 1.39 m shape)
    nowhere = both.sum() >= 3 and bool(refused[both].all())
    if mode == "never" or (mode == "auto" and not nowhere and (agrees[both].all() or not off)):
        use = overruled.copy()
    elif nowhere:
        use = both.copy()
    else:
        use = usable | overruled
    R, t = R0.copy(), t0.copy()
    R_data, t_data = np.full((C, 3, 3), np.nan), np.full((C, 3), np.nan)
    for i, c in enumerate(idx):
        if use[c]:
            R[c], t[c] = Ra[i], ta[i]
        if usable[c] or overruled[c]:
            R_data[c], t_data[c] = Ra[i], ta[i]
    return Reconciled(tuple(names), R, t, dt, dr, agrees, refused, use, aligned, float(s), mode, st, sr, overruled,
                      block, nowhere and mode != "never", displacement, R_data, t_data)


_BLOCK_TRIES = 1000  # three-camera sets ``_block`` fits from (all of them up to 19 cameras overruled)


def _block(boot: BootstrapResult, bi: np.ndarray, idx: np.ndarray, overruled: np.ndarray, R0: np.ndarray,
           t0: np.ndarray, lim_t: float, lim_r: float) -> np.ndarray:
    """(C,) bool: of the ``overruled`` (C,) cameras (``idx`` (N,) in the initial estimate
    R0, t0; ``bi`` (N,) the bootstrap's index of each), the three or more that, aligned on
    their own (bootstrap onto initial estimate), lie within ``lim_t`` m / ``lim_r`` deg of
    the initial estimate: the two agree on where they are relative to each other and
    disagree on one link, that of the block to the rest. Cameras swapped or moved one by one
    do not fit one similarity; a block does when the bootstrap chained it to the others
    through a wrong pair (slow, pausing walkers in the lab: five cameras of one room
    6-15 m / 61-73° off, each within 0.3 m / 12° of the estimate aligned on its own, the
    run 3.8 m off when they started from the data). Which of the two got the link wrong
    the cameras' own fit cannot say; the initial estimate, within its refusal limits for
    every camera of the block once the block's own similarity is taken, keeps them, and the
    pipeline's association decides."""
    out = np.zeros(len(overruled), bool)
    k = np.flatnonzero(overruled[idx])  # positions in idx / bi
    if len(k) < 3:
        return out
    Rb, tb, Ri, ti = boot.R[bi[k]], boot.t[bi[k]], R0[idx[k]], t0[idx[k]]
    best = np.zeros(len(k), bool)
    # the largest set one similarity fits, tried from every three (swapped cameras beside a
    # block are too many for a trimmed fit of all of them)
    for tri in itertools.islice(itertools.combinations(range(len(k)), 3), _BLOCK_TRIES):
        use = np.zeros(len(k), bool)
        use[list(tri)] = True
        al = align_poses(Rb, tb, Ri, ti, use, orientations=True)
        if al is None:
            continue
        fits = (al.dt <= lim_t) & (al.dr <= lim_r)
        if fits[use].all() and fits.sum() > best.sum():
            best = fits
    if best.sum() >= 3:
        out[idx[k[best]]] = True
    return out


def _frame_angle(R0: np.ndarray, R: np.ndarray) -> float:
    """deg: the mean rotation (chordal L2) between orientations R0 (N, 3, 3) and R (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return float(np.degrees(Rotation.from_matrix(np.einsum("nij,nkj->nik", R0, R)).mean().magnitude()))


def _reach(boot: BootstrapResult, bi: np.ndarray, scale: float, dt: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """(N,) how far the initial estimate's error of each camera ``bi`` (N,) (centre dt (N,)
    in its units, orientation dr (N,) deg) moves what the camera sees, at the median
    distance of the points it saw in the bootstrap (``scale``: initial-estimate units per
    bootstrap unit); NaN where that distance is not known."""
    if boot.depth is None:
        return np.full(len(bi), np.nan)
    return dt + np.radians(dr) * scale * boot.depth[bi]


def _typical_rms(d: np.ndarray, share: float = 0.75) -> float:
    """RMS of the smallest ``share`` of ``d`` (at least one; 0 for none)."""
    d = np.sort(np.asarray(d, dtype=np.float64))
    return float(np.sqrt(np.mean(d[: max(1, math.ceil(share * len(d)))] ** 2))) if len(d) else 0.0


def _held_by_data(boot: BootstrapResult, bi: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the bootstrap's placed cameras ``bi`` (N,) its last bundle
    adjustment holds as firmly as the others: at least a quarter of the median camera's
    observations, a median reprojection error within twice the median camera's (or 2 px
    of it), and a finite std. A camera the bootstrap chained wrongly keeps few views, or
    fits them badly."""
    if boot.residual_px is None or boot.observations is None:
        return np.zeros(len(bi), bool)
    res, obs, std = boot.residual_px[bi], boot.observations[bi], boot.std_translation[bi]
    placed = np.isfinite(res) & (obs > 0)
    if placed.sum() < 3:
        return np.zeros(len(bi), bool)
    med_res, med_obs = float(np.median(res[placed])), float(np.median(obs[placed]))
    with np.errstate(invalid="ignore"):
        return placed & np.isfinite(std) & (obs >= 0.25 * med_obs) & (res <= max(2 * med_res, med_res + 2.0))


def bootstrap_start(cameras: CameraSet, intrinsics: Mapping[str, Intrinsics], config: EngineConfig,
                    messages: Iterable[KeypointMessage], *, seed: int = 0, progress: Progress | None = None
                    ) -> tuple[Reconciled | None, BootstrapResult | None, str]:
    """The bootstrap on the first ``bootstrap.max_seconds`` of ``messages`` and its
    reconciliation with ``cameras``' initial estimate. Returns (reconciled or None,
    bootstrap or None, a note saying what happened); a bootstrap the data do not allow is
    not an error here: the initial estimate is then used as it is."""
    try:
        boot = bootstrap_messages(intrinsics, config, messages, seed=seed, progress=progress)
    except BootstrapError as e:
        return None, None, f"bootstrap not possible ({e}): the initial estimate is used as it is"
    return reconcile_cameras(boot, cameras, config)


def reconcile_cameras(boot: BootstrapResult, cameras: CameraSet, config: EngineConfig
                      ) -> tuple[Reconciled | None, BootstrapResult, str]:
    """``reconcile`` against a CameraSet's initial estimate; (reconciled, boot, note)."""
    R0 = np.array([cameras.extrinsics[n].pose.R for n in cameras.names])
    t0 = np.array([cameras.extrinsics[n].pose.t for n in cameras.names])
    rec = reconcile(boot, cameras.names, R0, t0, config)
    if rec is None:
        return None, boot, (f"the bootstrap placed {int(boot.located.sum())} cameras, fewer than 3 of them in the "
                            "initial estimate: the initial estimate is used as it is")
    return rec, boot, rec.summary()
