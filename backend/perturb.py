"""Initial estimates for evaluation: exact-magnitude random perturbations (the paper's protocol)."""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

import numpy as np

from .cameras import Extrinsics, Pose, natural_key
from .geometry import so3_exp


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def perturb_pose(pose: Pose, translation: float, rotation_deg: float, rng: np.random.Generator) -> Pose:
    """The camera moved exactly `translation` m and turned exactly `rotation_deg` about its centre."""
    dR = so3_exp(np.radians(rotation_deg) * _unit(rng))
    return Pose(dR @ pose.R, pose.t + translation * _unit(rng))


def perturb_extrinsics(cams: Mapping[str, Extrinsics], translation: float, rotation_deg: float,
                       *, seed: int = 0, keep_first: bool = True) -> dict[str, Extrinsics]:
    rng = np.random.default_rng(seed)
    names = sorted(cams, key=natural_key)
    out = {}
    for i, n in enumerate(names):
        e = cams[n]
        if i == 0 and keep_first:
            out[n] = replace(e, std_translation=None, std_rotation=None)
            continue
        out[n] = replace(e, pose=perturb_pose(e.pose, translation, rotation_deg, rng),
                         std_translation=None, std_rotation=None)
    return out
