"""How far apart the sensors' stamps run as they arrive, on recordings: what
``clock.estimate = "auto"`` watches (backend/stamp_watch.py), and whether it would start
the clock offsets' estimate at ``--auto-lead``.

    python bench/stamp_leads.py REC.msgpack [REC ...]
    python bench/stamp_leads.py --seeds 236-264      # the monitor bench's quiet runs (cached)
    python bench/stamp_leads.py --seeds 0-4 --duration 180 --jobs 2

Per recording: the sensor whose median lead (over the last minute, sampled every 0.5 s
of data, checked every 5 s) went furthest, how far and when, and when the estimate
would have started. The stamps cannot tell a short delay from a clock that runs
ahead; a start on synchronised sensors costs CPU, not accuracy
(docs/clock_offsets.md, Session 31). ``--seeds`` simulates the lab (2 walkers, the
simulator's default timing) as bench/accuracy.py does, cached in ``--cache``.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from backend.config import ClockConfig  # noqa: E402
from backend.stamp_watch import StampWatch  # noqa: E402
from proto import read_recording  # noqa: E402


def leads(path: Path, auto_lead: float) -> dict:
    """Replay ``path`` through the watch as the pipeline does offline (the data clock is
    the newest stamp; stamps of the far future or past are not screened here)."""
    watch = StampWatch(auto_lead)
    clock = t0 = None
    worst: tuple[str, float, float] | None = None  # sensor, lead s, data s
    started = None
    for m in read_recording(path):
        watch.observe(m.sensor, m.stamp)
        t0 = m.stamp if t0 is None else t0
        clock = m.stamp if clock is None or m.stamp > clock else clock
        far = watch.sample(clock)
        if far is None:
            continue
        if far and started is None:
            started = (clock - t0, ", ".join(f"{s} {1000 * v:+.0f} ms" for s, v in far.items()))
        for s, v in watch.leads().items():
            if worst is None or abs(v) > abs(worst[1]):
                worst = (s, v, clock - t0)
    return {"path": path.name, "seconds": None if clock is None else clock - t0, "worst": worst, "started": started}


def _seed_recording(seed: int, duration: float, cache: Path) -> Path:
    from accuracy import simulate

    return simulate(2, duration, seed, cache)


def _job(args: tuple) -> dict:
    what, duration, cache, auto_lead = args
    path = _seed_recording(what, duration, cache) if isinstance(what, int) else Path(what)
    out = leads(path, auto_lead)
    if isinstance(what, int):
        out["path"] = f"lab seed {what}"
    return out


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main(argv: list[str] | None = None) -> None:
    from rich.console import Console
    from rich.table import Table

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="*", type=Path)
    ap.add_argument("--seeds", type=_seeds, default=[], metavar="A-B", help="simulated lab runs (cached)")
    ap.add_argument("--duration", type=float, default=1500.0, help="s of each simulated run")
    ap.add_argument("--auto-lead", type=float, default=ClockConfig().auto_lead, help="s (clock.auto_lead)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/extrcal-accuracy-cache"))
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args(argv)
    todo = [(str(p), args.duration, args.cache, args.auto_lead) for p in args.recordings]
    todo += [(s, args.duration, args.cache, args.auto_lead) for s in args.seeds]
    if not todo:
        ap.error("give recordings or --seeds")
    con = Console()
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        results = list(pool.map(_job, todo))
    t = Table(title=f"The sensors' stamps as they arrive: median leads (auto_lead {1000 * args.auto_lead:.0f} ms)")
    for col in ("recording", "data s", "furthest sensor", "its lead (ms)", "at (s)", "the estimate would start"):
        t.add_column(col)
    for r in results:
        w = r["worst"]
        t.add_row(r["path"], f"{r['seconds'] or 0:.0f}", w[0] if w else "-", f"{1000 * w[1]:+.1f}" if w else "-",
                  f"{w[2]:.0f}" if w else "-", f"at {r['started'][0]:.0f} s: {r['started'][1]}" if r["started"] else "no")
    con.print(t)
    n = sum(r["started"] is not None for r in results)
    con.print(f"started in {n} of {len(results)} recordings")


if __name__ == "__main__":
    main()
