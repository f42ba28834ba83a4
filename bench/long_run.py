"""`extrcal calibrate` on long recordings: wall and CPU time, peak memory, accuracy.

A real recording runs for many minutes; the engine archives up to
`refine.archive_frames` framesets (1000 s at 10 Hz) and re-associates all of them at the
end (final batch, scale check). This prints, per duration, what one `extrcal calibrate`
(a subprocess, as a user runs it) costs and how accurate it ends:

    python bench/long_run.py                          # 180 and 600 s, 3 walkers, seed 2
    python bench/long_run.py --durations 180,600,1200 --persons 3 --seed 2

Recordings are simulated once (the 20-camera lab) and cached in --cache. Peak memory is
the child's maximum resident set (getrusage), one run at a time on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
LAB = REPO / "edge_clients" / "data" / "ais_lab20"


def recording(duration: float, persons: int, seed: int, cache: Path) -> Path:
    from edge_clients.sim import Scene, SimConfig, Simulator

    out = cache / f"lab_p{persons}_d{duration:g}_s{seed}.msgpack"
    if not out.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = cache / f".{os.getpid()}.{out.name}"
        Simulator(Scene.load(LAB), SimConfig(persons=persons, duration=duration, seed=seed)).write(tmp)
        os.replace(tmp, out)
    return out


def run(rec: Path, initial: Path, out: Path) -> dict:
    """One calibrate in a child process: wall s, CPU s and peak MB of that child alone."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "backend.cli", "calibrate", "--intrinsics", str(LAB / "intrinsics.yaml"),
                        "--initial", str(initial), "--recording", str(rec), "--output", str(out), "--quiet"],
                       capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode:
        raise SystemExit(f"calibrate failed on {rec}: {(p.stderr or p.stdout).strip().splitlines()[-1:]}")
    # ru_maxrss of children is the largest of any child so far: runs go from short to long
    return {"wall": wall, "cpu": (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime),
            "peak_mb": after.ru_maxrss / 1024}


def main(argv: list[str] | None = None) -> None:
    from backend.cameras import load_extrinsics, save_extrinsics
    from backend.evaluate import evaluate
    from backend.perturb import perturb_extrinsics

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--durations", default="180,600", help="s of simulated data, comma separated, ascending")
    ap.add_argument("--persons", type=int, default=3)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "extrcal-long-run-cache")
    args = ap.parse_args(argv)
    durations = sorted(float(x) for x in args.durations.split(",") if x)
    ref = load_extrinsics(LAB / "reference.yaml")
    initial = args.cache / f"initial_s{args.seed}.yaml"
    args.cache.mkdir(parents=True, exist_ok=True)
    save_extrinsics(initial, perturb_extrinsics(ref, 0.25, 10.0, seed=args.seed))
    rows = []
    for d in durations:
        rec = recording(d, args.persons, args.seed, args.cache)
        out = args.cache / f"result_{d:g}.yaml"
        r = run(rec, initial, out)
        got = load_extrinsics(out)
        a = evaluate({n: e.pose for n, e in got.items()}, {n: e.pose for n, e in ref.items()})
        rows.append((d, rec.stat().st_size / 1e6, r, a))
        print(f"{d:g} s done: {r['wall']:.0f} s wall", flush=True)
    print(f"\nextrcal calibrate, 20-camera lab, {args.persons} walkers, seed {args.seed}, 0.25 m / 10° start\n")
    print("| data (s) | recording (MB) | wall (s) | CPU (s) | x real time | peak memory (MB) | rigid (m) | shape (m) | orientation (°) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for d, mb, r, a in rows:
        print(f"| {d:g} | {mb:.0f} | {r['wall']:.0f} | {r['cpu']:.0f} | {d / r['wall']:.1f} | {r['peak_mb']:.0f} | "
              f"{a.position.mean:.4f} | {a.shape_position.mean:.4f} | {a.orientation.mean:.3f} |")


if __name__ == "__main__":
    main()
