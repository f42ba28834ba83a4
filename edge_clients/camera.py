"""The camera client: OpenCV capture → pose detector plugin → keypoint messages over Zenoh.

Each frame is stamped with the sensor's clock right after ``grab()`` returns (minus
``capture_latency``, the camera's exposure-to-delivery delay if known), before the
frame is decoded and the detector runs, so detector time does not leak into stamps.
OpenCV is imported here only: the base install never loads this module.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from proto import KeypointMessage

from .clock import Clock
from .detectors import DetectorError, to_person
from .publisher import RateMeter


class CameraError(RuntimeError):
    """A source that cannot be opened or read."""


def open_capture(source: str):
    """cv2.VideoCapture of a device index ("0"), a stream URL or a video file."""
    import cv2

    src: int | str = int(source) if source.isdigit() else source
    cap = cv2.VideoCapture(src)
    if not cap.isOpened():
        raise CameraError(f"cannot open the video source {source!r}"
                          + (" (no such camera device?)" if isinstance(src, int) else ""))
    return cap


def is_live(source: str) -> bool:
    """A device or a stream (reconnect on failure) rather than a file (stop at its end)."""
    return source.isdigit() or "://" in source


@dataclass
class CameraStats:
    frames: int = 0
    persons: int = 0
    empty: int = 0  # frames without persons (still published: the backend needs them)
    read_failures: int = 0
    reopened: int = 0
    detector_seconds: float = 0.0
    last_persons: int = 0
    fps: RateMeter = field(default_factory=RateMeter)

    def line(self, sensor: str, clock: Clock) -> str:
        det = self.detector_seconds / self.frames * 1e3 if self.frames else 0.0
        mean = self.persons / self.frames if self.frames else 0.0
        return (f"{sensor}: {self.fps.rate():.1f} fps, {self.frames} frames, persons now {self.last_persons} "
                f"(mean {mean:.2f}), detector {det:.0f} ms"
                + (f", {self.read_failures} read failures" if self.read_failures else "")
                + f"; {clock.status()}")


def run_camera(
    publisher,
    cap,
    detector: Callable,
    sensor: str,
    *,
    clock: Clock | None = None,
    source: str = "",
    stop: threading.Event | None = None,
    max_fps: float | None = None,
    frames: int | None = None,
    realtime: bool = False,
    capture_latency: float = 0.0,
    reopen: Callable[[], object] | None = None,
    on_frame: Callable[[CameraStats], None] | None = None,
) -> CameraStats:
    """Capture, detect and publish until ``stop``, ``frames`` frames, or the end of a file.

    A live source (``reopen`` given) that stops delivering is reopened every second.
    """
    import cv2

    clock = clock or Clock()
    stop = stop or threading.Event()
    stats = CameraStats()
    seq = 0
    period = 1.0 / max_fps if max_fps else 0.0
    if realtime and not period:
        fps = cap.get(cv2.CAP_PROP_FPS)
        period = 1.0 / fps if fps and fps > 0 else 0.0
    next_due = time.monotonic()
    while not stop.is_set() and (frames is None or stats.frames < frames):
        if period:
            wait = next_due - time.monotonic()
            if wait > 0 and stop.wait(wait):
                break
            next_due = max(next_due + period, time.monotonic() - period)
        ok = cap.grab()
        stamp = clock.now() - capture_latency  # right after grab: the capture instant
        if ok:
            ok, image = cap.retrieve()
        if not ok:
            if reopen is None:
                break  # end of a video file
            stats.read_failures += 1
            if stop.wait(1.0):
                break
            cap.release()
            try:
                cap = reopen()
                stats.reopened += 1
            except CameraError:
                pass
            continue
        h, w = image.shape[:2]
        t0 = time.perf_counter()
        dets = detector(image)
        stats.detector_seconds += time.perf_counter() - t0
        try:
            persons = tuple(to_person(d, (w, h)) for d in dets)
        except DetectorError:
            raise
        except (TypeError, ValueError, AttributeError) as e:  # a plugin returning something else entirely
            raise DetectorError(f"the detector returned {type(dets).__name__} items that are not detections ({e})") from None
        msg = KeypointMessage(sensor=sensor, seq=seq, stamp=stamp, size=(w, h), persons=persons)
        publisher.publish(msg)
        seq += 1
        stats.frames += 1
        stats.persons += len(persons)
        stats.last_persons = len(persons)
        stats.empty += not persons
        stats.fps.tick()
        if on_frame:
            on_frame(stats)
    return stats


def run_camera_cli(session, *, sensor: str, source: str, detector: Callable, site: str, clock: Clock,
                   max_fps: float | None, frames: int | None, realtime: bool, quiet: bool,
                   capture_latency: float = 0.0, wait_subscriber: float = 0.0) -> CameraStats:
    """`extrcal sensor camera`: the loop with a status line and a summary."""
    import typer

    from .publisher import SensorPublisher, StatusLine, stop_on_signals

    cap = open_capture(source)
    live = is_live(source)
    try:
        with SensorPublisher(session, site) as pub, stop_on_signals() as stop:
            pub.declare(sensor)  # liveliness from the start, not from the first detection
            if wait_subscriber > 0 and not pub.wait_matched([sensor], wait_subscriber, stop):
                typer.echo(f"no subscriber after {wait_subscriber} s; publishing anyway", err=True)
            holder: list[CameraStats] = [CameraStats()]
            status = StatusLine(lambda: holder[0].line(sensor, clock), enabled=not quiet)

            def on_frame(s: CameraStats) -> None:
                holder[0] = s
                status.update()

            with status:
                stats = run_camera(pub, cap, detector, sensor, clock=clock, source=source, stop=stop,
                                   max_fps=max_fps, frames=frames, realtime=realtime,
                                   capture_latency=capture_latency,
                                   reopen=(lambda: open_capture(source)) if live else None, on_frame=on_frame)
    finally:
        cap.release()
    mean = stats.persons / stats.frames if stats.frames else 0.0
    typer.echo(f"{sensor}: published {stats.frames} frames, {stats.persons} persons (mean {mean:.2f} per frame), "
               f"{stats.empty} frames without anyone")
    return stats
