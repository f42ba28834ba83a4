"""ONNX Runtime adapter for a user-supplied pose model (``--detector onnx:MODEL.onnx``).

Layouts, detected from the model's outputs (or forced with ``--detector-arg layout=...``):

``yolo`` (bottom-up, one pass, several persons) — e.g. an Ultralytics YOLOv8/11-pose
  export. Input ``[1, 3, H, W]`` float32 RGB scaled to [0, 1], the image letterboxed
  (aspect kept, grey 114 padding, centred). Output either
  ``[1, 56, N]`` (or ``[1, N, 56]``): per candidate cx, cy, w, h, score, then 17 × (x, y,
  conf) in input pixels — non-maximum suppression is done here; or ``[1, N, 57]``
  (end-to-end export): x0, y0, x1, y1, score, class, 17 × (x, y, conf), already suppressed.

``simcc`` (top-down, one person per crop) — e.g. RTMPose. Input ``[1, 3, H, W]`` (256 × 192
  for RTMPose-m) RGB normalised with ``mean``/``std`` (ImageNet in 0–255 units by default);
  outputs ``simcc_x [1, 17, W·r]`` and ``simcc_y [1, 17, H·r]`` (r = 2 for RTMPose): the
  joint is at the argmax / r, its confidence min(max_x, max_y).

``heatmap`` (top-down) — e.g. ViTPose, SimpleBaseline, HRNet. Same input as ``simcc``;
  output ``[1, 17, h, w]`` heatmaps: the joint is at the argmax (with a quarter-pixel shift
  toward the larger neighbour) scaled to the input, its confidence the peak value.

Top-down models need person boxes: by default the whole image is one crop (one person in
view); with ``boxes=DETECTOR.onnx`` the boxes come from a ``yolo`` pose model or a YOLO
detection model (``[1, 4 + classes, N]``, class 0 = person). Each box is widened by
``padding`` (1.25) and brought to the model's aspect ratio before the crop.

Confidences are clipped to [0, 1]. Models with dynamic input sizes take ``input_size``
(``W,H`` or one number).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import Detection, DetectorError, bbox_of

IMAGENET_MEAN = (123.675, 116.28, 103.53)
IMAGENET_STD = (58.395, 57.12, 57.375)


def _cv2():
    try:
        import cv2
    except ImportError:
        raise DetectorError("the ONNX detector needs OpenCV: pip install 'extrcal[onnx]'") from None
    return cv2


class _Model:
    """An ONNX Runtime session on the CPU with its input size."""

    def __init__(self, path: str | Path, input_size: Any = None, threads: int | None = None):
        try:
            import onnxruntime as ort
        except ImportError:
            raise DetectorError("the ONNX detector needs ONNX Runtime: pip install 'extrcal[onnx]'") from None
        path = Path(path)
        if not path.is_file():
            raise DetectorError(f"ONNX model {path} does not exist")
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = int(threads)
        try:
            self.session = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime's own exception types
            raise DetectorError(f"ONNX Runtime cannot load {path}: {e}") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise DetectorError(f"{path}: expected one image input [1, 3, H, W], got {[(i.name, i.shape) for i in inputs]}")
        self.input_name = inputs[0].name
        shape = inputs[0].shape
        self.outputs = self.session.get_outputs()
        w, h = shape[3], shape[2]
        if input_size is not None:
            parts = [int(x) for x in str(input_size).replace("x", ",").split(",")]
            w, h = (parts[0], parts[-1])
        if not (isinstance(w, int) and isinstance(h, int)):
            raise DetectorError(f"{path} has a dynamic input size {shape}: give --detector-arg input_size=W,H")
        self.size = (w, h)
        self.path = path

    def run(self, blob: np.ndarray) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: blob})


def letterbox(image: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Resize keeping the aspect and pad centred with grey 114 (Ultralytics' convention).

    Returns the (H, W, 3) padded image, the scale and the (left, top) padding, so that
    image pixel = (input pixel - pad) / scale."""
    cv2 = _cv2()
    h, w = image.shape[:2]
    W, H = size
    scale = min(W / w, H / h)
    nw, nh = int(round(w * scale)), int(round(h * scale))
    resized = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR) if (nw, nh) != (w, h) else image
    left, top = int(round((W - nw) / 2 - 0.1)), int(round((H - nh) / 2 - 0.1))
    out = np.full((H, W, 3), 114, dtype=np.uint8)
    out[top:top + nh, left:left + nw] = resized
    return out, scale, (float(left), float(top))


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float, max_det: int) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression. boxes: (N, 4) x0, y0, x1, y1."""
    order = np.argsort(-scores)
    keep: list[int] = []
    area = np.maximum(0, boxes[:, 2] - boxes[:, 0]) * np.maximum(0, boxes[:, 3] - boxes[:, 1])
    while order.size and len(keep) < max_det:
        i = order[0]
        keep.append(int(i))
        rest = order[1:]
        xx0 = np.maximum(boxes[i, 0], boxes[rest, 0])
        yy0 = np.maximum(boxes[i, 1], boxes[rest, 1])
        xx1 = np.minimum(boxes[i, 2], boxes[rest, 2])
        yy1 = np.minimum(boxes[i, 3], boxes[rest, 3])
        inter = np.maximum(0, xx1 - xx0) * np.maximum(0, yy1 - yy0)
        ious = inter / np.maximum(area[i] + area[rest] - inter, 1e-9)
        order = rest[ious <= iou]
    return np.array(keep, dtype=int)


def decode_yolo(out: np.ndarray, *, score_threshold: float, iou: float, max_det: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A YOLO output → (boxes (P, 4) x0 y0 x1 y1, scores (P,), kp (P, 17, 3) or None), input pixels.

    ``[1, 56, N]``/``[1, N, 56]``: pose with NMS here; ``[1, N, 57]``: end-to-end pose;
    ``[1, 4 + C, N]``: detection, class 0 (person) kept, NMS here."""
    a = np.asarray(out, dtype=np.float64)
    if a.ndim != 3 or a.shape[0] != 1:
        raise DetectorError(f"unexpected YOLO output shape {a.shape}")
    a = a[0]
    if a.shape[1] == 57 and a.shape[0] != 56:  # end-to-end: boxes already suppressed
        a = a[a[:, 4] >= score_threshold][:max_det]
        return a[:, :4], a[:, 4], a[:, 6:].reshape(-1, 17, 3)
    if a.shape[0] == 56 or (a.shape[1] != 56 and a.shape[0] < a.shape[1]):  # channels first
        a = a.T
    c = a.shape[1]
    if c == 56:
        boxes_c, scores, kp = a[:, :4], a[:, 4], a[:, 5:].reshape(-1, 17, 3)
    elif c > 4:
        boxes_c, scores, kp = a[:, :4], a[:, 4], None  # detection: class 0 = person
    else:
        raise DetectorError(f"unexpected YOLO output with {c} channels (pose: 56, end-to-end pose: 57, detection: 4 + classes)")
    ok = scores >= score_threshold
    boxes_c, scores = boxes_c[ok], scores[ok]
    kp = kp[ok] if kp is not None else None
    boxes = np.column_stack([boxes_c[:, 0] - boxes_c[:, 2] / 2, boxes_c[:, 1] - boxes_c[:, 3] / 2,
                             boxes_c[:, 0] + boxes_c[:, 2] / 2, boxes_c[:, 1] + boxes_c[:, 3] / 2])
    keep = nms(boxes, scores, iou, max_det)
    return boxes[keep], scores[keep], (kp[keep] if kp is not None else None)


