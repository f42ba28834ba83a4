"""Keypoint message v1: the one object every wire and file form decodes to.

Wire: a msgpack map. ``kp``/``cov`` may be nested lists or float32 little-endian
bytes (row-major). Recordings: the same map as JSON (nested lists). See
shared/FORMATS.md.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

VERSION = 1
N_JOINTS = 17
LAYOUTS = {"coco17": 17}
COCO17 = (
    "nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder",
    "l_elbow", "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee",
    "r_knee", "l_ankle", "r_ankle",
)
# Limits that keep one message from costing unbounded memory or time downstream.
MAX_PERSONS = 256
MAX_SIZE_PX = 16384
MAX_STAMP = 1e11  # s since the epoch: larger stamps are milli-, micro- or nanoseconds
MAX_SENSOR_LEN = 128
_SENSOR_NAME = re.compile(r"[A-Za-z0-9_.\-]+")  # ASCII letters, digits, '_', '-', '.' (fullmatch)


class MessageError(ValueError):
    """A message that does not match the v1 schema; ``field`` names where."""

    def __init__(self, field: str, reason: str):
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


@dataclass(frozen=True, eq=False)
class Person:
    """One detected person in one image.

    kp:  (17, 3) float64, columns u, v (raw distorted pixels), confidence in [0, 1];
         a joint that was not detected has confidence 0.
    cov: (17, 3) float64 pixel² covariance [xx, xy, yy] per joint, or None.
    bbox: (4,) float64 [x0, y0, x1, y1] or None.
    """

    kp: np.ndarray
    bbox: np.ndarray | None = None
    score: float | None = None
    cov: np.ndarray | None = None
    track: int | None = None

    def __post_init__(self) -> None:
        assert self.kp.shape == (N_JOINTS, 3) and self.kp.dtype == np.float64
        assert self.cov is None or self.cov.shape == (N_JOINTS, 3)
        assert self.bbox is None or self.bbox.shape == (4,)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Person):
            return NotImplemented
        return (
            np.array_equal(self.kp, other.kp)
            and _opt_equal(self.bbox, other.bbox)
            and _opt_equal(self.cov, other.cov)
            and self.score == other.score
            and self.track == other.track
        )


@dataclass(frozen=True, eq=True)
class KeypointMessage:
    """All detections of one sensor at one capture instant."""

    sensor: str
    seq: int
    stamp: float  # capture time, seconds since the Unix epoch (sensor clock)
    size: tuple[int, int]  # (width, height) of the image the pixels refer to
    persons: tuple[Person, ...] = field(default_factory=tuple)
    layout: str = "coco17"
    v: int = VERSION

    def keypoints(self) -> np.ndarray:
        """(P, 17, 3) float64 stack of all persons' keypoints."""
        if not self.persons:
            return np.zeros((0, N_JOINTS, 3))
        return np.stack([p.kp for p in self.persons])


