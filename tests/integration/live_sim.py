"""Simulated sensors of a part of the lab, in their own process (tests/integration)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable


def publish_room(endpoint: str, site: str, cams: tuple[str, ...], persons: int, heights: tuple[float, ...],
                 duration: float, seed: int, speed: float, lab: str, ready, stop,
                 quiet: dict[str, float] | None = None, sim: dict | None = None, release=None) -> None:
    """``cams`` of the lab as a scene of their own (its room plan: the walkers stay where
    the cameras look), ``persons`` walkers of ``heights``; messages simulated first, then
    published through Zenoh paced at ``speed`` x real time. ``ready``/``stop``:
    multiprocessing events. ``quiet``: sensor -> s of data in which it sees nobody (a
    corner people reach later), or until ``release`` (a multiprocessing event) is set, so a
    test can end it at a point of the service's progress rather than of the wall clock.
    ``sim``: more ``SimConfig`` fields (e.g. clock offsets)."""
    import dataclasses
    import signal
    import time

    from edge_clients.publisher import SensorPublisher, zenoh_session
    from edge_clients.sim import Scene, SimConfig, Simulator
    from proto.transport import ZenohSettings

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    scene = Scene.load(Path(lab)).subset(cams)
    sim = Simulator(scene, SimConfig(persons=persons, duration=duration, seed=seed, heights=heights, **(sim or {})))
    with zenoh_session(ZenohSettings(mode="peer", connect=(endpoint,))) as zs, \
            SensorPublisher(zs, site, block=True) as pub:
        pub.wait_matched(cams, timeout=30.0, stop=stop)
        ready.set()
        t0 = s0 = None
        for _, m in sim.messages():
            if t0 is None:
                t0, s0 = time.monotonic(), m.stamp
            delay = t0 + (m.stamp - s0) / speed - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
            if stop.is_set():
                break
            if quiet and m.stamp - s0 < quiet.get(m.sensor, 0.0) and not (release and release.is_set()):
                m = dataclasses.replace(m, persons=())
            pub.publish(m)


WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")  # the lab's west room


def west_room_service(state_dir: Path, lab: Path, site: str, speed: float) -> tuple[Any, str, str, dict]:
    """A service on free loopback ports for the west room's cameras, its data clock at
    ``speed``: (settings, Zenoh endpoint, the cameras' intrinsics YAML, true extrinsics)."""
    import yaml

    from backend.cameras import load_extrinsics
    from backend.settings import ServiceSettings
    from proto.transport import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = ServiceSettings.load(None, http={"port": 0}, zenoh={"listen": (endpoint,)}, state_dir=state_dir,
                                    site=site, clock="data", speed=speed)
    intr = yaml.safe_load((lab / "intrinsics.yaml").read_text())
    truth = {k: e for k, e in load_extrinsics(lab / "reference.yaml").items() if k in WEST}
    return settings, endpoint, yaml.safe_dump({c: intr[c] for c in WEST}), truth


def poll(client: Any, path: str, pred: Callable[[dict], bool], timeout: float, what: str,
         seen: list | None = None) -> dict:
    """GET ``path`` until ``pred`` holds (every 0.25 s), else fail saying ``what`` and the last
    answer; ``seen`` collects every answer."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = client.get(path).json()
        if seen is not None:
            seen.append(last)
        if pred(last):
            return last
        time.sleep(0.25)
    raise AssertionError(f"{what} within {timeout} s; last: {json.dumps(last)[:3000]}")


class SensorProcess:
    """Simulated sensors in a spawned process, as a context: started, ready (they found the
    service), stopped and joined. ``args(ready, stop)`` gives ``target``'s arguments with
    the two multiprocessing events where it takes them; ``release`` is a third, for a
    target that takes it (``publish_room``)."""

    def __init__(self, target: Callable[..., None], args: Callable[[Any, Any], tuple]):
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self.ready, self.stop_event, self.release = ctx.Event(), ctx.Event(), ctx.Event()
        self.proc = ctx.Process(target=target, daemon=True, args=args(self.ready, self.stop_event))

    def __enter__(self) -> "SensorProcess":
        self.proc.start()
        assert self.ready.wait(120), "the simulated sensors did not find the service"
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_event.set()
        self.proc.join(20)
        if self.proc.is_alive():
            self.proc.kill()
