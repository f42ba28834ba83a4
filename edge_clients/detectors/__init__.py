"""Pose detector plugins for the camera client.

A detector is any callable that takes one image and returns the persons in it::

    class MyDetector:
        def __init__(self, **kwargs): ...          # --detector-arg KEY=VALUE
        def __call__(self, image):                 # (H, W, 3) uint8, BGR (OpenCV)
            return [Detection(kp=..., bbox=..., score=...)]
        def close(self): ...                       # optional

``kp`` is (17, 3) [u, v, confidence] in COCO-17 order (proto.COCO17) in pixels of the
given image, a joint that was not found has confidence 0. ``bbox`` ([x0, y0, x1, y1])
and ``score`` are optional. Instead of Detection objects a plugin may return mappings
with the same keys. Run it with ``--detector package.module:MyDetector``.

Shipped: ``mediapipe`` (BlazePose, one person, the model comes with the mediapipe wheel)
and ``onnx:MODEL.onnx`` (ONNX Runtime, YOLO-pose or top-down SimCC/heatmap models).
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np

from proto import N_JOINTS, Person


class DetectorError(RuntimeError):
    """A detector that cannot be loaded or returns what the interface does not allow."""


@dataclass(frozen=True, eq=False)
class Detection:
    """One person. kp: (17, 3) float64 [u, v, conf]; bbox: (4,) [x0, y0, x1, y1] or None."""

    kp: np.ndarray
    bbox: np.ndarray | None = None
    score: float | None = None


class Detector(Protocol):
    def __call__(self, image: np.ndarray) -> Sequence[Detection | Mapping[str, Any]]: ...


def load_detector(spec: str, kwargs: Mapping[str, Any] | None = None) -> Callable:
    """``mediapipe`` | ``onnx:PATH`` | ``package.module:Name`` (a class or factory) → detector."""
    kwargs = dict(kwargs or {})
    try:
        if spec == "mediapipe":
            from .mediapipe_pose import MediaPipePose

            return MediaPipePose(**kwargs)
        if spec.startswith("onnx:"):
            from .onnx_pose import OnnxPose

            return OnnxPose(spec[len("onnx:"):], **kwargs)
        if ":" not in spec:
            raise DetectorError(f"unknown detector {spec!r}: expected mediapipe, onnx:MODEL.onnx or package.module:Class")
        mod_name, attr = spec.split(":", 1)
        try:
            mod = importlib.import_module(mod_name)
        except ImportError as e:
            raise DetectorError(f"cannot import detector module {mod_name!r} ({e})") from None
        factory = getattr(mod, attr, None)
        if factory is None:
            raise DetectorError(f"module {mod_name!r} has no {attr!r}")
        det = factory(**kwargs)
        if not callable(det):
            raise DetectorError(f"{spec} made a {type(det).__name__}, which is not callable on an image")
        return det
    except DetectorError:
        raise
    except TypeError as e:  # wrong --detector-arg names
        raise DetectorError(f"{spec}: {e}") from None
    except (ImportError, OSError, ValueError) as e:
        raise DetectorError(f"{spec}: {e}") from None


def to_person(det: Detection | Mapping[str, Any] | Any, size: tuple[int, int]) -> Person:
    """A plugin's detection → proto.Person: NaN joints become missing (confidence 0),
    confidences are clipped to [0, 1]; a wrong shape is the plugin's bug (DetectorError)."""
    get = det.get if isinstance(det, Mapping) else (lambda k, d=None: getattr(det, k, d))
    kp = np.array(get("kp"), dtype=np.float64)
    if kp.shape != (N_JOINTS, 3):
        raise DetectorError(f"a detection's kp must be ({N_JOINTS}, 3) [u, v, conf] (COCO-17), got {kp.shape}")
    bad = ~np.isfinite(kp).all(axis=1)
    kp[bad] = 0.0
    kp[:, 2] = np.clip(kp[:, 2], 0.0, 1.0)
    w, h = size
    # Far outside the image is a detector bug or a NaN-ish blow-up: that joint is missing.
    far = (kp[:, 0] < -w) | (kp[:, 0] > 2 * w) | (kp[:, 1] < -h) | (kp[:, 1] > 2 * h)
    kp[far] = 0.0
    bbox = get("bbox")
    if bbox is not None:
        bbox = np.array(bbox, dtype=np.float64).reshape(-1)
        if bbox.shape != (4,) or not np.isfinite(bbox).all():
            raise DetectorError(f"a detection's bbox must be 4 finite numbers [x0, y0, x1, y1], got {bbox}")
    score = get("score")
    if score is not None:
        score = float(score)
        if not math.isfinite(score):
            score = None
    return Person(kp=kp, bbox=bbox, score=score)


def bbox_of(kp: np.ndarray, min_conf: float = 0.0) -> np.ndarray | None:
    """[x0, y0, x1, y1] of the joints with confidence > min_conf, or None."""
    ok = kp[:, 2] > min_conf
    if not ok.any():
        return None
    uv = kp[ok, :2]
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
