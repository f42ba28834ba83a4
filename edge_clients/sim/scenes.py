"""Generated scenes: camera layouts that the lab does not have.

``corridor``: a long corridor with cameras mounted under the ceiling, all looking down the
corridor the same way, each overlapping only its neighbours (no floor point is seen by
three cameras). Every hypothesis then has two views, each pair of neighbours shares its
own persons, and nothing in one pair's images fixes the scale of the next pair: the
layout that tests whether the people's constant size carries scale along a chain
(docs/bones.md).

``room``: a rectangular room with cameras high in its corners (and, beyond four, along
its walls), each looking at the room's centre through a wide, distorted lens: the common
small installation, and a layout the lab does not have (every camera sees most of the
floor; baselines across the room; no camera looks the same way as another).

``grid``: a hall with many cameras (30, 40...) on a grid under its ceiling, each looking
down towards a random direction: more cameras than the lab, each seeing a few metres of
floor, half the pairs (30 cameras) or more (40) sharing none of it, walkers seen by a
handful at a time (the layout where pairs of cameras that each see a different walker
fit wrong relative poses, docs/bootstrap.md, Session 45).

``studio``: a capture space ringed by cameras at two heights (on stands at chest height
looking level, on the walls high up looking down) and one camera in the ceiling looking
straight down through a fisheye-like lens: views from every side and from above, a
camera whose image has no "up" (people radiate from its centre), cameras below the
walkers' heads, and lenses of three kinds in one network.

``tworooms``: two rooms side by side, joined by a door, each with its own cameras; one
camera in each looks through the door into the other room, so the two networks share
only what walkers in and near the doorway show them (a home, offices): a view graph
joined by one weak link.

``write_scene`` writes a scene as a camera directory (intrinsics.yaml, reference.yaml,
room.yaml, floorplan.pgm) that ``Scene.load``, ``extrcal simulate --cameras`` and
``extrcal calibrate`` read like the lab's.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import yaml

from backend.cameras import Extrinsics, Intrinsics, Pose, dump_extrinsics, dump_intrinsics, project, write_atomic

from .area import CELL, fov_limit, in_fov, wall_map
from .scene import Floor, FloorPlan, Scene

SCENES = ("corridor", "room", "grid", "studio", "tworooms")

_MPP = 0.05  # m per floor plan pixel
_WALL = 0.2  # m wall thickness in the plan


def corridor(cameras: int = 6, *, spacing: float = 3.5, width: float = 2.5, height: float = 2.6,
             pitch: float = 40.0, lateral: float = 0.5, yaw: float = 6.0) -> Scene:
    """A straight corridor along the floor's x axis, ``width`` m wide, with ``cameras``
    cameras ``spacing`` m apart at ``height`` m, looking down the corridor (+x),
    pitched ``pitch`` deg down, alternately ``lateral`` m left and right of the centre
    line and turned ``yaw`` deg towards it (so that neighbours' baselines are not along
    their optical axes). The lab's 848x480 lens (about 90° x 59°).

    With the defaults a standing person's torso and head are in view from about 0.6 m to
    5.3 m ahead of a camera: neighbours share about 1.2 m of the corridor, and the next
    but one starts 2 m beyond where a camera stops seeing (``floor_views`` checks it).
    World frame = floor frame: z up, the floor at z = 0, camera 0 above the origin.
    """
    if cameras < 2:
        raise ValueError(f"a corridor needs at least 2 cameras, got {cameras}")
    if not (spacing > 0 and width > 0.5 and height > 1.8 and 0 < pitch < 90):
        raise ValueError("corridor: spacing > 0, width > 0.5 m, height > 1.8 m, 0 < pitch < 90 deg expected")
    names = tuple(f"cam_{i}" for i in range(cameras))
    intr, poses = {}, {}
    th = math.radians(pitch)
    for i, n in enumerate(names):
        side = 1.0 if i % 2 == 0 else -1.0
        y = side * lateral
        psi = -side * math.radians(yaw)  # towards the centre line
        fwd = np.array([math.cos(psi), math.sin(psi), 0.0])
        z = math.cos(th) * fwd + np.array([0, 0, -math.sin(th)])
        x = np.array([math.sin(psi), -math.cos(psi), 0.0])  # image right: horizontal
        yv = np.cross(z, x)
        R = np.stack([x, yv, z], axis=1)
        poses[n] = Pose(R, np.array([i * spacing, y, height]))
        intr[n] = Intrinsics(n, 426.0, 426.0, 424.0, 240.0, np.array([-0.054, 0.063, 0.0, 0.0, -0.020]), (848, 480))
    # free floor: from 1 m behind the first camera to 6 m beyond the last one
    return _walled(names, intr, poses, (-1.0, -width / 2), ((cameras - 1) * spacing + 6.0, width / 2))


def _walled(names: tuple[str, ...], intr: dict, poses: dict, lo: tuple[float, float], hi: tuple[float, float],
            inner: tuple[tuple[float, float, float, float], ...] = ()) -> Scene:
    """A scene whose floor (world frame = floor frame, z up) is the rectangle ``lo``-``hi``
    (m) inside walls ``_WALL`` thick; ``inner``: more walls, rectangles (x0, y0, x1, y1) m."""
    x0, y0 = lo
    x1, y1 = hi
    W = int(round((x1 - x0 + 2 * _WALL) / _MPP))
    H = int(round((y1 - y0 + 2 * _WALL) / _MPP))
    free = np.zeros((H, W), bool)
    k = int(round(_WALL / _MPP))
    free[k:H - k, k:W - k] = True
    for a0, b0, a1, b1 in inner:  # image rows run against y (FloorPlan.pixel_of)
        free[H - int(round((b1 - y0 + _WALL) / _MPP)):H - int(round((b0 - y0 + _WALL) / _MPP)),
             int(round((a0 - x0 + _WALL) / _MPP)):int(round((a1 - x0 + _WALL) / _MPP))] = False
    plan = FloorPlan(occupied=~free, free=free, metres_per_pixel=_MPP, map_R=np.eye(2),
                     map_t=np.array([x0 - _WALL, y0 - _WALL]))
    floor = Floor.make(np.zeros(3), [1.0, 0, 0], [0, 0, 1.0])
    return Scene(names, intr, poses, floor, plan)


def _lens(name: str, resolution: tuple[int, int], hfov: float, k1: float, *, aspect: float = 1.002,
          centre: tuple[float, float] = (0.01, -0.01)) -> Intrinsics:
    """A lens ``hfov`` deg wide at ``resolution`` (w, h) with barrel distortion ``k1``
    (k2 = k1²/3), fy = ``aspect`` fx, the principal point off the image centre by
    ``centre`` times the width and the height."""
    w, h = resolution
    f = (w / 2) / math.tan(math.radians(hfov) / 2)
    return Intrinsics(name, f, f * aspect, w / 2 + centre[0] * w, h / 2 + centre[1] * h,
                      np.array([k1, k1 * k1 / 3, 0.0, 0.0, 0.0]), (w, h))


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_R_cam of a camera at ``centre`` looking at ``target``, image rows horizontal."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def room(cameras: int = 4, *, width: float = 7.0, depth: float = 5.0, height: float = 2.5, aim: float = 0.8,
         resolution: tuple[int, int] = (640, 480), hfov: float = 100.0, k1: float = -0.28,
         roll: tuple[float, ...] = ()) -> Scene:
    """A ``width`` x ``depth`` m room (floor x along the width, y along the depth, z up, the
    origin in a corner) with ``cameras`` cameras ``height`` m high: the first four in its
    corners (0.3 m in from the walls), the next ones at the middles of the walls, each
    looking at the point ``aim`` m above the room's centre (a wall camera a little off it,
    so that no two cameras' views are symmetric). Lens: ``resolution``, ``hfov`` deg wide,
    barrel distortion ``k1`` (k2 = k1²/3), the principal point 1 % off the image centre.
    ``roll``: deg, camera i turned by ``roll[i % len(roll)]`` about its optical axis (mounted
    in portrait, upside down: people lie sideways or stand on their heads in its images)."""
    if not 2 <= cameras <= 8:
        raise ValueError(f"a room takes 2 to 8 cameras, got {cameras}")
    if not (width > 1.5 and depth > 1.5 and height > 1.8 and 0 < hfov < 150):
        raise ValueError("room: width and depth > 1.5 m, height > 1.8 m, 0 < hfov < 150 deg expected")
    m = 0.3
    spots = [(m, m), (width - m, depth - m), (width - m, m), (m, depth - m),
             (width / 2, m), (width / 2, depth - m), (m, depth / 2), (width - m, depth / 2)]
    names = tuple(f"cam_{i}" for i in range(cameras))
    intr, poses = {}, {}
    centre = np.array([width / 2, depth / 2, aim])
    for i, n in enumerate(names):
        c = np.array([*spots[i], height])
        target = centre + (np.array([0.4 * (-1) ** i, 0.3, 0.0]) if i >= 4 else 0.0)
        R = _look_at(c, target)
        if roll:
            a = math.radians(roll[i % len(roll)])
            R = R @ np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        poses[n] = Pose(R, c)
        intr[n] = _lens(n, resolution, hfov, k1)
    return _walled(names, intr, poses, (0.0, 0.0), (width, depth))


def grid(cameras: int = 30, *, spacing: float = 3.0, height: float = 2.6, pitch: tuple[float, float] = (25.0, 45.0),
         seed: int = 0) -> Scene:
    """``cameras`` cameras on a square-ish grid (columns = ceil(sqrt(1.5 cameras))),
    ``spacing`` m apart, ``height`` to ``height`` + 0.3 m high, each pitched ``pitch``
    (uniform, deg) down towards a yaw drawn uniformly (``seed``), image rows horizontal.
    The lab's cam_0 lens (848x480, about 90° wide). No walls: people walk wherever a
    camera sees them (``area``). World frame = floor frame, z up, camera 0 above the origin."""
    if cameras < 2:
        raise ValueError(f"a grid needs at least 2 cameras, got {cameras}")
    if not (spacing > 0 and height > 1.8 and 0 < pitch[0] <= pitch[1] < 90):
        raise ValueError("grid: spacing > 0, height > 1.8 m, 0 < pitch[0] <= pitch[1] < 90 deg expected")
    rng = np.random.default_rng(seed)
    cols = int(math.ceil(math.sqrt(cameras * 1.5)))
    names = tuple(f"cam_{i}" for i in range(cameras))
    intr, poses = {}, {}
    for i, n in enumerate(names):
        r, c = divmod(i, cols)
        centre = np.array([c * spacing, r * spacing, height + 0.3 * rng.random()])
        yaw = rng.uniform(0, 2 * np.pi)
        th = np.radians(rng.uniform(*pitch))
        ahead = np.array([np.cos(yaw) * np.cos(th), np.sin(yaw) * np.cos(th), -np.sin(th)])
        poses[n] = Pose(_look_at(centre, centre + ahead), centre)
        intr[n] = Intrinsics(n, 426.366, 426.948, 425.388, 245.035,
                             np.array([-0.053925, 0.063101, 0.000206, -0.000723, -0.020201]), (848, 480))
    return Scene(names, intr, poses, Floor.make(np.zeros(3), [1.0, 0, 0], [0, 0, 1.0]), None)


def studio(cameras: int = 8, *, radius: float = 3.5, heights: tuple[float, float] = (1.3, 3.0), aim: float = 1.0,
           overhead: float | None = 3.4) -> Scene:
    """A square room ``2 (radius + 0.3)`` m wide (world frame = floor frame, z up, the
    origin at its centre) with ``cameras`` cameras on a circle of ``radius`` m, evenly
    spaced from +x, alternately ``heights[0]`` and ``heights[1]`` m high, each looking at
    the point ``aim`` m above the centre: the low ones through 1280x720 lenses 80° wide
    (k1 = -0.08), the high ones 848x480, 95° wide (the lab's k1 = -0.054). With
    ``overhead`` (m), one more camera above the centre looking straight down, 1024x1024,
    120° wide, k1 = -0.3, its image x along the floor's +x. Principal points 1 % off the
    image centres."""
    if cameras < 2:
        raise ValueError(f"a studio needs at least 2 cameras on its ring, got {cameras}")
    if not (radius > 1.0 and min(heights) > 0.3 and (overhead is None or overhead > 2.2)):
        raise ValueError("studio: radius > 1 m, heights > 0.3 m, overhead > 2.2 m expected")
    lenses = (((1280, 720), 80.0, -0.08), ((848, 480), 95.0, -0.054), ((1024, 1024), 120.0, -0.3))

    def lens(n: str, kind: int) -> Intrinsics:
        return _lens(n, *lenses[kind], aspect=1.001, centre=(0.01, 0.01))

    intr, poses = {}, {}
    target = np.array([0.0, 0.0, aim])
    for i in range(cameras):
        n, a = f"cam_{i}", 2 * math.pi * i / cameras
        c = np.array([radius * math.cos(a), radius * math.sin(a), heights[i % 2]])
        poses[n], intr[n] = Pose(_look_at(c, target), c), lens(n, i % 2)
    if overhead is not None:
        n = f"cam_{cameras}"
        # looking down: image x along +x, image y along -y (a right-handed camera frame)
        poses[n] = Pose(np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]), np.array([0.0, 0.0, overhead]))
        intr[n] = lens(n, 2)
    r = radius + 0.3
    return _walled(tuple(intr), intr, poses, (-r, -r), (r, r))


def tworooms(*, width: float = 5.0, depth: float = 4.0, height: float = 2.6, door: float = 1.0, aim: float = 0.9
             ) -> Scene:
    """Two ``width`` x ``depth`` m rooms side by side along x (world frame = floor frame, z
    up, the origin in the first room's corner), joined by a ``door`` m wide in the middle of
    the wall between them (x = ``width``, 0.2 m thick, floor to ceiling). Four cameras
    ``height`` m high in each: three in corners looking at the room's centre ``aim`` m above
    the floor (the far corners and one by the door) and one in the middle of the far wall
    looking through the door (cam_3 from the first room, cam_7 from the second). The
    room's 640x480 lens, 100° wide, k1 = -0.28."""
    if not (width > 2.0 and depth > 2.0 and height > 1.8 and 0.6 <= door < depth - 0.5):
        raise ValueError("tworooms: width and depth > 2 m, height > 1.8 m, 0.6 m <= door < depth - 0.5 m expected")
    m = 0.3
    intr, poses = {}, {}
    for r in range(2):
        x0, sgn = (0.0, 1.0) if r == 0 else (2 * width, -1.0)  # the second room mirrored
        near = x0 + sgn * (width - m)
        spots = [(x0 + sgn * m, m), (x0 + sgn * m, depth - m), (near, m if r == 0 else depth - m)]
        centre = np.array([x0 + sgn * width / 2, depth / 2, aim])
        for k, xy in enumerate(spots):
            n = f"cam_{4 * r + k}"
            c = np.array([*xy, height])
            poses[n] = Pose(_look_at(c, centre), c)
        n, c = f"cam_{4 * r + 3}", np.array([x0 + sgn * m, depth / 2 + 0.2, height])
        poses[n] = Pose(_look_at(c, np.array([width, depth / 2, aim])), c)
    for n in poses:
        intr[n] = _lens(n, (640, 480), 100.0, -0.28)
    t = _WALL / 2
    wall = ((width - t, 0.0, width + t, (depth - door) / 2), (width - t, (depth + door) / 2, width + t, depth))
    return _walled(tuple(sorted(poses, key=lambda n: int(n[4:]))), intr, poses, (0.0, 0.0), (2 * width, depth), wall)


def make(name: str, **kw) -> Scene:
    """A generated scene by name (``SCENES``)."""
    if name == "corridor":
        return corridor(**kw)
    if name == "room":
        return room(**kw)
    if name == "grid":
        return grid(**kw)
    if name == "studio":
        return studio(**kw)
    if name == "tworooms":
        return tworooms(**kw)
    raise ValueError(f"unknown scene {name!r} (known: {', '.join(SCENES)})")


def write_scene(scene: Scene, directory: str | os.PathLike, description: str = "") -> Path:
    """The scene as a camera directory: intrinsics.yaml, reference.yaml, room.yaml and
    (with a plan) floorplan.pgm; returns the directory."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    write_atomic(d / "intrinsics.yaml", dump_intrinsics({n: scene.intrinsics[n] for n in scene.names}))
    write_atomic(d / "reference.yaml", dump_extrinsics(
        {n: Extrinsics(scene.poses[n], scene.intrinsics[n].resolution) for n in scene.names}))
    f = scene.floor
    room: dict = {"description": description or f"generated scene, {len(scene.names)} cameras",
                  "floor": {"origin": f.origin.tolist(), "e1": f.e1.tolist(), "normal_up": f.up.tolist()}}
    plan = scene.floorplan
    if plan is not None:
        if not np.allclose(plan.map_R, np.eye(2)):
            raise ValueError("write_scene: only axis-aligned floor plans are supported")
        img = np.where(plan.occupied, 0, np.where(plan.free, 254, 205)).astype(np.uint8)
        H, W = img.shape
        write_atomic(d / "floorplan.pgm", f"P5\n{W} {H}\n255\n".encode() + img.tobytes())
        room["floorplan"] = {"image": "floorplan.pgm", "metres_per_pixel": plan.metres_per_pixel,
                             "floor_T_map": [float(plan.map_t[0]), float(plan.map_t[1]), 0.0, 0.0, 0.0, 0.0, 1.0]}
    write_atomic(d / "room.yaml", yaml.safe_dump(room, sort_keys=False, default_flow_style=None, width=120))
    return d


def floor_views(scene: Scene, heights: tuple[float, ...] = (1.0, 1.6), *, any_height: bool = False,
                coverage_range: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """Which camera sees which floor cell (a 0.1 m grid over the floor plan, or 12 m
    around the cameras): a standing person's points at ``heights`` m above the cell are
    in its image (3 % margin), in front, within range and not behind a wall; all of them
    (the simulator's coverage) or, ``any_height``, any of them (a person partly in view).
    Returns (xy (N, 2) floor cell centres, seen (C, N) bool)."""
    floor, plan = scene.floor, scene.floorplan
    Cf = floor.to_floor(scene.centres())
    lo, hi = Cf[:, :2].min(0) - coverage_range, Cf[:, :2].max(0) + coverage_range
    if plan is not None:
        plo, phi = plan.extent()
        lo, hi = np.maximum(lo, plo), np.minimum(hi, phi)
    nx, ny = np.ceil((hi - lo) / CELL).astype(int)
    gx, gy = np.meshgrid(lo[0] + (np.arange(nx) + 0.5) * CELL, lo[1] + (np.arange(ny) + 0.5) * CELL)
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    if plan is not None:
        xy = xy[plan.free_at(xy) & ~plan.occupied_at(xy)]
    walls = wall_map(scene)
    seen = np.zeros((len(scene.names), len(xy)), bool)
    for k, name in enumerate(scene.names):
        intr, pose = scene.intrinsics[name], scene.poses[name]
        w, h = intr.resolution
        lim = fov_limit(intr)
        per = []
        for hgt in heights:
            X = floor.to_world(np.concatenate([xy, np.full((len(xy), 1), hgt)], 1))
            uv, z = project(X, intr, pose)
            with np.errstate(invalid="ignore"):
                ok = (in_fov(pose.to_camera(X), lim) & (z > 0.3) & (uv[:, 0] >= 0.03 * w) & (uv[:, 0] <= 0.97 * w)
                      & (uv[:, 1] >= 0.03 * h) & (uv[:, 1] <= 0.97 * h))
            per.append(ok & (np.linalg.norm(xy - Cf[k, :2], axis=1) <= coverage_range))
        s = np.any(per, axis=0) if any_height else np.all(per, axis=0)
        if walls is not None:
            s &= ~walls.blocked(k, xy)
        seen[k] = s
    return xy, seen
