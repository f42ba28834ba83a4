"""One simulated edge sensor: a free-running camera with an NTP clock and a 2D pose
detector with realistic errors.

Timing: capture rate drawn in ``rates``, a random phase, jitter, dropped frames and
stalls; stamp = true capture + constant clock offset + drift x elapsed; arrival = true
capture + base delay + gamma jitter, in order per sensor (one TCP stream).

Detector, per person in view: joints outside the image are dropped; joints hidden by
walls, by other people (capsule body model) or by the person's own torso (arms) and a
face seen from behind are dropped or guessed with large noise and low confidence;
visible joints get pixel noise (per joint group, scaled with resolution and person
size, half of it correlated over time), confidences that follow visibility, size and
the error actually made; rare gross errors (left/right swaps, a joint snapping to a
neighbour); missed detections (more for small or truncated people); false detections
(random low-score skeletons and, on some sensors, a persistent "ghost").
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from backend.cameras import Intrinsics, Pose, project
from backend.geometry import closest_points_segments
from proto import KeypointMessage, Person

from .area import WallMap, fov_limit, in_fov
from .body import HIPS_W as HIPS, SHOULDERS_W as SHOULDERS, Body, pose_joints
from .config import SimConfig
from .seeding import rng_for

GROUP = np.array([0, 0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 1, 1, 2, 2, 3, 3])  # head, torso, limb, extremity
GROUP_NAMES = ("head", "torso", "elbow/knee", "wrist/ankle")
FLIP = np.array([0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15])
CONF_BASE = np.array([2.3, 2.6, 2.0, 1.6])[GROUP]
LIMB_PAIRS = ((7, 8), (9, 10), (13, 14), (15, 16))
# Capsules of the body model: (joint a, joint b, radius × height); -1 = mid-hip, -2 = mid-shoulder,
# -3 = head centre.
CAPSULES = ((-1, -2, 0.085), (-3, -3, 0.062), (11, 13, 0.045), (12, 14, 0.045), (13, 15, 0.035),
            (14, 16, 0.035), (5, 7, 0.03), (6, 8, 0.03), (7, 9, 0.026), (8, 10, 0.026))
ARMS = np.zeros(17, bool)
ARMS[7:11] = True

# detection flags (Truth.det_flags)
FLAG_SWAP = 1  # left/right swapped (whole body or a limb pair)
FLAG_SNAP = 2  # a joint reported on another person
FLAG_HIDDEN_GUESS = 4  # a hidden joint was guessed
FLAG_GHOST = 8  # persistent false detection
FLAG_DUPLICATE = 16  # a second detection of a person already detected in the frame


@dataclass
class Frame:
    """One captured frame of one sensor (true capture time, epoch s)."""

    seq: int
    capture: float
    stamp: float
    arrival: float


@dataclass
class Detection:
    person: int  # -1 = false detection
    flags: int
    kp: np.ndarray  # (17, 3) u, v, confidence
    bbox: np.ndarray  # (4,)
    score: float


def rotation(rotvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a rotation vector (rad), Rodrigues."""
    angle = float(np.linalg.norm(rotvec))
    if angle == 0.0:
        return np.eye(3)
    k = rotvec / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def bump_poses(name: str, pose: Pose, cfg: SimConfig) -> list[tuple[float, np.ndarray, np.ndarray, Pose]]:
    """The sensor's bumps in time order: (t_rel, displacement (3,) m, rotation vector (3,)
    rad in the world frame, pose from then on). The camera turns about its optical centre:
    R' = exp(rotvec) R, t' = t + displacement; bumps add up."""
    out = []
    for i, (tb, _, dt, dr) in enumerate(b for b in cfg.bumps if b[1] == name):
        rng = rng_for(cfg.seed, "bump", name, i)
        disp = _unit(rng) * dt
        rotvec = _unit(rng) * math.radians(dr)
        pose = Pose(rotation(rotvec) @ pose.R, pose.t + disp)
        out.append((tb, disp, rotvec, pose))
    return out


