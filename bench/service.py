"""Benchmark of the live service through real Zenoh on loopback.

For 20 cameras (the lab) and 100 cameras (a synthetic hall), at 30 Hz per camera:

- ingest: messages per second the service takes, drops, CPU of the service process
  (ingest, front end, API) and of its solver process, in cores;
- latency: publish → arrival on the loop (sensor stamps are the publish time, so
  ``arrival − stamp`` is the transport + hand-off latency), and publish → frameset
  (the frameset's instant to its emission: mostly the sync stage's wait);
- optimizer: cycle time from problem to applied (and the solve alone) under that load;
- event-loop lag (how late a 10 ms sleep wakes up);
- saturation: the publisher as fast as it can go for a few seconds.

The service runs as `extrcal serve` in its own process (wall clock, as with real
sensors); one publisher process replays pre-simulated messages (extrcal's simulator)
paced to real time, looping, with stamps rewritten to the publish time.

    python bench/service.py                 # 20 and 100 cameras, 30 Hz, 20 s each
    python bench/service.py --cameras 20 --seconds 10

Prints tables; no numbers are asserted (tests/ holds the pass/fail bars).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from backend.cameras import Extrinsics, Intrinsics, dump_extrinsics, load_extrinsics, load_intrinsics  # noqa: E402
from backend.config import apply_override  # noqa: E402
from backend.perturb import perturb_extrinsics  # noqa: E402
from proto.transport import free_port  # noqa: E402

LAB = REPO / "edge_clients" / "data" / "ais_lab20"


# ------------------------------------------------------------------ scenes


def lab_cameras() -> tuple[dict[str, Intrinsics], dict[str, Extrinsics]]:
    return load_intrinsics(LAB / "intrinsics.yaml"), load_extrinsics(LAB / "reference.yaml")


def hall_cameras(n: int, seed: int = 0) -> tuple[dict[str, Intrinsics], dict[str, Extrinsics]]:
    """``n`` cameras of a hall (``edge_clients.sim.scenes.grid``): on a 3 m grid under the
    ceiling, looking down at 25-45°, each towards a random direction."""
    from edge_clients.sim.scenes import grid

    scene = grid(n, seed=seed)
    return dict(scene.intrinsics), {k: Extrinsics(p, scene.intrinsics[k].resolution) for k, p in scene.poses.items()}


def simulate(cameras: int, rate: float, seconds: float, persons: int, out: Path) -> tuple[dict, dict, int]:
    """Pre-simulated messages (arrival order) pickled to ``out``; returns the camera files."""
    from edge_clients.sim import Scene, SimConfig, Simulator

    intr, ext = lab_cameras() if cameras == 20 else hall_cameras(cameras)
    scene = Scene.from_cameras(intr, {k: e.pose for k, e in ext.items()},
                               LAB / "room.yaml" if cameras == 20 else None)
    sim = Simulator(scene, SimConfig(persons=persons, duration=seconds, seed=0, rates=(rate, rate)))
    msgs = list(sim.messages())
    with open(out, "wb") as f:
        pickle.dump(msgs, f, protocol=pickle.HIGHEST_PROTOCOL)
    delay = float(np.median([a - m.stamp for a, m in msgs]))
    return intr, ext, len(msgs), delay


# ------------------------------------------------------------------ publisher process


def publisher(path: str, endpoint: str, site: str, seconds: float, paced: bool, ready, counts) -> None:
    """Replays the pickled messages in a loop for ``seconds``, stamps = publish time."""
    from edge_clients.publisher import SensorPublisher, zenoh_session
    from proto.transport import ZenohSettings

    with open(path, "rb") as f:
        msgs = pickle.load(f)
    names = sorted({m.sensor for _, m in msgs})
    span = msgs[-1][0] - msgs[0][0] + 1.0 / 30
    a0 = msgs[0][0]
    with zenoh_session(ZenohSettings(connect=(endpoint,))) as zs, SensorPublisher(zs, site, block=True) as pub:
        pub.wait_matched(names, timeout=30)
        ready.set()
        t0 = time.time()
        sent, loop = 0, 0
        while True:
            for arrival, m in msgs:
                target = t0 + loop * span + (arrival - a0)
                now = time.time()
                if now - t0 > seconds:
                    counts.value = sent
                    return
                if paced and target > now:
                    time.sleep(target - now)
                # the capture instant: as far before arrival as in the simulation
                stamp = (target if paced else time.time()) - (arrival - m.stamp)
                pub.publish(replace(m, stamp=stamp, seq=m.seq + loop * 1_000_000))
                sent += 1
            loop += 1


# ------------------------------------------------------------------ measuring


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (Linux /proc), NaN elsewhere."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def run(cameras: int, rate: float, seconds: float, persons: int, work: Path, log, config: dict | None = None) -> dict:
    import httpx

    data = work / f"msgs-{cameras}.pkl"
    t = time.perf_counter()
    intr, ext, n, sim_delay = simulate(cameras, rate, min(seconds, 6.0), persons, data)
    log(f"  simulated {n} messages in {time.perf_counter() - t:.1f} s (simulated network delay median "
        f"{1000 * sim_delay:.0f} ms)")
    hport, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    state = work / f"state-{cameras}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("EXTRCAL_")}
    with open(work / f"serve-{cameras}.log", "w") as out:
        server = subprocess.Popen([sys.executable, "-m", "backend.cli", "serve", "--http", f"127.0.0.1:{hport}",
                                   "--zenoh-listen", endpoint, "--state-dir", str(state), "--site", "bench",
                                   "--log-level", "warning"], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    client = httpx.Client(base_url=f"http://127.0.0.1:{hport}", timeout=60)
    result: dict = {"cameras": cameras, "rate": rate, "sim_delay": sim_delay}
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if client.get("/healthz").json()["ok"]:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline or server.poll() is not None:
                raise RuntimeError(f"extrcal serve did not start: {(work / f'serve-{cameras}.log').read_text()}")
            time.sleep(0.1)
        intr_yaml = "".join(
            f"{k}:\n  intrinsics: [{i.fx}, {i.fy}, {i.cx}, {i.cy}]\n  distortion_coeffs: {list(map(float, i.dist))}\n"
            f"  resolution: [{i.resolution[0]}, {i.resolution[1]}]\n" for k, i in intr.items())
        r = client.post("/sessions", json={
            "name": f"bench {cameras}", "intrinsics_yaml": intr_yaml,
            "initial_yaml": dump_extrinsics(perturb_extrinsics(ext, 0.1, 3.0, seed=1)),
            "reference_yaml": dump_extrinsics(ext), **({"config": config} if config else {})})
        r.raise_for_status()
        sid = r.json()["id"]

        ctx = multiprocessing.get_context("spawn")
        for paced, secs in ((True, seconds), (False, min(5.0, seconds))):
            ready, counts = ctx.Event(), ctx.Value("q", 0)
            pub = ctx.Process(target=publisher, args=(str(data), endpoint, "bench", secs, paced, ready, counts))
            pub.start()
            if not ready.wait(60):
                raise RuntimeError("the publisher did not connect")
            s0 = client.get("/status").json()
            pids = [server.pid] + children(server.pid)
            c0 = {p: cpu_seconds(p) for p in pids}
            w0 = time.monotonic()
            pub.join(secs + 60)
            time.sleep(0.5)  # the last messages through the hand-off
            w1 = time.monotonic()
            s1 = client.get("/status").json()
            cpu = {p: cpu_seconds(p) - c0[p] for p in pids}
            wall = w1 - w0
            recv = s1["messages"]["received"] - s0["messages"]["received"]
            key = "live" if paced else "saturation"
            lat = [x["latency"] for x in s1["sensors"].values() if x["latency"]]
            result[key] = {
                "offered": counts.value / secs, "received": recv / wall,
                "dropped": s1["queues"]["ingest"]["dropped"] - s0["queues"]["ingest"]["dropped"],
                "cpu_service": cpu[server.pid] / wall,
                "cpu_solver": sum(v for p, v in cpu.items() if p != server.pid) / wall,
                "latency_median": float(np.median([x["median"] for x in lat])) if lat else float("nan"),
                "latency_p95": float(np.median([x["p95"] for x in lat])) if lat else float("nan"),
                "frameset_delay": s1.get("frameset_delay"),
                "cycles": (s1["cycles"]["count"] or 0) - (s0["cycles"]["count"] or 0),
                "cycle_wall": s1["cycles"]["wall_seconds"], "cycle_solve": s1["cycles"]["solve_seconds"],
                "loop_lag_max": s1["loop_lag"]["max"], "loop_lag_p99": s1["loop_lag"]["p99"],
                "rejected": s1["messages"]["rejected"],
                "loop_work": s1.get("loop_work"),
                "clock_applied": {n: x["time_offset"]["applied"] for n, x in s1["sensors"].items()
                                  if (x.get("time_offset") or {}).get("applied")},
            }
            log(f"  {key}: {json.dumps(result[key], default=str)[:400]}")
        session = client.get(f"/sessions/{sid}").json()
        result["session"] = {"state": session["state"], "cycles": session["cycles"], "accuracy": session["accuracy"],
                             "reason": session.get("reason")}
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(60)
        except subprocess.TimeoutExpired:
            server.kill()
        client.close()
    return result


def fmt(x, scale: float = 1.0, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x * scale:.{digits}f}"


def _settings(pairs: list[str]) -> dict:
    """SECTION.KEY=VALUE pairs as the session body's nested config."""
    out: dict = {}
    for p in pairs:
        apply_override(out, p)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, nargs="+", default=[20, 100])
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--persons", type=int, nargs="+", default=None, help="per camera count (default 2 for 20, 8 for 100)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="engine setting of the session (repeatable), e.g. clock.estimate=false")
    ap.add_argument("--keep", type=Path, help="keep the service's state directory and log here (default: a "
                    "temporary directory, removed)")
    args = ap.parse_args()
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    results = []
    with tempfile.TemporaryDirectory(prefix="extrcal-bench-") as tmp:
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            tmp = str(args.keep)
        for i, n in enumerate(args.cameras):
            persons = args.persons[i] if args.persons else (2 if n <= 20 else 8)
            log(f"{n} cameras x {args.rate:g} Hz, {persons} people, {args.seconds:g} s")
            results.append(run(n, args.rate, args.seconds, persons, Path(tmp), log, _settings(args.set)))
    print(f"\nextrcal service on {os.cpu_count()} cores (load average {os.getloadavg()[0]:.1f} at the end); "
          "Zenoh on loopback; one publisher process\n")
    print("latency: arrival on the loop − capture stamp, less the simulated network delay (median "
          "over sensors of their median / p95): what Zenoh on loopback and the hand-off add.")
    print("publish→frameset: a frameset's instant to its emission (the sync stage waits for late messages).\n")
    print("| cameras | load | offered msg/s | received msg/s | dropped | service CPU (cores) | solver CPU | "
          "latency median / p95 ms | publish→frameset mean ms | loop lag max / p99 ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for key in ("live", "saturation"):
            x = r[key]
            fd = x["frameset_delay"] or {}
            print(f"| {r['cameras']} | {key} | {fmt(x['offered'], digits=0)} | {fmt(x['received'], digits=0)} | "
                  f"{x['dropped']} | {fmt(x['cpu_service'], digits=2)} | {fmt(x['cpu_solver'], digits=2)} | "
                  f"{fmt(x['latency_median'] - r['sim_delay'], 1000)} / {fmt(x['latency_p95'] - r['sim_delay'], 1000)} | "
                  f"{fmt(fd.get('mean'), 1000, 0)} | "
                  f"{fmt(x['loop_lag_max'], 1000)} / {fmt(x['loop_lag_p99'], 1000)} |")
    print("\n| cameras | cycles (live) | cycle wall mean / p95 / max s | solve mean / max s | session after the run |")
    print("|---|---|---|---|---|")
    for r in results:
        x = r["live"]
        cw, cs = x["cycle_wall"] or {}, x["cycle_solve"] or {}
        acc = (r["session"]["accuracy"] or {})
        print(f"| {r['cameras']} | {x['cycles']} | {fmt(cw.get('mean'), digits=2)} / {fmt(cw.get('p95'), digits=2)} / "
              f"{fmt(cw.get('max'), digits=2)} | {fmt(cs.get('mean'), digits=2)} / {fmt(cs.get('max'), digits=2)} | "
              f"{r['session']['state']}, {r['session']['cycles']} cycles, error "
              f"{fmt(acc.get('position_mean'), 100, 1)} cm / {fmt(acc.get('orientation_mean'), 1, 2)}°"
              + (f" ({r['session']['reason']})" if r["session"]["state"] == "failed" else "") + " |")
    print("\n| cameras | load | loop work: wall mean (CPU mean) / wall max ms per call |")
    print("|---|---|---|")
    for r in results:
        for key in ("live", "saturation"):
            w = r[key]["loop_work"] or {}
            print(f"| {r['cameras']} | {key} | " + ", ".join(
                f"{k} {1000 * v['mean']:.1f} ({1000 * v.get('cpu_mean', float('nan')):.1f}) / {1000 * v['max']:.0f}"
                for k, v in sorted(w.items())) + " |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))


if __name__ == "__main__":
    main()
