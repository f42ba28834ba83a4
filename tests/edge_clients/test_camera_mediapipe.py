"""MediaPipe BlazePose adapter: the 33 → COCO-17 mapping everywhere, the real model where installed.

The real-model test needs mediapipe <= 0.10.21 (its wheel carries the BlazePose model;
it needs numpy < 2, so it lives in a sensor's own environment, not in CI's) and a photo of
a person: scikit-image's astronaut, or the file named by EXTRCAL_TEST_PERSON_IMAGE.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from edge_clients.detectors.mediapipe_pose import BLAZEPOSE_TO_COCO, blazepose_to_coco
from proto import COCO17

BLAZEPOSE = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
    "right_ankle", "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)


def test_mapping_takes_the_same_named_joint():
    for coco_name, b in zip(COCO17, BLAZEPOSE_TO_COCO):
        want = coco_name.replace("l_", "left_").replace("r_", "right_")
        assert BLAZEPOSE[b] == want


def test_blazepose_to_coco_scales_to_pixels():
    lm = np.zeros((33, 3))
    lm[:, 0] = np.arange(33) / 33
    lm[:, 1] = 0.5
    lm[:, 2] = np.linspace(-0.1, 1.1, 33)  # visibilities slightly outside [0, 1] happen
    kp = blazepose_to_coco(lm, (640, 480))
    assert kp.shape == (17, 3)
    assert kp[11, 0] == pytest.approx(23 / 33 * 640) and kp[11, 1] == 240
    assert kp[:, 2].min() >= 0 and kp[:, 2].max() <= 1


def _person_image() -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    path = os.environ.get("EXTRCAL_TEST_PERSON_IMAGE")
    if not path:
        try:
            import skimage.data
        except ImportError:
            pytest.skip("no photo of a person: set EXTRCAL_TEST_PERSON_IMAGE or install scikit-image")
        return cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2BGR)
    img = cv2.imread(path)
    assert img is not None, path
    return img


def test_real_blazepose_finds_the_astronaut():
    mp = pytest.importorskip("mediapipe")
    if not hasattr(mp, "solutions"):
        pytest.skip(f"mediapipe {mp.__version__} has no bundled BlazePose (needs <= 0.10.21)")
    from edge_clients.detectors import load_detector

    image = _person_image()
    det = load_detector("mediapipe", {"static_image_mode": True})
    try:
        assert det(np.zeros_like(image)) == []
        (p,) = det(image)
    finally:
        det.close()
    kp = p.kp
    h, w = image.shape[:2]
    # Facing the camera: the person's left is on the image's right.
    assert kp[1, 0] > kp[2, 0] and kp[5, 0] > kp[6, 0]
    assert kp[0, 1] < kp[5, 1] and kp[0, 1] < kp[6, 1], "nose above the shoulders"
    assert (kp[[0, 1, 2, 5, 6], 2] > 0.9).all()
    assert 0 <= kp[0, 0] < w and 0 <= kp[0, 1] < h
