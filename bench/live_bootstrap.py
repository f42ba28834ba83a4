"""Benchmark: a live session without an initial estimate, through the service.

The 20-camera lab with its walkers (bench/accuracy.py's cached simulation: 2 persons of
1.96 m / 1.70 m, 180 s), replayed through Zenoh on loopback by a publisher process at
``--speed`` x real time; the service (in this process, its solver in its own) runs
with the data clock. A session without an initial estimate (``--person-height`` gives
the walkers' heights; without it the population prior sets the scale) collects,
bootstraps, hands over and calibrates; once the whole recording was sent and the first
adjustment after the hand-over ran, it is stopped (the final batch adjustment runs).

Printed per seed: the bootstrap's attempts (data s, wall s, cameras placed), the time to
the first pose (wall s since the session started, and s of data), the first cycle, and
the error against the truth after similarity alignment (shape: every camera, mean / max,
orientation), at the hand-over (the bootstrap's result), before the final batch (the
online estimate) and at the end.

    nice -n 19 python bench/live_bootstrap.py --seeds 0 --speed 1 --person-height 1.96,1.70

Timings depend on the machine's load (state it with the figures).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def publish(path: str, endpoint: str, site: str, speed: float, names: list[str], ready, stop) -> None:
    """Replay ``path`` through Zenoh at ``speed`` (stamps shifted to now, spaced as recorded)."""
    from edge_clients.publisher import SensorPublisher, zenoh_session
    from edge_clients.replay import run_replay
    from proto.transport import ZenohSettings

    with zenoh_session(ZenohSettings(mode="peer", connect=(endpoint,))) as zs, \
            SensorPublisher(zs, site, block=True) as pub:
        pub.wait_matched(names, timeout=30.0)
        ready.set()
        run_replay(pub, path, speed=speed, stop=stop)


def _get(c, path: str, **kw):
    """GET with retries: under heavy load a kept-alive connection can be reset."""
    import httpx

    for k in range(5):
        try:
            return c.get(path, **kw)
        except httpx.TransportError:
            if k == 4:
                raise
            time.sleep(1.0)


def run(seed: int, args, log) -> dict:
    import httpx

    from accuracy import HEIGHTS, lab_dir, simulate

    from backend.cameras import dump_extrinsics, load_extrinsics, parse_extrinsics
    from backend.evaluate import evaluate
    from backend.server import ServiceThread
    from proto.transport import free_port
    from backend.settings import ServiceSettings

    lab = lab_dir()
    rec = simulate(args.persons, args.duration, seed, Path(args.cache))
    ref = load_extrinsics(lab / "reference.yaml")
    truth = {k: v.pose for k, v in ref.items()}
    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    site = "benchboot"
    import tempfile

    state = Path(tempfile.mkdtemp(prefix="extrcal-bench-boot-"))
    settings = ServiceSettings.load(None, http={"port": 0}, zenoh={"listen": (endpoint,)}, state_dir=state,
                                    site=site, clock="data", speed=args.speed)
    body: dict = {"name": f"bench seed {seed}", "intrinsics_yaml": (lab / "intrinsics.yaml").read_text(),
                  "reference_yaml": dump_extrinsics(ref)}
    if args.person_height:
        body["person_height"] = [float(x) for x in args.person_height.split(",")]
    ctx = multiprocessing.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    out: dict = {"seed": seed, "speed": args.speed, "recording": str(rec), "heights": list(HEIGHTS[args.persons]),
                 "person_height": body.get("person_height")}
    with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=120) as c:
        proc = ctx.Process(target=publish, daemon=True,
                           args=(str(rec), endpoint, site, args.speed, sorted(ref), ready, stop))
        proc.start()
        assert ready.wait(120), "the publisher did not find the service"
        t0 = time.time()
        s = c.post("/sessions", json=body).json()
        sid = s["id"]
        first_cycle = None
        handover = None
        last_live = None
        replay_wall = None
        while True:
            s = _get(c, f"/sessions/{sid}").json()
            b = s.get("bootstrap") or {}
            if handover is None and b.get("phase") == "done":
                handover = {"wall": b["pose_wall"] - t0, "data": b["pose_data_seconds"]}
                print(f"  seed {seed}: handed over after {handover['wall']:.1f} s wall, {handover['data']:.1f} s of "
                      f"data: {b.get('note')}", file=log, flush=True)
            if first_cycle is None and s["cycles"] >= 1:
                first_cycle = {"wall": time.time() - t0, "data": (s["data_time"] or 0) - (s["first_data"] or 0)}
            if s["state"] in ("calibrating", "converged") and s.get("accuracy"):
                last_live = s["accuracy"]
            if not s["live"] or s["state"] in ("stopped", "failed"):
                break
            # the whole recording was sent and the first adjustment over it ran: stop (final batch)
            if not proc.is_alive() and handover is not None and s["cycles"] >= 2:
                out["replay_wall"] = replay_wall
                s = c.post(f"/sessions/{sid}/stop").json()
                break
            if replay_wall is None and not proc.is_alive():
                replay_wall = time.time() - t0
            time.sleep(0.5)
        stop.set()
        proc.join(20)
        if proc.is_alive():
            proc.kill()
        out["wall"] = time.time() - t0
        text = _get(c, f"/sessions/{sid}/result", params={"format": "yaml"}).text
        status = _get(c, "/status").json()
        out["loop_lag_max"] = status["loop_lag"]["max"]
        out["loop_work"] = {k: v for k, v in status["loop_work"].items() if k.startswith("bootstrap")}
        hist = _get(c, f"/sessions/{sid}/history").json()
    out.update(state=s["state"], reason=s["reason"], bootstrap={k: (s.get("bootstrap") or {}).get(k) for k in (
        "attempts", "placed", "not_placed", "scale", "frame", "pose_data_seconds")}, handover=handover,
               first_cycle=first_cycle, final_batch=s.get("final_batch"), cycles=s["cycles"])
    result = {k: v.pose for k, v in parse_extrinsics(text).items()}
    if result:
        acc = evaluate(result, truth)
        out["final"] = {"shape_position_mean": acc.shape_position.mean, "shape_position_max": acc.shape_position.max,
                        "orientation_mean": acc.shape_orientation.mean, "orientation_max": acc.shape_orientation.max,
                        "scale": acc.scale, "cameras": len(result),
                        "within": sum(1 for e in acc.per_camera.values() if e[2] <= 0.05 and e[3] <= 0.5)}
    live = [h for h in hist if not h.get("final_batch") and h.get("accuracy")]
    out["first_cycle_accuracy"] = live[0]["accuracy"] if live else None
    out["before_final_batch"] = live[-1]["accuracy"] if live else last_live
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--speed", type=float, default=1.0, help="replay speed (data s per wall s)")
    ap.add_argument("--persons", type=int, default=2)
    ap.add_argument("--duration", type=float, default=180.0, help="s of the simulated recording")
    ap.add_argument("--person-height", default=None, help="known heights for the session, e.g. 1.96,1.70")
    ap.add_argument("--cache", default="/tmp/extrcal-accuracy-cache")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    import logging

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    logging.getLogger("extrcal").addHandler(handler)
    logging.getLogger("extrcal").setLevel(logging.INFO)
    print(f"load average at the start: {os.getloadavg()[0]:.1f}", flush=True)
    runs = [run(seed, args, sys.stdout) for seed in args.seeds]
    print("\n| seed | attempts (data s / wall s / placed) | first pose: wall s / data s | first cycle: wall s / "
          "data s | at 1st cycle shape m | before final batch shape m / orient. ° | final shape mean / max m | "
          "orient. mean ° | scale | within 0.05 m / 0.5° |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        att = "; ".join(f"{a['data_seconds']:.0f}/{a['seconds']:.0f}/{a.get('placed', '-')}"
                        + ("" if a["accepted"] else " x") for a in r["bootstrap"]["attempts"] or [])
        h, fc = r["handover"] or {}, r["first_cycle"] or {}
        f, bf, c1 = r.get("final") or {}, r.get("before_final_batch") or {}, r.get("first_cycle_accuracy") or {}

        def g(d, k, fmt):
            return format(d[k], fmt) if d.get(k) is not None else "-"

        print(f"| {r['seed']} | {att} | {g(h, 'wall', '.0f')} / {g(h, 'data', '.0f')} | {g(fc, 'wall', '.0f')} / "
              f"{g(fc, 'data', '.0f')} | {g(c1, 'shape_position_mean', '.4f')} | "
              f"{g(bf, 'shape_position_mean', '.4f')} / {g(bf, 'shape_orientation_mean', '.3f')} | "
              f"{g(f, 'shape_position_mean', '.4f')} / {g(f, 'shape_position_max', '.4f')} | "
              f"{g(f, 'orientation_mean', '.3f')} | {g(f, 'scale', '.4f')} | {f.get('within', '-')}/{f.get('cameras', '-')} |")
        print(f"  state {r['state']}: {r['reason']}; not placed: {r['bootstrap']['not_placed']}; scale "
              f"{json.dumps(r['bootstrap']['scale'])}; event loop lag max {r['loop_lag_max']:.3f} s; "
              f"loop work {json.dumps(r['loop_work'])}")
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1, default=str))


if __name__ == "__main__":
    main()
