"""Do two halves of the data agree on the calibration? A check of the stated std.

The final batch's std is its marginal covariance: honest when every association is right
and the model holds. Where they are not, it can be far too small. Two walkers in a
camera chain leave a few phantom pairs: the chain bends by decimetres, and the result
still states 1-2 cm (docs/bones.md, Session 32). Nothing in the one solve shows it.

So the final batch is solved again on each of two halves of the archived frames:
alternate blocks of ``refine.split_block`` s, so that both halves see the whole walk.
Each half is solved from the result, and the halves' poses are compared after a robust
similarity alignment (the frame is the data's gauge). Each half states its own std;
if the model holds, the two differ per axis by about the root sum of their squares (a
distance of sqrt(3) times that). A camera whose halves differ by more than
``refine.split_ratio`` times that, in translation or rotation, is named. Its covariance
is widened by the square of the excess: the std the data show, not the one the model
claimed. Measured, well-posed networks are left alone: their halves differ by about what
their stds predict. The halves' own stds matter where a half has little data on a
camera: then it states a wide std itself, and the difference is no surprise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from .geometry import pose_std, rotation_angle_deg

SQRT3 = float(np.sqrt(3.0))


def interleaved_halves(times: np.ndarray, block: float) -> np.ndarray:
    """(N,) int 0/1: which half each frame time (N,) s falls in (alternate ``block`` s)."""
    assert block > 0
    if not len(times):
        return np.zeros(0, np.int64)
    return (np.floor((times - times.min()) / block).astype(np.int64) % 2)


@dataclass(frozen=True, eq=False)
class SplitCheck:
    """The halves compared. Per camera (C,): apart_m, apart_deg the halves' difference
    after alignment (NaN: not in both); stated_m, stated_deg the std the full solve stated
    (1D, RMS over the axes), before any widening; factor the std factor applied (1: none)."""

    names: tuple[str, ...]
    apart_m: np.ndarray
    apart_deg: np.ndarray
    stated_m: np.ndarray
    stated_deg: np.ndarray
    factor: np.ndarray
    ratio: float

    def __post_init__(self) -> None:
        C = len(self.names)
        for a in (self.apart_m, self.apart_deg, self.stated_m, self.stated_deg, self.factor):
            assert a.shape == (C,)

    @property
    def widened(self) -> list[str]:
        return [n for n, f in zip(self.names, self.factor) if f > 1.0]

    def to_dict(self) -> dict[str, Any]:
        def r(x: float, d: int) -> float | None:
            return round(float(x), d) if np.isfinite(x) else None

        return {"ratio": self.ratio, "widened": self.widened,
                "cameras": {n: {"apart_m": r(self.apart_m[c], 4), "apart_deg": r(self.apart_deg[c], 3),
                                "stated_m": r(self.stated_m[c], 4), "stated_deg": r(self.stated_deg[c], 3),
                                "factor": r(self.factor[c], 2)} for c, n in enumerate(self.names)}}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SplitCheck":
        """``to_dict``'s inverse (a resumed session keeps its report)."""
        names = tuple(d["cameras"])

        def col(k: str) -> np.ndarray:
            return np.array([np.nan if d["cameras"][n][k] is None else d["cameras"][n][k] for n in names], float)

        return cls(names, col("apart_m"), col("apart_deg"), col("stated_m"), col("stated_deg"),
                   np.nan_to_num(col("factor"), nan=1.0), float(d["ratio"]))

    def summary(self) -> str:
        ok = np.isfinite(self.apart_m)
        if not ok.any():
            return "split-half check: no camera was solved in both halves"
        worst = int(np.nanargmax(self.apart_m))
        head = (f"split-half check: the two halves of the data differ by up to {np.nanmax(self.apart_m):.3f} m / "
                f"{np.nanmax(self.apart_deg):.2f}° ({self.names[worst]})")
        if not self.widened:
            return head + ", as the stated std predicts"
        return (head + f"; the data do not pin {', '.join(self.widened)} as tightly as the solve stated: their std "
                f"widened by {', '.join(f'{f:.1f}x' for f in self.factor if f > 1.0)}")


