"""Calibration without an initial estimate, on the simulator (issue 8).

The 20-camera lab (shared/data/ais_lab20), two walkers of 1.96 m and 1.70 m, 180 s, several
seeds (recordings cached like bench/accuracy.py, with its helpers). Per seed:

- the bootstrap (``backend.bootstrap``) on the first T s of data, T in --checkpoints: per
  camera the error after a similarity alignment to the truth (``backend.evaluate``, the
  shape figures), how many cameras it placed, how many are within 0.05 m / 0.5°, its wall
  time; the smallest T at which every placed camera is within the bars;
- the scale: the bootstrap's estimate from the population prior, and from the known heights
  of the walkers (``people.measure_scale`` on the same poses), against the true scale (the
  similarity alignment's), with the reported std (z = error / std);
- the online pipeline from the bootstrap of the last checkpoint (``bootstrap.handover``)
  on the whole recording: rigid and shape errors per camera.

    python bench/bootstrap.py                         # 5 seeds, checkpoints 60, 90, 120 s
    python bench/bootstrap.py --seeds 2 --checkpoints 120 --no-online
    python bench/bootstrap.py --checkpoints 120 --no-online --population-heights   # the scale prior's honesty
    python bench/bootstrap.py --report b.json         # the tables of an earlier --out
    python bench/bootstrap.py --data-seconds 110 --out c.json   # `extrcal calibrate` on the first 110 s
    python bench/bootstrap.py --data-seconds 180 --jobs 2 \
        --sim clock_offsets=cam_2:-0.2,cam_5:-0.1,cam_9:0.05,cam_13:0.12,cam_17:0.2   # five clocks off

With --data-seconds T: the whole `extrcal calibrate` path without an initial estimate
(``backend.cli_engine.calibrate`` itself, in this process: the bootstrap, the online
pipeline from it, the final batch) on a copy of the recording cut after T s; per seed the
similarity-aligned errors of the bootstrap alone, the online estimate before the final batch
and the result, and the cameras not placed with their detections (a camera that never sees
a person together with another camera cannot be placed).

No figure is asserted here: tests/backend/test_bootstrap.py holds the pass/fail bars.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

BAR_POSITION = 0.05  # m, after similarity alignment
BAR_ORIENTATION = 0.5  # deg


def _shape(acc) -> dict:
    per = {n: (round(v[2], 5), round(v[3], 4)) for n, v in acc.per_camera.items()}
    pos = np.array([v[0] for v in per.values()])
    ori = np.array([v[1] for v in per.values()])
    return {"cameras": len(per), "shape_position": float(pos.mean()), "shape_position_max": float(pos.max()),
            "shape_orientation": float(ori.mean()), "shape_orientation_max": float(ori.max()),
            "within": int(np.sum((pos <= BAR_POSITION) & (ori <= BAR_ORIENTATION))),
            "position": acc.position.mean, "orientation": acc.orientation.mean, "scale": acc.scale,
            "per_camera": per}


def population_heights(seed: int, persons: int = 2) -> tuple[float, ...]:
    """Walkers drawn from the population the prior describes (backend/people.py: as many
    women as men, statures N(1.66, 0.07) and N(1.79, 0.07) m), per seed: whether the
    prior's stated std is honest for walkers it knows nothing of."""
    rng = np.random.default_rng([seed, 2026])
    return tuple(round(float(rng.normal(1.79 if rng.random() < 0.5 else 1.66, 0.07)), 3) for _ in range(persons))