def decode_simcc(simcc_x: np.ndarray, simcc_y: np.ndarray, ratio: float) -> np.ndarray:
    """(17, Wr), (17, Hr) → (17, 3) [x, y, conf] in input pixels."""
    x = np.argmax(simcc_x, axis=1)
    y = np.argmax(simcc_y, axis=1)
    conf = np.minimum(simcc_x.max(axis=1), simcc_y.max(axis=1))
    return np.column_stack([x / ratio, y / ratio, np.clip(conf, 0, 1)])


def decode_heatmap(hm: np.ndarray, input_size: tuple[int, int]) -> np.ndarray:
    """(17, h, w) heatmaps → (17, 3) [x, y, conf] in input pixels (pixel centres)."""
    J, h, w = hm.shape
    flat = hm.reshape(J, -1)
    idx = np.argmax(flat, axis=1)
    ys, xs = np.divmod(idx, w)
    px, py = xs.astype(float), ys.astype(float)
    for j in range(J):  # quarter-pixel shift toward the larger neighbour
        x, y = xs[j], ys[j]
        if 0 < x < w - 1:
            px[j] += 0.25 * np.sign(hm[j, y, x + 1] - hm[j, y, x - 1])
        if 0 < y < h - 1:
            py[j] += 0.25 * np.sign(hm[j, y + 1, x] - hm[j, y - 1, x])
    W, H = input_size
    return np.column_stack([(px + 0.5) * W / w, (py + 0.5) * H / h, np.clip(flat.max(axis=1), 0, 1)])


def crop_transform(box: np.ndarray, size: tuple[int, int], padding: float) -> np.ndarray:
    """2×3 affine from the image to the model input for ``box`` widened by ``padding``
    and brought to the input's aspect ratio (centre kept)."""
    W, H = size
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    bw, bh = max(x1 - x0, 1.0) * padding, max(y1 - y0, 1.0) * padding
    if bw / bh > W / H:
        bh = bw * H / W
    else:
        bw = bh * W / H
    s = W / bw
    return np.array([[s, 0, W / 2 - s * cx], [0, s, H / 2 - s * cy]])


