"""The fine clock-offset estimator alone, with and without a coarse stage in front of it.

Question answered: how close does a coarse stage have to bring the offsets for the
reprojection estimator (``backend.clock_offsets``) to reach the issue's 5 ms bar? The
bench's recording (20-camera lab, 2 persons, detector noise, offsets on 5 sensors,
``bench/clock_offsets.py``) is fed for ``--seconds`` to a pipeline whose poses stay the
reference (front end only, no adjustment: the estimator alone is measured), with

- ``none``: no coarse stage (what the pipeline does today);
- ``truth``: the true offsets applied from the start (a perfect coarse stage);
- ``truth+-15``: the true offsets ±15 ms (alternating sign) applied from the start.

In the last two the estimator's fine grid starts at the applied offsets. Printed per mode: per-sensor error (ms, relative to the median sensor),
sensors estimated, max error, and how far the stated std covers the errors (rms of
error / std: 1 when it is honest).

``--sim KEY=VALUE`` changes the simulated recording (e.g. ``intrinsics_error=0``,
``rates=30,30``); ``--true-3d`` replaces the persons the other views triangulate by the
simulator's true joints at the frameset instant (a diagnostic: how much of an error comes
from that 3D; docs/clock_offsets.md, Session 50).

    python bench/clock_fine_stage.py --seconds 90
    python bench/clock_fine_stage.py --seed 3 --seconds 180 --modes truth --true-3d
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import lab_dir, sim_settings, simulate  # noqa: E402
from bench.clock_offsets import DEFAULT_OFFSETS  # noqa: E402


def run(recording: Path, seconds: float, mode: str, true: dict[str, float]) -> tuple[dict, float]:
    from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
    from backend.config import EngineConfig
    from backend.pipeline import Pipeline
    from proto import read_recording

    lab = lab_dir()
    cams = CameraSet.combine(load_intrinsics(lab / "intrinsics.yaml"), load_extrinsics(lab / "reference.yaml"))
    cfg = EngineConfig.from_dict({"clock": {"estimate": True}, "refine": {"final_batch": False},
                                  "associate": {"relocalize": False}})
    p = Pipeline(cams, cfg)
    p._calibrated = lambda: True  # the poses are the reference: no adjustment to wait for
    med = float(np.median(list(true.values())))
    if mode != "none":
        sign = 1.0
        for c, n in enumerate(p.names):
            o = true[n] - med
            if abs(o) < 0.02:
                continue  # synchronised within NTP: nothing to apply
            if mode == "truth+-15":
                o += sign * 0.015
                sign = -sign
            p.clocks.applied[c] = o
            p.sync.set_offset(n, o)
        p.clocks.center[:] = p.clocks.applied  # the fine grid starts at the applied offsets
    t0 = time.perf_counter()
    first = None
    for msg in read_recording(recording):
        first = msg.stamp if first is None else first
        if msg.stamp - first > seconds:
            break
        p.push(msg)
        if p.clock is not None:
            p.advance(p.clock)  # poses stay the reference
    p.finish()
    return {c.sensor: c for c in p.state().clocks}, time.perf_counter() - t0


def true_3d(truth, med: float) -> None:
    """From now on the estimator's persons from the other views are the simulator's true
    joints (the person nearest the triangulated one, within 0.5 m) at the frameset
    instant ``time - med`` (the synchronised clock is the median sensor's)."""
    import backend.clock_offsets as co

    triangulate = co.ClockOffsetEstimator._triangulate

    def truly(self, rows, R, t):
        X = triangulate(self, rows, R, t)
        out = X.copy()
        for i, (r, _) in enumerate(rows):
            ok = np.isfinite(X[i]).all(-1)
            if not ok.any():
                continue
            J = truth.joints_at(r.time - med)[:, co.BODY]  # (P, J, 3)
            d = np.linalg.norm(J[:, ok] - X[i][ok], axis=-1).mean(-1)
            if d.min() < 0.5:
                out[i] = np.where(np.isfinite(X[i]), J[int(np.argmin(d))], np.nan)
        return out

    co.ClockOffsetEstimator._triangulate = truly


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--modes", default="none,truth,truth+-15")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    ap.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator setting (repeatable), as for `extrcal simulate --set`")
    ap.add_argument("--true-3d", action="store_true", help="the others' 3D replaced by the true joints (diagnostic)")
    a = ap.parse_args()
    from edge_clients.sim import Truth

    rec = simulate(2, 180.0, a.seed, a.cache, {**sim_settings(a.sim), "clock_offsets": DEFAULT_OFFSETS})
    truth = Truth.load(Truth.sidecar_path(rec))
    true = dict(zip(truth.sensors, truth.clock_offset.tolist()))
    med = float(np.median(list(true.values())))
    if a.true_3d:
        true_3d(truth, med)
    modes = a.modes.split(",")
    results = {m: run(rec, a.seconds, m, true) for m in modes}
    print(f"Fine clock-offset stage, reference poses, 20-camera lab, 2 persons, first {a.seconds:g} s, seed {a.seed}: "
          "error of the estimate (ms; n/a = no estimate)")
    print("| sensor | true | " + " | ".join(modes) + " |")
    print("|---|---|" + "---|" * len(modes))
    names = sorted(true, key=lambda s: int(s.split("_")[-1]))
    errs = {m: [] for m in modes}
    zs = {m: [] for m in modes}
    for n in names:
        tr = true[n] - med
        cells = []
        for m in modes:
            c = results[m][0][n]
            if c.offset is None:
                cells.append("n/a")
            else:
                e = 1000 * (c.offset - tr)
                errs[m].append(abs(e))
                if c.std:
                    zs[m].append(e / (1000 * c.std))
                cells.append(f"{e:+.1f}")
        star = " *" if n in DEFAULT_OFFSETS else ""
        print(f"| {n}{star} | {1000 * tr:+.1f} | " + " | ".join(cells) + " |")
    print("| estimated | | " + " | ".join(f"{len(errs[m])}/{len(names)}" for m in modes) + " |")
    print("| max error | | " + " | ".join(f"{max(errs[m]) if errs[m] else float('nan'):.1f}" for m in modes) + " |")
    print("| within 5 ms | | " + " | ".join(f"{sum(e <= 5 for e in errs[m])}" for m in modes) + " |")
    print("| rms error (ms) | | " + " | ".join(f"{np.sqrt(np.mean(np.square(errs[m]))):.2f}" if errs[m] else "n/a"
                                             for m in modes) + " |")
    print("| rms error / std | | " + " | ".join(f"{np.sqrt(np.mean(np.square(zs[m]))):.2f}" if zs[m] else "n/a"
                                              for m in modes) + " |")
    print("| wall s | | " + " | ".join(f"{results[m][1]:.0f}" for m in modes) + " |")


if __name__ == "__main__":
    main()
