"""Camera models and the AIS-compatible camera YAML files (shared/FORMATS.md).

Projection with OpenCV's distortion model is numpy (so the simulator and edge
clients need no OpenCV); undistortion uses OpenCV, imported lazily.
"""

from __future__ import annotations

import functools
import math
import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from .geometry import R_to_quat, quat_to_R

DIST_SIZES = (0, 4, 5, 8, 12, 14)


class CameraFileError(ValueError):
    """A camera file that does not match FORMATS.md; says file, line and field."""

    def __init__(self, source: str, line: int | None, field: str, reason: str):
        self.source, self.line, self.field, self.reason = source, line, field, reason
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {field}: {reason}" if field else f"{where}: {reason}")


@dataclass(frozen=True, eq=False)
class Intrinsics:
    """Pinhole + OpenCV distortion.

    dist: (n,) float64 with n in DIST_SIZES, OpenCV order (k1, k2, p1, p2, k3, ...).
    resolution: (width, height) the intrinsics refer to.
    """

    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray
    resolution: tuple[int, int]

    def __post_init__(self) -> None:
        assert self.dist.ndim == 1 and len(self.dist) in DIST_SIZES

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled_to(self, resolution: tuple[int, int]) -> "Intrinsics":
        """The same camera for images of another resolution (mean of the two ratios)."""
        w, h = resolution
        if (w, h) == tuple(self.resolution):
            return self
        s = 0.5 * (w / self.resolution[0] + h / self.resolution[1])
        return replace(
            self, fx=self.fx * s, fy=self.fy * s, cx=self.cx * s, cy=self.cy * s,
            resolution=(int(w), int(h)),
        )

    def at(self, size: tuple[int, int]) -> "Intrinsics | None":
        """The camera for a message of ``size`` (w, h): scaled to it, or None when its
        aspect differs (by more than 2 %): another camera mode, not this calibration."""
        w, h = size
        bw, bh = self.resolution
        if h <= 0 or abs((w / h) / (bw / bh) - 1) >= 0.02:
            return None
        return self.scaled_to((w, h))

    @functools.cached_property
    def fold_radius(self) -> float:
        """Distorted normalised radius beyond which the radial distortion polynomial
        stops growing (inf: not within 79° of the axis). Past it several directions map
        to one pixel (strong barrel coefficients fitted to the image centre fold back at
        its corners), so a keypoint there has no one ray."""
        return radial_fold(self.dist)[1]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Intrinsics):
            return NotImplemented
        return (
            self.name == other.name
            and np.allclose([self.fx, self.fy, self.cx, self.cy], [other.fx, other.fy, other.cx, other.cy])
            and len(self.dist) == len(other.dist)
            and np.allclose(self.dist, other.dist)
            and tuple(self.resolution) == tuple(other.resolution)
        )


def radial_fold(dist: np.ndarray) -> tuple[float, float]:
    """Where OpenCV's radial distortion (k1, k2, k3 over k4, k5, k6 of ``dist``) first
    stops growing with the radius: (undistorted, distorted) normalised radius, searched
    up to 5 (79° off the axis); (inf, inf) when it grows all the way."""
    d = np.zeros(8)
    d[: min(len(dist), 8)] = dist[:8]
    k1, k2, _, _, k3, k4, k5, k6 = d
    r = np.linspace(0.0, 5.0, 2001)
    r2 = r * r
    rd = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    falls = np.flatnonzero(~(np.diff(rd) > 0))
    return (float(r[falls[0]]), float(rd[falls[0]])) if len(falls) else (math.inf, math.inf)


