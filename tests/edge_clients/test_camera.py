"""`extrcal sensor camera` on a rendered video file with a detector plugin, over real Zenoh."""

from __future__ import annotations

import queue
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from edge_clients.detectors import Detection, DetectorError, load_detector, to_person
from proto import decode, keys
from proto.transport import ZenohSettings, free_port, open_session

cv2 = pytest.importorskip("cv2")

W, H, N_FRAMES = 160, 120, 12


def box_at(k: int) -> tuple[int, int, int, int]:
    """The white 'person' of frame k: x0, y0, x1, y1, moving right 5 px a frame."""
    return 20 + 5 * k, 30, 40 + 5 * k, 100


class BoxDetector:
    """A real plugin: finds the bright blob in the frame and lays a skeleton into its box."""

    def __init__(self, threshold: int = 128):
        self.threshold = threshold
        self.closed = False

    def __call__(self, image: np.ndarray) -> list:
        assert image.shape == (H, W, 3) and image.dtype == np.uint8
        ys, xs = np.nonzero(image.max(axis=2) > self.threshold)
        if xs.size == 0:
            return []
        x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        kp = np.zeros((17, 3))
        kp[:, 0] = (x0 + x1) / 2
        kp[:, 1] = np.linspace(y0, y1, 17)
        kp[:, 2] = 0.9
        kp[5, 0], kp[6, 0] = x1, x0  # shoulders at the box's sides
        if x0 > 50:  # from frame 7 on: also a mapping-style result
            return [{"kp": kp.tolist(), "bbox": [x0, y0, x1, y1], "score": 0.8}]
        return [Detection(kp=kp, bbox=np.array([x0, y0, x1, y1], float), score=0.8)]

    def close(self) -> None:
        self.closed = True


def render_video(path) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    assert writer.isOpened()
    for k in range(N_FRAMES):
        img = np.zeros((H, W, 3), np.uint8)
        if k != 3:  # frame 3: nobody in view
            x0, y0, x1, y1 = box_at(k)
            img[y0:y1, x0:x1] = 255
        writer.write(img)
    writer.release()


def test_camera_client_publishes_detections_of_a_video_file(tmp_path):
    from backend.cli import _register_all, app

    _register_all()
    video = tmp_path / "walk.avi"
    render_video(video)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    session = open_session(ZenohSettings(listen=(ep,)))
    got: queue.Queue = queue.Queue()
    alive: queue.Queue = queue.Queue()
    sub = session.declare_subscriber(keys.all_keypoints("lab"),
                                     lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
    tok = session.liveliness().declare_subscriber(keys.all_alive("lab"), lambda s: alive.put(str(s.key_expr)))
    try:
        t_before = time.time()
        res = CliRunner().invoke(app, [
            "sensor", "camera", "--sensor", "cam_3", "--source", str(video),
            "--detector", f"{__name__}:BoxDetector", "--detector-arg", "threshold=100",
            "--site", "lab", "--zenoh-connect", ep, "--wait-subscriber", "10", "-q"])
        t_after = time.time()
        assert res.exit_code == 0, res.output
        assert f"published {N_FRAMES} frames, {N_FRAMES - 1} persons" in res.output
        msgs = []
        deadline = time.monotonic() + 30
        while len(msgs) < N_FRAMES and time.monotonic() < deadline:
            try:
                key, payload = got.get(timeout=0.2)
            except queue.Empty:
                continue
            assert key == keys.keypoints("lab", "cam_3")
            msgs.append(decode(payload))
    finally:
        tok.undeclare()
        sub.undeclare()
        session.close()
    assert alive.get(timeout=30) == keys.alive("lab", "cam_3")
    assert [m.seq for m in msgs] == list(range(N_FRAMES))
    stamps = np.array([m.stamp for m in msgs])
    assert np.all(np.diff(stamps) > 0) and t_before < stamps[0] and stamps[-1] < t_after
    assert all(m.size == (W, H) for m in msgs)
    assert msgs[3].persons == ()
    for k, m in enumerate(msgs):
        if k == 3:
            continue
        (p,) = m.persons
        x0, y0, x1, y1 = box_at(k)
        # MJPG is lossy: the blob's edges may move by a pixel.
        assert p.bbox == pytest.approx([x0, y0, x1, y1], abs=2)
        assert p.kp[5, 0] == pytest.approx(x1, abs=2) and p.kp[6, 0] == pytest.approx(x0, abs=2)
        assert p.kp[:, 2] == pytest.approx(0.9, abs=1e-6) and p.score == pytest.approx(0.8)


def test_camera_errors_are_clear(tmp_path):
    from backend.cli import _register_all, app

    _register_all()
    runner = CliRunner()
    res = runner.invoke(app, ["sensor", "camera", "--sensor", "cam_3", "--source", str(tmp_path / "none.mp4"),
                              "--detector", f"{__name__}:BoxDetector", "-q", "--zenoh-connect", "tcp/127.0.0.1:1"])
    assert res.exit_code == 2 and "cannot open the video source" in res.output
    res = runner.invoke(app, ["sensor", "camera", "--sensor", "cam_3", "--detector", "no_such_module:X", "-q"])
    assert res.exit_code == 2 and "cannot import detector module 'no_such_module'" in res.output
    with pytest.raises(DetectorError, match="unexpected keyword argument"):
        load_detector(f"{__name__}:BoxDetector", {"nope": 1})
    with pytest.raises(DetectorError, match="unknown detector"):
        load_detector("yolo")


def test_to_person_cleans_what_plugins_return():
    kp = np.full((17, 3), 10.0)
    kp[:, 2] = 1.2
    kp[4] = np.nan
    kp[5, 0] = 1e9
    p = to_person({"kp": kp, "score": 0.5}, (100, 100))
    assert p.kp[0, 2] == 1.0 and p.kp[4, 2] == 0.0 and p.kp[5, 2] == 0.0
    with pytest.raises(DetectorError, match=r"\(17, 3\)"):
        to_person({"kp": np.zeros((33, 3))}, (100, 100))