def robust_similarity(R_src: np.ndarray, t_src: np.ndarray, R_dst: np.ndarray, t_dst: np.ndarray,
                      width_m: np.ndarray, width_rad: np.ndarray, rounds: int = 20
                      ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, Rw, tw) mapping the src poses (N, 3, 3), (N, 3) onto the dst poses: Rw·R_src ≈
    R_dst, s·Rw·t_src + tw ≈ t_dst. The turn is the cameras' orientations' chordal mean
    (along a corridor the centres leave the turn about it open; orientations do not),
    scale and shift the centres' least squares given it; both iteratively reweighted with
    Cauchy weights of widths ``width_m``, ``width_rad`` (N,), so that a camera the halves
    disagree on is not spread over the others."""
    N = len(t_src)
    wr = np.ones(N)
    wt = np.ones(N)
    Rw, s, tw = np.eye(3), 1.0, np.zeros(3)
    for _ in range(rounds):
        U, _, Vt = np.linalg.svd(np.einsum("n,nij,nkj->ik", wr, R_dst, R_src))  # sum w R_dst R_src^T
        E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        Rw = U @ E @ Vt
        w = wt / wt.sum()
        a = t_src @ Rw.T
        mu_a, mu_d = w @ a, w @ t_dst
        var = float(w @ np.sum((a - mu_a) ** 2, axis=1))
        s = float(w @ np.sum((a - mu_a) * (t_dst - mu_d), axis=1)) / var if var > 1e-12 else 1.0
        tw = mu_d - s * mu_a
        r_t = np.linalg.norm(s * a + tw - t_dst, axis=1)
        r_r = np.radians([rotation_angle_deg(Rw @ x, y) for x, y in zip(R_src, R_dst)])
        wt = 1.0 / (1.0 + (r_t / width_m) ** 2)
        wr = 1.0 / (1.0 + (r_r / width_rad) ** 2)
    return s, Rw, tw


def compare_halves(names: Sequence[str], S: np.ndarray,
                   halves: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], ratio: float) -> SplitCheck:
    """names (C,); S (C, 6, 6) the result's stated covariance; halves: two (R (C, 3, 3),
    t (C, 3), solved (C,) bool, cov (C, 6, 6)) solutions on the halves with their own
    stated covariances (NaN: none)."""
    C = len(names)
    assert S.shape == (C, 6, 6) and len(halves) == 2
    st, sr = pose_std(S)
    (R0, t0, a0, P0), (R1, t1, a1, P1) = halves
    # what the two halves' own stds let their difference be, per axis (1D)
    (t0_std, r0_std), (t1_std, r1_std) = pose_std(P0), pose_std(P1)
    d_m, d_rad = np.hypot(t0_std, t1_std), np.hypot(r0_std, r1_std)
    apart_m = np.full(C, np.nan)
    apart_deg = np.full(C, np.nan)
    both = a0 & a1 & np.isfinite(d_m) & (d_m > 0) & np.isfinite(d_rad) & (d_rad > 0)
    if both.sum() >= 3:
        sc, Rw, tw = robust_similarity(R1[both], t1[both], R0[both], t0[both], ratio * SQRT3 * d_m[both],
                                       ratio * SQRT3 * d_rad[both])
        apart_m[both] = np.linalg.norm(sc * t1[both] @ Rw.T + tw - t0[both], axis=1)
        apart_deg[both] = [rotation_angle_deg(Rw @ a, b) for a, b in zip(R1[both], R0[both])]
    with np.errstate(invalid="ignore", divide="ignore"):
        excess = np.fmax(apart_m / SQRT3 / d_m, np.radians(apart_deg) / SQRT3 / d_rad)
    factor = np.where(np.isfinite(excess) & (excess > ratio), excess, 1.0)
    return SplitCheck(tuple(names), apart_m, apart_deg, st, np.degrees(sr), factor, ratio)
