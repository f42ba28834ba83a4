"""An articulated COCO-17 skeleton scaled by body height, posed by a walking gait.

Segment lengths and heights are fractions of the body height H (Drillis & Contini;
the widths are the ones the calibration method assumes): shoulders 0.818 H above the
floor, torso (shoulders to hips) 0.2924 H, hip width 0.1526 H, shoulder width 0.1753 H,
thigh 0.245 H, shank 0.246 H, ankle 0.039 H, upper arm 0.186 H, forearm 0.146 H.

Everything is vectorised over ticks: ``pose_joints`` turns per-tick state arrays into
(n, 17, 3) joints in the floor frame (x, y on the floor, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TORSO = 0.2924
SHOULDER_H = 0.818
HIP_H = SHOULDER_H - TORSO
HIPS_W = 0.1526
SHOULDERS_W = 0.1753
THIGH, SHANK, ANKLE_H = 0.245, 0.246, 0.039
UPPER_ARM, FOREARM = 0.186, 0.146
STANCE = 0.6  # share of a gait cycle a foot is on the ground

# Face points relative to the top of the neck, in the head frame (x fwd, y left, z up), × H.
NECK_TOP = 0.07
FACE = np.array([
    [0.062, 0.0, 0.030],  # nose
    [0.050, 0.018, 0.048],  # l_eye
    [0.050, -0.018, 0.048],  # r_eye
    [0.000, 0.045, 0.040],  # l_ear
    [0.000, -0.045, 0.040],  # r_ear
])


@dataclass(frozen=True)
class Body:
    """One person's build and style."""

    height: float
    hips_w: float
    shoulders_w: float
    arm_swing: float  # rad, amplitude of the arm swing at normal speed
    lean: float  # rad, forward lean when walking
    foot_w: float  # m, lateral distance of the ankles from the centre line
    bob: float  # m, vertical excursion of the pelvis at normal speed

    @staticmethod
    def random(height: float, rng: np.random.Generator) -> "Body":
        k = rng.normal(1.0, 0.03, 2).clip(0.92, 1.08)
        return Body(
            height=height,
            hips_w=HIPS_W * height * k[0],
            shoulders_w=SHOULDERS_W * height * k[1],
            arm_swing=np.radians(rng.uniform(12, 25)),
            lean=np.radians(rng.uniform(2, 6)),
            foot_w=0.5 * HIPS_W * height * rng.uniform(0.7, 0.95),
            bob=rng.uniform(0.02, 0.035),
        )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross is slow on small arrays)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _rot(v: np.ndarray, axis: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """Rodrigues, row-wise: rotate v (n, 3) about unit axes (n, 3) by angles (n,)."""
    c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
    return v * c + _cross(axis, v) * s + axis * np.sum(axis * v, 1, keepdims=True) * (1 - c)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _knee(hip: np.ndarray, ankle: np.ndarray, fwd: np.ndarray, l1: float, l2: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-link IK with the knee bending forward; an ankle out of reach is pulled in
    (the heel rises). Returns (knee, ankle)."""
    d = ankle - hip
    dist = np.linalg.norm(d, axis=1)
    reach = 0.999 * (l1 + l2)
    far = dist > reach
    if np.any(far):
        ankle = ankle.copy()
        ankle[far] = hip[far] + d[far] * (reach / dist[far])[:, None]
        d = ankle - hip
        dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    n = fwd - np.sum(fwd * u, 1, keepdims=True) * u
    n = _unit(n)
    cos_a = np.clip((l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist), -1, 1)
    a = np.arccos(cos_a)
    knee = hip + l1 * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * n)
    return knee, ankle


def pose_joints(body: Body, pos: np.ndarray, heading: np.ndarray, phase: np.ndarray,
                amp: np.ndarray, speed: np.ndarray, stride_f: np.ndarray, bend: np.ndarray,
                reach: np.ndarray, reach_side: np.ndarray, reach_pitch: np.ndarray,
                head_yaw: np.ndarray) -> np.ndarray:
    """Joints (n, 17, 3) in the floor frame.

    pos (n, 2) floor point under the pelvis; heading (n,) rad; phase (n,) gait phase,
    rad (left heel strike at 0); amp (n,) gait amplitude (0 standing, 1 normal walk);
    speed (n,) m/s; stride_f (n,) gait cycles per second; bend (n,) 0..1 (bending
    down); reach (n,) 0..1 with reach_side (n,) +1 left / -1 right and reach_pitch (n,)
    rad of the raised arm; head_yaw (n,) rad relative to the torso.
    """
    H = body.height
    n = len(pos)
    z = np.tile([0.0, 0.0, 1.0], (n, 1))
    f = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], 1)
    left = np.stack([-np.sin(heading), np.cos(heading), np.zeros(n)], 1)
    ground = np.concatenate([pos, np.zeros((n, 1))], 1)

    # Pelvis: vertical bob (lowest at double support), lateral sway over the stance leg,
    # dropping and moving back when bending.
    bob = body.bob * amp * 0.5 * (1 + np.cos(2 * phase))
    sway = 0.02 * amp * np.sin(phase)
    pelvis = (ground + z * (HIP_H * H - bob - 0.01 * amp.clip(0, 1) - 0.07 * H * bend)[:, None]
              - f * (0.10 * H * bend)[:, None] + left * sway[:, None])
    pelvis_yaw = np.radians(5.0) * amp * np.cos(phase)
    lp = _rot(left, z, pelvis_yaw)
    hips = [pelvis + lp * (0.5 * body.hips_w), pelvis - lp * (0.5 * body.hips_w)]

    # Feet: fixed on the ground in stance, a raised arc in swing.
    # ± m around the pelvis; the ankle covers ~70 % of the body's travel during stance
    # (the foot rolls from heel to toe).
    excursion = 0.7 * STANCE * speed / np.maximum(stride_f, 1e-6) / 2
    excursion = np.where(stride_f > 1e-6, excursion, 0.0)
    feet = []
    for side, off in ((1.0, 0.0), (-1.0, 0.5)):
        s = np.mod(phase / (2 * np.pi) + off, 1.0)
        stance = s < STANCE
        u = (s - STANCE) / (1 - STANCE)
        x = np.where(stance, excursion * (1 - 2 * s / STANCE), -excursion + 2 * excursion * 0.5 * (1 - np.cos(np.pi * u)))
        lift = np.where(stance, 0.0, 0.09 * H / 1.75 * amp.clip(0, 1) * np.sin(np.pi * u))
        # Bending: feet stay under the shifted body, a little apart.
        x = x - 0.04 * H * bend
        feet.append(ground + f * x[:, None] + left * (side * body.foot_w) + z * (ANKLE_H * H + lift)[:, None])
    knees, ankles = [], []
    for hip, foot in zip(hips, feet):
        k, a = _knee(hip, foot, f, THIGH * H, SHANK * H)
        knees.append(k)
        ankles.append(a)

    # Torso: forward lean when walking, up to ~80° when bending; counter-rotation.
    pitch = body.lean * amp.clip(0, 1.2) + np.radians(80) * bend
    spine = np.cos(pitch)[:, None] * z + np.sin(pitch)[:, None] * f
    neck = pelvis + spine * (TORSO * H) + left * (-0.5 * sway)[:, None]
    ls = _rot(left, spine, -0.8 * pelvis_yaw)
    shoulders = [neck + ls * (0.5 * body.shoulders_w), neck - ls * (0.5 * body.shoulders_w)]
    tf = _cross(ls, spine)  # torso forward

    # Arms: pitch about the body's left axis measured from hanging straight down (world),
    # swinging opposite to the legs; bending lets them hang towards the floor; reaching
    # raises one arm.
    elbows, wrists = [], []
    for i, side in enumerate((1.0, -1.0)):
        swing = -side * body.arm_swing * amp.clip(0, 1.2) * np.cos(phase)
        a_up = swing + np.radians(4) * amp + np.radians(25) * bend
        flex = np.radians(12) + amp.clip(0, 1.2) * (np.radians(8) + np.radians(14) * np.maximum(0, np.sin(swing / max(body.arm_swing, 1e-6) * np.pi / 2)))
        mine = (reach_side == side).astype(float) * reach
        a_up = (1 - mine) * a_up + mine * reach_pitch
        flex = (1 - mine) * flex + mine * np.radians(8)
        out = np.radians(8) + mine * np.radians(10)
        down = -z
        # abduct outwards about the forward axis, then pitch forward about the left axis
        d0 = _rot(down, f, side * out)
        d_up = _rot(d0, left, -a_up)
        elbow = shoulders[i] + d_up * (UPPER_ARM * H)
        d_fore = _rot(d_up, left, -flex)
        elbows.append(elbow)
        wrists.append(elbow + d_fore * (FOREARM * H))

    # Head: follows the torso, yaws, looks up again a little when bent down.
    top = neck + spine * (NECK_TOP * H)
    hf = _rot(tf, spine, head_yaw)
    hl = _rot(ls, spine, head_yaw)
    hu = spine
    hp = np.radians(-35) * bend  # look back up towards the horizon
    hf2 = _rot(hf, hl, hp)
    hu2 = _rot(hu, hl, hp)
    face = top[:, None, :] + H * (FACE[None, :, 0:1] * hf2[:, None, :] + FACE[None, :, 1:2] * hl[:, None, :]
                                  + FACE[None, :, 2:3] * hu2[:, None, :])
    J = np.empty((n, 17, 3))
    J[:, 0:5] = face
    J[:, 5], J[:, 6] = shoulders
    J[:, 7], J[:, 8] = elbows
    J[:, 9], J[:, 10] = wrists
    J[:, 11], J[:, 12] = hips
    J[:, 13], J[:, 14] = knees
    J[:, 15], J[:, 16] = ankles
    return J
