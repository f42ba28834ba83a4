"""People walking through the scene: waypoints, smooth turns, stops, bending,
reaching, looking around, and keeping their distance from each other.

The world depends on the seed and the scene only (never on which sensors run), and is
stepped at ``world_rate``; joints between ticks are interpolated linearly.
"""

from __future__ import annotations

import math

import numpy as np

from .area import Area
from .body import Body, pose_joints
from .config import SimConfig
from .scene import Scene
from .seeding import rng_for

_STATE = ("x", "y", "heading", "phase", "amp", "speed", "stride_f", "bend", "reach",
          "reach_side", "reach_pitch", "head_yaw")


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


class Walker:
    """One person's behaviour; ``step`` advances one tick and returns its state row."""

    def __init__(self, pid: int, height: float, area: Area, cfg: SimConfig, start: np.ndarray):
        self.pid = pid
        self.rng = rng_for(cfg.seed, "walker", pid)
        self.body = Body.random(height, self.rng)
        self.area, self.cfg = area, cfg
        self.p = np.asarray(start, float).copy()
        self.heading = self.rng.uniform(-math.pi, math.pi)
        self.speed = 0.0
        self.phase = self.rng.uniform(0, 2 * math.pi)
        self.amp = 0.0
        self.stride_f = 0.0
        self.cruise = self.rng.uniform(*cfg.speed)
        self.path: list[np.ndarray] = []
        self.mode = "pause"
        self.timer = self.rng.uniform(0.5, 2.0)  # a short look around before the first walk
        self.action: tuple[str, float, float, float] | None = None  # kind, t0, t1, amount
        self.reach_side, self.reach_pitch = 1.0, math.radians(120)
        self.bend = self.reach = 0.0
        self.head_yaw, self.head_target, self.head_timer = 0.0, 0.0, 1.0
        self.best_d, self.no_progress = math.inf, 0.0
        self.wall_blocked = 0.0
        self.exact = False  # following a cell-exact path after getting stuck
        self.face_to: float | None = None
        self.t = 0.0

    # -------------------------------------------------------------- decisions

    def _new_goal(self) -> None:
        for _ in range(20):
            leave = self.rng.random() < self.cfg.leave_prob
            goal = self.area.sample(self.rng, leave)
            if np.linalg.norm(goal - self.p) < 2.0:
                continue
            path = self.area.path(self.p, goal)
            if path:
                self.path = path
                self.exact = False
                self.best_d, self.no_progress = math.inf, 0.0
                self.mode = "walk"
                self.cruise = self.rng.uniform(*self.cfg.speed)
                return
        self.mode, self.timer = "pause", 1.0  # nowhere to go from here right now

    def _arrive(self) -> None:
        self.path = []
        if self.rng.random() < self.cfg.pause_prob:
            self.mode = "pause"
            self.timer = self.rng.uniform(*self.cfg.pause)
            u = self.rng.random()
            t0 = self.t + self.rng.uniform(0.3, 0.8)
            t1 = self.t + self.timer - self.rng.uniform(0.3, 0.8)
            if u < self.cfg.bend_prob and t1 - t0 > 1.5:
                self.action = ("bend", t0, t1, self.rng.uniform(0.5, 1.0))
            elif u < self.cfg.bend_prob + self.cfg.reach_prob and t1 - t0 > 1.0:
                self.action = ("reach", t0, t1, self.rng.uniform(0.7, 1.0))
                self.reach_side = 1.0 if self.rng.random() < 0.5 else -1.0
                self.reach_pitch = math.radians(self.rng.uniform(70, 160))
            else:
                self.action = None
            self.face_to = self.heading + self.rng.uniform(-2.5, 2.5) if self.rng.random() < 0.5 else None
        else:
            self._new_goal()

    # -------------------------------------------------------------- dynamics

    def step(self, dt: float, others: list["Walker"]) -> list[float]:
        cfg = self.cfg
        self.t += dt
        v_des = 0.0
        want = self.heading
        if self.mode == "walk":
            reach = 0.05 if self.exact else 0.4  # an exact cell path is followed point by point
            while len(self.path) > 1 and np.linalg.norm(self.path[0] - self.p) < reach:
                self.path.pop(0)
            target = self.path[0]
            d = float(np.linalg.norm(target - self.p))
            if len(self.path) == 1 and d < 0.25:
                self._arrive()
            else:
                want = math.atan2(target[1] - self.p[1], target[0] - self.p[0])
                v_des = self.cruise * (min(1.0, 0.4 + d / 1.5) if len(self.path) == 1 else 1.0)
                if self.exact:
                    v_des = min(v_des, 0.6)
        if self.mode == "pause":
            self.timer -= dt
            if self.face_to is not None:
                want = self.face_to
            if self.timer <= 0:
                self.action = None
                self.face_to = None
                self._new_goal()

        # Other people: a push away and sideways (pass on the right), slowing down when
        # someone is right ahead.
        slow = 1.0
        if self.mode == "walk":
            dx, dy = math.cos(want), math.sin(want)
            for o in others:
                if o is self:
                    continue
                rx, ry = o.p[0] - self.p[0], o.p[1] - self.p[1]
                dist = math.hypot(rx, ry)
                if dist > 2.5 or dist < 1e-9:
                    continue
                ux, uy = rx / dist, ry / dist
                ahead = ux * dx + uy * dy
                if ahead <= 0:
                    continue
                k = ahead * math.exp((cfg.min_separation - dist) / 0.6)
                dx += k * (-ux + uy)  # away, and to the right of the line to the other
                dy += k * (-uy - ux)
                if ahead > 0.8:
                    slow = min(slow, max(0.0, (dist - cfg.min_separation) / 1.0))
            want = math.atan2(dy, dx)
        v_des *= slow

        err = _wrap(want - self.heading)
        rate = max(-math.radians(cfg.turn_rate), min(math.radians(cfg.turn_rate), 3.0 * err))
        self.heading = _wrap(self.heading + rate * dt)
        # slow down to turn (nobody walks a wide arc into a wall): stop beyond 60°
        v_des *= min(1.0, max(0.0, (math.cos(err) - 0.5) / 0.4))
        acc = 1.0 if v_des > self.speed else 1.5
        self.speed += max(-acc * dt, min(acc * dt, v_des - self.speed))
        step = self.speed * dt
        move = step * np.array([math.cos(self.heading), math.sin(self.heading)])
        new = self.p + move
        blocked = not self.area.walkable(new)
        if blocked and step > 0:  # slide along the wall instead of sticking to it
            for slide in (np.array([move[0], 0.0]), np.array([0.0, move[1]])):
                if abs(slide).sum() > 0.3 * step and self.area.walkable(self.p + slide):
                    new, blocked = self.p + slide, False
                    break
        for o in others:
            if o is not self and np.linalg.norm(new - o.p) < cfg.min_separation:
                if np.linalg.norm(new - o.p) < np.linalg.norm(self.p - o.p):
                    blocked = True
        if blocked:
            self.speed = 0.0
            if step > 0 and not self.area.walkable(self.p + move) and self.path and not self.exact:
                self.wall_blocked += dt
                if self.wall_blocked > 0.3:  # a wall corner in the way: follow the cells exactly
                    exact = self.area.path(self.p, self.path[-1], smooth=False)
                    if exact:
                        self.path, self.exact = exact, True
                    self.wall_blocked = 0.0
        else:
            self.p = new
            self.wall_blocked = 0.0
        if self.mode == "walk" and self.path:
            # No progress towards the goal for 3 s (a wall corner, someone in the way):
            # follow the grid cells exactly; still none: go somewhere else.
            d_goal = float(np.linalg.norm(self.path[-1] - self.p))
            if d_goal < self.best_d - 0.3:
                self.best_d, self.no_progress = d_goal, 0.0
            else:
                self.no_progress += dt
            if self.no_progress > 3.0:
                exact = None if self.exact else self.area.path(self.p, self.path[-1], smooth=False)
                if exact:
                    self.path, self.exact, self.no_progress = exact, True, 0.0
                else:
                    self._new_goal()

        # Gait: cadence grows with the square root of speed; the swing fades when stopping.
        v = self.speed
        self.amp += (min(v / 1.3, 1.2) - self.amp) * min(1.0, dt / 0.25)
        self.stride_f = 0.5 * cfg.step_freq * math.sqrt(max(v, 0.3) / 1.3) if v > 0.02 else 0.0
        self.phase = (self.phase + 2 * math.pi * self.stride_f * dt) % (2 * math.pi)

        # Actions while stopped: ramp in and out over half a second.
        target_b = target_r = 0.0
        if self.action is not None:
            kind, t0, t1, amount = self.action
            if t0 <= self.t <= t1:
                ramp = min(1.0, (self.t - t0) / 0.6, (t1 - self.t) / 0.6)
                if kind == "bend":
                    target_b = amount * max(0.0, ramp)
                else:
                    target_r = amount * max(0.0, ramp)
        self.bend += (target_b - self.bend) * min(1.0, dt / 0.15)
        self.reach += (target_r - self.reach) * min(1.0, dt / 0.15)

        # Head: glances around, wider when standing.
        self.head_timer -= dt
        if self.head_timer <= 0:
            wide = 1.0 if self.mode == "pause" else 0.35
            self.head_target = self.rng.uniform(-1.0, 1.0) * wide
            self.head_timer = self.rng.uniform(0.8, 3.0)
        self.head_yaw += (self.head_target - self.head_yaw) * min(1.0, dt / 0.3)
        return [self.p[0], self.p[1], self.heading, self.phase, self.amp, self.speed, self.stride_f,
                self.bend, self.reach, self.reach_side, self.reach_pitch, self.head_yaw]


