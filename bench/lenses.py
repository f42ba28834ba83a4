"""Lenses off their calibration files: estimated or not, with and without profile views.

The scene of tests/backend/test_cli_calibrate.py's lens test, over several seeds: the lab's
west room (6 cameras), 2 walkers (1.90 m, 1.75 m) for 60 s, the simulated lenses off the
files by ``--error`` (relative focal std; the principal point by that times half the image
width), initial estimates 0.05 m / 2° off. ``extrcal calibrate`` runs
(``backend.cli_engine.calibrate``, in this process) with ``optimize.lenses`` auto and off, each with the paper's preprocessing
(``preprocess.partial_torso=false``) and the default (profile views kept). Printed: the
shape position error (m, mean over the cameras) of each, and the means over seeds.

    python bench/lenses.py                    # seeds 2-6, ~8 min on a quiet machine
    python bench/lenses.py --seeds 2,3 --error 0.05
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

WEST = ("cam_11", "cam_13", "cam_14", "cam_15", "cam_16", "cam_17")
RUNS = (("paper", False, "auto"), ("paper", False, "off"), ("profiles", True, "auto"), ("profiles", True, "off"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="2,3,4,5,6", help="simulator seeds, comma-separated")
    ap.add_argument("--error", type=float, default=0.03, help="simulator intrinsics_error")
    args = ap.parse_args()

    import accuracy
    import typer

    from backend.cameras import Extrinsics, load_extrinsics, save_extrinsics, save_intrinsics
    from backend.cli_engine import calibrate
    from backend.evaluate import evaluate
    from backend.perturb import perturb_extrinsics
    from edge_clients.sim import Scene, SimConfig, Simulator

    lab = accuracy.lab_dir()  # EXTRCAL_LAB, else the shared lab or its copy
    full = Scene.load(lab)
    scene = Scene.from_cameras({n: full.intrinsics[n] for n in WEST}, {n: full.poses[n] for n in WEST},
                               lab / "room.yaml")
    ref = {n: Extrinsics(full.poses[n], full.intrinsics[n].resolution) for n in WEST}
    table: dict[tuple[str, str], list[float]] = {(name, mode): [] for name, _, mode in RUNS}
    print(f"lab {lab}, west room, 60 s, lenses {100 * args.error:g} % off; shape position error (m)")
    print(f"{'seed':>4} " + " ".join(f"{name + ' ' + mode:>14}" for name, _, mode in RUNS))
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        save_intrinsics(d / "intrinsics.yaml", {n: full.intrinsics[n] for n in WEST})
        save_extrinsics(d / "initial.yaml", perturb_extrinsics(ref, 0.05, 2.0, seed=1))
        for seed in (int(s) for s in args.seeds.split(",")):
            rec = d / f"lenses{seed}.jsonl.gz"
            Simulator(scene, SimConfig(persons=2, duration=60.0, seed=seed, heights=(1.9, 1.75),
                                       intrinsics_error=args.error)).write(rec)
            row = []
            for name, profiles, mode in RUNS:
                out = d / f"{seed}-{name}-{mode}.yaml"
                try:
                    calibrate(intrinsics=d / "intrinsics.yaml", recording=rec, output=out, initial=d / "initial.yaml",
                              distrust_initial=False, person_height=None, reference=None, config=None,
                              set_=[f"optimize.lenses={mode}", "refine.split_check=false",
                                    f"preprocess.partial_torso={str(profiles).lower()}"],
                              seed=1, history=None, skip_bad=False, quiet=True)
                except typer.Exit as e:  # cli.fail: its message is on stderr
                    raise SystemExit(f"seed {seed} {name} {mode}: calibrate exited with code {e.exit_code}")
                got = load_extrinsics(out)
                e = evaluate({n: got[n].pose for n in WEST}, {n: x.pose for n, x in ref.items()}, list(WEST))
                table[name, mode].append(e.shape_position.mean)
                row.append(e.shape_position.mean)
            print(f"{seed:>4} " + " ".join(f"{v:>14.4f}" for v in row), flush=True)
    print(f"{'mean':>4} " + " ".join(f"{np.mean(table[name, mode]):>14.4f}" for name, _, mode in RUNS))


if __name__ == "__main__":
    main()
