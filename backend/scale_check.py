"""The initial estimate's scale checked against the people's, and corrected when asked.

A run with an initial estimate keeps its frame and scale (the paper's protocol,
``Refiner.keep_scale``): the geometry converges to the data's shape, the scale stays what
the initial estimate's cameras, each off by its error, say. People carry a scale too
(``backend.people``): a known height pins it to 1-2 %, the population prior to about 4 %
for two walkers. The two are independent measurements of one number, each with its std:

- the people's: ``people.ScaleEstimate`` measured on the final estimate (metres per unit);
- the initial estimate's: the least-squares scale of n centres, each scattered by sigma
  per axis about the true shape, has the relative std sigma / sqrt(sum |c_i - c|^2)
  (c: their centroid). sigma is read off the data: the scatter of the initial estimate's
  centres about the final estimate after a similarity alignment (3n - 7 degrees of
  freedom). From a 0.25 m start in the 20-camera lab that is 0.4 %, from 0.75 m 1.3 %.

``bootstrap.initial_scale``: 'keep' reports the check only (FORMATS.md: a result keeps the
initial estimate's scale); 'combine' takes the inverse-variance mean of the two in log
scale; 'people' the people's alone (a walker of known height against a rough floor plan);
'auto' is 'combine' when the walkers' heights are known, else 'keep' (the population
prior speaks of a population, not of who walked here: 5.8 % off for the simulator's pair).
A correction is refused when the two disagree by more than ``bootstrap.refuse_sigma`` of
their joint std (an initial estimate in other units, a wrong height): reported, not made.
The correction scales the result about the centroid of the cameras it used, so the frame
(orientation and centroid) stays the initial estimate's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from .config import BootstrapConfig, EngineConfig
from .geometry import trimmed_similarity
from .people import ScaleEstimate, measure_scale


@dataclass(frozen=True, eq=False)
class ScaleCheck:
    """people: metres per unit of the estimate the people were measured in, with its
    relative std and method; initial_rel_std: the initial estimate's own relative scale std;
    cameras: how many centres that std rests on; mode: what was asked ('auto' resolved);
    factor: what the estimate's centres are multiplied by about ``centre`` (3,) (1: kept);
    refused: a correction was asked for and not made (the two disagree)."""

    people: ScaleEstimate
    initial_rel_std: float
    cameras: int
    mode: str
    factor: float
    centre: np.ndarray
    refused: bool = False

    def __post_init__(self) -> None:
        assert self.centre.shape == (3,)

    @property
    def sigmas(self) -> float:
        """How far apart the two scales are, in std of their difference."""
        return abs(float(np.log(self.people.factor))) / float(np.hypot(self.people.rel_std, self.initial_rel_std))

    @property
    def corrected(self) -> bool:
        return self.factor != 1.0

    @property
    def rel_std(self) -> float:
        """Relative std of the scale the result has."""
        if not self.corrected:
            return self.initial_rel_std
        if self.mode == "people":
            return self.people.rel_std
        return float((self.people.rel_std**-2 + self.initial_rel_std**-2) ** -0.5)

    def apply(self, t: np.ndarray) -> np.ndarray:
        """Centres (..., 3) as the corrected result has them."""
        return self.centre + self.factor * (np.asarray(t, dtype=np.float64) - self.centre)

    def summary(self) -> str:
        p = self.people
        head = (f"scale check: the initial estimate's metre is {p.factor:.4f} ± {100 * p.rel_std:.1f} % true metres by "
                f"the people ({p.method}); its own scale ± {100 * self.initial_rel_std:.1f} % ({self.cameras} cameras); "
                f"{self.sigmas:.1f} sigma apart")
        if self.refused:
            return (f"{head}; NOT corrected ({self.mode}): they disagree by more than the refuse limit: check the "
                    "initial estimate's units and the walkers' heights")
        if self.corrected:
            return (f"{head}; scale corrected by {100 * (self.factor - 1):+.2f} % about the cameras' centroid "
                    f"({self.mode}; ± {100 * self.rel_std:.1f} % now)")
        warn = " (they disagree: check the initial estimate's units and scale)" if self.sigmas > 3 else ""
        return f"{head}; the initial estimate's scale kept ({self.mode}){warn}"

    @staticmethod
    def from_dict(d: dict) -> "ScaleCheck":
        pe = d["people"]
        people = ScaleEstimate(float(pe["factor"]), float(pe["rel_std"]), str(pe["method"]), int(pe["persons"]),
                               tuple(float(h) for h in pe["heights"]), str(pe.get("note", "")))
        return ScaleCheck(people, float(d["initial_rel_std"]), int(d["cameras"]), str(d["mode"]), float(d["factor"]),
                          np.array(d["centre"], dtype=np.float64), bool(d["refused"]))

    def to_dict(self) -> dict:
        return {"people": self.people.to_dict(), "initial_rel_std": self.initial_rel_std, "cameras": self.cameras,
                "sigmas": self.sigmas, "mode": self.mode, "factor": self.factor, "rel_std": self.rel_std,
                "centre": [float(x) for x in self.centre], "refused": self.refused}


def initial_scale_std(initial_t: np.ndarray, final_t: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(relative scale std of the initial estimate, kept (n,) bool) from its centres
    ``initial_t`` (n, 3) against the final estimate's ``final_t`` (n, 3) of the same
    cameras (module doc). None with fewer than 4 centres kept by the robust alignment or
    no spread."""
    assert initial_t.shape == final_t.shape and initial_t.ndim == 2 and initial_t.shape[1] == 3
    if len(initial_t) < 4:
        return None
    fit = trimmed_similarity(final_t, initial_t)
    if fit is None:
        return None
    s, R, t, keep = fit
    n = int(keep.sum())
    if n < 4:
        return None
    res = s * final_t[keep] @ R.T + t - initial_t[keep]
    sigma = float(np.sqrt(np.sum(res**2) / (3 * n - 7)))
    spread = float(np.sum((initial_t[keep] - initial_t[keep].mean(axis=0)) ** 2))
    if spread <= 0:
        return None
    return max(sigma / np.sqrt(spread), 1e-6), keep