@dataclass(frozen=True, eq=False)
class Pose:
    """Camera pose in the world: R = world_R_cam (3, 3), t = optical centre (3,)."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        assert self.R.shape == (3, 3) and self.t.shape == (3,)

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_quat(translation, quat_xyzw) -> "Pose":
        return Pose(quat_to_R(quat_xyzw), np.asarray(translation, dtype=np.float64).copy())

    @property
    def quat(self) -> np.ndarray:
        return R_to_quat(self.R)

    def to_camera(self, X: np.ndarray) -> np.ndarray:
        """World points (N, 3) → camera frame (N, 3)."""
        return (np.asarray(X) - self.t) @ self.R

    def to_world(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X) @ self.R.T + self.t

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return np.allclose(self.R, other.R) and np.allclose(self.t, other.t)


@dataclass(frozen=True, eq=False)
class Extrinsics:
    """One camera's entry of an extrinsics file."""

    pose: Pose
    resolution: tuple[int, int]
    std_translation: float | None = None  # metres
    std_rotation: float | None = None  # degrees

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Extrinsics):
            return NotImplemented
        return self.pose == other.pose and tuple(self.resolution) == tuple(other.resolution)


# ------------------------------------------------------------------ projection


def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Normalised undistorted (N, 2) → normalised distorted (N, 2), OpenCV's model."""
    xy = np.asarray(xy, dtype=np.float64)
    d = np.zeros(14)
    d[: len(dist)] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = d
    if tx or ty:
        return _distort_cv2(xy, dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return np.stack([xd, yd], axis=1)


def _distort_cv2(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    import cv2  # the tilted-sensor model is rare; let OpenCV do it

    pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, np.float64))
    return out.reshape(-1, 2)


def project(X: np.ndarray, intr: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) → distorted pixels (N, 2) and depth (N,) along the optical axis.

    Points with depth <= 0 get NaN pixels.
    """
    Xc = pose.to_camera(np.asarray(X, dtype=np.float64).reshape(-1, 3))
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = Xc[:, :2] / z[:, None]
    xy[z <= 1e-9] = np.nan
    return normalized_to_pixels(distort(xy, intr.dist) if len(intr.dist) else xy, intr), z


def normalized_to_pixels(xy: np.ndarray, intr: Intrinsics) -> np.ndarray:
    return np.stack([intr.fx * xy[:, 0] + intr.cx, intr.fy * xy[:, 1] + intr.cy], axis=1)


def pixels_to_normalized_distorted(uv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    return np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy], axis=1)


def undistort(uv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Distorted pixels (N, 2) → undistorted normalised coordinates (N, 2).

    OpenCV's iterative inverse with a tight criterion (its default 5 iterations leave
    sub-pixel bias at the image corners of wide lenses).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 2))
    if not len(intr.dist) or not np.any(intr.dist):
        return pixels_to_normalized_distorted(uv, intr)
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    src = uv.reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        out = cv2.undistortPointsIter(src, intr.K, intr.dist, None, None, crit)
    else:  # OpenCV 5 folded the criteria into undistortPoints
        out = cv2.undistortPoints(src, intr.K, intr.dist, None, None, None, crit)
    return out.reshape(-1, 2)


def rays(uv: np.ndarray, intr: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels (N, 2) → world ray origin (3,) and unit directions (N, 3)."""
    xy = undistort(uv, intr)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ pose.R.T
    return pose.t.copy(), d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------------ YAML files


