"""What a message costs the service's loop in ``Pipeline.push``, with the sensor clock
offsets' estimate (``clock.estimate``) off, on and "auto": the estimate also builds every
sensor's person tracks and keeps the raw messages (``clock.retime_seconds``), per message,
on the loop; "auto" (synchronised clocks: it does not start) adds its watch of the stamps,
which ``advance`` runs, here after every message.

    python bench/push_cost.py                 # 20 cameras (the lab, 2 persons) and 100 (a hall, 8 persons)
    python bench/push_cost.py --cameras 100 --seconds 10

The messages are bench/service.py's (simulated at 30 Hz); each is pushed with an arrival
50 ms after its stamp, as live. CPU time of the pushing thread, per message.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from service import LAB, hall_cameras, lab_cameras  # noqa: E402
from backend.cameras import CameraSet  # noqa: E402
from backend.config import EngineConfig  # noqa: E402
from backend.pipeline import Pipeline  # noqa: E402


def messages(cameras: int, seconds: float, rate: float):
    from edge_clients.sim import Scene, SimConfig, Simulator

    intr, ext = lab_cameras() if cameras == 20 else hall_cameras(cameras)
    scene = Scene.from_cameras(intr, {k: e.pose for k, e in ext.items()}, LAB / "room.yaml" if cameras == 20 else None)
    sim = Simulator(scene, SimConfig(persons=2 if cameras <= 20 else 8, duration=seconds, seed=0, rates=(rate, rate)))
    return CameraSet.combine(intr, ext), [m for _, m in sim.messages()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[20, 100])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--rate", type=float, default=30.0)
    args = ap.parse_args()
    print("| cameras | messages | clock.estimate | push µs per message (CPU) |")
    print("|---|---|---|---|")
    for n in args.cameras:
        cams, msgs = messages(n, args.seconds, args.rate)
        for est in (False, True, "auto"):
            p = Pipeline(cams, EngineConfig.from_dict({"clock": {"estimate": est}}), seed=0)
            watch = est == "auto"
            t = time.thread_time()
            for m in msgs:
                p.push(m, arrival=m.stamp + 0.05)
                if watch:
                    p._watch_stamps(m.stamp + 0.05)
            dt = time.thread_time() - t
            started = " (started)" if watch and p.estimating else ""
            print(f"| {n} | {len(msgs)} | {str(est).lower()}{started} | {1e6 * dt / len(msgs):.1f} |", flush=True)


if __name__ == "__main__":
    main()
