"""The scene: cameras, the floor, the floor plan (walls) and where people can walk.

The world frame is the cameras' frame (that of reference.yaml). The floor comes from
room.yaml when the scene has one; otherwise from the camera geometry (``floor_from_cameras``):
cameras are mounted high and looking down, with little roll, so

- "up" is the direction most orthogonal to all cameras' x axes (the smallest
  eigenvector of sum x xᵀ; a roll-free camera's x axis is horizontal), signed so that
  the cameras' image-up axes (-y) point along it; when the x axes do not pin it down
  (cameras all facing one way, eigenvalue gap < 5 %), the mean of the -y axes is used;
- the floor lies ``camera_height`` (default 2.6 m) below the median camera centre
  along "up".
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from backend.cameras import (
    CameraFileError,
    CameraSet,
    Intrinsics,
    Pose,
    load_extrinsics,
    load_intrinsics,
    natural_key,
)
from backend.geometry import quat_to_R


@dataclass(frozen=True, eq=False)
class Floor:
    """The floor plane in the world (camera) frame: origin (3,), axes e1, e2 in the plane
    and the upward unit normal ``up`` (3,), all float64; (e1, e2, up) is right-handed."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    up: np.ndarray

    def __post_init__(self) -> None:
        for a in (self.origin, self.e1, self.e2, self.up):
            assert a.shape == (3,)

    @staticmethod
    def make(origin, e1, up) -> "Floor":
        up = np.asarray(up, np.float64)
        up = up / np.linalg.norm(up)
        e1 = np.asarray(e1, np.float64)
        e1 = e1 - (e1 @ up) * up
        if np.linalg.norm(e1) < 1e-9:
            raise ValueError("floor: e1 is parallel to the normal")
        e1 = e1 / np.linalg.norm(e1)
        return Floor(np.asarray(origin, np.float64).copy(), e1, np.cross(up, e1), up)

    @property
    def R(self) -> np.ndarray:
        """(3, 3) world_R_floor, columns e1, e2, up."""
        return np.stack([self.e1, self.e2, self.up], axis=1)

    def to_world(self, X: np.ndarray) -> np.ndarray:
        """Floor-frame points (..., 3) (x, y in the plane, z height) → world (..., 3)."""
        return np.asarray(X) @ self.R.T + self.origin

    def to_floor(self, X: np.ndarray) -> np.ndarray:
        return (np.asarray(X) - self.origin) @ self.R


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Occupancy image of walls and pillars on the floor.

    occupied: (H, W) bool, dark pixels, row 0 at the top of the image; free: (H, W) bool,
    known-free (bright) pixels; grey is unknown (neither). ``metres_per_pixel``;
    map_R (2, 2), map_t (2,): floor xy = map_R @ map xy + map_t, where the map xy of
    pixel (row, col) spans [col, col + 1] x [H - row - 1, H - row] times m/px (origin at
    the bottom-left corner of the image, as ROS map_server).
    """

    occupied: np.ndarray
    free: np.ndarray
    metres_per_pixel: float
    map_R: np.ndarray
    map_t: np.ndarray

    def pixel_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Floor xy (..., 2) → (row, col) int arrays and an inside-the-image mask."""
        m = (np.asarray(xy) - self.map_t) @ self.map_R  # inverse rotation
        H, W = self.occupied.shape
        col = np.floor(m[..., 0] / self.metres_per_pixel).astype(np.int64)
        row = H - 1 - np.floor(m[..., 1] / self.metres_per_pixel).astype(np.int64)
        inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
        return np.clip(row, 0, H - 1), np.clip(col, 0, W - 1), inside

    def occupied_at(self, xy: np.ndarray) -> np.ndarray:
        """Floor xy (..., 2) → bool, True on walls (outside the image counts as free)."""
        r, c, inside = self.pixel_of(xy)
        return self.occupied[r, c] & inside

    def free_at(self, xy: np.ndarray) -> np.ndarray:
        r, c, inside = self.pixel_of(xy)
        return self.free[r, c] & inside

    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Floor-frame (min xy, max xy) of the image."""
        H, W = self.occupied.shape
        s = self.metres_per_pixel
        corners = np.array([[0, 0], [W * s, 0], [0, H * s], [W * s, H * s]]) @ self.map_R.T + self.map_t
        return corners.min(0), corners.max(0)


@dataclass(frozen=True, eq=False)
class Scene:
    """Cameras (intrinsics at the message resolution, poses in the world) + floor (+ plan).

    names: sensor ids in natural order (cam_2 before cam_10).
    """

    names: tuple[str, ...]
    intrinsics: Mapping[str, Intrinsics]
    poses: Mapping[str, Pose]
    floor: Floor
    floorplan: FloorPlan | None = None

    @staticmethod
    def load(cameras_dir: str | os.PathLike, *, camera_height: float = 2.6) -> "Scene":
        """A directory with intrinsics.yaml and reference.yaml (poses in the world frame),
        and optionally room.yaml (floor plane, floor plan; see ``load_room``)."""
        d = Path(cameras_dir)
        if not d.is_dir():
            raise FileNotFoundError(f"camera directory {d} does not exist")
        cams = CameraSet.combine(load_intrinsics(d / "intrinsics.yaml"),
                                 load_extrinsics(d / "reference.yaml"),
                                 str(d / "intrinsics.yaml"), str(d / "reference.yaml"))
        room = d / "room.yaml"
        return Scene.from_cameras(cams.intrinsics, cams.poses(), room if room.is_file() else None,
                                  camera_height=camera_height)

    @staticmethod
    def from_cameras(intrinsics: Mapping[str, Intrinsics], poses: Mapping[str, Pose],
                     room: Any = None, *, camera_height: float = 2.6) -> "Scene":
        """Cameras given directly (intrinsics at the resolution of the messages).

        room: None (floor from the camera geometry), a path to a room.yaml, or its parsed
        mapping (a relative floor plan image path is then relative to the cwd).
        """
        only_i, only_p = set(intrinsics) - set(poses), set(poses) - set(intrinsics)
        if only_i or only_p:
            raise ValueError(f"camera sets differ: intrinsics only {sorted(only_i)}, poses only {sorted(only_p)}")
        if not intrinsics:
            raise ValueError("a scene needs at least one camera")
        names = tuple(sorted(intrinsics, key=natural_key))
        intr = {n: intrinsics[n] for n in names}
        pos = {n: poses[n] for n in names}
        if room is None:
            floor, plan = floor_from_cameras(pos, camera_height), None
        else:
            floor, plan = load_room(room)
        return Scene(names, intr, pos, floor, plan)

    def subset(self, names: Sequence[str]) -> "Scene":
        """These cameras as a scene of their own, on the same floor and plan (a room of a
        larger network)."""
        unknown = sorted(set(names) - set(self.names))
        if unknown:
            raise ValueError(f"not in the scene: {', '.join(unknown)}")
        keep = tuple(n for n in self.names if n in set(names))
        return Scene(keep, {n: self.intrinsics[n] for n in keep}, {n: self.poses[n] for n in keep},
                     self.floor, self.floorplan)

    def centres(self) -> np.ndarray:
        """(C, 3) camera centres in the world, in ``names`` order."""
        return np.array([self.poses[n].t for n in self.names])


def floor_from_cameras(poses: Mapping[str, Pose], camera_height: float = 2.6) -> Floor:
    """The floor plane guessed from cameras mounted high and looking down (module doc)."""
    Rs = np.array([p.R for p in poses.values()])  # world_R_cam: columns are the camera axes
    xs, ys = Rs[:, :, 0], Rs[:, :, 1]
    image_up = -ys.mean(0)
    w, V = np.linalg.eigh(xs.T @ xs)
    up = V[:, 0]
    if len(xs) < 2 or w[1] - w[0] < 0.05 * len(xs):
        up = image_up
    up = up / np.linalg.norm(up)
    if up @ image_up < 0:
        up = -up
    C = np.array([p.t for p in poses.values()])
    h = float(np.median(C @ up)) - camera_height
    centre = C.mean(0)
    origin = centre - (centre @ up - h) * up
    # e1: the mean viewing direction on the floor (any in-plane direction would do).
    z = Rs[:, :, 2].mean(0)
    e1 = z - (z @ up) * up
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    return Floor.make(origin, e1, up)


def load_room(room: Any) -> tuple[Floor, FloorPlan | None]:
    """room.yaml (path or parsed mapping) → floor plane and optional floor plan.

    floor: {origin: [x, y, z], e1: [x, y, z], normal_up: [x, y, z]} in the world frame;
    floorplan (optional): {image: floorplan.png (or .pgm), metres_per_pixel: 0.05,
    floor_T_map: [x, y, z, qx, qy, qz, qw]} = the image origin (bottom-left corner) in
    the floor frame.
    """
    base = Path(".")
    source = "<room>"
    if isinstance(room, (str, os.PathLike)):
        source = str(room)
        p = Path(room)
        if not p.is_file():
            raise CameraFileError(source, None, "", "room file does not exist")
        base = p.parent
        try:
            room = yaml.safe_load(p.read_text())
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            raise CameraFileError(source, mark.line + 1 if mark else None, "",
                                  f"not valid YAML: {getattr(e, 'problem', e)}") from None
    if not isinstance(room, Mapping) or not isinstance(room.get("floor"), Mapping):
        raise CameraFileError(source, None, "floor", "missing (origin, e1, normal_up)")

    def vec(d: Mapping, key: str, where: str, n: int) -> np.ndarray:
        v = d.get(key)
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise CameraFileError(source, None, f"{where}.{key}", f"expected {n} finite numbers, got {v!r}")
        return np.array(v, np.float64)

    f = room["floor"]
    try:
        floor = Floor.make(vec(f, "origin", "floor", 3), vec(f, "e1", "floor", 3), vec(f, "normal_up", "floor", 3))
    except ValueError as e:
        raise CameraFileError(source, None, "floor", str(e)) from None
    fp = room.get("floorplan")
    if not fp:
        return floor, None
    if not isinstance(fp, Mapping) or not isinstance(fp.get("image"), str):
        raise CameraFileError(source, None, "floorplan.image", "expected an image file name")
    mpp = fp.get("metres_per_pixel", 0.05)
    if not isinstance(mpp, (int, float)) or not mpp > 0:
        raise CameraFileError(source, None, "floorplan.metres_per_pixel", f"expected a positive number, got {mpp!r}")
    T = vec(fp, "floor_T_map", "floorplan", 7)
    img_path = base / fp["image"]
    gray = read_gray_image(img_path)
    R3 = quat_to_R(T[3:])
    # The plan lies in the floor: keep the in-plane part of its rotation.
    yaw = math.atan2(R3[1, 0], R3[0, 0])
    map_R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    plan = FloorPlan(occupied=gray < 100, free=gray > 230, metres_per_pixel=float(mpp),
                     map_R=map_R, map_t=T[:2].copy())
    return floor, plan


def read_gray_image(path: str | os.PathLike) -> np.ndarray:
    """(H, W) uint8 from an 8-bit PNG (grey, grey+alpha, RGB, RGBA, palette; not
    interlaced) or a binary PGM (P5), without an imaging library."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"floor plan image {p} does not exist")
    data = p.read_bytes()
    if data[:2] == b"P5":
        return _read_pgm(data, p)
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{p}: not a PNG or binary PGM image")
    pos, idat, plte = 8, [], None
    header = None
    while pos + 8 <= len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        typ, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if typ == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif typ == b"IDAT":
            idat.append(body)
        elif typ == b"PLTE":
            plte = np.frombuffer(body, np.uint8).reshape(-1, 3)
        elif typ == b"IEND":
            break
    if header is None:
        raise ValueError(f"{p}: PNG without IHDR")
    w, h, depth, ctype, _, _, interlace = header
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(ctype)
    if depth != 8 or channels is None or interlace:
        raise ValueError(f"{p}: only 8-bit non-interlaced PNGs are supported (depth {depth}, type {ctype})")
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    stride = w * channels
    raw = raw[: h * (stride + 1)].reshape(h, stride + 1)
    out = np.zeros((h, stride), np.uint8)
    prev = np.zeros(stride, np.int64)
    for r in range(h):
        ftype, line = raw[r, 0], raw[r, 1:].astype(np.int64)
        if ftype == 0:
            cur = line
        elif ftype == 1:  # Sub: cumulative per channel
            cur = line.reshape(w, channels).cumsum(0).reshape(-1) & 255
        elif ftype == 2:
            cur = (line + prev) & 255
        else:  # Average, Paeth: sequential
            cur = np.zeros(stride, np.int64)
            for i in range(stride):
                a = cur[i - channels] if i >= channels else 0
                b = prev[i]
                if ftype == 3:
                    cur[i] = (line[i] + (a + b) // 2) & 255
                else:
                    c = prev[i - channels] if i >= channels else 0
                    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                    cur[i] = (line[i] + pred) & 255
        out[r] = cur
        prev = cur
    img = out.reshape(h, w, channels)
    if ctype == 3:
        if plte is None:
            raise ValueError(f"{p}: palette PNG without PLTE")
        img = plte[img[..., 0]]
        channels = 3
    if channels >= 3:
        return (img[..., :3].astype(np.float64) @ [0.299, 0.587, 0.114]).round().astype(np.uint8)
    return img[..., 0].copy()


def _read_pgm(data: bytes, p: Path) -> np.ndarray:
    tokens: list[bytes] = []
    pos = 2
    while len(tokens) < 3:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    w, h, maxval = (int(t) for t in tokens)
    pos += 1
    if maxval > 255:
        raise ValueError(f"{p}: only 8-bit PGM is supported")
    img = np.frombuffer(data[pos:pos + w * h], np.uint8).reshape(h, w)
    return (img.astype(np.float64) * 255 / maxval).round().astype(np.uint8) if maxval != 255 else img.copy()