def run_seed(seed: int, checkpoints: list[float], cache: Path, online: bool, say, population: bool = False) -> dict:
    import accuracy

    from backend.bootstrap import BootstrapError, bootstrap, camera_set, collect_frames, handover
    from backend.cameras import load_extrinsics, load_intrinsics, natural_key
    from backend.config import EngineConfig
    from backend.evaluate import evaluate
    from backend.people import measure_scale
    from backend.pipeline import run_offline
    from proto import read_recording

    lab = accuracy.lab_dir()
    heights = population_heights(seed) if population else accuracy.HEIGHTS[2]
    rec = accuracy.simulate(2, 180.0, seed, cache, {"heights": list(heights)} if population else {})
    intr = load_intrinsics(lab / "intrinsics.yaml")
    ref = {n: e.pose for n, e in load_extrinsics(lab / "reference.yaml").items()}
    names = tuple(sorted(intr, key=natural_key))
    focal = np.array([0.5 * (intr[n].fx + intr[n].fy) for n in names])
    cfg = EngineConfig().for_images(i.resolution for i in intr.values())
    t0 = time.perf_counter()
    frames = collect_frames(names, intr, cfg, read_recording(rec))
    say(f"seed {seed}: walkers {heights} m, {len(frames)} framesets read in {time.perf_counter() - t0:.0f} s")
    out: dict = {"seed": seed, "load": os.getloadavg()[0], "checkpoints": [], "walkers": list(heights)}
    boot = None
    for T in checkpoints:
        part = [f for f in frames if f[0] - frames[0][0] <= T]
        t0 = time.perf_counter()
        try:
            boot = bootstrap(part, names, focal, cfg, seed=seed)
        except BootstrapError as e:
            out["checkpoints"].append({"T": T, "error": str(e)})
            say(f"seed {seed} T {T:g}: {e}")
            boot = None
            continue
        wall = time.perf_counter() - t0
        acc = evaluate(boot.poses(), ref)
        row = {"T": T, "wall": wall, "placed": int(boot.located.sum()),
               "not_placed": [n for c, n in enumerate(names) if not boot.located[c]], **_shape(acc)}
        # scale: true metres per unit of the result = the similarity alignment's scale
        true = acc.scale
        R, t = boot.R, boot.t
        if boot.scale is not None:
            row["scale_prior"] = {"error": 1.0 / true - 1.0, "rel_std": boot.scale.rel_std,
                                  "heights": list(boot.scale.heights), "persons": boot.scale.persons}
        known, _ = measure_scale(part, R, t, cfg.associate, cfg.bootstrap, heights=heights, cameras=boot.located)
        if known is not None:
            row["scale_known"] = {"error": known.factor / true - 1.0, "rel_std": known.rel_std,
                                  "heights": list(known.heights), "persons": known.persons}
        out["checkpoints"].append(row)
        say(f"seed {seed} T {T:g}: {row['placed']} placed, {row['within']} within bars, shape "
            f"{row['shape_position']:.4f} m (max {row['shape_position_max']:.4f}) "
            f"{row['shape_orientation']:.3f}° (max {row['shape_orientation_max']:.3f}), "
            f"prior scale err {100 * row.get('scale_prior', {}).get('error', float('nan')):+.2f} %, "
            f"known {100 * row.get('scale_known', {}).get('error', float('nan')):+.2f} %, {wall:.0f} s")
    if online and boot is not None:
        cams = camera_set(intr, boot)
        t0 = time.perf_counter()
        p = run_offline(cams, handover(cfg, boot), read_recording(rec), seed=seed)
        acc = evaluate(p.state().poses(), ref, [n for n in cams.names if n in ref])
        out["online"] = {"wall": time.perf_counter() - t0, "from_T": checkpoints[-1], **_shape(acc)}
        say(f"seed {seed} online: shape {acc.shape_position.mean:.4f} m (max {acc.shape_position.max:.4f}) "
            f"{acc.shape_orientation.mean:.3f}° (max {acc.shape_orientation.max:.3f}), scale {acc.scale:.4f}")
    return out


def first_seconds(rec: Path, seconds: float) -> Path:
    """The recording's messages stamped within ``seconds`` of its first stamp (the median
    of the first 16 messages' stamps, as the pipeline's clock starts), cached next to it."""
    from proto import read_recording, write_recording

    out = rec.with_name(f"{rec.name}.first{seconds:g}s.msgpack")
    if out.is_file():
        return out
    head = []
    for m in read_recording(rec):
        head.append(m.stamp)
        if len(head) >= 16:
            break
    t0 = float(np.median(head))
    tmp = out.with_name(f".{os.getpid()}.{out.name}")
    write_recording(tmp, (m for m in read_recording(rec) if m.stamp - t0 <= seconds))
    os.replace(tmp, out)
    return out