# surface_offset per COCO joint, signed by side (+ left): head 0, shoulders 1, elbows and
# knees 0.5, wrists and ankles 0.25, hips 1.25 (a hip's keypoint is put on the outline
# of the pelvis, well outside the joint).
_SURFACE_SIDE = np.array([0, 0, 0, 0, 0, 1, -1, 0.5, -0.5, 0.25, -0.25, 1.25, -1.25, 0.5, -0.5, 0.25, -0.25])


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


class SensorSim:
    def __init__(self, name: str, index: int, intr: Intrinsics, pose: Pose, cfg: SimConfig,
                 walls: WallMap | None, floor_R: np.ndarray, floor_origin: np.ndarray):
        self.name, self.index, self.pose, self.cfg = name, index, pose, cfg
        self.walls, self.floor_R, self.floor_origin = walls, floor_R, floor_origin
        # The real lens differs a little from its calibration file (which the backend uses).
        lens = rng_for(cfg.seed, "lens", name)
        e = lens.standard_normal(4) * cfg.intrinsics_error
        if cfg.noise and cfg.intrinsics_error > 0:
            w0 = intr.resolution[0]
            f = 1.0 + e[0]
            intr = replace(intr, fx=intr.fx * f, fy=intr.fy * f * (1.0 + e[1] / 3.0),
                           cx=intr.cx + e[2] * w0 / 2.0, cy=intr.cy + e[3] * w0 / 2.0)
        self.intr = intr
        self.size = (int(intr.resolution[0]), int(intr.resolution[1]))
        w, h = self.size
        self.res_scale = math.sqrt(w * h / (848.0 * 480.0))
        t = rng_for(cfg.seed, "timing", name)
        self.timing = t
        self.stamping = rng_for(cfg.seed, "stamp", name)  # drawn from only with stamp_jitter
        rates = dict(cfg.sensor_rates)
        drawn = t.uniform(*cfg.rates)
        self.rate = float(rates.get(name, drawn))
        self.phase = t.uniform(0, 1 / self.rate)
        self.offset = t.normal(0, cfg.clock_std)
        self.drift = t.normal(0, cfg.drift_std)
        # configured clocks replace the drawn ones (drawn anyway: the stream stays the same)
        self.offset = float(dict(cfg.clock_offsets).get(name, self.offset))
        self.drift = float(dict(cfg.clock_drifts).get(name, self.drift))
        self.pose0 = pose
        self.bumps = bump_poses(name, pose, cfg)  # [(t_rel, displacement, rotvec, new pose)]
        self.delay_base = t.uniform(*cfg.delay)
        self.seq0 = int(t.integers(0, 100000))
        self.k = 0  # next nominal frame
        self.last_arrival = -math.inf
        self.stall_until = -math.inf
        self.det = rng_for(cfg.seed, "detector", name)
        self.dup = rng_for(cfg.seed, "duplicate", name)  # its own stream: duplicates leave the rest as it was
        g = rng_for(cfg.seed, "ghost", name)
        self.ghost = None
        if g.random() < cfg.ghost_prob:
            hpx = g.uniform(0.2, 0.5) * h
            self.ghost = (g.uniform(0.15 * w, 0.85 * w), g.uniform(0.3 * h, 0.7 * h), hpx,
                          _template(g, hpx))
        self.ar_t, self.ar_e = -math.inf, None  # correlated noise state (P, 17, 2)
        self.counters: Counter = Counter()
        self.sigma = np.array([cfg.sigma_head, cfg.sigma_torso, cfg.sigma_limb, cfg.sigma_extremity])[GROUP]
        self.fov = fov_limit(intr)
        self.missed_last: np.ndarray | None = None  # (P,) person missed in the previous frame

    # ------------------------------------------------------------------ timing

    def frames_until(self, t_rel_end: float) -> list[Frame]:
        """Frames with nominal capture time (relative to start) < t_rel_end, dropped ones
        consumed and left out. The draws for a call's frames come in one block."""
        cfg = self.cfg
        end = min(t_rel_end, cfg.duration)
        k_end = max(self.k, int(math.ceil((end - self.phase) * self.rate)))
        while self.phase + k_end / self.rate < end:  # guard against rounding
            k_end += 1
        while k_end > self.k and self.phase + (k_end - 1) / self.rate >= end:
            k_end -= 1
        n = k_end - self.k
        if n <= 0:
            return []
        r = self.timing.random((n, 3))
        jit = self.timing.standard_normal(n) * cfg.frame_jitter
        extra = self.timing.gamma(2.0, 1.0, n) * (cfg.delay_jitter / 2.0)
        lim = 0.3 / self.rate
        late = (np.clip(self.stamping.standard_normal(n), -3.0, 3.0) * cfg.stamp_jitter if cfg.stamp_jitter > 0
                else np.zeros(n))
        out = []
        for i in range(n):
            k = self.k + i
            nominal = self.phase + k / self.rate
            t_rel = max(0.0, nominal + max(-lim, min(lim, float(jit[i]))))
            if r[i, 1] < cfg.stall_prob:
                self.stall_until = t_rel + cfg.stall[0] + r[i, 2] * (cfg.stall[1] - cfg.stall[0])
            if r[i, 0] < cfg.drop_prob or t_rel < self.stall_until:
                continue
            capture = cfg.start_time + t_rel
            stamp = capture + self.offset + self.drift * t_rel + float(late[i])
            arrival = max(capture + self.delay_base + float(extra[i]), self.last_arrival + 1e-4)
            self.last_arrival = arrival
            out.append(Frame(self.seq0 + k, capture, stamp, arrival))
        self.k = k_end
        return out

    # ------------------------------------------------------------------ detector

    def pose_at(self, t_rel: float) -> Pose:
        """The camera's true pose at true time ``t_rel`` (s since the start): bumps included."""
        pose = self.pose0
        for tb, _, _, p in self.bumps:
            if t_rel >= tb:
                pose = p
        return pose

    def detect(self, frames: list[Frame], J: np.ndarray) -> list[list[Detection]]:
        """Detections of each frame, sorted by score. J: (n, P, 17, 3) true world joints
        at the frames' capture times. Vectorised over the frames of a chunk; the random
        draws depend only on this sensor's stream, the frames and the world. Frames on
        either side of a bump are detected in separate blocks, each with its pose."""
        if not self.bumps:
            return self._detect(frames, J)
        start = self.cfg.start_time
        seg = np.array([sum(f.capture - start >= tb for tb, _, _, _ in self.bumps) for f in frames], dtype=int)
        out: list[list[Detection]] = []
        i = 0
        while i < len(frames):
            j = i
            while j < len(frames) and seg[j] == seg[i]:
                j += 1
            self.pose = self.pose0 if seg[i] == 0 else self.bumps[seg[i] - 1][3]
            out += self._detect(frames[i:j], J[i:j])
            i = j
        return out

    def _detect(self, frames: list[Frame], J: np.ndarray) -> list[list[Detection]]:
        n, P = J.shape[:2]
        if n == 0:
            return []
        cfg, (w, h) = self.cfg, self.size
        rng = self.det
        uv, depth = project(self._keypoints_3d(J).reshape(-1, 3), self.intr, self.pose)
        uv = uv.reshape(n, P, 17, 2)
        depth = depth.reshape(n, P, 17)
        fov = in_fov(self.pose.to_camera(J.reshape(-1, 3)), self.fov).reshape(n, P, 17)
        with np.errstate(invalid="ignore"):
            in_img = fov & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        uv = np.where(np.isfinite(uv), uv, 0.0)
        hidden = np.zeros((n, P, 17), bool)
        if self.walls is not None and P:
            fxy = ((J.reshape(-1, 3) - self.floor_origin) @ self.floor_R)[:, :2]
            hidden |= self.walls.blocked(self.index, fxy).reshape(n, P, 17)
        if P:
            hidden |= self._occluded(J, uv, depth, in_img)
            face = self._face_away(J)
            hidden |= face
        visible = in_img & ~hidden
        guessable = in_img & hidden
        front = depth > 0.2
        vmax = np.max(np.where(front, uv[..., 1], -np.inf), -1, initial=-np.inf)
        vmin = np.min(np.where(front, uv[..., 1], np.inf), -1, initial=np.inf)
        size_px = np.where(np.isfinite(vmax) & np.isfinite(vmin), vmax - vmin, 0.0)
        size = np.maximum(size_px, 10.0)
        n_vis = visible.sum(-1)
        lo = np.min(np.where(visible[..., None], uv, np.inf), 2)
        hi = np.max(np.where(visible[..., None], uv, -np.inf), 2)
        ext = np.where(n_vis[..., None] > 0, hi - lo, 0.0)
        p_det = _sigmoid((np.maximum(ext[..., 1], 0.6 * ext[..., 0]) - cfg.min_person_px) / 6.0) \
            * np.clip((n_vis - 3) / 5.0, 0.0, 1.0)
        size_term = 0.8 * np.log(np.clip(size / 150.0, 0.3, 3.0))
        kp = np.zeros((n, P, 17, 3))
        flags = np.zeros((n, P), np.int64)
        if not cfg.noise:
            detected = (p_det >= 0.5) & (n_vis > 0)
            kp[..., :2] = np.where(visible[..., None], uv, 0.0)
            kp[..., 2] = np.where(visible, _sigmoid(CONF_BASE + size_term[..., None]), 0.0)
            noise = np.where(visible[..., None], 0.0, np.nan)
        else:
            z1 = rng.standard_normal((n, P, 17, 2))
            z2 = rng.standard_normal((n, P, 17, 2))
            zc = rng.standard_normal((n, P, 17))
            uj = rng.random((n, P, 17, 3))
            up = rng.random((n, P, 4))
            # misses come in bursts: after a miss, the next frame is missed with miss_burst
            detected = np.zeros((n, P), bool)
            last = self.missed_last if self.missed_last is not None else np.zeros(P, bool)
            for i in range(n):
                p_miss = np.where(last, cfg.miss_burst, cfg.miss_prob)
                detected[i] = (up[i, :, 0] < p_det[i] * (1 - p_miss)) & (n_vis[i] > 0)
                last = ~detected[i] & (p_det[i] >= 0.5)
            self.missed_last = last
            self.counters["missed"] += int(np.sum(~detected & (p_det >= 0.5)))
            sf = np.clip(np.sqrt(size / 150.0), 0.6, 1.6)
            sig = self.sigma * (cfg.noise_scale * self.res_scale) * sf[..., None]  # (n, P, 17)
            # half of the variance follows an AR(1) process per person and joint over frames
            e = np.empty((n, P, 17, 2))
            t_prev, e_prev = self.ar_t, self.ar_e if self.ar_e is not None else np.zeros((P, 17, 2))
            for i, fr in enumerate(frames):
                rho = math.exp(-(fr.capture - t_prev) / cfg.noise_tau) if cfg.noise_tau > 0 else 0.0
                e_prev = rho * e_prev + math.sqrt(1 - rho * rho) * z1[i]
                e[i] = e_prev
                t_prev = fr.capture
            self.ar_t, self.ar_e = t_prev, e_prev
            err = sig[..., None] * (math.sqrt(0.5) * e + math.sqrt(0.5) * z2)
            nrm = np.sum(err**2, -1) / np.maximum(sig, 1e-9) ** 2
            logit = CONF_BASE + size_term[..., None] - 0.25 * (nrm - 2.0) + 0.8 * zc  # E[nrm] = 2
            kp[..., :2] = np.where(visible[..., None], uv + err, 0.0)
            kp[..., 2] = np.where(visible, _sigmoid(logit), 0.0)
            noise = np.where(visible[..., None], err, np.nan)
            # hidden joints: dropped, or guessed badly with low (rarely high) confidence
            g = guessable & (uj[..., 0] >= cfg.hidden_drop)
            big = (15.0 * self.res_scale) * sf[..., None, None]
            kp[..., :2] = np.where(g[..., None], uv + big * z2, kp[..., :2])
            conf_g = np.where(uj[..., 2] < 0.05, 0.6 + 0.2 * uj[..., 1], 0.05 + 0.4 * uj[..., 1])
            kp[..., 2] = np.where(g, conf_g, kp[..., 2])
            flags |= np.where(g.any(-1), FLAG_HIDDEN_GUESS, 0)
            self.counters["guessed"] += int(np.sum(g & detected[..., None]))
            # left/right swaps, four times as likely for a person seen from behind
            away = face[..., 0] if P else np.zeros((n, P), bool)
            sw = detected & (up[..., 1] < cfg.swap_prob * np.where(away, 4.0, 1.0))
            whole = sw & (up[..., 2] < 0.6)
            kp[whole] = kp[whole][:, FLIP]
            noise[whole] = np.nan
            pair = np.minimum((up[..., 3] * len(LIMB_PAIRS)).astype(int), len(LIMB_PAIRS) - 1)
            for k, (ja, jb) in enumerate(LIMB_PAIRS):
                m = sw & ~whole & (pair == k)
                if m.any():
                    kp[m, ja], kp[m, jb] = kp[m, jb].copy(), kp[m, ja].copy()
                    noise[m, ja] = noise[m, jb] = np.nan
            flags |= np.where(sw, FLAG_SWAP, 0)
            rep = kp[..., 2] > 0
            kp[..., 0] = np.where(rep, np.clip(kp[..., 0], 0, w - 1e-3), 0.0)
            kp[..., 1] = np.where(rep, np.clip(kp[..., 1], 0, h - 1e-3), 0.0)
            if P >= 2:
                self._snap(kp, noise, flags, uv, visible, detected, lo, hi, rng)
            _round_reported(kp, cfg.pixel_decimals)
        bbox, score = self._boxes(kp)
        if cfg.noise:
            score = np.clip(np.round(score + 0.05 * (up[..., 3] - 0.5), 4), 0.01, 0.999)
        # figures of the correctly detected persons
        c = self.counters
        dk = kp[detected]
        c["detections"] += int(detected.sum())
        c["joints"] += int(np.sum(dk[..., 2] > 0))
        c["confident"] += int(np.sum(dk[..., 2] >= 0.6))
        nz = noise[detected]
        ok = ~np.isnan(nz[..., 0])
        sq = np.where(ok, np.sum(np.where(ok[..., None], nz, 0.0) ** 2, -1) / 2, 0.0)
        for gi in range(4):
            c[f"sq{gi}"] += float(sq[:, GROUP == gi].sum())
            c[f"n{gi}"] += int(ok[:, GROUP == gi].sum())
        out = []
        if cfg.noise:
            n_false = rng.poisson(cfg.false_rate, n)
            ghost_fire = rng.random(n) < cfg.ghost_rate
        for i in range(n):
            dets = [Detection(int(p), int(flags[i, p]), kp[i, p].copy(), bbox[i, p].copy(), float(score[i, p]))
                    for p in np.flatnonzero(detected[i])]
            if cfg.noise:
                dets.extend(self._false(rng, int(n_false[i]), bool(ghost_fire[i])))
                if cfg.duplicate_prob > 0:
                    dets.extend(self._duplicates(dets))
            dets.sort(key=lambda d: -d.score)
            out.append(dets)
        return out

    def _boxes(self, kp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """bbox (..., 4) around the reported joints (padded; the head top and feet lie
        beyond the keypoints) and a score (...,) from their confidences."""
        w, h = self.size
        rep = kp[..., 2] > 0
        lo = np.min(np.where(rep[..., None], kp[..., :2], np.inf), -2)
        hi = np.max(np.where(rep[..., None], kp[..., :2], -np.inf), -2)
        any_rep = rep.any(-1)[..., None]
        lo = np.where(any_rep, lo, 0.0)
        hi = np.where(any_rep, hi, 0.0)
        bw, bh = (hi - lo)[..., 0], (hi - lo)[..., 1]
        bbox = np.stack([np.maximum(0.0, lo[..., 0] - 0.1 * bw), np.maximum(0.0, lo[..., 1] - 0.12 * bh),
                         np.minimum(float(w), hi[..., 0] + 0.1 * bw), np.minimum(float(h), hi[..., 1] + 0.05 * bh)], -1)
        nrep = rep.sum(-1)
        mean_c = np.where(nrep > 0, np.sum(kp[..., 2], -1) / np.maximum(nrep, 1), 0.0)
        score = np.round(np.clip(0.25 + 0.7 * mean_c * np.sqrt(nrep / 17.0), 0.01, 0.999), 4)
        return np.round(bbox, 1), score

    def _occluded(self, J: np.ndarray, uv: np.ndarray, depth: np.ndarray, in_img: np.ndarray) -> np.ndarray:
        """(n, P, 17) joints behind another person's body, or an arm behind the own torso.

        Capsule body model; a joint is tested only against people whose image box
        (padded) holds it and who are nearer the camera somewhere."""
        n, P = J.shape[:2]
        Hgt = np.linalg.norm(J[:, :, 0] - 0.5 * (J[:, :, 15] + J[:, :, 16]), axis=-1) * 1.05 + 0.1  # (n, P)
        mid_hip = 0.5 * (J[:, :, 11] + J[:, :, 12])
        mid_sh = 0.5 * (J[:, :, 5] + J[:, :, 6])
        head = 0.5 * (J[:, :, 3] + J[:, :, 4])
        ext = {-1: mid_hip, -2: mid_sh, -3: head}
        A = np.stack([ext[a] if a < 0 else J[:, :, a] for a, _, _ in CAPSULES], 2)  # (n, P, K, 3)
        B = np.stack([ext[b] if b < 0 else J[:, :, b] for _, b, _ in CAPSULES], 2)
        R = np.array([r for _, _, r in CAPSULES])[None, None, :] * Hgt[:, :, None]  # (n, P, K)
        C = self.pose.t
        out = np.zeros((n, P, 17), bool)
        # candidates: (frame, target, joint, occluder)
        front = depth > 0.2
        lo = np.min(np.where(front[..., None], uv, np.inf), 2)  # (n, P, 2)
        hi = np.max(np.where(front[..., None], uv, -np.inf), 2)
        dmin = np.min(np.where(front, depth, np.inf), -1)  # (n, P)
        fx = self.intr.fx
        pad = 0.12 * Hgt * fx / np.maximum(dmin, 0.2)  # px
        u, v = uv[..., 0], uv[..., 1]
        inside = ((u[:, :, :, None] >= lo[:, None, None, :, 0] - pad[:, None, None, :])
                  & (u[:, :, :, None] <= hi[:, None, None, :, 0] + pad[:, None, None, :])
                  & (v[:, :, :, None] >= lo[:, None, None, :, 1] - pad[:, None, None, :])
                  & (v[:, :, :, None] <= hi[:, None, None, :, 1] + pad[:, None, None, :]))
        nearer = dmin[:, None, None, :] < depth[:, :, :, None]
        cand = inside & nearer & in_img[..., None] & ~np.eye(P, dtype=bool)[None, :, None, :]
        fi, pi, ji, qi = np.nonzero(cand)
        if len(fi):
            X = J[fi, pi, ji]
            d = X - C
            L = np.linalg.norm(d, axis=-1, keepdims=True)
            end = C + d * np.clip((L - 0.08) / L, 0, 1)  # stop 8 cm short of the joint
            dist, _, _ = closest_points_segments(np.broadcast_to(C, (len(fi), len(CAPSULES), 3)),
                                                 np.broadcast_to(end[:, None], (len(fi), len(CAPSULES), 3)),
                                                 A[fi, qi], B[fi, qi])
            hit = np.any(dist < R[fi, qi], axis=1)
            out[fi[hit], pi[hit], ji[hit]] = True
        # arms behind the own torso
        fi, pi, ji = np.nonzero(in_img & ARMS[None, None, :])
        if len(fi):
            X = J[fi, pi, ji]
            d = X - C
            L = np.linalg.norm(d, axis=-1, keepdims=True)
            end = C + d * np.clip((L - 0.08) / L, 0, 1)
            dist, _, _ = closest_points_segments(np.broadcast_to(C, X.shape), end, A[fi, pi, 0], B[fi, pi, 0])
            hit = dist < R[fi, pi, 0]
            out[fi[hit], pi[hit], ji[hit]] = True
        return out

    def _keypoints_3d(self, J: np.ndarray) -> np.ndarray:
        """(n, P, 17, 3): the 3D points this camera's detector reports for the joints J:
        the joints moved out along the body's left-right axis by ``surface_offset``
        (times the joint's factor), the part of that move across the camera's ray (a
        silhouette's outline seen from the front is the widest, from the side none)."""
        r = self.cfg.surface_offset
        if r <= 0 or not self.cfg.noise or J.shape[1] == 0:
            return J
        lat = 0.5 * ((J[:, :, 5] - J[:, :, 6]) + (J[:, :, 11] - J[:, :, 12]))  # right to left
        lat /= np.maximum(np.linalg.norm(lat, axis=-1, keepdims=True), 1e-9)
        ray = J - self.pose.t
        ray /= np.maximum(np.linalg.norm(ray, axis=-1, keepdims=True), 1e-9)
        across = lat[:, :, None] - np.sum(lat[:, :, None] * ray, -1, keepdims=True) * ray  # (n, P, 17, 3)
        return J + (r * _SURFACE_SIDE)[:, None] * across

    def _face_away(self, J: np.ndarray) -> np.ndarray:
        """(n, P, 17): nose and eyes of a face seen from behind, the far ear in profile."""
        ears = 0.5 * (J[:, :, 3] + J[:, :, 4])
        fwd = J[:, :, 0] - ears
        fwd /= np.linalg.norm(fwd, axis=-1, keepdims=True)
        lat = J[:, :, 3] - J[:, :, 4]
        lat /= np.linalg.norm(lat, axis=-1, keepdims=True)
        to_cam = self.pose.t - ears
        to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
        c = np.sum(fwd * to_cam, -1)
        s = np.sum(lat * to_cam, -1)
        out = np.zeros(J.shape[:3], bool)
        out[:, :, 0:3] = (c < -0.15)[..., None]
        out[:, :, 3] = s < -0.6
        out[:, :, 4] = s > 0.6
        return out

    def _snap(self, kp, noise, flags, uv, visible, detected, lo, hi, rng) -> None:
        """A joint of a detected person reported on an overlapping other person."""
        n, P = detected.shape
        overlap = (np.all(np.minimum(hi[:, :, None], hi[:, None, :]) > np.maximum(lo[:, :, None], lo[:, None, :]), -1)
                   & ~np.eye(P, dtype=bool)[None])
        u = rng.random((n, P, P, 3))
        fi, pi, qi = np.nonzero(overlap & detected[:, :, None] & (u[..., 0] < self.cfg.snap_prob))
        for f, p, q in zip(fi, pi, qi):
            cand = np.flatnonzero(visible[f, q] & (kp[f, p, :, 2] > 0) & (GROUP >= 2))
            if not len(cand):
                continue
            j = int(cand[min(int(u[f, p, q, 1] * len(cand)), len(cand) - 1)])
            kp[f, p, j, :2] = uv[f, q, j]
            kp[f, p, j, 2] = 0.4 + 0.4 * u[f, p, q, 2]
            noise[f, p, j] = np.nan
            flags[f, p] |= FLAG_SNAP

    def _duplicates(self, dets: list[Detection]) -> list[Detection]:
        """Second detections of some of the persons in ``dets`` (``duplicate_prob`` each), as
        a top-down detector sends when two of its boxes on one person survive non-maximum
        suppression: the pose estimated again from the other crop (each joint moved by 1.5 %
        of the person's height, a fifth of them lost), confidences and score lower."""
        rng, out = self.dup, []
        for d in dets:
            if d.person < 0 or rng.random() >= self.cfg.duplicate_prob:
                continue
            kp = d.kp.copy()
            rep = kp[:, 2] > 0
            hpx = max(float(np.ptp(kp[rep, 1])) if rep.sum() >= 2 else 0.0, 10.0)
            kp[:, :2] += rng.normal(0.0, 0.015 * hpx, (17, 2))
            kp[:, 2] *= rng.uniform(0.6, 1.0, 17)
            rep &= (rng.random(17) >= 0.2) & (kp[:, 0] >= 0) & (kp[:, 0] < self.size[0]) \
                & (kp[:, 1] >= 0) & (kp[:, 1] < self.size[1])
            kp[~rep] = 0.0
            _round_reported(kp, self.cfg.pixel_decimals)
            bbox, _ = self._boxes(kp)
            score = float(round(d.score * rng.uniform(0.5, 0.95), 4))
            out.append(Detection(d.person, d.flags | FLAG_DUPLICATE, kp, bbox, score))
        self.counters["duplicates"] += len(out)
        return out

    def _false(self, rng, count: int, ghost: bool) -> list[Detection]:
        w, h = self.size
        out = []
        for _ in range(count):
            hpx = rng.uniform(0.12, 0.6) * h
            tpl = _template(rng, hpx)
            cx, cy = rng.uniform(0, w), rng.uniform(0.2 * h, h)
            out.append(self._fake(rng, tpl, cx, cy, 0.06 * hpx, 0))
        if ghost and self.ghost is not None:
            cx, cy, hpx, tpl = self.ghost
            out.append(self._fake(rng, tpl, cx, cy, 2.0 * self.res_scale, FLAG_GHOST))
        return out

    def _fake(self, rng, tpl, cx, cy, sigma, flags) -> Detection:
        w, h = self.size
        kp = np.zeros((17, 3))
        keep = rng.random(17) < 0.65
        pts = tpl + np.array([cx, cy]) + rng.normal(0, sigma, (17, 2))
        conf = 0.05 + 0.5 * rng.random(17)
        conf = np.where(rng.random(17) < 0.1, 0.6 + 0.15 * rng.random(17), conf)
        keep &= (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)
        if keep.sum() < 2:
            pts = np.clip(pts, 0, [w - 1, h - 1])
            keep[5] = keep[6] = True
        kp[keep, :2] = pts[keep]
        kp[keep, 2] = conf[keep]
        if self.cfg.pixel_decimals is not None:
            kp[:, :2] = np.round(kp[:, :2], self.cfg.pixel_decimals)
            kp[:, 2] = np.round(kp[:, 2], 4)
        bbox, score = self._boxes(kp)
        score = float(round(min(float(score), 0.2 + 0.3 * rng.random()), 4))
        return Detection(-1, flags, kp, bbox, score)


def _round_reported(kp: np.ndarray, decimals: int | None) -> None:
    """Reported keypoints (..., 17, 3) rounded in place as a sensor sends them: pixels to
    ``decimals`` (None: not rounded), confidences to 4 decimals and at least 1e-4; joints
    not reported (confidence 0) stay 0."""
    if decimals is not None:
        rep = kp[..., 2] > 0
        kp[..., :2] = np.round(kp[..., :2], decimals)
        kp[..., 2] = np.where(rep, np.clip(np.round(kp[..., 2], 4), 1e-4, 1.0), 0.0)


_TEMPLATES: np.ndarray | None = None


def _template(rng: np.random.Generator, hpx: float) -> np.ndarray:
    """(17, 2) pixel offsets of a person-like shape about its centre, ``hpx`` tall: one of
    a bank of walking poses seen from various sides, maybe mirrored."""
    global _TEMPLATES
    if _TEMPLATES is None:
        body = Body(height=1.0, hips_w=HIPS, shoulders_w=SHOULDERS, arm_swing=0.35, lean=0.05, foot_w=0.06, bob=0.0)
        k = np.arange(24)
        J = pose_joints(body, np.zeros((24, 2)), (k % 8) * (np.pi / 4), (k // 8) * 2.1, np.full(24, 1.0),
                        np.full(24, 1.3 / 1.75), np.full(24, 0.9), np.zeros(24), np.zeros(24), np.ones(24),
                        np.zeros(24), np.zeros(24))
        # seen from the front at eye level: image u = -y, v = -z
        _TEMPLATES = np.stack([-J[..., 1], -(J[..., 2] - 0.5)], -1)
    tpl = _TEMPLATES[int(rng.integers(len(_TEMPLATES)))] * hpx
    if rng.random() < 0.5:
        tpl = tpl * [-1.0, 1.0]
    return tpl


def to_message(sensor: str, fr: Frame, size: tuple[int, int], dets: list[Detection]) -> KeypointMessage:
    persons = tuple(Person(kp=d.kp, bbox=d.bbox, score=d.score) for d in dets)
    return KeypointMessage(sensor=sensor, seq=fr.seq, stamp=fr.stamp, size=size, persons=persons)
