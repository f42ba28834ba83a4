"""MediaPipe BlazePose (``--detector mediapipe``): CPU, model inside the mediapipe wheel.

Uses the legacy ``mediapipe.solutions.pose`` graph with ``model_complexity=1``
(pose_landmark_full.tflite and pose_detection.tflite ship inside the wheels of
mediapipe 0.10.x up to 0.10.21; the "lite" and "heavy" variants, and every model of the
newer Tasks API, are downloaded at run time, which offline sensors cannot do). mediapipe
0.10.21 needs numpy < 2, so install the sensor in its own environment:
``pip install 'extrcal[mediapipe]'``.

BlazePose tracks one person per image. Its 33 landmarks map to COCO-17 by name; the
confidence of a joint is the landmark's visibility. Its hip landmarks sit a little
higher and wider than COCO's annotation convention — harmless for calibration, which
only needs consistent joints across views.
"""

from __future__ import annotations

import numpy as np

from . import Detection, DetectorError, bbox_of

# COCO-17 joint j is BlazePose landmark BLAZEPOSE_TO_COCO[j].
BLAZEPOSE_TO_COCO = (
    0,   # nose
    2,   # left eye
    5,   # right eye
    7,   # left ear
    8,   # right ear
    11,  # left shoulder
    12,  # right shoulder
    13,  # left elbow
    14,  # right elbow
    15,  # left wrist
    16,  # right wrist
    23,  # left hip
    24,  # right hip
    25,  # left knee
    26,  # right knee
    27,  # left ankle
    28,  # right ankle
)


def blazepose_to_coco(landmarks: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(33, 3) BlazePose [x, y, visibility] (x, y normalised to [0, 1]) → (17, 3) COCO
    [u, v, conf] in pixels of an image of ``size`` (width, height)."""
    assert landmarks.shape == (33, 3), landmarks.shape
    w, h = size
    lm = landmarks[list(BLAZEPOSE_TO_COCO)]
    return np.column_stack([lm[:, 0] * w, lm[:, 1] * h, np.clip(lm[:, 2], 0.0, 1.0)])


class MediaPipePose:
    """One person per image. Keyword arguments (``--detector-arg``): ``min_detection_confidence``,
    ``min_tracking_confidence`` (0.5 each), ``static_image_mode`` (False: track between frames),
    ``smooth_landmarks`` (False: no temporal filter, whose lag would shift joints away from
    the capture instant)."""

    def __init__(self, *, min_detection_confidence: float = 0.5, min_tracking_confidence: float = 0.5,
                 static_image_mode: bool = False, smooth_landmarks: bool = False):
        try:
            import mediapipe as mp
            pose_mod = mp.solutions.pose
        except (ImportError, AttributeError):
            raise DetectorError(
                "the mediapipe detector needs mediapipe 0.10.x (<= 0.10.21, whose wheel carries the "
                "BlazePose models): pip install 'extrcal[mediapipe]' (in a separate environment: it needs numpy < 2)"
            ) from None
        import cv2

        self._cv2 = cv2
        self._pose = pose_mod.Pose(
            static_image_mode=bool(static_image_mode),
            model_complexity=1,  # the only BlazePose model inside the wheel
            smooth_landmarks=bool(smooth_landmarks),
            enable_segmentation=False,
            min_detection_confidence=float(min_detection_confidence),
            min_tracking_confidence=float(min_tracking_confidence),
        )

    def __call__(self, image: np.ndarray) -> list[Detection]:
        assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8, "BGR uint8 (H, W, 3)"
        h, w = image.shape[:2]
        res = self._pose.process(self._cv2.cvtColor(image, self._cv2.COLOR_BGR2RGB))
        if res.pose_landmarks is None:
            return []
        lm = np.array([[p.x, p.y, p.visibility] for p in res.pose_landmarks.landmark], dtype=np.float64)
        kp = blazepose_to_coco(lm, (w, h))
        return [Detection(kp=kp, bbox=bbox_of(kp, 0.5), score=float(kp[:, 2].mean()))]

    def close(self) -> None:
        self._pose.close()