class _Doc:
    """A parsed YAML mapping with the line of each top-level key, for error messages."""

    def __init__(self, text: str, source: str):
        self.source = source
        try:
            node = yaml.compose(text, Loader=yaml.SafeLoader)
            data = yaml.safe_load(text)
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            line = mark.line + 1 if mark else None
            problem = getattr(e, "problem", None) or str(e)
            raise CameraFileError(source, line, "", f"not valid YAML: {problem}") from None
        if data is None:
            raise CameraFileError(source, None, "", "file is empty")
        if not isinstance(data, dict):
            raise CameraFileError(source, 1, "", "expected a mapping of camera names")
        self.data: dict = data
        self.lines: dict[str, int] = {}
        for k, v in node.value:
            self.lines[str(k.value)] = k.start_mark.line + 1
            if isinstance(v, yaml.MappingNode):
                for kk, _ in v.value:
                    self.lines[f"{k.value}.{kk.value}"] = kk.start_mark.line + 1

    def error(self, key: str, reason: str) -> CameraFileError:
        cam = key.split(".")[0]
        return CameraFileError(self.source, self.lines.get(key, self.lines.get(cam)), key, reason)

    def numbers(self, cam: str, key: str, sizes: tuple[int, ...]) -> list[float]:
        entry = self.data[cam]
        if key not in entry:
            raise self.error(cam, f"missing '{key}'")
        v = entry[key]
        if not isinstance(v, list) or len(v) not in sizes:
            got = f"{len(v)} values" if isinstance(v, list) else type(v).__name__
            want = " or ".join(str(s) for s in sizes)
            raise self.error(f"{cam}.{key}", f"expected {want} numbers, got {got}")
        out = []
        for i, x in enumerate(v):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise self.error(f"{cam}.{key}", f"element {i} is {x!r}, not a finite number")
            out.append(float(x))
        return out

    def cameras(self) -> list[str]:
        names = []
        for cam, entry in self.data.items():
            if not isinstance(entry, dict):
                raise self.error(str(cam), "expected a mapping with the camera's fields")
            names.append(str(cam))
        return names


def _resolution(doc: _Doc, cam: str) -> tuple[int, int]:
    w, h = doc.numbers(cam, "resolution", (2,))
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise doc.error(f"{cam}.resolution", f"expected positive integer width and height, got {w}x{h}")
    return int(w), int(h)


def _read(path: str | os.PathLike, what: str) -> str:
    p = Path(path)
    if not p.is_file():
        raise CameraFileError(str(p), None, "", f"{what} file does not exist")
    try:
        return p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise CameraFileError(str(p), None, "", f"cannot read: {e}") from None


def load_intrinsics(path: str | os.PathLike) -> dict[str, Intrinsics]:
    return parse_intrinsics(_read(path, "intrinsics"), str(path))


def load_extrinsics(path: str | os.PathLike) -> dict[str, Extrinsics]:
    return parse_extrinsics(_read(path, "extrinsics"), str(path))


def parse_intrinsics(text: str, source: str = "<intrinsics>") -> dict[str, Intrinsics]:
    doc = _Doc(text, source)
    out = {}
    for cam in doc.cameras():
        fx, fy, cx, cy = doc.numbers(cam, "intrinsics", (4,))
        if fx <= 0 or fy <= 0:
            raise doc.error(f"{cam}.intrinsics", f"focal lengths must be positive, got {fx}, {fy}")
        dist = doc.numbers(cam, "distortion_coeffs", DIST_SIZES) if "distortion_coeffs" in doc.data[cam] else []
        out[cam] = Intrinsics(cam, fx, fy, cx, cy, np.array(dist, dtype=np.float64), _resolution(doc, cam))
    return out


def parse_extrinsics(text: str, source: str = "<extrinsics>") -> dict[str, Extrinsics]:
    doc = _Doc(text, source)
    out = {}
    for cam in doc.cameras():
        t = doc.numbers(cam, "translation", (3,))
        q = doc.numbers(cam, "rotation", (4,))
        n = math.sqrt(sum(x * x for x in q))
        if abs(n - 1) > 1e-3:
            raise doc.error(f"{cam}.rotation", f"quaternion [x, y, z, w] must be unit length, norm is {n:.6f}")
        res = _resolution(doc, cam) if "resolution" in doc.data[cam] else None
        entry = doc.data[cam]
        std_t = entry.get("std_translation")
        std_r = entry.get("std_rotation")
        out[cam] = Extrinsics(
            Pose.from_quat(t, q), res if res else (0, 0),
            float(std_t) if isinstance(std_t, (int, float)) else None,
            float(std_r) if isinstance(std_r, (int, float)) else None,
        )
    return out


