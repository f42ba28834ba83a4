"""How much does a clock-offset job (``Pipeline.clock_job``) in a thread stall an asyncio
loop, against running it inline (what ``advance`` did on the service's loop)?

The bench's seed-1 recording with offsets (bench/clock_offsets.py), 0.25 m / 10° start:
the pipeline runs with inline jobs until ``SECONDS`` of data, then the next job runs in
``asyncio.to_thread`` while a task measures how late ``asyncio.sleep(0.01)`` wakes; then
the same job inline on a copy of the pipeline.

    python bench/clock_job_thread.py 70
"""
import asyncio
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.accuracy import lab_dir, simulate  # noqa: E402
from bench.clock_offsets import DEFAULT_OFFSETS  # noqa: E402
from backend.cameras import CameraSet, load_extrinsics, load_intrinsics  # noqa: E402
from backend.config import EngineConfig  # noqa: E402
from backend.perturb import perturb_extrinsics  # noqa: E402
from backend.pipeline import Pipeline  # noqa: E402
from proto import read_recording  # noqa: E402

rec = simulate(2, 180.0, 1, Path("/tmp/extrcal-accuracy-cache"), {"clock_offsets": DEFAULT_OFFSETS})
lab = lab_dir()
ref_ext = load_extrinsics(lab / "reference.yaml")
cams = CameraSet.combine(load_intrinsics(lab / "intrinsics.yaml"), perturb_extrinsics(ref_ext, 0.25, 10, seed=1))
p = Pipeline(cams, EngineConfig.from_dict({"clock": {"estimate": True}}), seed=1)
t_start = None
jobs = 0
for msg in read_recording(rec):
    p.push(msg)
    if p.clock is None:
        continue
    t_start = t_start or p.clock
    p.advance(p.clock, clock_offsets=False)
    q = p.next_problem(p.clock)
    if q is not None:
        from backend.optimize import solve
        p.apply(q, solve(q))
    job = p.clock_job(p.clock)
    if job is not None:
        jobs += 1
        if p.clock - t_start < float(sys.argv[1]):
            t0 = time.perf_counter(); r = job.run(); p.apply_clock(job, r)
            print(f"inline job at {p.clock - t_start:.0f} s: {time.perf_counter() - t0:.1f} s", flush=True)
            continue
        break

async def main(job):
    lat = []
    stop = False
    async def ticker():
        while not stop:
            t = time.perf_counter(); await asyncio.sleep(0.01); lat.append(time.perf_counter() - t - 0.01)
    tk = asyncio.create_task(ticker())
    await asyncio.sleep(1.0)
    base = np.array(lat); lat.clear()
    t0 = time.perf_counter()
    r = await asyncio.to_thread(job.run)
    wall = time.perf_counter() - t0
    stop = True; await tk
    lat_ = np.array(lat)
    print(f"thread job: {wall:.1f} s wall; loop tick overshoot idle: median {1e3*np.median(base):.1f} ms max {1e3*base.max():.1f} ms; "
          f"during job: median {1e3*np.median(lat_):.1f} ms, p99 {1e3*np.percentile(lat_, 99):.1f} ms, max {1e3*lat_.max():.1f} ms, ticks {len(lat_)}")
    return r

copy_ = pickle.loads(pickle.dumps(p))
asyncio.run(main(job))
job2 = copy_.clocks.begin(job.now, job.R, job.t)
t0 = time.perf_counter(); job2.run()
print(f"the same job inline: {time.perf_counter() - t0:.1f} s (the loop would be blocked this long)")