class OnnxPose:
    """See the module docstring. Keyword arguments come from ``--detector-arg``."""

    def __init__(
        self,
        model: str | Path,
        *,
        layout: str | None = None,
        score_threshold: float = 0.25,
        iou: float = 0.45,
        max_det: int = 50,
        input_size: Any = None,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        padding: float = 1.25,
        boxes: str | None = None,
        box_input_size: Any = None,
        threads: int | None = None,
    ):
        self.model = _Model(model, input_size, threads)
        self.layout = layout or self._guess_layout()
        if self.layout not in ("yolo", "simcc", "heatmap"):
            raise DetectorError(f"unknown layout {self.layout!r}: yolo, simcc or heatmap")
        self.score_threshold, self.iou, self.max_det = float(score_threshold), float(iou), int(max_det)
        self.mean = np.asarray(mean, dtype=np.float32)
        self.std = np.asarray(std, dtype=np.float32)
        self.padding = float(padding)
        self.box_model = _Model(boxes, box_input_size, threads) if boxes else None
        if self.box_model is not None and self.layout == "yolo":
            raise DetectorError("boxes=... is for top-down models (simcc, heatmap); a yolo model finds its own persons")

    def _guess_layout(self) -> str:
        shapes = [o.shape for o in self.model.outputs]
        if len(shapes) == 2 and all(len(s) == 3 for s in shapes):
            return "simcc"
        if len(shapes) >= 1 and len(shapes[0]) == 4:
            return "heatmap"
        if len(shapes) >= 1 and len(shapes[0]) == 3 and (56 in shapes[0][1:] or 57 in shapes[0][1:]):
            return "yolo"
        raise DetectorError(
            f"{self.model.path}: cannot tell the layout from the outputs {shapes}; "
            "give --detector-arg layout=yolo|simcc|heatmap")

    # -------------------------------------------------------------- inference

    def __call__(self, image: np.ndarray) -> list[Detection]:
        assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8, "BGR uint8 (H, W, 3)"
        if self.layout == "yolo":
            boxes, scores, kp = self._yolo(self.model, image)
            return [Detection(kp=k, bbox=b, score=float(s)) for b, s, k in zip(boxes, scores, kp)]
        h, w = image.shape[:2]
        if self.box_model is not None:
            boxes, scores, _ = self._yolo(self.box_model, image)
        else:
            boxes, scores = np.array([[0.0, 0.0, w, h]]), np.array([np.nan])
        out = []
        for box, s in zip(boxes, scores):
            kp = self._top_down(image, box)
            if not (kp[:, 2] > 0).any():
                continue
            score = float(s) if np.isfinite(s) else float(kp[:, 2].mean())
            bbox = box if np.isfinite(s) else bbox_of(kp, 0.0)
            out.append(Detection(kp=kp, bbox=bbox, score=score))
        return out

    def _yolo(self, model: _Model, image: np.ndarray):
        cv2 = _cv2()
        padded, scale, (left, top) = letterbox(image, model.size)
        blob = cv2.cvtColor(padded, cv2.COLOR_BGR2RGB).astype(np.float32).transpose(2, 0, 1)[None] / 255.0
        boxes, scores, kp = decode_yolo(model.run(blob)[0], score_threshold=self.score_threshold,
                                        iou=self.iou, max_det=self.max_det)
        pad = np.array([left, top, left, top])
        boxes = (boxes - pad) / scale
        if kp is not None:
            kp = kp.copy()
            kp[:, :, 0] = (kp[:, :, 0] - left) / scale
            kp[:, :, 1] = (kp[:, :, 1] - top) / scale
            kp[:, :, 2] = np.clip(kp[:, :, 2], 0, 1)
        return boxes, np.clip(scores, 0, 1), kp

    def _top_down(self, image: np.ndarray, box: np.ndarray) -> np.ndarray:
        cv2 = _cv2()
        W, H = self.model.size
        A = crop_transform(box, (W, H), self.padding)
        crop = cv2.warpAffine(image, A, (W, H), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))
        rgb = cv2.cvtColor(crop, cv2.COLOR_BGR2RGB).astype(np.float32)
        blob = ((rgb - self.mean) / self.std).transpose(2, 0, 1)[None].astype(np.float32)
        outs = self.model.run(blob)
        if self.layout == "simcc":
            sx, sy = (np.asarray(o, dtype=np.float64)[0] for o in outs[:2])
            if sx.shape[0] != 17 or sy.shape[0] != 17:
                raise DetectorError(f"SimCC outputs must be [1, 17, ·], got {outs[0].shape}, {outs[1].shape}")
            kp = decode_simcc(sx, sy, ratio=sx.shape[1] / W)
        else:
            hm = np.asarray(outs[0], dtype=np.float64)[0]
            if hm.shape[0] != 17:
                raise DetectorError(f"heatmap output must be [1, 17, h, w], got {outs[0].shape}")
            kp = decode_heatmap(hm, (W, H))
        # Back from the crop to the image: A maps image → input, both axes scaled by A[0, 0].
        s = A[0, 0]
        kp[:, 0] = (kp[:, 0] - A[0, 2]) / s
        kp[:, 1] = (kp[:, 1] - A[1, 2]) / s
        return kp
