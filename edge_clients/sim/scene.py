"""The scene: cameras, the floor, the floor plan (walls) and where people can walk."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from backend.cameras import Intrinsics, Pose


@dataclass(frozen=True, eq=False)
class Floor:
    """The floor plane in the world (camera) frame: origin (3,), axes e1, e2 in the plane
    and the upward normal ``up`` (3,), all float64; (e1, e2, up) is right-handed."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    up: np.ndarray


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Occupancy image of walls and pillars on the floor.

    occupied: (H, W) bool, row 0 at the top of the image; free: (H, W) bool (known free);
    metres_per_pixel; map_R (2, 2), map_t (2,): floor xy = map_R @ map xy + map_t, where
    map xy of the centre of pixel (row, col) is ((col + 0.5) m, (H - row - 0.5) m) * m/px.
    """

    occupied: np.ndarray
    free: np.ndarray
    metres_per_pixel: float
    map_R: np.ndarray
    map_t: np.ndarray


@dataclass(frozen=True, eq=False)
class Scene:
    """Cameras (intrinsics at the message resolution, poses in the world) + floor (+ plan)."""

    names: tuple[str, ...]
    intrinsics: Mapping[str, Intrinsics]
    poses: Mapping[str, Pose]
    floor: Floor
    floorplan: FloorPlan | None = None

    @staticmethod
    def load(cameras_dir: str | os.PathLike, *, camera_height: float = 2.6) -> "Scene":
        """intrinsics.yaml + reference.yaml (+ optional room.yaml with floorplan)."""
        raise NotImplementedError("work in progress")

    @staticmethod
    def from_cameras(intrinsics: Mapping[str, Intrinsics], poses: Mapping[str, Pose],
                     room: Any = None, *, camera_height: float = 2.6) -> "Scene":
        raise NotImplementedError("work in progress")
