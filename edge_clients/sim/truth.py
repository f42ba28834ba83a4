"""Ground truth of a simulated run and its ``<recording>.truth.npz`` sidecar.

Sidecar arrays (numpy .npz, compressed; S sensors, P persons, T world ticks, M messages,
D detections):

    sensors        (S,) str      sensor ids (the scene's cameras), natural order
    start_time     ()  float64   epoch s of simulated t = 0
    seed           ()  int64
    config         ()  str       SimConfig as JSON
    times          (T,) float64  epoch s of the world ticks (1 / world_rate apart)
    joints         (P, T, 17, 3) float64  true COCO-17 joints in the world (camera) frame;
                                 between ticks the truth is the linear interpolation
                                 (``Truth.joints_at``), exactly what the sensors saw
    heights        (P,) float64  body heights, m
    states         (P, T, 12) float64  walker state per tick, columns ``state_names``
    state_names    (12,) str     x, y (floor frame, m), heading (rad), gait phase, gait
                                 amplitude, speed (m/s), stride frequency (Hz), bend,
                                 reach, reach side, reach pitch (rad), head yaw (rad)
    msg_sensor     (M,) int32    index into ``sensors``
    msg_seq        (M,) int64    the message's ``seq``
    msg_capture    (M,) float64  true capture time, epoch s
    msg_stamp      (M,) float64  the message's ``stamp`` (sensor clock)
    msg_arrival    (M,) float64  when it reached the backend (epoch s, true time)
    det_msg        (D,) int64    index into the msg_* arrays
    det_sensor     (D,) int32    = msg_sensor[det_msg]
    det_seq        (D,) int64    = msg_seq[det_msg]
    det_index      (D,) int32    index of the detection in the message's ``persons``
    det_person     (D,) int32    person id (row of ``joints``), -1 = false detection
    det_capture    (D,) float64  = msg_capture[det_msg]
    det_flags      (D,) uint8    1 left/right swap, 2 joint snapped to another person,
                                 4 hidden joint guessed, 8 persistent false ("ghost")
    clock_offset   (S,) float64  s; stamp = capture + clock_offset + clock_drift * (capture - start_time)
    clock_drift    (S,) float64  clock rate error (1e-6 = 1 ppm)
    capture_rate   (S,) float64  Hz
    delay_base     (S,) float64  s, base network + processing delay
    lens_fx, lens_fy, lens_cx, lens_cy  (S,) float64  the intrinsics the sensors really
                                 imaged with (at the message resolution; they differ
                                 from the calibration files by ``intrinsics_error``)
    floor_origin, floor_e1, floor_e2, floor_up  (3,) float64  the floor plane (world frame)
    bump_sensor    (B,) int32    bumped cameras (SimConfig.bumps), index into ``sensors``, in time order
    bump_time      (B,) float64  epoch s (true time) from which the new pose holds
    bump_translation (B, 3) float64  the move of the optical centre, m (world frame)
    bump_rotation  (B, 3) float64  rotation vector (rad, world frame): R_new = exp(rot) R_old
    bump_R, bump_t (B, 3, 3), (B, 3) float64  the camera's true pose (world_R_cam, centre)
                                 from ``bump_time`` on (``Truth.pose_at`` needs the scene's poses)
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

STATE_NAMES = ("x", "y", "heading", "phase", "amp", "speed", "stride_f", "bend", "reach",
               "reach_side", "reach_pitch", "head_yaw")


def interpolate(times: np.ndarray, joints: np.ndarray, t) -> np.ndarray:
    """Joints at times t (n,) → (n, P, 17, 3), linear between the ticks ``times`` (T,)
    of ``joints`` (P, T, 17, 3). The simulator and ``Truth.joints_at`` both use this, so
    the truth is exactly what the sensors saw."""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    T = len(times)
    assert joints.shape[1] == T and T >= 2
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, T - 2)
    w = (t - times[k]) / (times[k + 1] - times[k])
    a = joints[:, k]
    b = joints[:, k + 1]
    out = a * (1.0 - w)[None, :, None, None] + b * w[None, :, None, None]
    return out.transpose(1, 0, 2, 3)


@dataclass(frozen=True, eq=False)
class Truth:
    """Everything the simulator knows about a run; arrays as in the module doc."""

    sensors: tuple[str, ...]
    start_time: float
    seed: int
    config: dict
    times: np.ndarray
    joints: np.ndarray
    heights: np.ndarray
    states: np.ndarray
    msg_sensor: np.ndarray
    msg_seq: np.ndarray
    msg_capture: np.ndarray
    msg_stamp: np.ndarray
    msg_arrival: np.ndarray
    det_msg: np.ndarray
    det_sensor: np.ndarray
    det_seq: np.ndarray
    det_index: np.ndarray
    det_person: np.ndarray
    det_capture: np.ndarray
    det_flags: np.ndarray
    clock_offset: np.ndarray
    clock_drift: np.ndarray
    capture_rate: np.ndarray
    delay_base: np.ndarray
    lens_fx: np.ndarray
    lens_fy: np.ndarray
    lens_cx: np.ndarray
    lens_cy: np.ndarray
    floor_origin: np.ndarray
    floor_e1: np.ndarray
    floor_e2: np.ndarray
    floor_up: np.ndarray
    bump_sensor: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    bump_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bump_translation: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bump_rotation: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bump_R: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    bump_t: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        P, T = self.joints.shape[:2]
        assert self.joints.shape == (P, T, 17, 3) and self.times.shape == (T,)
        assert self.states.shape == (P, T, len(STATE_NAMES)) and self.heights.shape == (P,)
        M, D = len(self.msg_seq), len(self.det_msg)
        for name in ("msg_sensor", "msg_capture", "msg_stamp", "msg_arrival"):
            assert getattr(self, name).shape == (M,), name
        for name in ("det_sensor", "det_seq", "det_index", "det_person", "det_capture", "det_flags"):
            assert getattr(self, name).shape == (D,), name

    def pose_at(self, sensor: str, t: float, initial_R: np.ndarray, initial_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of ``sensor`` at epoch time ``t``, given its pose before any bump (the scene's)."""
        s = self.sensors.index(sensor)
        R, c = initial_R, initial_t
        for k in np.flatnonzero(self.bump_sensor == s):
            if t >= self.bump_time[k]:
                R, c = self.bump_R[k], self.bump_t[k]
        return R, c

    @property
    def persons(self) -> int:
        return self.joints.shape[0]

    def joints_at(self, t) -> np.ndarray:
        """True joints at epoch time(s) t: (P, 17, 3) for a scalar, (n, P, 17, 3) for (n,)."""
        out = interpolate(self.times, self.joints, t)
        return out[0] if np.ndim(t) == 0 else out

    def _msg_index(self, sensor: str, seq: int) -> int:
        s = self.sensors.index(sensor)
        idx = np.flatnonzero((self.msg_sensor == s) & (self.msg_seq == seq))
        if not len(idx):
            raise KeyError(f"no message {sensor} seq {seq} in the truth")
        return int(idx[0])

    def capture_time(self, sensor: str, seq: int) -> float:
        """True capture time (epoch s) of a message."""
        return float(self.msg_capture[self._msg_index(sensor, seq)])

    def persons_of(self, sensor: str, seq: int) -> np.ndarray:
        """Person id of each detection of a message, in message order (-1 = false)."""
        m = self._msg_index(sensor, seq)
        sel = np.flatnonzero(self.det_msg == m)
        return self.det_person[sel][np.argsort(self.det_index[sel])]

    def save(self, path: str | os.PathLike) -> None:
        arrays = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "sensors":
                v = np.array(v, dtype=str)
            elif f.name == "config":
                v = np.array(json.dumps(v))
            arrays[f.name] = np.asarray(v)
        arrays["state_names"] = np.array(STATE_NAMES)
        tmp = Path(str(path) + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)

    @staticmethod
    def load(path: str | os.PathLike) -> "Truth":
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"truth file {p} does not exist")
        with np.load(p, allow_pickle=False) as z:
            optional = {f.name for f in fields(Truth) if f.name.startswith("bump_")}  # older sidecars
            missing = [f.name for f in fields(Truth) if f.name not in z.files and f.name not in optional]
            if missing:
                raise ValueError(f"{p}: not a simulator truth file (missing {', '.join(missing)})")
            kw = {}
            for f in fields(Truth):
                if f.name not in z.files:
                    continue
                v = z[f.name]
                if f.name == "sensors":
                    v = tuple(str(s) for s in v)
                elif f.name == "config":
                    v = json.loads(str(v))
                elif f.name in ("start_time",):
                    v = float(v)
                elif f.name == "seed":
                    v = int(v)
                kw[f.name] = v
        return Truth(**kw)

    @staticmethod
    def sidecar_path(recording: str | os.PathLike) -> Path:
        return Path(str(recording) + ".truth.npz")
