"""Overload bench: 10x the expected message rate into a real `extrcal serve` for a minute.

    python bench/overload.py                       # 100 sensors x 300 Hz offered, 60 s
    python bench/overload.py --seconds 30 --publishers 3

The service runs as `extrcal serve` (data clock) in its own process with a session on the
20-camera lab (initial = the reference perturbed by 0.25 m / 10°, the reference given so
that the session reports its error). Expected load: 100 sensors x 30 Hz; offered: 100
sensors x 300 Hz, i.e. the lab's 20 cameras replayed at 10x real time (their simulated
messages, 30 Hz in data time, re-stamped so that data time runs 10x faster than the wall)
plus 80 more sensors on the same network at 300 Hz each (copies of the lab's messages
under other names: sensors that are not in the session, as on a shared network).
Publishers are separate processes with their own Zenoh sessions (the 20 session cameras in
one, so their stamps stay consistent with each other, the 80 others spread over the rest),
publishing as fast as they can up to the target rate, at nice 19 (sensors are other
machines in a deployment: the load generator must not take the service's CPU).

While it runs, the bench samples every second the service's RSS (and its solver
process's) from /proc/<pid>/status, polls GET /status from a client (latency p50/p99 over
the overload, and the drop counters), and GET /sessions/{id} (cycles, error against the
reference). Prints a table over time and a summary; no numbers are asserted.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

LAB = REPO / "edge_clients" / "data" / "ais_lab20"
SITE = "overload"
SPEEDUP = 10.0  # data seconds per wall second for the session's cameras: 30 Hz -> 300 Hz


def simulate(seconds: float, persons: int, out: Path) -> tuple[int, list[str]]:
    """The lab at 30 Hz for ``seconds`` of data time, pickled to ``out`` (arrival order)."""
    from backend.cameras import load_extrinsics, load_intrinsics
    from edge_clients.sim import Scene, SimConfig, Simulator

    intr, ext = load_intrinsics(LAB / "intrinsics.yaml"), load_extrinsics(LAB / "reference.yaml")
    scene = Scene.from_cameras(intr, {k: e.pose for k, e in ext.items()}, LAB / "room.yaml")
    msgs = list(Simulator(scene, SimConfig(persons=persons, duration=seconds, seed=0)).messages())
    with open(out, "wb") as f:
        pickle.dump(msgs, f, protocol=pickle.HIGHEST_PROTOCOL)
    return len(msgs), sorted(intr)


def publisher(path: str, endpoint: str, names: dict, seconds: float, start, ready, counts) -> None:
    """Replays the pickled lab messages in a loop, 10x faster than real time.

    names: lab camera -> the sensor names that publish that camera's messages here (the
    camera itself, or other sensors). Stamps: data time = wall time of the first message
    plus the simulated offset, so data time runs SPEEDUP x faster than the wall.
    """
    from edge_clients.publisher import SensorPublisher, zenoh_session
    from proto.transport import ZenohSettings

    # Sensors are other machines in a deployment: here the load generator must not take
    # the CPU the service under test would have (it still competes, at the lowest priority).
    os.nice(19)

    with open(path, "rb") as f:
        msgs = pickle.load(f)
    msgs = [(a, m) for a, m in msgs if m.sensor in names]
    span = msgs[-1][0] - msgs[0][0] + 1.0 / 30
    a0 = msgs[0][0]
    everyone = [s for ss in names.values() for s in ss]
    with zenoh_session(ZenohSettings(connect=(endpoint,))) as zs, SensorPublisher(zs, SITE, block=True) as pub:
        pub.wait_matched(everyone, timeout=60)
        ready.set()
        while start.value == 0.0 or time.time() < start.value:  # a common start instant
            time.sleep(0.005)
        t0 = start.value
        sent, loop = 0, 0
        while True:
            for arrival, m in msgs:
                offset = loop * span + (arrival - a0)  # data seconds since the start
                target = t0 + offset / SPEEDUP
                now = time.time()
                if now - t0 > seconds:
                    counts.value = sent
                    return
                if target > now:
                    time.sleep(target - now)
                stamp = t0 + loop * span + (m.stamp - a0)
                seq = m.seq + loop * 1_000_000
                for s in names[m.sensor]:
                    pub.publish(replace(m, sensor=s, stamp=stamp, seq=seq))
                    sent += 1
            loop += 1


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def pct(xs, q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def main() -> int:
    import httpx

    from backend.cameras import dump_extrinsics, load_extrinsics
    from backend.perturb import perturb_extrinsics
    from proto.transport import free_port

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="wall seconds of overload")
    ap.add_argument("--sensors", type=int, default=100, help="sensors in all (the first 20 are the session's)")
    ap.add_argument("--publishers", type=int, default=4, help="publisher processes (one for the session's cameras)")
    ap.add_argument("--persons", type=int, default=2)
    ap.add_argument("--sim-seconds", type=float, default=60.0, help="data seconds simulated (replayed in a loop)")
    ap.add_argument("--profile", type=Path, default=None,
                    help="run the service under cProfile (its main thread: the event loop) and write the stats here")
    a = ap.parse_args()
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731

    with tempfile.TemporaryDirectory(prefix="extrcal-overload-") as tmp:
        work = Path(tmp)
        data = work / "msgs.pkl"
        t = time.perf_counter()
        n, cams = simulate(a.sim_seconds, a.persons, data)
        log(f"simulated {n} messages ({a.sim_seconds:g} s of the lab at 30 Hz) in {time.perf_counter() - t:.0f} s")

        # who publishes what: process 0 the session's cameras, the rest the other sensors
        others = [f"other_{i}" for i in range(a.sensors - len(cams))]
        plan: list[dict[str, list[str]]] = [{c: [c] for c in cams}]
        for p in range(max(1, a.publishers - 1)):
            mine = others[p::max(1, a.publishers - 1)]
            plan.append({c: [s for i, s in enumerate(mine) if (others.index(s)) % len(cams) == cams.index(c)]
                         for c in cams})
            plan[-1] = {c: ss for c, ss in plan[-1].items() if ss}
        plan = [p for p in plan if p]
        offered_target = a.sensors * 30 * SPEEDUP

        hport, zport = free_port(), free_port()
        endpoint = f"tcp/127.0.0.1:{zport}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("EXTRCAL_")}
        out = open(work / "serve.log", "w")
        prof = ["-m", "cProfile", "-o", str(a.profile.resolve())] if a.profile else []
        server = subprocess.Popen([sys.executable, *prof, "-m", "backend.cli", "serve", "--http", f"127.0.0.1:{hport}",
                                   "--zenoh-listen", endpoint, "--state-dir", str(work / "state"), "--site", SITE,
                                   "--clock", "data", "--log-level", "warning"],
                                  cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
        client = httpx.Client(base_url=f"http://127.0.0.1:{hport}", timeout=60)
        procs: list = []
        try:
            deadline = time.monotonic() + 90
            while True:
                try:
                    if client.get("/healthz").json()["ok"]:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError(f"extrcal serve did not start: {(work / 'serve.log').read_text()[-2000:]}")
                time.sleep(0.1)
            ref = load_extrinsics(LAB / "reference.yaml")
            r = client.post("/sessions", json={
                "name": "overload", "intrinsics_yaml": (LAB / "intrinsics.yaml").read_text(),
                "initial_yaml": dump_extrinsics(perturb_extrinsics(ref, 0.25, 10)),
                "reference_yaml": (LAB / "reference.yaml").read_text(), "stop": {"duration": 1e6}})
            r.raise_for_status()
            sid = r.json()["id"]

            idle_rss = rss_kib(server.pid)
            ctx = multiprocessing.get_context("spawn")
            readies, counters = [], []
            start = ctx.Value("d", 0.0)  # set once every publisher matched
            for p in plan:
                ready, count = ctx.Event(), ctx.Value("q", 0)
                proc = ctx.Process(target=publisher, daemon=True,
                                   args=(str(data), endpoint, p, a.seconds, start, ready, count))
                proc.start()
                procs.append(proc)
                readies.append(ready)
                counters.append(count)
            for rd in readies:
                if not rd.wait(120):
                    raise RuntimeError("a publisher did not connect")
            start_at = time.time() + 0.5
            start.value = start_at
            log(f"{len(plan)} publisher processes matched")
            while time.time() < start_at:
                time.sleep(0.01)

            # ------------------------------------------------ measuring while it runs
            lat: list[float] = []
            age: list[float] = []  # s since the status served was made
            stop = threading.Event()

            def poll_status() -> None:
                with httpx.Client(base_url=f"http://127.0.0.1:{hport}", timeout=60) as c:
                    while not stop.is_set():
                        t0 = time.perf_counter()
                        r = c.get("/status")
                        r.raise_for_status()
                        lat.append(time.perf_counter() - t0)
                        age.append(time.time() - r.json()["as_of"])
                        stop.wait(0.1)

            poller = threading.Thread(target=poll_status, daemon=True)
            poller.start()
            rows = []
            s0 = client.get("/status").json()
            w0 = time.monotonic()
            next_row = 0.0
            while any(p.is_alive() for p in procs) or time.monotonic() - w0 < a.seconds:
                el = time.monotonic() - w0
                if el >= next_row:
                    st = client.get("/status").json()
                    se = client.get(f"/sessions/{sid}").json()
                    acc = se.get("accuracy") or {}
                    solver = children(server.pid)
                    rows.append({
                        "t": el, "rss": rss_kib(server.pid), "rss_solver": sum(rss_kib(x) or 0 for x in solver),
                        "received": st["messages"]["received"] - s0["messages"]["received"],
                        "dropped": st["queues"]["ingest"]["dropped"],
                        "queue": st["queues"]["ingest"]["length"],
                        "hyp_dropped": (st["queues"].get("hypotheses") or {}).get("dropped"),
                        "cycles": se["cycles"], "state": se["state"],
                        "pos": acc.get("position_mean"), "rot": acc.get("orientation_mean"),
                        "p99": pct(lat, 99) if lat else float("nan"),
                    })
                    log(f"t {el:5.1f} s  rss {rows[-1]['rss'] / 1024:.0f} MiB  received {rows[-1]['received']}  "
                        f"dropped {rows[-1]['dropped']}  cycles {se['cycles']}  "
                        f"error {fmt(rows[-1]['pos'], 100)} cm / {fmt(rows[-1]['rot'], 1, 2)} deg")
                    next_row += 5.0
                time.sleep(0.2)
                if time.monotonic() - w0 > a.seconds + 120:
                    raise RuntimeError("the publishers did not finish")
            wall = time.monotonic() - w0
            stop.set()
            poller.join(30)
            time.sleep(1.0)
            st = client.get("/status").json()
            se = client.get(f"/sessions/{sid}").json()
            offered = sum(c.value for c in counters)
            received = st["messages"]["received"] - s0["messages"]["received"]
            rej = {k: v - s0["messages"]["rejected"].get(k, 0) for k, v in st["messages"]["rejected"].items()}
            rej = {k: v for k, v in rej.items() if v}
            acc = se.get("accuracy") or {}
            final = {"rss": rss_kib(server.pid), "cycles": se["cycles"], "state": se["state"],
                     "pos": acc.get("position_mean"), "rot": acc.get("orientation_mean")}
            def taken(status: dict) -> int:
                sensors = status["sensors"].values() if isinstance(status["sensors"], dict) else status["sensors"]
                return sum(x.get("accepted", 0) for x in sensors if x.get("name") in cams)

            accepted = taken(st) - taken(s0)
        finally:
            for p in procs:
                if p.is_alive():
                    p.kill()
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(60)
            except subprocess.TimeoutExpired:
                server.kill()
            client.close()
            out.close()

    print(f"\nextrcal serve (data clock) on {os.cpu_count()} cores shared with other jobs (load average "
          f"{os.getloadavg()[0]:.1f}); Zenoh on loopback; {len(plan)} publisher processes; "
          f"session on the 20-camera lab, initial 0.25 m / 10° off\n")
    print("| t s | service RSS MiB | solver RSS MiB | received | ingest dropped | ingest queue | hypotheses dropped "
          "| /status p99 so far ms | cycles | state | error cm / ° |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['t']:.0f} | {r['rss'] / 1024:.0f} | {r['rss_solver'] / 1024:.0f} | {r['received']} | {r['dropped']} "
              f"| {r['queue']} | {r['hyp_dropped']} | {fmt(r['p99'], 1000)} | {r['cycles']} | {r['state']} "
              f"| {fmt(r['pos'], 100)} / {fmt(r['rot'], 1, 2)} |")
    print(f"| end | {final['rss'] / 1024:.0f} | | {received} | {st['queues']['ingest']['dropped']} | | "
          f"{(st['queues'].get('hypotheses') or {}).get('dropped')} | | {final['cycles']} | {final['state']} "
          f"| {fmt(final['pos'], 100)} / {fmt(final['rot'], 1, 2)} |")
    print()
    print("| offered target msg/s | offered msg/s | received msg/s | ingest dropped | accepted (session sensors) "
          "| service RSS idle → max → end MiB | GET /status p50 / p99 / max ms (n) | cycles | error start → end cm / ° |")
    print("|---|---|---|---|---|---|---|---|---|")
    first = next((r for r in rows if r["pos"] is not None), rows[0])
    print(f"| {offered_target:.0f} | {offered / a.seconds:.0f} | {received / wall:.0f} | {st['queues']['ingest']['dropped']} "
          f"| {accepted} | {idle_rss / 1024:.0f} → {max(r['rss'] for r in rows) / 1024:.0f} → {final['rss'] / 1024:.0f} "
          f"| {fmt(pct(lat, 50), 1000)} / {fmt(pct(lat, 99), 1000)} / {fmt(max(lat) if lat else None, 1000)} ({len(lat)}) "
          f"| {final['cycles']} | {fmt(first['pos'], 100)} / {fmt(first['rot'], 1, 2)} → "
          f"{fmt(final['pos'], 100)} / {fmt(final['rot'], 1, 2)} |")
    print()
    print(f"age of the /status served (now - as_of) p50 / p99 / max: {fmt(pct(age, 50), 1000)} / "
          f"{fmt(pct(age, 99), 1000)} / {fmt(max(age) if age else None, 1000)} ms")
    print(f"event loop lag p99 / max: {fmt(st['loop_lag']['p99'], 1000)} / {fmt(st['loop_lag']['max'], 1000)} ms; "
          "work on the loop (count, mean / max ms, CPU share of the wall): " + "; ".join(
              f"{k} {v['count']}, {v['mean'] * 1000:.2f} / {v['max'] * 1000:.1f}, {v['cpu_mean'] / v['mean']:.0%}"
              for k, v in st["loop_work"].items() if v["mean"] > 0))
    print("rejected by reason during the overload: " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items(), key=lambda x: -x[1])))
    return 0


def fmt(x, scale: float = 1.0, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x * scale:.{digits}f}"


if __name__ == "__main__":
    sys.exit(main())
