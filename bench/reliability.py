"""Reliability bench: fuzzed payloads through the live ingest path, and kill -9 restarts.

    python bench/reliability.py                    # >= 100,000 fuzzed payloads
    python bench/reliability.py --payloads 20000
    python bench/reliability.py --crash 20         # kill -9 `extrcal serve` 20 times

Fuzz: the strategies of tests/backend/test_fuzz_ingest.py (hypothesis), batches of bad
payloads with good messages at random places, through ``Service._ingest_one`` of a real
service (Zenoh on loopback, uvicorn, a session on three lab cameras). Every batch is
accounted for (rejected by reason + accepted + ignored = sent), and every good message
must be taken. Prints payloads tried, rejections by reason, crashes, time.

Crash: a real ``extrcal serve`` subprocess with simulated sensors (their own process and
Zenoh peer) feeding a session; at random moments SIGKILL, then every file of the session
is parsed (session/config/state/snapshot JSON, result YAML, history lines), the daemon
restarted, and the session must resume from the snapshot's cycle and go on.
Prints one row per kill and a summary. Exit status 1 on any failure.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _load(rel: str, name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / rel)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def lab_dir() -> Path:
    for p in (REPO.parent / "shared" / "data" / "ais_lab20", REPO / "edge_clients" / "data" / "ais_lab20"):
        if (p / "intrinsics.yaml").is_file():
            return p
    raise SystemExit("the 20-camera lab (shared/data/ais_lab20) is not beside the checkout")


# ------------------------------------------------------------------ fuzz


def fuzz(payloads: int, batch: int) -> dict:
    import itertools

    import httpx
    import numpy as np
    import yaml
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from backend.cameras import dump_extrinsics, load_extrinsics
    from backend.server import ServiceThread
    from proto.transport import free_port
    from backend.settings import ServiceSettings

    fz = _load("tests/backend/test_fuzz_ingest.py", "fuzz_strategies")
    lab = lab_dir()
    intr = yaml.safe_load((lab / "intrinsics.yaml").read_text())
    ref = load_extrinsics(lab / "reference.yaml")
    body = {"intrinsics_yaml": yaml.safe_dump({c: intr[c] for c in fz.CAMS}),
            "initial_yaml": dump_extrinsics({c: ref[c] for c in fz.CAMS})}
    totals = {"sent": 0, "good": 0, "batches": 0, "failures": []}
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        s = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0},
                                 zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)},
                                 state_dir=Path(tmp), token=fz.TOKEN, site=fz.SITE)
        with ServiceThread(s) as svc:
            r = httpx.post(svc.url + "/sessions", json=body, headers={"Authorization": f"Bearer {fz.TOKEN}"}, timeout=30)
            assert r.status_code == 201, r.text
            svc.resolutions = {c: tuple(intr[c]["resolution"]) for c in fz.CAMS}
            svc.good_seq = itertools.count(1)
            start = svc.call(lambda: fz.counts(svc.service))

            def one(data):
                rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
                bad = data.draw(st.lists(fz.bad_payload(svc.resolutions), min_size=1, max_size=batch))
                items = [(c, spec, False) for c, spec in bad]
                for _ in range(data.draw(st.integers(1, 4))):
                    cam = data.draw(st.sampled_from(fz.CAMS))
                    items.insert(data.draw(st.integers(0, len(items))), (cam, fz.good_message(svc, cam, rng), True))
                before, after, good = fz.run_batch(svc, items)
                try:
                    fz.check_accounting(before, after, good, len(items))
                except AssertionError as e:
                    totals["failures"].append(repr(e)[:200])
                totals["sent"] += len(items)
                totals["good"] += sum(good.values())
                totals["batches"] += 1
                if totals["batches"] % 500 == 0:
                    print(f"  {totals['sent']} payloads, {time.monotonic() - t0:.0f} s", flush=True)

            while totals["sent"] < payloads:  # runs of at most 2000 batches, until enough were sent
                left = max(1, min(2000, int((payloads - totals["sent"]) / (batch / 2 + 3)) + 1))
                settings(max_examples=left, deadline=None, database=None, derandomize=False,
                         suppress_health_check=list(HealthCheck))(given(data=st.data())(one))()
            end = svc.call(lambda: fz.counts(svc.service))
            status = httpx.get(svc.url + "/status", timeout=30).json()
            alive = httpx.get(svc.url + "/healthz", timeout=30).json().get("ok")
    totals["seconds"] = time.monotonic() - t0
    totals["rejected"] = end["rejected"] - start["rejected"]
    totals["accepted"] = sum(end["accepted"].values()) - sum(start["accepted"].values())
    totals["status_rejected_total"] = sum(status["messages"]["rejected"].values())
    totals["alive"] = bool(alive)
    return totals


def print_fuzz(t: dict) -> None:
    print()
    print("| payloads tried | good among them | accepted | rejected | accounting failures | service alive | seconds |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {t['sent']} | {t['good']} | {t['accepted']} | {sum(t['rejected'].values())} | {len(t['failures'])} "
          f"| {'yes' if t['alive'] else 'NO'} | {t['seconds']:.0f} |")
    print()
    print("| rejected by reason | count |")
    print("|---|---|")
    for reason, n in sorted(t["rejected"].items(), key=lambda x: -x[1]):
        print(f"| {reason} | {n} |")
    for f in t["failures"][:5]:
        print("failure:", f)


# ------------------------------------------------------------------ crash


def check_files(d: Path) -> dict:
    """Parse every file of a session directory; raises on a truncated or half-written one."""
    from backend.cameras import parse_extrinsics

    out = {}
    for name in ("session.json", "config.json", "state.json", "snapshot.json"):
        p = d / name
        if p.exists():
            out[name] = json.loads(p.read_text())  # a half-written file does not parse
    if (d / "result.yaml").exists():
        out["result.yaml"] = parse_extrinsics((d / "result.yaml").read_text(), "result.yaml")
    lines = (d / "history.jsonl").read_text().split("\n") if (d / "history.jsonl").exists() else []
    torn = 0
    for i, line in enumerate(lines):
        if not line:
            continue
        try:
            json.loads(line)
        except ValueError:
            if i != len(lines) - 1:  # only the very last line may be torn by a crash (append-only)
                raise ValueError(f"history.jsonl line {i + 1} is broken and not the last") from None
            torn += 1
    out["torn_history_lines"] = torn
    out["history_lines"] = sum(1 for x in lines if x)
    return out


class Daemon:
    def __init__(self, state: Path, http_port: int, endpoint: str, site: str):
        self.args = [sys.executable, "-m", "backend.cli", "serve", "--http", f"127.0.0.1:{http_port}",
                     "--zenoh-listen", endpoint, "--state-dir", str(state), "--site", site, "--clock", "data",
                     "--log-level", "warning"]
        self.log = state / "serve.log"
        self.proc: subprocess.Popen | None = None

    def start(self, client, timeout: float = 90) -> None:
        import httpx

        env = {k: v for k, v in os.environ.items() if not k.startswith("EXTRCAL_")}
        with open(self.log, "a") as out:
            self.proc = subprocess.Popen(self.args, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=REPO)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"extrcal serve exited with {self.proc.returncode}: {self.log.read_text()[-2000:]}")
            try:
                if client.get("/healthz").json().get("ok"):
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError("extrcal serve did not start")

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def _poll(client, path: str, pred, timeout: float, what: str) -> dict:
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = client.get(path).json()
            if pred(last):
                return last
        except Exception:  # noqa: BLE001 - the daemon may be between lives
            pass
        time.sleep(0.2)
    raise AssertionError(f"{what} (last: {str(last)[:300]})")


def crash(kills: int, seed: int = 0, state: Path | None = None, out=print) -> list[dict]:
    """kill -9 the daemon ``kills`` times at random moments; returns one row per kill."""
    import httpx

    from proto.transport import free_port

    live = _load("tests/integration/test_service_live.py", "live_helpers")
    rnd = random.Random(seed)
    lab = lab_dir()
    state = state or Path(tempfile.mkdtemp(prefix="extrcal-crash-"))
    http_port, zport = free_port(), free_port()
    endpoint, site = f"tcp/127.0.0.1:{zport}", "crash"
    client = httpx.Client(base_url=f"http://127.0.0.1:{http_port}", timeout=30)
    daemon = Daemon(state, http_port, endpoint, site)
    rows: list[dict] = []
    try:
        daemon.start(client)
        with live.Sensors(endpoint, site, lab, seed=seed + 2, duration=3600.0):
            sid = client.post("/sessions", json={**live._session_body(lab), "stop": {"duration": 36000}}).json()["id"]
            d = state / "sessions" / sid
            _poll(client, f"/sessions/{sid}", lambda s: s["cycles"] >= 1, 120, "no first cycle")
            for k in range(1, kills + 1):
                t0 = time.monotonic()
                time.sleep(rnd.uniform(0.0, 3.0))  # a random moment: mid-cycle, mid-write, idle
                daemon.kill()
                files = check_files(d)
                snap_cycle = files["snapshot.json"]["cycle"] if "snapshot.json" in files else 0
                daemon.start(client)
                s = client.get(f"/sessions/{sid}").json()
                ok = bool(s["live"] and s["resumed"] == k and s["cycles"] == snap_cycle
                          and f"resumed at cycle {snap_cycle}" in s["reason"])
                hist = client.get(f"/sessions/{sid}/history").json()
                ok = ok and all(int(h["cycle"]) <= snap_cycle for h in hist)
                # it goes on from there
                _poll(client, f"/sessions/{sid}", lambda s: s["cycles"] > snap_cycle, 120,
                      f"kill {k}: the resumed session did not go on")
                rows.append({"kill": k, "resumed_at": snap_cycle, "history_lines": files["history_lines"],
                             "torn_history": files["torn_history_lines"], "resumed_ok": ok,
                             "seconds": time.monotonic() - t0})
                out(f"kill {k:3d}: resumed at cycle {snap_cycle:4d}, history {files['history_lines']:4d} lines "
                    f"(torn last line: {files['torn_history_lines']}), resume {'ok' if ok else 'WRONG: ' + str(s)[:200]}")
                if not ok:
                    break
        daemon.stop()
        check_files(d)
    finally:
        if daemon.proc is not None and daemon.proc.poll() is None:
            daemon.proc.kill()
            daemon.proc.wait(10)
        client.close()
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--payloads", type=int, default=100_000)
    ap.add_argument("--batch", type=int, default=40, help="bad payloads per batch at most")
    ap.add_argument("--crash", type=int, default=0, help="kill -9 the daemon this many times instead of fuzzing")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if a.crash:
        t0 = time.monotonic()
        try:
            rows = crash(a.crash, a.seed)
        except Exception as e:  # noqa: BLE001 - reported as the bench's result
            print(f"FAILED: {type(e).__name__}: {e}")
            return 1
        good = sum(r["resumed_ok"] for r in rows)
        print()
        print("| kills | resumed from the last persisted cycle | files unparseable | torn last history line | minutes |")
        print("|---|---|---|---|---|")
        print(f"| {len(rows)} | {good} | 0 | {sum(r['torn_history'] for r in rows)} | {(time.monotonic() - t0) / 60:.1f} |")
        return 0 if good == a.crash else 1
    t = fuzz(a.payloads, a.batch)
    print_fuzz(t)
    return 0 if not t["failures"] and t["alive"] and t["sent"] >= a.payloads else 1


if __name__ == "__main__":
    sys.exit(main())
