"""Where people walk: a floor grid of camera coverage, free space and paths.

Coverage of a floor cell = cameras that see a standing person's torso (1.0 m) and head
(1.6 m) there: both in the image (3 % margin), in front of the camera and at most
``coverage_range`` away, and (with a floor plan) no wall between. People walk in free
space (the floor plan's bright pixels, 0.25 m away from walls; without a plan, where at
least one camera sees); they mostly head for cells seen by >= 2 cameras and sometimes
(``leave_prob``) for cells seen by fewer, within 3 m of those (stepping out of the views).
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from backend.cameras import project, radial_fold

from .scene import Scene

CELL = 0.1  # m
CLEARANCE = 0.25  # m between a walker's centre and a wall
LEAVE_REACH = 3.0  # m: "leave" waypoints lie at most this far from where >= 2 cameras see


@dataclass(frozen=True, eq=False)
class Area:
    """Floor grid. Cell (i, j) has its centre at floor xy = lo + (j + 0.5, i + 0.5) * CELL.

    coverage: (Ny, Nx) int, cameras that see a person standing there;
    walk: (Ny, Nx) bool, where walkers may be; targets, leave: (Ny, Nx) bool, where they
    go (>= 2 cameras / fewer), both inside walk's main connected component.
    """

    lo: np.ndarray
    coverage: np.ndarray
    walk: np.ndarray
    targets: np.ndarray
    leave: np.ndarray

    def cell_of(self, xy) -> tuple[int, int]:
        j = int(math.floor((xy[0] - self.lo[0]) / CELL))
        i = int(math.floor((xy[1] - self.lo[1]) / CELL))
        return i, j

    def centre(self, i: int, j: int) -> np.ndarray:
        return self.lo + (np.array([j, i]) + 0.5) * CELL

    def walkable(self, xy) -> bool:
        i, j = self.cell_of(xy)
        ny, nx = self.walk.shape
        return 0 <= i < ny and 0 <= j < nx and bool(self.walk[i, j])

    def line_clear(self, a, b, half_width: float = 0.6 * CELL) -> bool:
        """Every cell along a strip of ±half_width around the segment a → b (floor xy)
        is walkable (a thin line could graze the corner of a wall cell)."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        d = b - a
        length = float(np.hypot(d[0], d[1]))
        n = max(2, int(length / (0.25 * CELL)) + 1)
        pts = a + np.linspace(0, 1, n)[:, None] * d
        if half_width > 0 and length > 1e-9:
            side = np.array([-d[1], d[0]]) / length * half_width
            pts = np.concatenate([pts, pts + side, pts - side])
        j = np.floor((pts[:, 0] - self.lo[0]) / CELL).astype(int)
        i = np.floor((pts[:, 1] - self.lo[1]) / CELL).astype(int)
        ny, nx = self.walk.shape
        if np.any((i < 0) | (i >= ny) | (j < 0) | (j >= nx)):
            return False
        return bool(np.all(self.walk[i, j]))

    def sample(self, rng: np.random.Generator, leave: bool) -> np.ndarray:
        """A random floor xy in the target (or leave) region."""
        mask = self.leave if leave and self.leave.any() else self.targets
        idx = np.flatnonzero(mask)
        k = idx[rng.integers(len(idx))]
        i, j = divmod(int(k), mask.shape[1])
        return self.centre(i, j) + rng.uniform(-0.5, 0.5, 2) * CELL

    def path(self, a, b, smooth: bool = True) -> list[np.ndarray]:
        """Floor xy waypoints from a to b through walkable cells; [] when there is no
        path (the caller picks another goal). ``smooth``: straight when clear and string
        pulled; otherwise the plain cell-centre path from the centre of a's cell (every
        leg stays inside walkable cells)."""
        if smooth and self.line_clear(a, b):
            return [np.asarray(b, float)]
        start, goal = self.cell_of(a), self.cell_of(b)
        cells = _astar(self.walk, start, goal)
        if cells is None:
            return []
        pts = [self.centre(*start)] + [self.centre(i, j) for i, j in cells[1:-1]] + [np.asarray(b, float)]
        if not smooth:
            return pts
        # String pulling: keep a waypoint only where the straight line would leave the area.
        out, cur, k = [], np.asarray(a, float), 0
        while k < len(pts):
            far = k
            for m in range(len(pts) - 1, k, -1):
                if self.line_clear(cur, pts[m]):
                    far = m
                    break
            out.append(pts[far])
            cur, k = pts[far], far + 1
        return out


