"""Bumped cameras: how fast the monitor flags a camera moved after convergence, how well
it is calibrated again, how still the others stay; and false alarms without bumps.

    python bench/monitor.py                      # bumps 5 cm / 2°, 3 cm / 0°, 0 cm / 2°, seed 0
    python bench/monitor.py --bumps 0.03/0,0/2 --seeds 2 --quiet-runs 2 --jobs 2
    python bench/monitor.py --cameras cam_11,cam_12,cam_13,cam_14,cam_15,cam_16,cam_17 --camera cam_14 \
        --bumps 0/3 --seeds 4 --calibrate 120 --bump-time 240   # the west room, a small one
    python bench/monitor.py --layout room8 --camera cam_5 --bumps 0.03/0,0/2 --seeds 2 --calibrate 120 \
        --bump-time 240   # a generated room (bench/layouts.py): wide lenses, nothing tuned there

The 20-camera lab (or --cameras: a part of it as a room of its own; or --layout: one of
bench/layouts.py's generated rooms, walkers of 1.80 / 1.65 m), 2 persons (--persons); the
calibration starts from the reference perturbed by 0.10 m / 5° (the first camera kept).
A session calibrates from the first --calibrate s (180) of the recording as ``extrcal
calibrate`` does, final batch included; the monitoring session
starts from its result (its snapshot restored, as the service resumes a session), the
online pipeline without a final batch and with the monitor on (``monitor.enabled``),
and watches the rest; a camera is bumped at --bump-time s (360: 180 s after the watch
began). ``--calibrate 0``: the online estimate watched from the start as its cameras
converge (what this bench measured before: the network then is 5-8 cm off). --jobs runs
that many recordings in parallel. Figures:

- flagged after: data seconds from the bump to the monitor's alarm for that camera, and
  of them the seconds with evidence: in which the monitor had the camera's joints against
  points the others triangulated (a camera that sees nobody the others see has nothing
  to be flagged on);
- bumped camera vs its new true pose, at +60 s and +120 s: the estimate similarity-aligned
  to the truth on the other cameras (the frame is theirs), position m / orientation °;
- others moved: the change of the other cameras' estimates from the bump to the end, after
  a similarity alignment of the others (the whole estimate's gauge drift is not a camera
  moving), median and max over them, mm; the others are the cameras watched (converged)
  at the bump: the ones still converging move by design;
- false alarms: alarms for any camera in runs without bumps (and for non-bumped cameras
  in the bump runs), with the data hours watched.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from accuracy import HEIGHTS, lab_dir, sim_settings, simulate  # noqa: E402
from layouts import LAYOUTS, cameras_of  # noqa: E402
from layouts import simulate as simulate_layout  # noqa: E402


def _aligned_error(poses: dict, truth: dict, bumped: str) -> tuple[float, float]:
    from backend.geometry import rotation_angle_deg, umeyama

    others = [n for n in poses if n != bumped and n in truth]
    src = np.array([poses[n][1] for n in others])
    dst = np.array([truth[n][1] for n in others])
    s, R, t = umeyama(src, dst, with_scale=True)
    Rb, tb = poses[bumped]
    pos = s * R @ tb + t
    rot = R @ Rb
    return float(np.linalg.norm(pos - truth[bumped][1])), rotation_angle_deg(rot, truth[bumped][0])


def run(seed: int, bump: tuple[float, float] | None, camera: str, bump_time: float, duration: float,
        cache: Path, calibrate: float = 180.0, overrides: tuple[str, ...] = (), cameras: tuple[str, ...] = (),
        sim: tuple[tuple[str, object], ...] = (), layout: str = "", persons: int = 2) -> dict:
    from backend.cameras import CameraSet, load_extrinsics, load_intrinsics
    from backend.config import EngineConfig
    from backend.perturb import perturb_extrinsics
    from backend.pipeline import Pipeline
    from edge_clients.sim import Truth
    from proto import read_recording

    sim_set = {**dict(sim), **({"bumps": ((bump_time, camera, bump[0], bump[1]),)} if bump else {})}
    if layout:
        rec = simulate_layout(layout, persons, duration, seed, cache, sim_set)
        lab = cameras_of(rec)
    else:
        rec = simulate(persons, duration, seed, cache, sim_set, cameras)
        lab = lab_dir()
    truth = Truth.load(Truth.sidecar_path(rec))
    ref = {n: e for n, e in load_extrinsics(lab / "reference.yaml").items() if not cameras or n in cameras}
    intrinsics = {n: i for n, i in load_intrinsics(lab / "intrinsics.yaml").items() if not cameras or n in cameras}
    cams = CameraSet.combine(intrinsics, perturb_extrinsics(ref, 0.10, 5.0, seed=seed))
    base = EngineConfig.load(None, list(overrides))
    cfg = base.merged({"refine": {"final_batch": False}, "monitor": {"enabled": True}})
    names = list(cams.names)
    t0 = float(truth.start_time)
    messages = iter(read_recording(rec))
    wall = time.perf_counter()
    calibration = None
    if calibrate > 0:
        # the session: the first `calibrate` s calibrated as `extrcal calibrate` does (final
        # batch included); its result is what the monitoring session starts from (restored
        # from its snapshot, as the service resumes a session)
        p = Pipeline(cams, base, seed=seed)
        for m in messages:
            p.push(m)
            if p.clock is None:
                continue
            p.step(p.clock)
            if p.clock - t0 >= calibrate:
                break
        p.finish()
        calibration = _network_error(p.refiner.R, p.refiner.t, names, ref)
        snapshot = p.snapshot()
        # the cameras the session left converged are watched from the start (as they
        # would be had the monitor been on in the session)
        snapshot["watched"] = [bool(p.refiner.converged(c)) for c in range(len(names))]
        p = Pipeline.restore(cams, cfg, snapshot, seed=seed)
    else:
        p = Pipeline(cams, cfg, seed=seed)
    at_bump = None
    watched_at_bump: set[str] = set()
    track: list[tuple[float, dict]] = []
    watched_from = None
    camera_seconds = 0.0  # watched camera-seconds of data
    last = None
    evidence: set[int] = set()  # whole data seconds after the bump with the bumped camera's correspondences
    bumped = names.index(camera) if bump is not None else None
    for m in messages:
        p.push(m)
        if p.clock is None:
            continue
        report = p.step(p.clock)
        if report is None:
            continue
        rel = p.clock - t0
        if bumped is not None and rel >= bump_time and not any(a.cam == bumped for a in p.monitor.alarms):
            evidence.update(int(d.time - t0 - bump_time) for d in p.monitor.cams[bumped].data
                            if d.time - t0 >= bump_time)
        if last is not None:
            camera_seconds += float(p.watched.sum()) * (rel - last)
        last = rel
        if watched_from is None and p.watched.any():
            watched_from = rel
        poses = {n: (p.refiner.R[c].copy(), p.refiner.t[c].copy()) for c, n in enumerate(names)
                 if p.refiner.cycles[c] > 0 or p.monitor.alarms}
        if at_bump is None and rel >= bump_time:
            at_bump = poses
            watched_at_bump = {names[c] for c in np.flatnonzero(p.watched)}
        track.append((rel, poses))
    wall = time.perf_counter() - wall
    alarms = [(a.time - t0, names[a.cam]) for a in p.monitor.alarms]
    out = {"seed": seed, "bump": bump, "camera": camera, "alarms": alarms, "data_s": duration, "wall_s": wall,
           "calibration": calibration,
           "watched_from": watched_from, "camera_hours": camera_seconds / 3600,
           "watched_s": duration - watched_from if watched_from is not None else 0.0}
    if bump is None:
        return out
    true_now = {n: (ref[n].pose.R, ref[n].pose.t) for n in names}
    tb = float(truth.start_time) + bump_time
    true_now[camera] = truth.pose_at(camera, tb + 1e-6, ref[camera].pose.R, ref[camera].pose.t)
    mine = [a for a in alarms if a[1] == camera and a[0] >= bump_time]
    out["flagged_after"] = mine[0][0] - bump_time if mine else None
    out["flagged_after_evidence"] = (sum(s < out["flagged_after"] for s in evidence)
                                     if out["flagged_after"] is not None else None)
    out["false_alarms"] = [a for a in alarms if not (a[1] == camera and a[0] >= bump_time)]
    for dt in (60.0, 120.0):
        snap = next((poses for rel, poses in track if rel >= bump_time + dt), track[-1][1])
        out[f"error_{int(dt)}"] = _aligned_error(snap, true_now, camera) if camera in snap else None
    end = track[-1][1]
    # the cameras watched (converged) at the bump: those still converging move by design
    others = [n for n in at_bump if n != camera and n in end and n in watched_at_bump]
    moved = [np.linalg.norm(end[n][1] - at_bump[n][1]) for n in others]
    out["others_moved_raw_mm"] = 1000 * float(max(moved)) if moved else None
    out["others_moved_mm"] = out["others_moved_median_mm"] = None
    out["others_moved_worst"] = None
    out["watched_at_bump"] = len(watched_at_bump)
    if len(others) >= 3:
        # the same after a similarity alignment of the others (the gauge and scale drift of
        # the whole estimate is not a camera moving): median and max over the other cameras
        from backend.geometry import umeyama

        src = np.array([end[n][1] for n in others])
        dst = np.array([at_bump[n][1] for n in others])
        sc, R, tr = umeyama(src, dst, with_scale=True)
        res = np.linalg.norm(sc * src @ R.T + tr - dst, axis=1)
        out["others_moved_mm"] = 1000 * float(np.max(res))
        out["others_moved_median_mm"] = 1000 * float(np.median(res))
        out["others_moved_worst"] = others[int(np.argmax(res))]
    out["before_bump"] = _aligned_error(at_bump, {**true_now, camera: (ref[camera].pose.R, ref[camera].pose.t)},
                                        camera) if at_bump and camera in at_bump else None
    return out


def _network_error(R: np.ndarray, t: np.ndarray, names: list[str], ref: dict) -> tuple[float, float]:
    """The calibration's mean position error (m, after a similarity alignment on all
    cameras: its shape) and mean orientation error (deg, after the same alignment)."""
    from backend.geometry import rotation_angle_deg, umeyama

    dst = np.array([ref[n].pose.t for n in names])
    s, Rg, tg = umeyama(t, dst, with_scale=True)
    pos = np.linalg.norm(s * t @ Rg.T + tg - dst, axis=1)
    rot = [rotation_angle_deg(Rg @ R[c], ref[n].pose.R) for c, n in enumerate(names)]
    return float(np.mean(pos)), float(np.mean(rot))


def _job(args: tuple) -> dict:
    return run(*args)


def _print_run(con, r: dict) -> None:
    if r["bump"] is None:
        con.print(f"  no bump, seed {r['seed']}, {r['data_s']:g} s (watched from {r['watched_from']} s): "
                  f"alarms {r['alarms']}, calibration (shape m, deg) {r['calibration']}, {r['wall_s']:.0f} s wall")
        return
    b = r["bump"]
    con.print(f"  seed {r['seed']} bump {b}: calibration (shape m, deg) {r['calibration']}")
    con.print(f"  seed {r['seed']} bump {b[0]:.2f} m / {b[1]:g}°: before the bump {r['before_bump']}, flagged after "
              f"{r['flagged_after']} s ({r['flagged_after_evidence']} s with evidence), +60 s {r['error_60']}, "
              f"+120 s {r['error_120']}, others moved (aligned) "
              f"median {r['others_moved_median_mm']} max {r['others_moved_mm']} mm ({r['others_moved_worst']}), raw "
              f"{r['others_moved_raw_mm']} mm, false alarms {r['false_alarms']}, cameras watched at the bump "
              f"{r['watched_at_bump']}, {r['wall_s']:.0f} s wall")


def main(argv: list[str] | None = None) -> None:
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from rich.console import Console
    from rich.table import Table

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bumps", default="0.05/2,0.03/0,0/2", help="m/deg, comma separated")
    ap.add_argument("--camera", default="cam_8")
    ap.add_argument("--cameras", default="", metavar="NAME,NAME,...",
                    help="a part of the lab as a room of its own, e.g. the west room's cam_11,...,cam_17 (the live "
                         "monitor test's; --camera cam_14); default: all 20")
    ap.add_argument("--layout", default="", choices=["", *LAYOUTS],
                    help="a generated room of bench/layouts.py instead of the lab (its cameras are cam_0, cam_1, ...)")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--persons", type=int, default=2, choices=sorted(HEIGHTS),
                    help="walkers (the lab's heights as bench/accuracy.py's; a layout's alternate 1.80 / 1.65 m)")
    ap.add_argument("--calibrate", type=float, default=180.0,
                    help="s of data the session calibrates from (final batch included) before the watch; 0: the "
                         "online pipeline from the start, without the final batch, watched as its cameras converge")
    ap.add_argument("--bump-time", type=float, default=360.0, help="s: after the session converged")
    ap.add_argument("--after", type=float, default=125.0, help="s of data after the bump")
    ap.add_argument("--quiet-runs", type=int, default=1, help="runs without bumps (false alarms), seeds --quiet-seed...")
    ap.add_argument("--quiet-duration", type=float, default=600.0)
    ap.add_argument("--quiet-seed", type=int, default=100, help="seed of the first run without bumps (the next ones follow)")
    ap.add_argument("--jobs", type=int, default=1, help="runs in parallel (processes)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="engine parameter override (repeatable), as for `extrcal calibrate --set`, "
                         "e.g. monitor.chi2=30")
    ap.add_argument("--sim", dest="sim_set", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator setting (repeatable), as for `extrcal simulate --set`: other lenses, "
                         "detectors, motion, e.g. intrinsics_error=0.01 surface_offset=0.04")
    args = ap.parse_args(argv)
    from backend.config import EngineConfig
    EngineConfig.load(None, args.overrides)  # a bad override fails here, not in every job
    sim = tuple(sorted(sim_settings(args.sim_set).items()))
    con = Console()
    if sim:
        con.print(f"simulator settings: {dict(sim)}")
    bumps = [tuple(float(x) for x in b.split("/")) for b in args.bumps.split(",") if b]
    sets = tuple(args.overrides)
    cameras = tuple(c for c in args.cameras.split(",") if c)
    if cameras and args.camera not in cameras:
        raise SystemExit(f"--camera {args.camera} is not one of --cameras {args.cameras}")
    if args.layout and cameras:
        raise SystemExit("--cameras picks cameras of the lab; with --layout the room's cameras are all watched")
    if args.layout:
        from edge_clients.sim.scenes import make

        names = make(LAYOUTS[args.layout][0], **LAYOUTS[args.layout][1]).names
        if args.camera not in names:
            raise SystemExit(f"--camera {args.camera} is not a camera of {args.layout} ({', '.join(names)})")
    jobs = [(seed, b, args.camera, args.bump_time, args.bump_time + args.after, args.cache, args.calibrate, sets,
             cameras, sim, args.layout, args.persons) for seed in range(args.seeds) for b in bumps]
    jobs += [(args.quiet_seed + k, None, args.camera, 0.0, args.quiet_duration, args.cache, args.calibrate, sets,
              cameras, sim, args.layout, args.persons) for k in range(args.quiet_runs)]
    wall = time.perf_counter()
    results = []
    # each run is printed as it ends: a long quiet bench interrupted keeps the hours it ran
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            for fut in as_completed([ex.submit(_job, j) for j in jobs]):
                results.append(fut.result())
                _print_run(con, results[-1])
    else:
        for j in jobs:
            results.append(_job(j))
            _print_run(con, results[-1])
    wall = time.perf_counter() - wall
    results.sort(key=lambda r: (r["bump"] is None, r["seed"]))
    rows = [r for r in results if r["bump"] is not None]
    quiet = [r for r in results if r["bump"] is None]

    where = args.layout or (f"{len(cameras)} cameras of the lab" if cameras else "20-camera lab")
    t = Table(title=f"Bumped {args.camera} at {args.bump_time:g} s ({where}, {args.persons} persons, start 0.10 m / 5°)")
    for col in ("seed", "bump", "flagged after (s)", "of them with evidence (s)", "before: m / °", "+60 s: m / °",
                "+120 s: m / °", "others moved, median / max (mm)", "other alarms"):
        t.add_column(col)
    fmt = lambda e: "-" if e is None else f"{e[0]:.3f} / {e[1]:.2f}"  # noqa: E731
    for r in rows:
        t.add_row(str(r["seed"]), f"{r['bump'][0]:.2f} m / {r['bump'][1]:g}°",
                  "not flagged" if r["flagged_after"] is None else f"{r['flagged_after']:.1f}",
                  "-" if r["flagged_after_evidence"] is None else str(r["flagged_after_evidence"]),
                  fmt(r["before_bump"]), fmt(r["error_60"]), fmt(r["error_120"]),
                  "-" if r["others_moved_mm"] is None else f"{r['others_moved_median_mm']:.1f} / {r['others_moved_mm']:.1f}",
                  str(len(r["false_alarms"])))
    con.print(t)
    hours = sum(r["watched_s"] for r in results) / 3600
    cam_hours = sum(r["camera_hours"] for r in results)
    n_false = sum(len(r["alarms"]) for r in quiet) + sum(len(r["false_alarms"]) for r in rows)
    con.print(f"false alarms: {n_false} in {hours:.2f} h of watched data ({cam_hours:.1f} camera-hours watched; "
              f"runs without bumps: {len(quiet)} x {args.quiet_duration:g} s, and the bump runs); "
              f"{n_false / hours if hours else float('nan'):.2f} per hour; {wall:.0f} s wall, --jobs {args.jobs}")


if __name__ == "__main__":
    main()
