"""Sensor clock offsets on the simulator: estimated vs true, and what they cost the calibration.

The 20-camera lab, 2 persons (1.96 m, 1.70 m), 180 s; 5 of the 20 sensors get constant
clock offsets (``SimConfig.clock_offsets``, default -200, -100, +50, +120, +200 ms). The
offline pipeline (``backend.pipeline.run_offline``) runs up to six times from the same
initial estimate (0.25 m / 10°, ``backend.perturb``):

- offsets, estimation on (``clock.estimate = true``);
- synchronised clocks (the same seed without the offsets), estimation on: what it
  invents when there is nothing to find;
- synchronised clocks, estimation off;
- offsets, estimation off;
- offsets and synchronised clocks with ``clock.estimate = "auto"`` (the default: the
  estimate starts when a sensor's stamps run apart from the others' as they arrive).

Printed (for the estimated runs): per sensor the true offset (relative to the median sensor, as reported), the
estimate, its std (and its two parts: the jackknife over blocks of data, the spread over the
reference cameras measured at the end), the error and the offset applied; how far the stds
cover the errors (rms of error / std over the sensors estimated: 1 when honest, with the
reported std and with the blocks' alone); then the calibration error of each
run (``backend.evaluate``: rigid position / orientation, shape position, mean over all 20
cameras and over the 5 offset ones).

    python bench/clock_offsets.py                       # seed 1, all six runs
    python bench/clock_offsets.py --seed 2 --duration 120 --json out.json
    python bench/clock_offsets.py --runs "offsets, estimated" --drifts cam_5=1e-4   # a drifting clock too
    python bench/clock_offsets.py --sim noise_scale=2 --set clock.retime_seconds=0  # other detector, other setting

Also printed per run: the archived views timed again with the final offsets
(backend/retime.py) and the raw messages kept for it (count, MB pickled).

Recordings are cached like bench/accuracy.py does (--cache).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import lab_dir, simulate  # noqa: E402

DEFAULT_OFFSETS = {"cam_2": -0.200, "cam_5": -0.100, "cam_9": 0.050, "cam_13": 0.120, "cam_17": 0.200}


def run(recording: Path, seed: int, estimate: bool | str, start: tuple[float, float], overrides: list[str] = ()) -> dict:
    from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
    from backend.config import EngineConfig
    from backend.evaluate import evaluate
    from backend.perturb import perturb_extrinsics
    from backend.pipeline import run_offline
    from proto import read_recording

    lab = lab_dir()
    ref_ext = load_extrinsics(lab / "reference.yaml")
    ref = {n: e.pose for n, e in ref_ext.items()}
    init = perturb_extrinsics(ref_ext, start[0], start[1], seed=seed)
    cams = CameraSet.combine(load_intrinsics(lab / "intrinsics.yaml"), init)
    cfg = EngineConfig.load(None, [f"clock.estimate={str(estimate).lower()}", *overrides])
    t0 = time.perf_counter()
    p = run_offline(cams, cfg, read_recording(recording), seed=seed)
    seconds = time.perf_counter() - t0
    state = p.state()
    acc = evaluate(state.poses(), ref)
    raw = (len(p.raw), len(pickle.dumps(p.raw)) / 1e6) if p.raw is not None else (0, 0.0)
    return {"seconds": seconds, "accuracy": acc.to_dict(), "clocks": {c.sensor: c.to_dict() for c in state.clocks},
            "estimated": p.estimating,
            "retimed": dict(p.retimed), "raw_messages": raw[0], "raw_mb": raw[1]}


def table(name: str, est: dict, true: dict[str, float], offsets: dict[str, float], a) -> None:
    """Per sensor: true offset (relative to the median sensor), estimate, std, error, applied."""
    med = float(np.median(list(true.values())))
    print(f"Clock offsets ({name}), 20-camera lab, 2 persons, {a.duration:g} s, seed {a.seed}, start {a.start} "
          "(ms, relative to the median sensor)")
    print("| sensor | true | estimated | std (blocks / references) | error | applied | note |")
    print("|---|---|---|---|---|---|---|")
    errs, other, z, z_blocks = [], [], [], []
    for n in sorted(true, key=lambda s: int(s.split("_")[-1]) if s.split("_")[-1].isdigit() else s):
        c = est.get(n, {})
        tr = 1000 * (true[n] - med)
        o = c.get("offset")
        e = None if o is None else 1000 * o - tr
        if e is not None:
            (errs if n in offsets else other).append(abs(e))
            if c.get("std"):
                z.append(e / (1000 * c["std"]))
            if c.get("std_blocks"):
                z_blocks.append(e / (1000 * c["std_blocks"]))
        fmt = lambda x: "n/a" if x is None else f"{x:+.1f}"  # noqa: E731
        parts = "/".join("n/a" if c.get(k) is None else f"{1000 * c[k]:.1f}" for k in ("std_blocks", "std_references"))
        std = "n/a" if c.get("std") is None else f"{1000 * c['std']:.1f} ({parts})"
        star = " *" if n in offsets else ""
        print(f"| {n}{star} | {tr:+.1f} | {fmt(None if o is None else 1000 * o)} | {std} | {fmt(e)} | "
              f"{fmt(1000 * c.get('applied', 0.0))} | {c.get('note') or ''} |")
    if offsets:
        print(f"offset sensors (*) estimated: {len(errs)}/{len(offsets)}, max error "
              f"{max(errs) if errs else float('nan'):.1f} ms")
    print(f"other sensors estimated: {len(other)}/{len(true) - len(offsets)}, max error "
          f"{max(other) if other else float('nan'):.1f} ms; largest offset applied "
          f"{max((abs(1000 * est[n].get('applied', 0.0)) for n in est if n not in offsets), default=0.0):.1f} ms")
    rms = lambda v: float(np.sqrt(np.mean(np.square(v)))) if v else float("nan")  # noqa: E731
    print(f"rms error / std over the {len(z)} sensors estimated: {rms(z):.2f} (the blocks' std alone: "
          f"{rms(z_blocks):.2f}); |error| > 2 std: {sum(abs(x) > 2 for x in z)} ({sum(abs(x) > 2 for x in z_blocks)})")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=180.0)
    ap.add_argument("--offsets", default=",".join(f"{k}={v}" for k, v in DEFAULT_OFFSETS.items()),
                    help="sensor=seconds,... (default: 5 of the 20)")
    ap.add_argument("--start", default="0.25/10", help="initial error m/deg")
    ap.add_argument("--drifts", default="", help="sensor=s/s,... clock rate errors of sensors (1e-4 = 100 ppm: 18 ms in 180 s)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="engine setting (repeatable)")
    ap.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator setting for both recordings (repeatable), e.g. noise_scale=2")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--runs", default="all", help="the runs to make, ';'-separated names as printed (default all)")
    a = ap.parse_args()
    offsets = {k: float(v) for k, v in (x.split("=") for x in a.offsets.split(","))}
    start = tuple(float(x) for x in a.start.split("/"))
    drifts = {k: float(v) for k, v in (x.split("=") for x in a.drifts.split(",") if x)}
    sim = {k: float(v) for k, v in (x.split("=", 1) for x in a.sim)}
    rec_off = simulate(2, a.duration, a.seed, a.cache,
                       {**sim, "clock_offsets": offsets, **({"clock_drifts": drifts} if drifts else {})})
    rec_sync = simulate(2, a.duration, a.seed, a.cache, sim)
    from edge_clients.sim import Truth

    truth = Truth.load(Truth.sidecar_path(rec_off))
    true = dict(zip(truth.sensors, truth.clock_offset.tolist()))
    truth_sync = Truth.load(Truth.sidecar_path(rec_sync))
    true_sync = dict(zip(truth_sync.sensors, truth_sync.clock_offset.tolist()))
    plan = {
        "offsets, estimated": (rec_off, True),
        "synchronised clocks, estimated": (rec_sync, True),
        "synchronised clocks": (rec_sync, False),
        "offsets, not estimated": (rec_off, False),
        "offsets, auto": (rec_off, "auto"),
        "synchronised clocks, auto": (rec_sync, "auto"),
    }
    keep = [k for k in plan if a.runs == "all" or k in a.runs.split(";")]
    runs = {k: run(plan[k][0], a.seed, plan[k][1], start, a.set) for k in keep}
    for name, tr_all, off in (("offsets, estimated", true, offsets),
                              ("synchronised clocks, estimated", true_sync, {}), ("offsets, auto", true, offsets)):
        if name in runs and runs[name]["estimated"]:
            table(name, runs[name]["clocks"], tr_all, off, a)
    print()
    print("| run | rigid position (m) | orientation (°) | shape position (m) | offset sensors: position (m) / orientation (°) "
          "| estimate ran | views timed again | raw messages kept (MB pickled) | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in runs.items():
        acc = r["accuracy"]
        pc = acc["per_camera"]
        po = np.mean([pc[n]["position"] for n in offsets])
        oo = np.mean([pc[n]["orientation"] for n in offsets])
        print(f"| {name} | {acc['position']['mean']:.4f} | {acc['orientation']['mean']:.3f} | "
              f"{acc['shape_position']['mean']:.4f} | {po:.4f} / {oo:.3f} | {'yes' if r['estimated'] else 'no'} | "
              f"{sum(r['retimed'].values())} | "
              f"{r['raw_messages']} ({r['raw_mb']:.0f}) | {r['seconds']:.0f} |")
    if a.json:
        a.json.write_text(json.dumps({"true": true, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
