"""Accuracy figures of a calibration against a reference (shared/FORMATS.md)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Mapping

import numpy as np

from .cameras import Pose, natural_key
from .geometry import align_poses as align_cameras, centres_fix_rotation, project_so3, rotation_angle_deg, umeyama


MIN_CAMERAS = 2  # an alignment needs two cameras' poses (or three centres)


@dataclass(frozen=True)
class Stats:
    mean: float
    std: float
    min: float
    max: float

    @staticmethod
    def of(x: np.ndarray) -> "Stats":
        x = np.asarray(x, dtype=np.float64)
        return Stats(float(x.mean()), float(x.std()), float(x.min()), float(x.max()))


@dataclass(frozen=True)
class Accuracy:
    """Rigid figures (the paper's), shape figures (similarity) and the scale factor.

    per_camera: name → (rigid position error m, orientation error deg,
    shape position error m, shape orientation error deg).
    """

    cameras: tuple[str, ...]
    position: Stats
    orientation: Stats
    shape_position: Stats
    shape_orientation: Stats
    scale: float
    per_camera: Mapping[str, tuple[float, float, float, float]]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cameras"] = list(self.cameras)
        d["per_camera"] = {k: dict(zip(("position", "orientation", "shape_position", "shape_orientation"), v))
                           for k, v in self.per_camera.items()}
        return d

    def summary(self) -> str:
        return (
            f"position {self.position.mean:.4f} m (max {self.position.max:.4f}), "
            f"orientation {self.orientation.mean:.3f}° (max {self.orientation.max:.3f}), "
            f"shape {self.shape_position.mean:.4f} m / {self.shape_orientation.mean:.3f}°, "
            f"scale {self.scale:.5f}"
        )


def _align(src: np.ndarray, dst: np.ndarray, src_R: np.ndarray, dst_R: np.ndarray, with_scale: bool
           ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with dst ≈ s·R·src + t. src, dst: (N, 3) camera centres, src_R, dst_R:
    (N, 3, 3) world_R_cam. Umeyama on the centres (shared/FORMATS.md); where they cannot
    fix the rotation (two cameras, or all on one line: any turn about the line fits), the
    rotation is the chordal mean of dst_R·src_Rᵀ, i.e. the orientations fix it, and the
    scale is the ratio of the centres' spreads."""
    if centres_fix_rotation(src):
        return umeyama(src, dst, with_scale=with_scale)
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    R = project_so3(np.einsum("nij,nkj->ik", dst_R, src_R))
    ns, nd = float(np.sum(xs**2)), float(np.sum(xd**2))
    s = float(np.sqrt(nd / ns)) if with_scale and ns > 0 else 1.0
    return s, R, dst.mean(0) - s * R @ src.mean(0)


def align_poses(result: Mapping[str, Pose], reference: Mapping[str, Pose], names, *, with_scale: bool
                ) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) that maps the result's frame onto the reference's, over the cameras
    ``names`` (as the accuracy figures align)."""
    return _align(np.array([result[n].t for n in names]), np.array([reference[n].t for n in names]),
                  np.array([result[n].R for n in names]), np.array([reference[n].R for n in names]), with_scale)


def _errors(result: Mapping[str, Pose], reference: Mapping[str, Pose], names, with_scale: bool):
    src = np.array([result[n].t for n in names])
    dst = np.array([reference[n].t for n in names])
    s, R, t = align_poses(result, reference, names, with_scale=with_scale)
    pos = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
    ori = np.array([rotation_angle_deg(R @ result[n].R, reference[n].R) for n in names])
    return s, pos, ori


def up_tilt(result: Mapping[str, Pose], reference: Mapping[str, Pose], up: np.ndarray) -> float:
    """deg: the result's z axis against ``up`` (3,), the floor's upward normal in the
    reference's frame, through the similarity that maps the result's poses onto the
    reference's (orientations too: a corridor's centres leave the turn about it loose).
    How level a result whose world is the floor's frame stands; NaN with < 3 cameras."""
    names = sorted(set(result) & set(reference), key=natural_key)
    if len(names) < 3:
        return float("nan")
    a = align_cameras(np.array([result[n].R for n in names]), np.array([result[n].t for n in names]),
                      np.array([reference[n].R for n in names]), np.array([reference[n].t for n in names]),
                      orientations=True)
    if a is None:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(a.Rw[:, 2] @ up / np.linalg.norm(up), -1.0, 1.0))))


def evaluate(result: Mapping[str, Pose], reference: Mapping[str, Pose],
             cameras: list[str] | None = None) -> Accuracy:
    """Compare camera poses; both map camera name → Pose. Needs >= 2 shared cameras
    (with two, or all on one line, the orientations take part in the alignment)."""
    names = cameras or sorted(set(result) & set(reference), key=natural_key)
    missing = [n for n in names if n not in result or n not in reference]
    if missing:
        raise ValueError(f"cameras missing from result or reference: {', '.join(missing)}")
    if len(names) < MIN_CAMERAS:
        raise ValueError(f"need at least {MIN_CAMERAS} cameras in common to align, got {len(names)}")
    _, pos, ori = _errors(result, reference, names, with_scale=False)
    scale, spos, sori = _errors(result, reference, names, with_scale=True)
    per = {n: (float(pos[i]), float(ori[i]), float(spos[i]), float(sori[i])) for i, n in enumerate(names)}
    return Accuracy(tuple(names), Stats.of(pos), Stats.of(ori), Stats.of(spos), Stats.of(sori),
                    float(scale), per)
