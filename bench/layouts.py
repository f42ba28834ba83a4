"""Other camera layouts than the lab: does `extrcal calibrate` hold where nothing was tuned?

Generated rooms (``edge_clients.sim.scenes.room``: 4 or 8 cameras high in the corners and
along the walls of a 7 x 5 m room, all looking at its centre through 100° lenses with
strong barrel distortion, 640 x 480), variations of them (``hall``: 8 HD cameras 3.5 m
high round a 16 x 10 m hall; ``warehouse``: 8 of them 5 m high round 24 x 16 m through
55° lenses; ``low``: 4 cameras at head height; ``steep``: 4 cameras
under a 3.4 m ceiling of a 4 x 4 m room looking steeply down; ``rolled``: room8's cameras
mounted rolled about their optical axes, portrait and upside down), the corridor and halls
of 30 or 40 cameras on a 3 m grid, each looking down a random way (``grid30``, ``grid40``:
``scenes.grid``, a new grid for each seed; run them with ``--persons 3`` or 4); people walking
(``--persons``, heights 1.80 / 1.65 m). Each case runs the command a user runs,
``extrcal calibrate`` in a subprocess, from a perturbed initial estimate (the paper's
protocol, ``--starts`` m/deg) or from none (``none``: bootstrap, metric scale from the
population prior; ``height``: from the walkers' known heights), and prints the errors
against the truth (FORMATS.md: rigid, shape, orientation, scale; over the cameras in the
result; a run that left cameras out or uncalibrated names them and counts as "short").

    python bench/layouts.py                                   # room4, room8; 3 seeds; ~10 min
    python bench/layouts.py --layouts room4 --starts none,height --seeds 5 --jobs 2
    python bench/layouts.py --starts 0.75/20,0.75/20+height --set bootstrap.initial_scale=combine
    python bench/layouts.py --starts none --sim noise_scale=2 --sim swap_prob=0.03   # a harsher detector
    python bench/layouts.py --layouts grid30 --persons 3 --starts none --seeds 4 --jobs 2   # ~1 h
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

HEIGHTS = (1.80, 1.65)
LAYOUTS = {
    "room2": ("room", {"cameras": 2}),
    "room3": ("room", {"cameras": 3}),
    "room4": ("room", {"cameras": 4}),
    "room8": ("room", {"cameras": 8}),
    "corridor": ("corridor", {}),
    # a hall: people small in HD images, long baselines, mild lenses
    "hall": ("room", {"cameras": 8, "width": 16.0, "depth": 10.0, "height": 3.5, "aim": 1.0, "hfov": 70.0,
                      "resolution": (1280, 720), "k1": -0.05}),
    # a warehouse: people 5-25 m away through narrow HD lenses high up, weak angles between views
    "warehouse": ("room", {"cameras": 8, "width": 24.0, "depth": 16.0, "height": 5.0, "aim": 1.0, "hfov": 55.0,
                           "resolution": (1920, 1080), "k1": -0.03}),
    # cameras at head height looking across: people hide each other, views nearly level
    "low": ("room", {"cameras": 4, "height": 1.9, "aim": 1.2}),
    # room8's cameras mounted rolled about their optical axes: portrait both ways, upside down
    "rolled": ("room", {"cameras": 8, "roll": (0.0, 90.0, 180.0, -90.0, 30.0, 135.0, -60.0, 180.0)}),
    # a small room's cameras near a high ceiling looking steeply down: people foreshortened
    "steep": ("room", {"cameras": 4, "width": 4.0, "depth": 4.0, "height": 3.4, "aim": 0.3, "hfov": 110.0}),
    # a capture space: cameras all round at chest height and high up, one in the ceiling
    # looking straight down (an image with no "up"), three kinds of lens
    "studio": ("studio", {}),
    # two rooms joined by a door, four cameras each: the two networks see each other's
    # floor only through the doorway
    "tworooms": ("tworooms", {}),
    # many cameras on a grid under a hall's ceiling, turned every way (a new grid each seed):
    # half the pairs share no floor, pairs of cameras seeing different walkers fit wrong poses
    "grid30": ("grid", {"cameras": 30, "seed": None}),
    "grid40": ("grid", {"cameras": 40, "seed": None}),
}


def simulate(layout: str, persons: int, duration: float, seed: int, cache: Path, sim_set: dict | None = None) -> Path:
    """The recording of one layout and seed (its truth sidecar, its camera directory), cached;
    ``sim_set``: other simulator settings (bumps, lenses, detectors)."""
    from edge_clients.sim import SimConfig, Simulator, Truth
    from edge_clients.sim.scenes import make, write_scene

    name, kw = LAYOUTS[layout]
    if "seed" in kw and kw["seed"] is None:  # a layout drawn anew for each seed
        kw = {**kw, "seed": seed}
    h = hashlib.sha1()
    for f in sorted((REPO / "edge_clients" / "sim").glob("*.py")):
        h.update(f.read_bytes())
    h.update(repr((layout, kw, persons, duration, seed, HEIGHTS[:persons])).encode())
    if sim_set:
        h.update(repr(sorted(sim_set.items())).encode())
    out = cache / f"{layout}_p{persons}_d{duration:g}_s{seed}_{h.hexdigest()[:10]}.msgpack"
    if out.is_file() and Truth.sidecar_path(out).is_file():
        return out
    cache.mkdir(parents=True, exist_ok=True)
    scene = make(name, **kw)
    write_scene(scene, cameras_of(out), f"generated {layout}")
    tmp = cache / f".{os.getpid()}.{out.name}"
    heights = tuple((HEIGHTS * persons)[:persons])
    Simulator(scene, SimConfig(**{**(sim_set or {}), "persons": persons, "duration": duration, "seed": seed,
                                  "heights": heights})).write(tmp)
    os.replace(Truth.sidecar_path(tmp), Truth.sidecar_path(out))
    os.replace(tmp, out)
    return out


def cameras_of(recording: Path) -> Path:
    return Path(f"{recording}.cameras")


def run(recording: Path, start: str, seed: int, persons: int, work: Path, overrides: list[str]) -> dict:
    """One `extrcal calibrate` of ``recording`` from ``start`` ('T/R' m/deg, 'none' or
    'height'; 'T/R+height': the initial estimate and the walkers' heights) with ``--set``
    ``overrides``; its errors against the truth."""
    import yaml

    from backend.cameras import load_extrinsics, save_extrinsics
    from backend.evaluate import evaluate, up_tilt
    from backend.perturb import perturb_extrinsics

    d = cameras_of(recording)
    ref = load_extrinsics(d / "reference.yaml")
    tag = f"{recording.stem}_{start.replace('/', '-')}_{hashlib.sha1(repr(overrides).encode()).hexdigest()[:6]}"
    known = start.endswith("height")
    start = start.removesuffix("+height")
    out = work / f"{tag}.yaml"
    cmd = [sys.executable, "-m", "backend.cli", "calibrate", "--intrinsics", str(d / "intrinsics.yaml"),
           "--recording", str(recording), "--output", str(out), "--seed", str(seed), "--quiet"]
    initial = None
    if start not in ("none", "height"):
        t, r = (float(x) for x in start.split("/"))
        initial = perturb_extrinsics(ref, t, r, seed=seed)
        save_extrinsics(work / f"{tag}.initial.yaml", initial)
        cmd += ["--initial", str(work / f"{tag}.initial.yaml")]
    if known:
        cmd += ["--person-height", ",".join(f"{h:g}" for h in (HEIGHTS * persons)[:persons])]
    for o in overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t0
    res = {"layout": recording.name.split("_")[0], "start": f"{start}+height" if known and start != "height" else start,
           "seed": seed, "wall": wall,
           "ok": p.returncode == 0}
    if p.returncode != 0:
        res["error"] = (p.stderr or p.stdout).strip().splitlines()[-1:] or ["?"]
        return res
    got = load_extrinsics(out)
    header = [ln[2:] for ln in out.read_text().splitlines() if ln.startswith("# ")]
    # a camera the bootstrap did not place is left out of the result: it counts as not calibrated
    named = next((ln.split(": ", 1)[1] for ln in header if "(not calibrated)" in ln or ln.startswith("not calibrated")),
                 "")
    missing = [n for n in ref if n not in got and n not in named.split(", ")]
    res["not_calibrated"] = ", ".join(x for x in [named] + missing if x)
    res["placed"] = f"{len(got)}/{len(ref)}"
    poses = {n: e.pose for n, e in got.items()}
    truth = {n: e.pose for n, e in ref.items()}
    try:
        a = evaluate(poses, truth)
    except ValueError as e:  # a bootstrap that placed fewer than 3 cameras
        res.update(ok=False, error=[f"{e} ({len(got)} cameras in the result)"])
        return res
    res.update(position=a.position.mean, position_max=a.position.max, shape=a.shape_position.mean,
               orientation=a.orientation.mean, orientation_max=a.orientation.max, scale=a.scale)
    # is the stated std honest? each camera's shape error against the std_translation it states
    stds = {n: got[n].std_translation for n in a.per_camera if got[n].std_translation}
    res["std_mean"] = float(np.mean(list(stds.values()))) if stds else float("nan")
    res["beyond_3std"] = sum(1 for n, s in stds.items() if a.per_camera[n][2] > 3 * s)
    res["cameras"] = len(a.per_camera)
    res["split"] = next((ln for ln in header if ln.startswith("split-half check")), "")
    # which final batch was kept, where more than one was solved (the held one, from the data's shape, ...)
    res["final_batch"] = next((ln.removeprefix("final batch adjustment: ") for ln in header
                               if ln.startswith("final batch adjustment: ") and "kept" in ln), "")
    if initial is not None:
        b = evaluate({n: e.pose for n, e in initial.items()}, truth)
        res["initial_position"] = b.position.mean
    else:  # the result's frame is the floor's (z up): how far from the truth's up
        up = yaml.safe_load((d / "room.yaml").read_text())["floor"]["normal_up"]
        res["tilt"] = up_tilt(poses, truth, np.asarray(up, dtype=np.float64))
    return res


def table(runs: list[dict], layouts: list[str], starts: list[str], args) -> str:
    """Markdown: per layout and start, the mean over seeds (errors over the cameras in the result)."""
    lines = [f"extrcal calibrate on generated layouts ({args.persons} persons, {args.duration:g} s, {args.seeds} seeds; "
             f"mean over seeds, errors over the cameras in the result; 'short': runs that left cameras out or "
             f"uncalibrated, named above){' --set ' + ' '.join(args.overrides) if args.overrides else ''}"
             f"{' --sim ' + ' '.join(args.sim_set) if args.sim_set else ''}",
             "",
             "| layout | start | ok | rigid pos (m) | worst camera (m) | shape pos (m) | orient (°) | worst (°) | scale "
             "| stated std (m) | shape error > 3 std | initial rigid (m) | floor frame's z tilt (°) | wall (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for lay in layouts:
        for st in starts:
            rs = [r for r in runs if r["layout"] == lay and r["start"] == st]
            ok = [r for r in rs if r["ok"]]
            short = sum(1 for r in ok if r["not_calibrated"])
            if not ok:
                lines.append(f"| {lay} | {st} | 0/{len(rs)} | - | - | - | - | - | - | - | - | - | - | - |")
                continue
            m = (lambda k, d=4: f"{np.mean([r[k] for r in ok]):.{d}f}")  # noqa: E731
            mx = (lambda k, d: f"{max(r[k] for r in ok):.{d}f}")  # noqa: E731
            lines.append(f"| {lay} | {st} | {len(ok)}/{len(rs)}" + (f" ({short} short)" if short else "")
                         + f" | {m('position')} | {mx('position_max', 3)} | "
                         f"{m('shape')} | {m('orientation', 3)} | {mx('orientation_max', 2)} | {m('scale')} | "
                         f"{m('std_mean')} | {sum(r['beyond_3std'] for r in ok)}/{sum(r['cameras'] for r in ok)} | "
                         f"{m('initial_position', 3) if 'initial_position' in ok[0] else '-'} | "
                         f"{mx('tilt', 2) + ' max' if 'tilt' in ok[0] else '-'} | {m('wall', 0)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from rich.console import Console

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layouts", default="room4,room8", help=f"comma separated: {', '.join(LAYOUTS)}")
    ap.add_argument("--starts", default="0.25/10,0.75/20,none,height", help="m/deg perturbations, none, height")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--persons", type=int, default=2)
    ap.add_argument("--duration", type=float, default=180.0)
    ap.add_argument("--jobs", type=int, default=1, help="calibrations in parallel (subprocesses)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-layouts-cache"))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="engine parameter for every run (extrcal calibrate --set)")
    ap.add_argument("--sim", dest="sim_set", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator setting for every recording (as `extrcal simulate --set`: detectors, lenses, clocks)")
    ap.add_argument("--out", type=Path, default=None, help="write every run as JSON")
    args = ap.parse_args(argv)
    from accuracy import sim_settings

    sim_set = sim_settings(args.sim_set)
    con = Console()
    layouts = [x for x in args.layouts.split(",") if x]
    for x in layouts:
        if x not in LAYOUTS:
            raise SystemExit(f"unknown layout {x!r} (known: {', '.join(LAYOUTS)})")
    starts = [x for x in args.starts.split(",") if x]
    work = args.cache / "runs"
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max(1, args.jobs)) as ex:
        recs = {(lay, s): ex.submit(simulate, lay, args.persons, args.duration, s, args.cache, sim_set)
                for lay in layouts for s in range(args.seeds)}
        recs = {k: f.result() for k, f in recs.items()}
        con.print(f"{len(recs)} recording(s) in {time.perf_counter() - t0:.0f} s (cached in {args.cache})")
        futs = [ex.submit(run, recs[(lay, s)], st, s, args.persons, work, args.overrides)
                for lay in layouts for st in starts for s in range(args.seeds)]
        runs = []
        for f in futs:
            r = f.result()
            runs.append(r)
            con.print(f"  {r['layout']} {r['start']} seed {r['seed']}: " + (
                f"rigid {r['position']:.4f} m (max {r['position_max']:.3f}), shape {r['shape']:.4f} m, "
                f"{r['orientation']:.3f}° (max {r['orientation_max']:.2f}), scale {r['scale']:.4f}"
                + f", stated std {r['std_mean']:.4f} m, {r['beyond_3std']} beyond 3 std"
                + (f", not calibrated: {r['not_calibrated']}" if r['not_calibrated'] else "")
                + (f"\n    {r['split']}" if r["split"] else "")
                + (f"\n    final batch: {r['final_batch']}" if r.get("final_batch") else "")
                if r["ok"] else f"FAILED: {r['error']}") + f" | {r['wall']:.0f} s", highlight=False)
    con.print(table(runs, layouts, starts, args), highlight=False, soft_wrap=True)
    if args.out is not None:
        args.out.write_text(json.dumps(runs, indent=1))


if __name__ == "__main__":
    main()
