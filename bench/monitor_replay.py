"""Record what the monitor is given in a lab run, and replay the monitor on it (to
diagnose its alarms, or try a change of its evidence or test without re-running the
pipeline; exact as long as no alarm changed the pipeline's estimate).

    python bench/monitor_replay.py record --seed 101 --duration 600 --out /tmp/q101.pkl [--calibrate 180]
    python bench/monitor_replay.py record --seed 1 --duration 360 --calibrate 120 --bump 0.03/0 --bump-time 240 --out /tmp/b1.pkl
    python bench/monitor_replay.py replay /tmp/q101.pkl ['{"chi2": 30}']

``record``: the monitor's hypotheses and every ``evaluate`` call's inputs (data time,
watched cameras, the estimate) of a run, set up as bench/monitor.py does
(``--calibrate 0``: the online estimate watched as it converges); ``--bump M/DEG`` moves
``--camera`` at ``--bump-time`` (a replay is exact up to the first alarm: after it the
recorded estimate is the recalibrating one). ``replay``: the
monitor (config overrides as JSON) over a recording: its alarms and the largest test
statistic of each test, whatever the thresholds.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from accuracy import lab_dir, simulate  # noqa: E402


def record(seed: int, duration: float, out: Path, calibrate: float, cache: Path,
           bump: tuple[float, str, float, float] | None = None) -> None:
    from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
    from backend.config import EngineConfig
    from backend.perturb import perturb_extrinsics
    from backend.pipeline import Pipeline
    from edge_clients.sim import Truth
    from proto import read_recording

    sim_set = {"bumps": (bump,)} if bump else {}  # (time s, camera, m, deg), as SimConfig.bumps
    rec = simulate(2, duration, seed, cache, sim_set)
    t0 = Truth.load(Truth.sidecar_path(rec)).start_time
    lab = lab_dir()
    ref = load_extrinsics(lab / "reference.yaml")
    cams = CameraSet.combine(load_intrinsics(lab / "intrinsics.yaml"), perturb_extrinsics(ref, 0.10, 5.0, seed=seed))
    cfg = EngineConfig().merged({"refine": {"final_batch": False}, "monitor": {"enabled": True}})
    messages = iter(read_recording(rec))
    if calibrate > 0:  # as bench/monitor.py: a session calibrates, its result is watched
        p = Pipeline(cams, EngineConfig(), seed=seed)
        for m in messages:
            p.push(m)
            if p.clock is not None:
                p.step(p.clock)
                if p.clock - t0 >= calibrate:
                    break
        p.finish()
        snapshot = p.snapshot()
        snapshot["watched"] = [bool(p.refiner.converged(c)) for c in range(len(cams.names))]
        p = Pipeline.restore(cams, cfg, snapshot, seed=seed)
    else:
        p = Pipeline(cams, cfg, seed=seed)
    hyps: list = []
    evals: list = []
    add, evaluate = p.monitor.add, p.monitor.evaluate

    def add_recorded(h):
        hyps.extend(h)
        add(h)

    def evaluate_recorded(now, watched, R, t):
        evals.append((now, watched.copy(), R.copy(), t.copy(), len(hyps)))
        return evaluate(now, watched, R, t)

    p.monitor.add, p.monitor.evaluate = add_recorded, evaluate_recorded
    for m in messages:
        p.push(m)
        if p.clock is not None:
            p.step(p.clock)
    with open(out, "wb") as f:
        pickle.dump({"rec": str(rec), "t0": t0, "bump": bump, "names": list(cams.names), "focal": p.focal, "hyps": hyps,
                     "evals": evals}, f)
    print(f"{len(hyps)} hypotheses, {len(evals)} evaluations, alarms "
          f"{[(round(a.time - t0, 1), cams.names[a.cam]) for a in p.monitor.alarms]}")


def replay(path: Path, overrides: dict) -> None:
    from backend import monitor as M
    from backend.config import EngineConfig

    with open(path, "rb") as f:
        d = pickle.load(f)
    ecfg = EngineConfig().merged({"monitor": {"enabled": True, **overrides}})
    m = M.Monitor(ecfg.monitor, d["focal"], outlier_px=ecfg.optimize.outlier_px,
                  min_angle_deg=ecfg.optimize.min_triangulation_angle)
    stats: list[float] = []
    test = M.change_test

    def any_step(z, W, start, now, cfg, floor, **kw):
        found = test(z, W, start, now, cfg.model_copy(update={"chi2": 1e-9, "min_translation": 0.0,
                                                              "min_rotation": 0.0}), floor, **kw)
        if found is not None and kw.get("leave_one_out", True):  # the tests, not the blame's steps
            stats.append(found[0])
        return test(z, W, start, now, cfg, floor, **kw)

    M.change_test = any_step
    alarms, i = [], 0
    for now, watched, R, t, n in d["evals"]:
        m.add(d["hyps"][i:n])
        i = n
        alarms += m.evaluate(now, watched, R, t)[0]
    t0 = d["t0"]
    print("alarms", [(round(a.time - t0, 1), d["names"][a.cam], round(a.chi2, 1), round(a.translation, 3),
                      round(a.rotation, 2)) for a in alarms])
    x = np.array(stats or [0.0])
    print(f"tests {len(stats)}, largest statistic per test: median {np.median(x):.1f}, "
          f"99 % {np.quantile(x, 0.99):.1f}, max {x.max():.1f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--seed", type=int, default=101)
    r.add_argument("--duration", type=float, default=600.0)
    r.add_argument("--calibrate", type=float, default=180.0)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    r.add_argument("--bump", default=None, help="M/DEG: move --camera by M metres and DEG degrees")
    r.add_argument("--camera", default="cam_8")
    r.add_argument("--bump-time", type=float, default=240.0)
    p = sub.add_parser("replay")
    p.add_argument("recording", type=Path)
    p.add_argument("overrides", nargs="?", default="{}", help="monitor config overrides, JSON")
    args = ap.parse_args(argv)
    if args.cmd == "record":
        bump = None
        if args.bump:
            m, deg = (float(v) for v in args.bump.split("/"))
            bump = (args.bump_time, args.camera, m, deg)
        record(args.seed, args.duration, args.out, args.calibrate, args.cache, bump)
    else:
        replay(args.recording, json.loads(args.overrides))


if __name__ == "__main__":
    main()