def check_scale(initial_t: np.ndarray, final_t: np.ndarray, used: np.ndarray, people: ScaleEstimate,
                config: BootstrapConfig, mode: str | None = None) -> ScaleCheck | None:
    """The check of a final estimate ``final_t`` (C, 3) in the initial estimate's frame and
    scale against the people measured on it, and the correction ``bootstrap.initial_scale``
    (or ``mode``) asks for. ``initial_t`` (C, 3): the initial estimate's centres;
    ``used`` (C,) bool: the cameras the run calibrated. None when fewer than 4 of them
    give the initial estimate's std."""
    C = len(final_t)
    assert initial_t.shape == (C, 3) and final_t.shape == (C, 3) and used.shape == (C,)
    idx = np.flatnonzero(used)
    got = initial_scale_std(initial_t[idx], final_t[idx])
    if got is None:
        return None
    initial_rel, keep = got
    centre = final_t[idx[keep]].mean(axis=0)
    mode = mode or config.initial_scale
    if mode == "auto":
        mode = "combine" if people.method == "known height" else "keep"
    log_k = float(np.log(people.factor))
    if mode == "combine":
        log_k *= initial_rel**2 / (initial_rel**2 + people.rel_std**2)
    elif mode != "people":
        log_k = 0.0
    check = ScaleCheck(people, float(initial_rel), int(keep.sum()), mode, float(np.exp(log_k)), centre)
    if check.corrected and check.sigmas > config.refuse_sigma:
        return replace(check, factor=1.0, refused=True)
    return check


def check_run(frames, R: np.ndarray, t: np.ndarray, used: np.ndarray, initial_t: np.ndarray, config: EngineConfig,
              heights: Sequence[float] = ()) -> ScaleCheck | None:
    """``check_scale`` of a run's final estimate R (C, 3, 3), t (C, 3) (``used`` (C,) bool:
    the cameras it calibrated), the people measured on its archived ``frames``
    (``Pipeline.frames``) with ``heights`` (m) if known. None when no person was measured
    well enough or too few cameras were calibrated."""
    scale, _ = measure_scale(frames, R, t, config.associate, config.bootstrap, heights=heights, cameras=used)
    if scale is None:
        return None
    return check_scale(initial_t, t, used, scale, config.bootstrap)