def fov_limit(intr) -> float:
    """Largest tan(angle off the optical axis) a camera sees, in undistorted normalised
    coordinates: 15 % beyond the image corners, and short of where the lens polynomial
    folds back (OpenCV's model maps directions far outside the view into the image)."""
    w, h = intr.resolution
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], float)
    r_corner = float(np.max(np.hypot((corners[:, 0] - intr.cx) / intr.fx, (corners[:, 1] - intr.cy) / intr.fy)))
    r_fold = radial_fold(intr.dist)[0]
    return float(min(1.15 * r_corner, 0.95 * r_fold))


def in_fov(Xc: np.ndarray, limit: float) -> np.ndarray:
    """(N,) bool: camera-frame points (N, 3) in front and within ``fov_limit``."""
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.hypot(Xc[:, 0], Xc[:, 1]) / z
    return (z > 0.2) & (r <= limit)


def build_area(scene: Scene, coverage_range: float) -> Area:
    """The walking grid of a scene (cached per scene object and range)."""
    key = (id(scene), float(coverage_range))
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is scene:
        return hit[1]
    area = _build_area(scene, coverage_range)
    _remember(key, scene, area)
    return area


_CACHE: dict = {}


def _remember(key, scene, value) -> None:
    if len(_CACHE) >= 16:  # a handful of scenes per process; don't pin them all
        _CACHE.clear()
    _CACHE[key] = (scene, value)


def _build_area(scene: Scene, coverage_range: float) -> Area:
    floor, plan = scene.floor, scene.floorplan
    Cf = floor.to_floor(scene.centres())
    lo = Cf[:, :2].min(0) - coverage_range
    hi = Cf[:, :2].max(0) + coverage_range
    if plan is not None:
        plo, phi = plan.extent()
        lo, hi = np.maximum(lo, plo), np.minimum(hi, phi)
    lo = np.floor(lo / CELL) * CELL
    nx, ny = (np.ceil((hi - lo) / CELL).astype(int))
    xs = lo[0] + (np.arange(nx) + 0.5) * CELL
    ys = lo[1] + (np.arange(ny) + 0.5) * CELL
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    coverage = np.zeros(len(xy), np.int32)
    walls = wall_map(scene)
    heads = [floor.to_world(np.concatenate([xy, np.full((len(xy), 1), hgt)], 1)) for hgt in (1.0, 1.6)]
    for k, name in enumerate(scene.names):
        intr, pose = scene.intrinsics[name], scene.poses[name]
        w, h = intr.resolution
        idx = np.flatnonzero(np.linalg.norm(xy - Cf[k, :2], axis=1) <= coverage_range)
        lim = fov_limit(intr)
        for X in heads:
            if not len(idx):
                break
            uv, z = project(X[idx], intr, pose)
            with np.errstate(invalid="ignore"):
                ok = (in_fov(pose.to_camera(X[idx]), lim) & (z > 0.3) & (uv[:, 0] >= 0.03 * w) & (uv[:, 0] <= 0.97 * w)
                      & (uv[:, 1] >= 0.03 * h) & (uv[:, 1] <= 0.97 * h))
            idx = idx[ok]
        if walls is not None and len(idx):
            idx = idx[~walls.blocked(k, xy[idx])]
        coverage[idx] += 1
    coverage = coverage.reshape(ny, nx)
    if plan is not None:
        free = plan.free_at(xy).reshape(ny, nx) & ~plan.occupied_at(xy).reshape(ny, nx)
        walk = _erode(free, int(round(CLEARANCE / CELL)))
    else:
        walk = _erode(coverage >= 1, 2)
    targets = walk & (coverage >= 2)
    if not targets.any():
        raise ValueError("no floor area is seen by two cameras: cannot place walkers "
                         "(check the camera poses and the floor plane)")
    # Keep the connected part of the walkable area that holds most target cells.
    labels = _label(walk)
    counts = np.bincount(labels[targets], minlength=labels.max() + 1)
    counts[0] = 0
    main = labels == int(np.argmax(counts))
    # Leaving the views: step out of them near their edge, not off to distant rooms.
    near = _grow(targets & main, int(round(LEAVE_REACH / CELL)), within=main)
    return Area(lo=lo, coverage=coverage, walk=main, targets=targets & main, leave=main & near & (coverage < 2))


@dataclass(frozen=True, eq=False)
class WallMap:
    """Per camera, the distance on the floor to the first wall in each direction.

    dist: (C, B) float64 m over B bearings (2π / B apart) from each camera's floor point
    xy: (C, 2). A wall hides a point when it is nearer along the point's bearing (both
    neighbouring bearings, to be safe at corners). Walls are taken as floor to ceiling.
    """

    xy: np.ndarray
    dist: np.ndarray

    def blocked(self, k: int, pts: np.ndarray) -> np.ndarray:
        """(N,) bool for floor points (N, 2) seen from camera k."""
        d = np.asarray(pts).reshape(-1, 2) - self.xy[k]
        B = self.dist.shape[1]
        a = np.arctan2(d[:, 1], d[:, 0]) * (B / (2 * np.pi))
        i0 = np.floor(a).astype(np.int64) % B
        lim = np.minimum(self.dist[k, i0], self.dist[k, (i0 + 1) % B])
        return np.hypot(d[:, 0], d[:, 1]) > lim


