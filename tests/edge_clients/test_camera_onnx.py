"""The ONNX Runtime pose adapter on tiny models built here with onnx.helper.

The models compute their outputs from the image (mean brightness), so the test checks
the preprocessing (RGB / 255, letterbox, crop and normalisation) as well as the decoding
(NMS, score threshold, letterbox and crop undone)."""

from __future__ import annotations

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
cv2 = pytest.importorskip("cv2")

from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from edge_clients.detectors import DetectorError, load_detector  # noqa: E402
from edge_clients.detectors.onnx_pose import crop_transform, decode_heatmap, nms  # noqa: E402


def save_model(path, in_shape, outputs: dict[str, tuple[np.ndarray, np.ndarray]]):
    """A model whose output k is mean(image) * A_k + B_k (A, B constants of the output's shape)."""
    nodes = [helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0)]
    inits, outs = [], []
    for name, (a, b) in outputs.items():
        inits += [numpy_helper.from_array(a.astype(np.float32), f"{name}_a"),
                  numpy_helper.from_array(b.astype(np.float32), f"{name}_b")]
        nodes += [helper.make_node("Mul", ["m", f"{name}_a"], [f"{name}_ma"]),
                  helper.make_node("Add", [f"{name}_ma", f"{name}_b"], [name])]
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(a.shape)))
    graph = helper.make_graph(nodes, "tiny_pose", [helper.make_tensor_value_info("images", TensorProto.FLOAT, list(in_shape))],
                              outs, initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def yolo_candidates() -> tuple[np.ndarray, np.ndarray]:
    """[1, 56, 4] candidates in 64×64 input pixels: A (score from brightness), B overlapping
    A with a lower score (suppressed), C apart, D below the threshold."""
    b = np.zeros((1, 56, 4))
    a = np.zeros((1, 56, 4))
    for i, (cx, cy, w, h, s) in enumerate([(20, 30, 10, 20, 0.2), (21, 31, 10, 20, 0.6),
                                           (48, 30, 8, 16, 0.5), (40, 40, 8, 8, 0.1)]):
        b[0, :5, i] = cx, cy, w, h, s
        kp = np.column_stack([np.full(17, cx), cy - h / 2 + np.arange(17) * h / 16, np.linspace(0.2, 1.0, 17)])
        b[0, 5:, i] = kp.reshape(-1)
    a[0, 4, 0] = 0.5  # candidate A's score grows with the image's brightness in [0, 1]
    return a, b


def test_yolo_pose_layout_letterbox_nms_and_threshold(tmp_path):
    path = tmp_path / "yolo_pose.onnx"
    a, b = yolo_candidates()
    save_model(path, (1, 3, 64, 64), {"output0": (a, b)})
    det = load_detector(f"onnx:{path}")
    assert det.layout == "yolo"
    image = np.full((96, 128, 3), 255, np.uint8)  # letterboxed at scale 0.5, 8 px grey bars top and bottom
    mean = (48 * 1.0 + 16 * 114 / 255) / 64
    persons = det(image)
    score_a = 0.2 + 0.5 * mean  # > 0.6: A wins over B, which overlaps it
    assert score_a > 0.6
    assert [round(p.score, 4) for p in persons] == [round(score_a, 4), 0.5]
    pa, pc = persons
    # Input pixel → image pixel: (x - 0, y - 8) / 0.5.
    assert pa.bbox == pytest.approx([(15 - 0) / 0.5, (20 - 8) / 0.5, (25 - 0) / 0.5, (40 - 8) / 0.5], abs=1e-4)
    assert pa.kp[0, :2] == pytest.approx([40.0, 24.0], abs=1e-4)
    assert pa.kp[16, :2] == pytest.approx([40.0, 64.0], abs=1e-4)
    assert pa.kp[:, 2] == pytest.approx(np.linspace(0.2, 1.0, 17), abs=1e-6)
    assert pc.bbox == pytest.approx([88, 28, 104, 60], abs=1e-4)
    # A dark image: A's score 0.2 + 0.5·mean falls below B's, so B is kept instead of A.
    dark = det(np.zeros((96, 128, 3), np.uint8))
    assert [round(p.score, 4) for p in dark] == [0.6, 0.5]
    assert dark[0].bbox == pytest.approx([32, 26, 52, 66], abs=1e-4)


def test_yolo_end_to_end_layout(tmp_path):
    path = tmp_path / "yolo_e2e.onnx"
    b = np.zeros((1, 3, 57))
    b[0, 0, :6] = 10, 10, 30, 50, 0.9, 0
    b[0, 0, 6:] = np.tile([20, 30, 0.7], 17)
    b[0, 1, :6] = 0, 0, 5, 5, 0.1, 0  # below the threshold
    save_model(path, (1, 3, 64, 64), {"output0": (np.zeros_like(b), b)})
    (p,) = load_detector(f"onnx:{path}", {"score_threshold": 0.3})(np.zeros((64, 64, 3), np.uint8))
    assert p.bbox == pytest.approx([10, 10, 30, 50]) and p.score == pytest.approx(0.9)
    assert p.kp[:, :2] == pytest.approx(np.tile([20.0, 30.0], (17, 1)))


def test_simcc_top_down_on_the_whole_image(tmp_path):
    """RTMPose-like: input 48×64 (W×H), SimCC ratio 2, the whole image as the person's box."""
    path = tmp_path / "simcc.onnx"
    W, H, r = 48, 64, 2
    sx, sy = np.zeros((1, 17, W * r)), np.zeros((1, 17, H * r))
    for j in range(17):
        sx[0, j, 20 + j] = 0.8  # x = (20 + j) / 2 input px
        sy[0, j, 30 + 2 * j] = 0.9 if j != 4 else 0.05  # joint 4: low confidence
    save_model(path, (1, 3, H, W), {"simcc_x": (np.zeros_like(sx), sx), "simcc_y": (np.zeros_like(sy), sy)})
    det = load_detector(f"onnx:{path}")
    assert det.layout == "simcc"
    image = np.zeros((120, 160, 3), np.uint8)
    (p,) = det(image)
    A = crop_transform(np.array([0, 0, 160, 120.0]), (W, H), 1.25)
    s = A[0, 0]
    j = np.arange(17)
    assert p.kp[:, 0] == pytest.approx(((20 + j) / 2 - A[0, 2]) / s, abs=1e-6)
    assert p.kp[:, 1] == pytest.approx(((30 + 2 * j) / 2 - A[1, 2]) / s, abs=1e-6)
    assert p.kp[4, 2] == pytest.approx(0.05) and p.kp[0, 2] == pytest.approx(0.8)
    # The crop is centred on the image and covers 1.25× its width (the wider side).
    assert (W / 2 - A[0, 2]) / s == pytest.approx(80) and 1 / s * W == pytest.approx(200)


def test_heatmap_decoding_and_nms_helpers():
    hm = np.zeros((17, 16, 12))
    hm[:, 5, 7] = 0.7
    hm[:, 5, 8] = 0.3  # larger right neighbour: a quarter pixel to the right
    kp = decode_heatmap(hm, (48, 64))
    assert kp[0] == pytest.approx([(7.25 + 0.5) * 4, (5 + 0.5) * 4, 0.7])
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30]], float)
    assert list(nms(boxes, np.array([0.5, 0.9, 0.4]), 0.45, 10)) == [1, 2]


def test_bad_models_are_refused_clearly(tmp_path):
    with pytest.raises(DetectorError, match="does not exist"):
        load_detector(f"onnx:{tmp_path / 'missing.onnx'}")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(DetectorError, match="cannot load"):
        load_detector(f"onnx:{junk}")
    odd = tmp_path / "odd.onnx"
    save_model(odd, (1, 3, 8, 8), {"out": (np.zeros((1, 7)), np.zeros((1, 7)))})
    with pytest.raises(DetectorError, match="layout=yolo"):
        load_detector(f"onnx:{odd}")
