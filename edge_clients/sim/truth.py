"""Ground truth of a simulated run and its .truth.npz sidecar."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Truth:
    """Everything the simulator knows; see ``save`` for the sidecar's arrays."""

    sensors: tuple[str, ...]
    start_time: float
    times: np.ndarray  # (T,) float64 epoch s of the world ticks
    joints: np.ndarray  # (P, T, 17, 3) float64 true 3D joints (world frame)
    heights: np.ndarray  # (P,)

    @staticmethod
    def load(path: str | os.PathLike) -> "Truth":
        raise NotImplementedError("work in progress")