def visibility(rec: Path, names, intr, cfg) -> dict[str, dict]:
    """Per camera: detections in the recording, and framesets (after the pipeline's front
    end, sync and preprocess) in which it sees a person together with another camera."""
    from backend.bootstrap import collect_frames
    from proto import read_recording

    det = {n: 0 for n in names}
    for m in read_recording(rec):
        if m.sensor in det:
            det[m.sensor] += len(m.persons)
    together = np.zeros(len(names), np.int64)
    for _, views in collect_frames(names, intr, cfg, read_recording(rec)):
        for v in views:
            together[v[0].cam] += 1
    return {n: {"detections": det[n], "with_another": int(together[c])} for c, n in enumerate(names)}


def run_calibrate(seed: int, seconds: float, cache: Path, overrides: list[str], say, sim_set: dict | None = None) -> dict:
    """The whole `extrcal calibrate` path without an initial estimate (``cli_engine.calibrate``
    itself: bootstrap, online pipeline, final batch) on the first ``seconds`` of the
    recording. Errors after a similarity alignment to the truth of: the bootstrap alone
    (its poses in out.yaml.bootstrap.json), the online estimate of the last regular cycle
    (the history's second-to-last line; the last is after the final batch) and the result."""
    import tempfile

    import accuracy
    import typer
    import yaml

    from backend.cameras import Pose, load_extrinsics, load_intrinsics, natural_key
    from backend.cli_engine import calibrate
    from backend.config import EngineConfig
    from backend.evaluate import evaluate, up_tilt
    from backend.geometry import quat_to_R

    lab = accuracy.lab_dir()
    rec = first_seconds(accuracy.simulate(2, 180.0, seed, cache, sim_set or {}), seconds)
    intr = load_intrinsics(lab / "intrinsics.yaml")
    ref = {n: e.pose for n, e in load_extrinsics(lab / "reference.yaml").items()}
    names = tuple(sorted(intr, key=natural_key))
    out: dict = {"seed": seed, "seconds": seconds, "load": os.getloadavg()[0], "overrides": overrides}
    out["visibility"] = visibility(rec, names, intr, EngineConfig.load(None, overrides))
    with tempfile.TemporaryDirectory(prefix="extrcal-bench-boot-") as d:
        res, hist = Path(d) / "out.yaml", Path(d) / "history.jsonl"
        t0 = time.perf_counter()
        try:
            calibrate(intrinsics=lab / "intrinsics.yaml", recording=rec, output=res, initial=None,
                      distrust_initial=False, person_height=None, reference=None, config=None, set_=overrides,
                      seed=seed, history=hist, skip_bad=False, quiet=True)
        except typer.Exit as e:  # cli.fail: the bootstrap or the run failed (its message is on stderr)
            out["error"] = f"calibrate exited with code {e.exit_code}"
            return out
        out["wall"] = time.perf_counter() - t0
        meta = json.loads(Path(f"{res}.bootstrap.json").read_text())
        boot = {n: Pose(quat_to_R(v["rotation"]), np.array(v["translation"])) for n, v in meta["poses"].items()}
        final = {n: e.pose for n, e in load_extrinsics(res).items()}
        res_comment = [ln.lstrip("# ").strip() for ln in res.read_text().splitlines() if ln.startswith("#")]
        lines = hist.read_text().splitlines()
    out["bootstrap_seconds"] = meta["seconds"]
    out["not_placed"] = meta["not_located"]
    out["scale"] = meta["scale"]
    out["bridge_checks"] = meta.get("bridge_checks", [])
    out["resections"] = meta.get("resections", [])
    out["placed_later"] = meta.get("placed_later", [])  # backend/late_join.py: resected while the run goes on or at its end
    out["late_resections"] = meta.get("late_resections", [])
    out["final_batch"] = next((ln for ln in res_comment if ln.startswith("final batch adjustment")), None)
    out["bootstrap"] = _shape(evaluate(boot, ref))
    up = np.asarray(yaml.safe_load((lab / "room.yaml").read_text())["floor"]["normal_up"], dtype=np.float64)
    out["tilt"] = {"bootstrap": up_tilt(boot, ref, up), "final": up_tilt(final, ref, up)}  # the floor frame's z
    if len(lines) >= 2:
        cams = json.loads(lines[-2])["cameras"]
        online = {c["name"]: Pose(quat_to_R(c["rotation"]), np.array(c["translation"])) for c in cams}
        out["online"] = _shape(evaluate(online, ref))
    out["final"] = _shape(evaluate(final, ref))
    f = out["final"]
    say(f"seed {seed}, {seconds:g} s: bootstrap {out['bootstrap']['within']}/{out['bootstrap']['cameras']} within "
        f"bars, final {f['within']}/{f['cameras']}, shape {f['shape_position']:.4f} m (max "
        f"{f['shape_position_max']:.4f}) {f['shape_orientation']:.3f}° (max {f['shape_orientation_max']:.3f}); "
        f"not placed: {', '.join(out['not_placed']) or '-'}; placed later: "
        f"{', '.join(j['name'] + (' (joined the running pipeline)' if j.get('live') else '') for j in out['placed_later']) or '-'}; "
        f"{out['wall']:.0f} s")
    return out