def dump_extrinsics(cams: Mapping[str, Extrinsics], *, comment: str | None = None,
                    extra: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """Extrinsics YAML text (FORMATS.md); ``extra`` adds per-camera keys."""
    doc: dict[str, Any] = {}
    for cam, e in cams.items():
        d: dict[str, Any] = {
            "translation": [float(x) for x in e.pose.t],
            "rotation": [float(x) for x in e.pose.quat],
            "resolution": [int(e.resolution[0]), int(e.resolution[1])],
        }
        if e.std_translation is not None:
            d["std_translation"] = float(e.std_translation)
        if e.std_rotation is not None:
            d["std_rotation"] = float(e.std_rotation)
        if extra and cam in extra:
            d.update(extra[cam])
        doc[cam] = d
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)
    if comment:
        text = "".join(f"# {line}\n" for line in comment.splitlines()) + text
    return text


def dump_intrinsics(cams: Mapping[str, Intrinsics]) -> str:
    """Intrinsics YAML text (FORMATS.md), cameras in the given order."""
    doc = {
        cam: {
            "intrinsics": [float(i.fx), float(i.fy), float(i.cx), float(i.cy)],
            "distortion_coeffs": [float(x) for x in i.dist],
            "resolution": [int(i.resolution[0]), int(i.resolution[1])],
        }
        for cam, i in cams.items()
    }
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)


def save_intrinsics(path: str | os.PathLike, cams: Mapping[str, Intrinsics]) -> None:
    write_atomic(path, dump_intrinsics(cams))


def write_atomic(path: str | os.PathLike, text: str | bytes) -> None:
    """Write a file so that readers see the old or the new content, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = text.encode() if isinstance(text, str) else text
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o644)  # mkstemp makes 0600; results are meant to be shared
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:  # make the rename itself durable
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def save_extrinsics(path: str | os.PathLike, cams: Mapping[str, Extrinsics], **kw: Any) -> None:
    write_atomic(path, dump_extrinsics(cams, **kw))


@dataclass(frozen=True)
class CameraSet:
    """Intrinsics and a pose estimate for the same cameras, in a stable order."""

    names: tuple[str, ...]
    intrinsics: Mapping[str, Intrinsics]
    extrinsics: Mapping[str, Extrinsics]

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """Each camera's keypoint message size (width, height): the pixels the engine
        works in (``EngineConfig.for_images``)."""
        return [self.extrinsics[n].resolution for n in self.names]

    @staticmethod
    def load(intrinsics: str | os.PathLike, extrinsics: str | os.PathLike) -> "CameraSet":
        return CameraSet.combine(load_intrinsics(intrinsics), load_extrinsics(extrinsics),
                                 str(intrinsics), str(extrinsics))

    @staticmethod
    def combine(intr: Mapping[str, Intrinsics], ext: Mapping[str, Extrinsics],
                intr_src: str = "intrinsics", ext_src: str = "extrinsics") -> "CameraSet":
        only_i = sorted(set(intr) - set(ext), key=_natural)
        only_e = sorted(set(ext) - set(intr), key=_natural)
        if only_i or only_e:
            parts = []
            if only_i:
                parts.append(f"in the intrinsics only: {', '.join(only_i)}")
            if only_e:
                parts.append(f"in the extrinsics only: {', '.join(only_e)}")
            raise CameraFileError(ext_src, None, "", "camera sets differ: " + "; ".join(parts))
        names = tuple(sorted(intr, key=_natural))
        # Intrinsics are expressed at the resolution of the keypoint messages.
        ext2 = {}
        intr2 = {}
        for n in names:
            e = ext[n]
            res = e.resolution if e.resolution != (0, 0) else intr[n].resolution
            ext2[n] = replace(e, resolution=res)
            intr2[n] = intr[n].scaled_to(res)
        return CameraSet(names, intr2, ext2)

    def poses(self) -> dict[str, Pose]:
        return {n: self.extrinsics[n].pose for n in self.names}


def _natural(name: str) -> tuple:
    """cam_2 before cam_10."""
    import re

    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name))


natural_key = _natural