class World:
    """All walkers. ``advance(k)`` computes ticks up to index k; ``joints_window`` gives
    the joints of the ticks still held."""

    def __init__(self, scene: Scene, cfg: SimConfig, area: Area):
        self.scene, self.cfg, self.area = scene, cfg, area
        self.dt = 1.0 / cfg.world_rate
        P = cfg.persons
        hr = rng_for(cfg.seed, "world")
        if cfg.heights is not None:
            heights = list(cfg.heights)
        else:
            heights = list(hr.normal(1.75, 0.07, P).clip(1.55, 2.0))
        self.heights = np.array(heights, float)
        starts: list[np.ndarray] = []
        for p in range(P):
            best = None
            for _ in range(50):
                c = area.sample(hr, False)
                if all(np.linalg.norm(c - s) > 1.5 for s in starts):
                    best = c
                    break
                best = c if best is None else best
            starts.append(best)
        self.walkers = [Walker(p, heights[p], area, cfg, starts[p]) for p in range(P)]
        self.next_tick = 0  # index of the next tick to compute
        self.k0 = 0  # index of the first tick held in ``self.J``
        self.J = np.zeros((P, 0, 17, 3))  # (P, n, 17, 3) world frame
        self.states = np.zeros((P, 0, len(_STATE)))

    def tick_time(self, k):
        """Epoch s of tick k (same formula everywhere so truth and sensors agree)."""
        return self.cfg.start_time + np.asarray(k, dtype=np.float64) * self.dt

    def advance(self, k_end: int) -> tuple[np.ndarray, np.ndarray]:
        """Compute ticks next_tick..k_end (inclusive); return their (P, n, 17, 3) joints
        and (P, n, 12) states (for the truth)."""
        n = k_end + 1 - self.next_tick
        P = len(self.walkers)
        if n <= 0:
            return np.zeros((P, 0, 17, 3)), np.zeros((P, 0, len(_STATE)))
        rows = np.zeros((P, n, len(_STATE)))
        for i in range(n):
            if self.next_tick + i == 0:
                for w in self.walkers:  # tick 0 is the initial state
                    rows[w.pid, i] = [w.p[0], w.p[1], w.heading, w.phase, 0, 0, 0, 0, 0, 1, 0, 0]
                continue
            for w in self.walkers:
                rows[w.pid, i] = w.step(self.dt, self.walkers)
        floor = self.scene.floor
        J = np.zeros((P, n, 17, 3))
        for w in self.walkers:
            r = rows[w.pid]
            Jf = pose_joints(w.body, r[:, 0:2], r[:, 2], r[:, 3], r[:, 4], r[:, 5], r[:, 6], r[:, 7],
                             r[:, 8], r[:, 9], r[:, 10], r[:, 11])
            J[w.pid] = floor.to_world(Jf)
        self.next_tick = k_end + 1
        self.J = np.concatenate([self.J, J], axis=1)
        self.states = np.concatenate([self.states, rows], axis=1)
        return J, rows

    def drop_before(self, k: int) -> None:
        """Forget ticks before index k (bounded memory)."""
        cut = max(0, min(k - self.k0, self.J.shape[1]))
        if cut:
            self.J = self.J[:, cut:]
            self.states = self.states[:, cut:]
            self.k0 += cut

    def window_times(self) -> np.ndarray:
        return self.tick_time(np.arange(self.k0, self.k0 + self.J.shape[1]))