def _tilts(r: dict) -> str:
    t = r.get("tilt")  # runs of --out files written before the column
    return f"{t['bootstrap']:.2f} / {t['final']:.2f}" if t else "-"


def _worst(s: dict) -> str:
    """The camera furthest outside the bars (or the worst within them)."""
    n, (p, o) = max(s["per_camera"].items(), key=lambda kv: max(kv[1][0] / BAR_POSITION, kv[1][1] / BAR_ORIENTATION))
    return f"{n} {p:.3f} m / {o:.2f}°"


def print_calibrate(runs: list[dict]) -> None:
    print("\n## `extrcal calibrate` without an initial estimate on the first T s of data\n")
    print("Similarity-aligned error per placed camera: bootstrap alone, online pipeline before the final "
          "batch, the result (after the final batch). Cameras within 0.05 m / 0.5°.\n")
    print("| seed | data s | placed | bootstrap within | online within | result within | result shape pos mean / max (m) "
          "| orient mean / max (°) | worst camera (result) | z tilt bootstrap / result (°) | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        if "error" in r:
            print(f"| {r['seed']} | {r['seconds']:g} | failed: {r['error']} | | | | | | | | |")
            continue
        b, f = r["bootstrap"], r["final"]
        o = r.get("online")
        ow = f"{o['within']}/{o['cameras']}" if o else "n/a"
        print(f"| {r['seed']} | {r['seconds']:g} | {f['cameras']}/20 | {b['within']}/{b['cameras']} | "
              f"{ow} | {f['within']}/{f['cameras']} | "
              f"{f['shape_position']:.4f} / {f['shape_position_max']:.4f} | "
              f"{f['shape_orientation']:.3f} / {f['shape_orientation_max']:.3f} | {_worst(f)} | "
              f"{_tilts(r)} | {r['wall']:.0f} |")
    print("\nCameras the bootstrap did not place (detections in the data / framesets seen together with another camera):\n")
    for r in runs:
        if "error" in r:
            continue
        vis = r["visibility"]
        later = {j["name"] for j in r.get("placed_later", [])}
        lost = ", ".join(f"{n} ({vis[n]['detections']} / {vis[n]['with_another']})"
                         + (" placed later" if n in later else "") for n in r["not_placed"])
        print(f"- seed {r['seed']}, {r['seconds']:g} s: {lost or 'none'}")
    late = [r for r in runs if r.get("late_resections")]
    if late:
        print("\nCameras the bootstrap did not place, resected against the online estimate while the run went on "
              "(\"live\") or at its end (backend/late_join.py; the last resection's notes; errors in the result, "
              "similarity-aligned):\n")
        for r in late:
            placed = {j["name"] for j in r.get("placed_later", [])}
            live = {j["name"] for j in r.get("placed_later", []) if j.get("live")}
            errs = "; ".join(f"{n}{' (live)' if n in live else ''} {r['final']['per_camera'][n][0]:.3f} m / "
                             f"{r['final']['per_camera'][n][1]:.2f}°" for n in sorted(placed) if n in r["final"]["per_camera"])
            print(f"- seed {r['seed']}, {r['seconds']:g} s: {'; '.join(r['late_resections'])}"
                  + (f" → in the result: {errs}" if errs else ""))
    res = [r for r in runs if r.get("resections")]
    if res:
        print("\nCameras no pair placed, resected against the placed cameras' persons (backend/resect.py):\n")
        for r in res:
            print(f"- seed {r['seed']}, {r['seconds']:g} s: {'; '.join(r['resections'])}")
    fb = [r for r in runs if r.get("final_batch")]
    if fb:
        print("\nFinal batch adjustment kept:", ", ".join(f"seed {r['seed']} {r['final_batch'].split('from the ')[-1]}"
                                                    for r in fb))
    checks = [r for r in runs if r.get("bridge_checks")]
    if checks:
        print("\nCameras reached only over bridge pairs, checked against the others' persons:\n")
        for r in checks:
            print(f"- seed {r['seed']}, {r['seconds']:g} s: {', '.join(r['bridge_checks'])}")
    print("\nload average at the start of each run:", ", ".join(f"{r['load']:.1f}" for r in runs))


def _needed(r: dict) -> float | None:
    """Data seconds of the first checkpoint at which every placed camera is within the bars
    and no camera that a later checkpoint places is missing."""
    rows = [c for c in r["checkpoints"] if "error" not in c]
    if not rows:
        return None
    most = max(c["placed"] for c in rows)
    for c in rows:
        if c["placed"] == most and c["within"] == c["placed"]:
            return c["T"]
    return None


def print_tables(runs: list[dict]) -> None:
    print("\n## Bootstrap (no initial estimate): per checkpoint, similarity-aligned error per camera\n")
    print("| seed | data s | placed | within 0.05 m / 0.5° | shape pos mean / max (m) | orient mean / max (°) "
          "| scale err, prior (± std) | scale err, known heights (± std) | wall s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        for c in r["checkpoints"]:
            if "error" in c:
                print(f"| {r['seed']} | {c['T']:g} | failed: {c['error']} | | | | | | |")
                continue
            sp, sk = c.get("scale_prior"), c.get("scale_known")
            fs = lambda s: f"{100 * s['error']:+.2f} % (± {100 * s['rel_std']:.1f} %)" if s else "n/a"  # noqa: E731
            print(f"| {r['seed']} | {c['T']:g} | {c['placed']}/20 | {c['within']}/{c['placed']} | "
                  f"{c['shape_position']:.4f} / {c['shape_position_max']:.4f} | "
                  f"{c['shape_orientation']:.3f} / {c['shape_orientation_max']:.3f} | {fs(sp)} | {fs(sk)} | "
                  f"{c['wall']:.0f} |")
    print("\n## Data seconds needed (first checkpoint with every placed camera within the bars)\n")
    print("| seed | data s | not placed |")
    print("|---|---|---|")
    for r in runs:
        last = [c for c in r["checkpoints"] if "error" not in c]
        print(f"| {r['seed']} | {_needed(r) or 'not reached'} | {', '.join(last[-1]['not_placed']) if last else ''} |")
    on = [r for r in runs if "online" in r]
    if on:
        print("\n## Online pipeline from the bootstrap (whole 180 s recording)\n")
        print("| seed | from (s) | cameras | within bars | shape pos mean / max (m) | orient mean / max (°) "
              "| rigid pos (m) | scale vs truth | wall s |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in on:
            o = r["online"]
            print(f"| {r['seed']} | {o['from_T']:g} | {o['cameras']} | {o['within']}/{o['cameras']} | "
                  f"{o['shape_position']:.4f} / {o['shape_position_max']:.4f} | "
                  f"{o['shape_orientation']:.3f} / {o['shape_orientation_max']:.3f} | {o['position']:.4f} | "
                  f"{1 / o['scale']:.4f} | {o['wall']:.0f} |")
    print("\nload average at the start of each seed:", ", ".join(f"{r['load']:.1f}" for r in runs))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--checkpoints", default="60,90,120", help="data seconds the bootstrap gets, comma separated")
    ap.add_argument("--no-online", action="store_true", help="skip the online pipeline after the bootstrap")
    ap.add_argument("--data-seconds", help="instead: the whole `extrcal calibrate` path (bootstrap, online pipeline, "
                    "final batch) on only the first T s of each recording; T comma separated")
    ap.add_argument("--set", dest="set_", action="append", default=[], help="engine parameter override (with "
                    "--data-seconds), e.g. bootstrap.min_pair_frames=20 (repeatable)")
    ap.add_argument("--cache", type=Path, default=Path(tempfile_dir()) / "extrcal-accuracy-cache")
    ap.add_argument("--out", type=Path, help="write the runs as JSON")
    ap.add_argument("--sim", dest="sim_set", action="append", default=[], metavar="KEY=VALUE",
                    help="with --data-seconds: simulator setting (as `extrcal simulate --set`: other motion, detectors)")
    ap.add_argument("--jobs", type=int, default=1, help="with --data-seconds: runs in parallel processes (wall "
                    "times then include each other's load)")
    ap.add_argument("--report", type=Path, help="print the tables of an earlier --out and stop")
    ap.add_argument("--population-heights", action="store_true", help="walkers drawn per seed from the population "
                    "the scale prior describes, not 1.96 m and 1.70 m (without --data-seconds)")
    a = ap.parse_args(argv)
    if a.report:
        data = json.loads(a.report.read_text())
        print_calibrate(data["runs"]) if data.get("mode") == "calibrate" else print_tables(data["runs"])
        return
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    if a.data_seconds:
        from backend.cameras import write_atomic

        sim_set = __import__("accuracy").sim_settings(a.sim_set)
        runs = []
        todo = [(seed, float(T)) for T in a.data_seconds.split(",") for seed in range(a.first_seed, a.first_seed + a.seeds)]
        if a.jobs > 1:
            from concurrent.futures import ProcessPoolExecutor

            for seed, T in todo:  # the cut recordings, once, before the workers read them
                first_seconds(__import__("accuracy").simulate(2, 180.0, seed, a.cache, sim_set), T)
            with ProcessPoolExecutor(a.jobs) as ex:
                futs = [ex.submit(run_calibrate, seed, T, a.cache, a.set_, _say, sim_set) for seed, T in todo]
                for f in futs:
                    runs.append(f.result())
                    if a.out:
                        write_atomic(a.out, json.dumps({"mode": "calibrate", "runs": runs}, indent=1))
        else:
            for seed, T in todo:
                runs.append(run_calibrate(seed, T, a.cache, a.set_, say, sim_set))
                if a.out:
                    write_atomic(a.out, json.dumps({"mode": "calibrate", "runs": runs}, indent=1))
        print_calibrate(runs)
        return
    checkpoints = [float(x) for x in a.checkpoints.split(",")]
    runs = []
    for seed in range(a.first_seed, a.first_seed + a.seeds):
        runs.append(run_seed(seed, checkpoints, a.cache, not a.no_online, say, a.population_heights))
        if a.out:
            from backend.cameras import write_atomic

            write_atomic(a.out, json.dumps({"runs": runs}, indent=1))
    print_tables(runs)


def _say(m: str) -> None:
    print(m, file=sys.stderr, flush=True)


def tempfile_dir() -> str:
    import tempfile

    return tempfile.gettempdir()


if __name__ == "__main__":
    main()
