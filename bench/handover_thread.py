"""How long does the hand-over of a live bootstrap (``Handover.build``) stall the
service's event loop, against the length of the archive it takes?

The service builds the online pipeline from an accepted bootstrap in
``asyncio.to_thread`` (backend/service.py ``_bootstrap_turn``): every frameset collected
until then is associated and queued. Numpy and OpenCV give the GIL back; pure Python
and GTSAM do not, and the loop waits. On a starved machine a session collected 795 s of
data before its bootstrap was accepted and the service answered no HTTP request for a
minute (docs/notes-session25.md): this measures that step alone.

Per archive length: the west room's 7 cameras (2 walkers, tests/integration's scene)
collected by a ``Collector``, its bootstrap run inline (the solver process's work,
not measured), then ``Handover.build`` in a thread while a task measures how late
``asyncio.sleep(0.01)`` wakes, and the same build inline.

    python bench/handover_thread.py --seconds 60 300 800
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

WEST = ("cam_11", "cam_12", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")


async def _in_thread(fn) -> tuple[float, np.ndarray, object]:
    """``fn()`` in ``asyncio.to_thread`` with a 10 ms ticker on the loop: (wall s, the
    ticks' overshoot in s, fn's result)."""
    lat: list[float] = []
    done = False

    async def ticker() -> None:
        while not done:
            t = time.perf_counter()
            await asyncio.sleep(0.01)
            lat.append(time.perf_counter() - t - 0.01)

    tk = asyncio.create_task(ticker())
    await asyncio.sleep(0.2)
    lat.clear()
    t0 = time.perf_counter()
    out = await asyncio.to_thread(fn)
    wall = time.perf_counter() - t0
    done = True
    await tk
    return wall, np.array(lat), out


def run(seconds: float, seed: int, cache: Path) -> dict:
    from accuracy import lab_dir, simulate

    import yaml

    from backend.config import EngineConfig
    from backend.live_bootstrap import Collector, Handover, LiveOptions, run_job
    from backend.session import SessionInputs
    from proto import read_recording

    rec = simulate(2, seconds + 5.0, seed, cache, {"heights": (1.96, 1.70)}, cameras=WEST)
    intr = yaml.safe_load((lab_dir() / "intrinsics.yaml").read_text())
    cfg = EngineConfig().merged({"bootstrap": {"live_first": 60.0, "max_seconds": 60.0}})
    cams = SessionInputs.parse(yaml.safe_dump({n: intr[n] for n in WEST}), None, None, cfg).cameras
    col = Collector(cams, cfg, LiveOptions(heights=(1.96, 1.70)), initial=False, seed=seed)
    t0 = time.perf_counter()
    for msg in read_recording(rec):
        col.push(msg)
        col.advance(col.clock)
    col.advance(col.clock + 1.0)
    print(f"  {seconds:.0f} s: collected {len(col.frames)} framesets in {time.perf_counter() - t0:.1f} s",
          file=sys.stderr, flush=True)
    # the bootstrap on its first 60 s, as the service's first attempt; the hand-over on all
    job = col.job()
    first = tuple(f for f in job.frames if f[0] - job.frames[0][0] <= 60.0)
    outcome = run_job(replace(job, frames=first, data_seconds=60.0))
    assert outcome.result is not None, outcome.error
    print(f"  bootstrap on the first 60 s: {outcome.seconds:.1f} s", file=sys.stderr, flush=True)
    frames = tuple(col.frames)

    def build():
        return Handover.build(job, outcome.result, cams, col.cfg, False, seed=seed, frames=frames)

    wall, lat, h = asyncio.run(_in_thread(build))
    t0 = time.perf_counter()
    build()
    inline = time.perf_counter() - t0
    return {"seconds": col.data_seconds, "frames": len(frames), "hypotheses": h.hypotheses, "wall": wall,
            "inline": inline, "ticks": len(lat), "median": float(np.median(lat)) if len(lat) else float("nan"),
            "p99": float(np.percentile(lat, 99)) if len(lat) else float("nan"),
            "max": float(lat.max()) if len(lat) else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, nargs="+", default=[60.0, 300.0, 800.0],
                    help="s of data collected before the hand-over")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    args = ap.parse_args()
    print("| archive s | framesets | hypotheses queued | build in a thread s | build inline s | loop ticks | "
          "tick overshoot median / p99 / max ms |")
    print("|---|---|---|---|---|---|---|")
    for s in args.seconds:
        r = run(s, args.seed, args.cache)
        print(f"| {r['seconds']:.0f} | {r['frames']} | {r['hypotheses']} | {r['wall']:.2f} | {r['inline']:.2f} | "
              f"{r['ticks']} | {1e3 * r['median']:.1f} / {1e3 * r['p99']:.1f} / {1e3 * r['max']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
