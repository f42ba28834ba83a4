"""People keep their size: a corridor whose cameras overlap only their neighbours.

The generated corridor (``edge_clients.sim.scenes.corridor``: 6 cameras 3.5 m apart, each
sharing floor only with its neighbours), 1 walker (1.80 m; ``--persons 2`` adds one of
1.65 m) for 150 s, initial estimates 0.25 m / 10° off per camera (``backend.perturb``,
cam_0 kept), several seeds. Each run goes through the full online pipeline
(``run_offline``: cycles, then the final batch adjustment) with ``optimize.bones`` off,
"batch" (first and final adjustment) and "all" (every cycle too); the *limit* is a batch
adjustment with the simulator's true associations on the same frames
(bench/accuracy.py's), with bones off and on. Figures are means over the cameras: rigid
position (the initial estimate's scale kept, as the pipeline does), shape position (after
a similarity alignment), orientation; cycle time p50 and the run's wall time.

    python bench/corridor.py                       # 3 seeds, ~5 min on a quiet machine
    python bench/corridor.py --seeds 5 --out c.json
    python bench/corridor.py --bones off,all --seeds 1

Recordings are cached in --cache (keyed by the simulator's source and the scene).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

HEIGHTS = (1.80, 1.65)  # the first walker's alone with --persons 1
DURATION = 150.0
START = (0.25, 10.0)


def simulate(seed: int, cache: Path, persons: int = 1) -> Path:
    """The corridor recording of one seed (with its truth and camera directory), cached."""
    from edge_clients.sim import SimConfig, Simulator, Truth
    from edge_clients.sim.scenes import corridor, write_scene

    h = hashlib.sha1()
    for f in sorted((REPO / "edge_clients" / "sim").glob("*.py")):
        h.update(f.read_bytes())
    heights = HEIGHTS[:persons]
    # one walker keeps the key it had before --persons, so earlier caches stay valid
    h.update(repr((heights[0] if persons == 1 else heights, DURATION, seed)).encode())
    tag = "" if persons == 1 else f"_p{persons}"
    out = cache / f"corridor6{tag}_d{DURATION:g}_s{seed}_{h.hexdigest()[:10]}.msgpack"
    if out.is_file() and Truth.sidecar_path(out).is_file():
        return out
    cache.mkdir(parents=True, exist_ok=True)
    scene = corridor()
    write_scene(scene, cameras_of(out), "corridor: 6 cameras, each overlapping only its neighbours")
    tmp = cache / f".{os.getpid()}.{out.name}"
    Simulator(scene, SimConfig(persons=persons, duration=DURATION, seed=seed, heights=heights)).write(tmp)
    os.replace(Truth.sidecar_path(tmp), Truth.sidecar_path(out))
    os.replace(tmp, out)
    return out


def cameras_of(recording: Path) -> Path:
    return Path(f"{recording}.cameras")


def _acc(poses, ref) -> dict:
    from backend.evaluate import evaluate

    a = evaluate(poses, ref)
    return {"position": a.position.mean, "position_max": a.position.max, "shape_position": a.shape_position.mean,
            "orientation": a.orientation.mean, "scale": a.scale}


def run(recording: Path, seed: int, bones: str) -> dict:
    from accuracy import limit

    from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
    from backend.config import EngineConfig
    from backend.perturb import perturb_extrinsics
    from backend.pipeline import run_offline
    from edge_clients.sim import Truth
    from proto import read_recording

    d = cameras_of(recording)
    ref_ext = load_extrinsics(d / "reference.yaml")
    ref = {n: e.pose for n, e in ref_ext.items()}
    init = perturb_extrinsics(ref_ext, *START, seed=seed)
    cams = CameraSet.combine(load_intrinsics(d / "intrinsics.yaml"), init)
    cfg = EngineConfig.load(None, [f'optimize.bones="{bones}"'])
    msgs = list(read_recording(recording))
    solves: list[float] = []
    final: list[float] = []
    ended = [False]

    def feed():
        yield from msgs
        ended[0] = True

    def progress(state, report) -> None:
        (final if ended[0] else solves).append(report.solve_seconds)

    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    p = run_offline(cams, cfg, feed(), seed=seed, progress=progress)
    wall = time.perf_counter() - t0
    state = p.state()
    out = {"seed": seed, "bones": bones, "initial": _acc(cams.poses(), ref), "final": _acc(state.poses(), ref),
           "cycles": len(solves), "cycle_p50": float(np.median(solves)) if solves else None,
           "final_batch_seconds": final[-1] if final else None, "wall": wall, "load": load}
    if bones in ("off", "batch"):  # the limit depends only on whether the batch has bones
        truth = Truth.load(Truth.sidecar_path(recording))
        info, poses, _ = limit(p, cfg, truth, ref, seed, "initial")
        out["limit"] = {**_acc(poses, ref), "hypotheses": info["hypotheses"], "seconds": info["seconds"]}
    return out


def _f(x, d=4) -> str:
    return "n/a" if x is None else f"{x:.{d}f}"


def table(runs: list[dict]) -> str:
    lines = ["| seed | bones | initial pos (m) | final rigid pos mean / max (m) | shape pos (m) | orient (°) | scale "
             "| limit rigid / shape (m) | cycles | cycle p50 (s) | final batch (s) | wall (s) | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        f, lim = r["final"], r.get("limit")
        lim_s = f"{_f(lim['position'])} / {_f(lim['shape_position'])}" if lim else "(as batch)"
        lines.append(f"| {r['seed']} | {r['bones']} | {_f(r['initial']['position'])} | {_f(f['position'])} / "
                     f"{_f(f['position_max'])} | {_f(f['shape_position'])} | {_f(f['orientation'], 3)} | "
                     f"{_f(f['scale'], 4)} | {lim_s} | {r['cycles']} | {_f(r['cycle_p50'], 3)} | "
                     f"{_f(r['final_batch_seconds'], 1)} | {r['wall']:.0f} | {r['load']:.1f} |")
    lines += ["", "| bones | seeds | final rigid pos mean (m) | worst seed (m) | shape pos mean (m) | orient (°) "
              "| limit rigid (m) | cycle p50 (s) |", "|---|---|---|---|---|---|---|---|"]
    for b in dict.fromkeys(r["bones"] for r in runs):
        rs = [r for r in runs if r["bones"] == b]
        pos = [r["final"]["position"] for r in rs]
        lim = [r["limit"]["position"] for r in rs if r.get("limit")]
        cyc = [r["cycle_p50"] for r in rs if r["cycle_p50"] is not None]
        lines.append(f"| {b} | {len(rs)} | {np.mean(pos):.4f} | {max(pos):.4f} | "
                     f"{np.mean([r['final']['shape_position'] for r in rs]):.4f} | "
                     f"{np.mean([r['final']['orientation'] for r in rs]):.3f} | "
                     f"{_f(float(np.mean(lim)) if lim else None)} | {_f(float(np.mean(cyc)) if cyc else None, 3)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--bones", default="off,batch,all", help="optimize.bones values to run, comma-separated")
    ap.add_argument("--persons", type=int, default=1, choices=(1, 2), help="walkers (1.80 m, then 1.65 m)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-corridor-cache"))
    ap.add_argument("--out", type=Path, help="write every run as JSON")
    args = ap.parse_args(argv)
    runs = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rec = simulate(seed, args.cache, args.persons)
        for b in args.bones.split(","):
            r = run(rec, seed, b.strip())
            print(f"seed {seed} bones {r['bones']}: rigid {r['final']['position']:.4f} m, shape "
                  f"{r['final']['shape_position']:.4f} m, {r['wall']:.0f} s", file=sys.stderr, flush=True)
            runs.append(r)
    print(table(runs))
    if args.out:
        args.out.write_text(json.dumps(runs, indent=1))


if __name__ == "__main__":
    main()