def _opt_equal(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(a, b)


# ---------------------------------------------------------------- validation


def _num(value: Any, name: str, *, finite: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise MessageError(name, f"expected a number, got {type(value).__name__}")
    x = float(value)
    if finite and not math.isfinite(x):
        raise MessageError(name, f"expected a finite number, got {x}")
    return x


def _int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise MessageError(name, f"expected an integer, got {type(value).__name__}")
    return value


def _matrix(value: Any, name: str, rows: int, cols: int) -> np.ndarray:
    """Nested lists or packed float32 LE bytes → (rows, cols) float64."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        raw = bytes(value)
        want = rows * cols * 4
        if len(raw) != want:
            raise MessageError(
                name, f"packed float32 needs {want} bytes ({rows}x{cols}), got {len(raw)}"
            )
        arr = np.frombuffer(raw, dtype="<f4").reshape(rows, cols).astype(np.float64)
    elif isinstance(value, (list, tuple)):
        arr = _fast_matrix(value, rows, cols)
        if arr is None:  # something is off: find it and say where
            _explain_matrix(value, name, rows, cols)
            arr = np.array(value, dtype=np.float64)  # well-formed after all: NaN/inf, named below
    else:
        raise MessageError(name, f"expected a list or packed bytes, got {type(value).__name__}")
    # one reduction when all is well (a sum of finite values is finite unless huge ones overflow)
    if not math.isfinite(arr.sum()) and not np.isfinite(arr).all():
        i = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise MessageError(f"{name}[{i}]", "NaN or infinite value")
    return arr


def _fast_matrix(value: list | tuple, rows: int, cols: int) -> np.ndarray | None:
    """(rows, cols) float64 of well-formed nested lists, else None (no bools, no strings)."""
    if len(value) != rows:
        return None
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if arr.shape != (rows, cols) or not np.all(np.isfinite(arr)):
        return None  # None becomes NaN in np.array: let the slow path name it
    for row in value:
        for x in row:
            if x.__class__ is bool:
                return None
    return arr


def _explain_matrix(value: list | tuple, name: str, rows: int, cols: int) -> None:
    if len(value) != rows:
        raise MessageError(name, f"expected {rows} rows of {cols}, got {len(value)}")
    for i, row in enumerate(value):
        if not isinstance(row, (list, tuple)) or len(row) != cols:
            got = len(row) if isinstance(row, (list, tuple)) else type(row).__name__
            raise MessageError(f"{name}[{i}]", f"expected {cols} numbers, got {got}")
        for j, x in enumerate(row):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                raise MessageError(f"{name}[{i}][{j}]", f"expected a number, got {type(x).__name__}")


def _person(d: Any, name: str, size: tuple[int, int]) -> Person:
    if not isinstance(d, dict):
        raise MessageError(name, f"expected a map, got {type(d).__name__}")
    if "kp" not in d:
        raise MessageError(f"{name}.kp", "missing")
    kp = _matrix(d["kp"], f"{name}.kp", N_JOINTS, 3)
    # Few reductions, no temporaries: this runs for every person of every message, on the
    # service loop, 10,000s of times a second under overload (bench/overload.py).
    conf = kp[:, 2]
    if conf.min() < 0 or conf.max() > 1:
        j = int(np.argmax((conf < 0) | (conf > 1)))
        raise MessageError(f"{name}.kp[{j}]", f"confidence {conf[j]} outside [0, 1]")
    # Pixels may fall slightly outside the image (detectors extrapolate), but not absurdly.
    w, h = size
    uv = kp[conf > 0, :2]
    if len(uv):
        hi = uv.max(axis=0)
        if uv.min() < -max(w, h) or hi[0] > 2 * w or hi[1] > 2 * h:
            raise MessageError(f"{name}.kp", f"pixel coordinates far outside the {w}x{h} image")
    bbox = None
    if d.get("bbox") is not None:
        b = d["bbox"]
        if not isinstance(b, (list, tuple)) or len(b) != 4:
            raise MessageError(f"{name}.bbox", "expected [x0, y0, x1, y1]")
        bbox = np.array([_num(x, f"{name}.bbox[{i}]") for i, x in enumerate(b)])
    score = None if d.get("score") is None else _num(d["score"], f"{name}.score")
    cov = None
    if d.get("cov") is not None:
        cov = _matrix(d["cov"], f"{name}.cov", N_JOINTS, 3)
        if np.any(cov[:, 0] < 0) or np.any(cov[:, 2] < 0):
            raise MessageError(f"{name}.cov", "negative variance")
    track = None if d.get("track") is None else _int(d["track"], f"{name}.track")
    return Person(kp=kp, bbox=bbox, score=score, cov=cov, track=track)


def from_dict(d: Any, *, default_version: int | None = None) -> KeypointMessage:
    """Validate a decoded map (msgpack or JSON) into a KeypointMessage.

    ``default_version`` is used when ``v`` is missing (JSON Lines: 1); the wire
    requires it.
    """
    if not isinstance(d, dict):
        raise MessageError("", f"expected a map at the top level, got {type(d).__name__}")
    v = d.get("v", default_version)
    if v is None:
        raise MessageError("v", "missing")
    if _int(v, "v") != VERSION:
        raise MessageError("v", f"unsupported version {v} (this build reads {VERSION})")
    for key in ("sensor", "seq", "stamp", "size", "persons"):
        if key not in d:
            raise MessageError(key, "missing")
    sensor = d["sensor"]
    if not isinstance(sensor, str) or not sensor:
        raise MessageError("sensor", "expected a non-empty string")
    if len(sensor) > MAX_SENSOR_LEN or _SENSOR_NAME.fullmatch(sensor) is None:
        raise MessageError("sensor", "only letters, digits, '_', '-', '.' (at most 128)")
    seq = _int(d["seq"], "seq")
    if seq < 0:
        raise MessageError("seq", f"must be >= 0, got {seq}")
    stamp = _num(d["stamp"], "stamp")
    if stamp <= 0:
        raise MessageError("stamp", f"must be seconds since the Unix epoch, got {stamp}")
    if stamp >= MAX_STAMP:  # the year 5138: a clock counted in smaller units
        unit = next(u for u, k in (("nanoseconds", 1e17), ("microseconds", 1e14), ("milliseconds", MAX_STAMP))
                    if stamp >= k)
        raise MessageError("stamp", f"{stamp:.6g} is not seconds since the Unix epoch ({unit}?)")
    size = d["size"]
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise MessageError("size", "expected [width, height]")
    w, h = (_int(x, f"size[{i}]") for i, x in enumerate(size))
    if not (0 < w <= MAX_SIZE_PX and 0 < h <= MAX_SIZE_PX):
        raise MessageError("size", f"{w}x{h} is not a plausible image size")
    layout = d.get("layout", "coco17")
    if not isinstance(layout, str) or layout not in LAYOUTS:  # a list here is unhashable
        raise MessageError("layout", f"unknown layout {str(layout)[:40]!r} (known: {', '.join(LAYOUTS)})")
    persons = d["persons"]
    if not isinstance(persons, (list, tuple)):
        raise MessageError("persons", f"expected a list, got {type(persons).__name__}")
    if len(persons) > MAX_PERSONS:
        raise MessageError("persons", f"{len(persons)} persons, at most {MAX_PERSONS}")
    return KeypointMessage(
        sensor=sensor,
        seq=seq,
        stamp=stamp,
        size=(w, h),
        persons=tuple(_person(p, f"persons[{i}]", (w, h)) for i, p in enumerate(persons)),
        layout=layout,
    )


def to_dict(msg: KeypointMessage, *, packed: bool = False) -> dict[str, Any]:
    """The map form; ``packed`` stores kp/cov as float32 LE bytes (wire only)."""

    def mat(a: np.ndarray) -> Any:
        return a.astype("<f4").tobytes() if packed else a.tolist()

    persons = []
    for p in msg.persons:
        d: dict[str, Any] = {"kp": mat(p.kp)}
        if p.bbox is not None:
            d["bbox"] = p.bbox.tolist()
        if p.score is not None:
            d["score"] = p.score
        if p.cov is not None:
            d["cov"] = mat(p.cov)
        if p.track is not None:
            d["track"] = p.track
        persons.append(d)
    return {
        "v": msg.v,
        "sensor": msg.sensor,
        "seq": msg.seq,
        "stamp": msg.stamp,
        "size": list(msg.size),
        "layout": msg.layout,
        "persons": persons,
    }


def encode(msg: KeypointMessage, *, packed: bool = True) -> bytes:
    """msgpack bytes for the wire."""
    return msgpack.packb(to_dict(msg, packed=packed), use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview) -> KeypointMessage:
    """Validate msgpack bytes from the wire; raises MessageError."""
    try:
        d = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises a zoo of types for garbage
        raise MessageError("", f"not a msgpack map ({type(e).__name__}: {e})") from None
    return from_dict(d)