def wall_map(scene: Scene, bearings: int = 720, max_range: float = 20.0) -> WallMap | None:
    """Walls of the floor plan as seen from each camera (None without a plan)."""
    plan = scene.floorplan
    if plan is None:
        return None
    key = ("walls", id(scene))
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is scene:
        return hit[1]
    solid = _solid(plan)
    cxy = scene.floor.to_floor(scene.centres())[:, :2]
    ang = np.arange(bearings) * (2 * np.pi / bearings)
    dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    # Skip the first 0.3 m: cameras hang on walls and pillars.
    r = np.arange(0.3, max_range, 0.8 * plan.metres_per_pixel)
    dist = np.full((len(cxy), bearings), np.inf)
    for k, c in enumerate(cxy):
        pts = c + r[None, :, None] * dirs[:, None, :]  # (B, R, 2)
        rr, cc, inside = plan.pixel_of(pts)
        hit_w = solid[rr, cc] & inside
        first = np.argmax(hit_w, axis=1)
        dist[k] = np.where(hit_w.any(axis=1), r[first], np.inf)
    wm = WallMap(cxy, dist)
    _remember(key, scene, wm)
    return wm


def _solid(plan) -> np.ndarray:
    """Occupied pixels without isolated specks (scan noise does not hide people)."""
    occ = plan.occupied
    p = np.pad(occ, 1).astype(np.int8)
    n = sum(p[1 + di:p.shape[0] - 1 + di, 1 + dj:p.shape[1] - 1 + dj]
            for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj)
    return occ & (n >= 2)


def _erode(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask.copy()
    out = mask.copy()
    p = np.pad(mask, r, constant_values=False)
    ny, nx = mask.shape
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            if di * di + dj * dj <= r * r:
                out &= p[r + di:r + di + ny, r + dj:r + dj + nx]
    return out


def _grow(mask: np.ndarray, steps: int, within: np.ndarray) -> np.ndarray:
    """Cells reachable from ``mask`` in ``steps`` 8-neighbour moves inside ``within``
    (through doors, not through walls)."""
    out = mask & within
    ny, nx = mask.shape
    for _ in range(steps):
        p = np.pad(out, 1)
        grown = out.copy()
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                grown |= p[1 + di:1 + di + ny, 1 + dj:1 + dj + nx]
        out = grown & within
    return out


def _label(mask: np.ndarray) -> np.ndarray:
    """4-connected component labels (0 = background)."""
    labels = np.zeros(mask.shape, np.int32)
    ny, nx = mask.shape
    cur = 0
    for start in zip(*np.nonzero(mask)):
        if labels[start]:
            continue
        cur += 1
        labels[start] = cur
        q = deque([start])
        while q:
            i, j = q.popleft()
            for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
                if 0 <= a < ny and 0 <= b < nx and mask[a, b] and not labels[a, b]:
                    labels[a, b] = cur
                    q.append((a, b))
    return labels


def _astar(walk: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    ny, nx = walk.shape
    if not (0 <= goal[0] < ny and 0 <= goal[1] < nx and walk[goal]):
        return None
    if not (0 <= start[0] < ny and 0 <= start[1] < nx):
        return None
    s2 = math.sqrt(2)

    def h(c):
        dy, dx = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return max(dx, dy) + (s2 - 1) * min(dx, dy)

    g = {start: 0.0}
    parent: dict = {start: None}
    heap = [(h(start), 0.0, start)]
    while heap:
        _, gc, c = heapq.heappop(heap)
        if c == goal:
            out = []
            while c is not None:
                out.append(c)
                c = parent[c]
            return out[::-1]
        if gc > g.get(c, math.inf):
            continue
        i, j = c
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if not (di or dj):
                    continue
                a, b = i + di, j + dj
                if not (0 <= a < ny and 0 <= b < nx and walk[a, b]):
                    continue
                if di and dj and not (walk[i, b] and walk[a, j]):
                    continue  # no corner cutting
                ng = gc + (s2 if di and dj else 1.0)
                if ng < g.get((a, b), math.inf):
                    g[(a, b)] = ng
                    parent[(a, b)] = c
                    heapq.heappush(heap, (ng + h((a, b)), ng, (a, b)))
    return None
