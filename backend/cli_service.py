"""`extrcal serve` (the live service) and `extrcal demo` (service + simulated lab)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .cli import fail


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(demo)


def _settings(config: Path | None, http: str | None, zenoh_listen: list[str] | None,
              zenoh_connect: list[str] | None, zenoh_mode: str | None, site: str | None,
              state_dir: Path | None, token: str | None, clock: str | None = None, speed: float | None = None):
    from .settings import ServiceSettings, SettingsError, parse_hostport

    try:
        host_port = parse_hostport(http) if http else None
        return ServiceSettings.load(
            config,
            http={"host": host_port[0], "port": host_port[1]} if host_port else None,
            zenoh={"listen": tuple(zenoh_listen) if zenoh_listen else None,
                   "connect": tuple(zenoh_connect) if zenoh_connect else None,
                   "mode": zenoh_mode},
            site=site, state_dir=state_dir, token=token, clock=clock, speed=speed,
        )
    except SettingsError as e:
        raise fail(str(e))


def serve(
    config: Annotated[Optional[Path], typer.Option("--config", help="service TOML (see docs/service.md)")] = None,
    http: Annotated[Optional[str], typer.Option(help="HOST:PORT of the REST API [127.0.0.1:8000]")] = None,
    zenoh_listen: Annotated[Optional[list[str]], typer.Option("--zenoh-listen", help="Zenoh endpoint to listen on (repeatable) [tcp/127.0.0.1:7447]")] = None,
    zenoh_connect: Annotated[Optional[list[str]], typer.Option("--zenoh-connect", help="Zenoh endpoint to connect to (repeatable)")] = None,
    zenoh_mode: Annotated[Optional[str], typer.Option("--zenoh-mode", help="peer | client | router [peer]")] = None,
    site: Annotated[Optional[str], typer.Option(help="site name in the key expressions [default]")] = None,
    state_dir: Annotated[Optional[Path], typer.Option("--state-dir", help="sessions, results, history [./extrcal-state]")] = None,
    token: Annotated[Optional[str], typer.Option(help="bearer token for POST endpoints (required off loopback)", envvar=None)] = None,
    clock: Annotated[Optional[str], typer.Option(help="wall (NTP-synchronised sensors) | data (replays, simulations)")] = None,
    log_level: Annotated[str, typer.Option(help="debug | info | warning | error")] = "info",
    log_format: Annotated[str, typer.Option(help="text | json (one object per line, for log collectors)")] = "text",
) -> None:
    """Run the live calibration service: Zenoh ingest, pipeline, REST API, sessions.

    Settings come from --config, EXTRCAL_* environment variables and these flags (highest).
    Sessions are started over HTTP (POST /sessions); see /docs for the API."""
    import asyncio

    from .server import serve as run

    settings = _settings(config, http, zenoh_listen, zenoh_connect, zenoh_mode, site, state_dir, token, clock)
    from .logs import setup as setup_logging

    try:
        setup_logging(log_level, log_format)
    except ValueError as e:
        raise fail(str(e))

    def started(service) -> None:
        host, port = service.http_address
        typer.echo(f"extrcal service on http://{_url_host(host)}:{port} (API docs /docs), "
                   f"Zenoh {settings.zenoh.mode} {', '.join(settings.zenoh.listen or settings.zenoh.connect)}, "
                   f"site {settings.site}, state in {settings.state_dir}", err=True)
        if service.active is not None:
            typer.echo(f"resumed session {service.active.record.id}", err=True)

    try:
        asyncio.run(run(settings, on_started=started, log_level="warning" if log_level != "debug" else "info"))
    except OSError as e:
        raise fail(str(e))
    typer.echo("extrcal service stopped", err=True)


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def demo(
    speed: Annotated[float, typer.Option(help="simulated seconds per real second")] = 1.0,
    duration: Annotated[float, typer.Option(help="simulated seconds to run at most")] = 180.0,
    http: Annotated[str, typer.Option(help="HOST:PORT of the REST API")] = "127.0.0.1:8000",
    persons: Annotated[int, typer.Option(help="people walking in the lab")] = 2,
    translation: Annotated[float, typer.Option(help="m the initial estimate is off per camera")] = 0.25,
    rotation: Annotated[float, typer.Option(help="deg the initial estimate is off per camera")] = 10.0,
    seed: int = 0,
    state_dir: Annotated[Optional[Path], typer.Option("--state-dir", help="where sessions go [a temporary directory]")] = None,
    until_converged: Annotated[bool, typer.Option(help="end as soon as the session converges")] = True,
) -> None:
    """The 20-camera lab end to end on this machine: simulated sensors publish over Zenoh
    (loopback), the service calibrates from a perturbed initial estimate, and a table
    compares the result with the simulator's truth."""
    try:
        run_demo(speed=speed, duration=duration, http=http, persons=persons, translation=translation,
                 rotation=rotation, seed=seed, state_dir=state_dir, until_converged=until_converged)
    except (OSError, ValueError) as e:
        raise fail(str(e))


# ------------------------------------------------------------------ the demo

def lab_dir() -> Path:
    """The 20-camera lab shipped with the package (edge_clients/data/ais_lab20)."""
    import edge_clients

    return Path(edge_clients.__file__).parent / "data" / "ais_lab20"


def publish_simulation(endpoint: str, site: str, persons: int, duration: float, seed: int, speed: float,
                       sensors: list[str] | None, ready, stop, lab: str, rate: tuple[float, float] | None = None) -> None:
    """Simulated sensors of the lab on their own Zenoh peer, paced at ``speed`` × real time.

    Runs in its own process: simulating 20 cameras takes most of a core, which the
    service's loop must not share. ``ready``/``stop`` are multiprocessing events.
    """
    import signal
    import time as _time

    from edge_clients.publisher import SensorPublisher, zenoh_session

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the demo, which stops us via `stop`
    from edge_clients.sim import Scene, SimConfig, Simulator
    from proto.transport import ZenohSettings

    kw = {"rates": rate} if rate else {}
    sim = Simulator(Scene.load(lab), SimConfig(persons=persons, duration=duration, seed=seed, **kw))
    names = list(sensors or sim.scene.names)
    with zenoh_session(ZenohSettings(mode="peer", connect=(endpoint,))) as zs, \
            SensorPublisher(zs, site, block=True) as pub:
        pub.wait_matched(names, timeout=30.0, stop=stop)
        ready.set()
        t0 = a0 = None
        for arrival, msg in sim.messages(sensors):
            if stop.is_set():
                break
            if t0 is None:
                t0, a0 = _time.monotonic(), arrival
            delay = t0 + (arrival - a0) / speed - _time.monotonic()
            if delay > 0:
                if stop.wait(delay):
                    break
            pub.publish(msg)


def run_demo(*, speed: float, duration: float, http: str, persons: int, translation: float, rotation: float,
             seed: int, state_dir: Path | None, until_converged: bool, out=None) -> dict:
    """Service + simulated lab + a session from a perturbed start; returns the final session."""
    import multiprocessing
    import sys
    import tempfile

    import httpx

    from .cameras import dump_extrinsics, load_extrinsics
    from .evaluate import evaluate
    from .perturb import perturb_extrinsics
    from .server import ServiceThread
    from proto.transport import free_port
    from .settings import ServiceSettings, parse_hostport

    out = out or sys.stdout
    if speed <= 0 or duration <= 0:
        raise ValueError("--speed and --duration must be positive")
    lab = lab_dir()
    host, port = parse_hostport(http)
    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    state = Path(state_dir) if state_dir else Path(tempfile.mkdtemp(prefix="extrcal-demo-"))
    settings = ServiceSettings.load(None, http={"host": host, "port": port}, zenoh={"listen": (endpoint,)},
                                    state_dir=state, site="demo", clock="data", speed=speed)
    ref = load_extrinsics(lab / "reference.yaml")
    initial = perturb_extrinsics(ref, translation, rotation, seed=seed)
    truth = {k: v.pose for k, v in ref.items()}

    ctx = multiprocessing.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    with ServiceThread(settings) as st:
        url = st.url
        print(f"extrcal demo: 20-camera lab, {persons} people, {speed:g}x real time, at most {duration:g} s "
              f"of simulated time", file=out)
        print(f"service: {url}/status  (API docs {url}/docs, live events {url}/events)", file=out)
        print(f"state directory: {state}", file=out)
        proc = ctx.Process(target=publish_simulation, name="simulated-sensors",
                           args=(endpoint, "demo", persons, duration + 5.0, seed, speed, None, ready, stop, str(lab)))
        proc.start()
        client = httpx.Client(base_url=url, timeout=60)
        try:
            if not ready.wait(120):
                raise OSError("the simulated sensors did not connect to the service")
            init_err = evaluate({k: v.pose for k, v in initial.items()}, truth)
            r = client.post("/sessions", json={
                "name": "demo", "intrinsics_yaml": (lab / "intrinsics.yaml").read_text(),
                "initial_yaml": dump_extrinsics(initial), "reference_yaml": (lab / "reference.yaml").read_text(),
                "stop": {"duration": duration, "converged": until_converged}, "seed": seed,
                # Network and processing delays are wall time: at K x speed they are K times
                # longer in data time, and the framesets must wait for them that much longer.
                "config": {"sync": {"wait": 0.25 * max(speed, 1.0)}},
            })
            r.raise_for_status()
            sid = r.json()["id"]
            print(f"session {sid}: {url}/sessions/{sid}", file=out)
            session = _follow(client, sid, proc, out)
            if session["state"] not in ("stopped", "failed"):
                session = client.post(f"/sessions/{sid}/stop").json()
        except KeyboardInterrupt:
            print("\ninterrupted: stopping the session", file=out)
            session = client.post(f"/sessions/{sid}/stop").json() if "sid" in locals() else {}
        finally:
            stop.set()
            proc.join(30)
            if proc.is_alive():
                proc.terminate()
            client.close()
    if session:
        _result_table(session, truth, init_err, out)
    return session


def _follow(client, sid: str, proc, out) -> dict:
    """A live progress line until the session ends or the simulation runs out."""
    import time

    tty = hasattr(out, "isatty") and out.isatty()
    last_print = 0.0
    while True:
        s = client.get(f"/sessions/{sid}").json()
        st = client.get("/status").json()
        if s["state"] in ("stopped", "failed"):
            break
        if not proc.is_alive() and not st["queues"]["ingest"]["length"]:
            # the simulation is over: give the pipeline a moment for the last framesets
            time.sleep(1.0)
            s = client.get(f"/sessions/{sid}").json()
            break
        line = _progress(s, st)
        now = time.monotonic()
        if tty:
            print("\r" + line[:150].ljust(150), end="", file=out, flush=True)
        elif now - last_print > 5:
            print(line, file=out, flush=True)
            last_print = now
        time.sleep(0.5)
    if tty:
        print(file=out)
    return s


def _progress(s: dict, st: dict) -> str:
    cams = s.get("cameras") or []
    conv = sum(1 for c in cams if c["converged"])
    first = s.get("first_data")
    clock = st["clock"]["now"]
    t = (clock - first) if first and clock else 0.0
    acc = s.get("accuracy") or {}
    rate = sum(x["rate"] for x in st["sensors"].values())
    err = (f"error {acc['position_mean']:.3f} m / {acc['orientation_mean']:.2f}°"
           if acc.get("position_mean") is not None else "error -")
    return (f"t {t:6.1f} s  {s['state']:<16} cycle {s.get('cycles') or 0:4d}  converged {conv:2d}/{len(cams)}  "
            f"{err}  {rate:5.0f} msg/s")


def _result_table(session: dict, truth: dict, init_err, out) -> None:
    from rich.console import Console
    from rich.table import Table

    from .cameras import Pose, natural_key
    from .evaluate import evaluate

    cams = {c["name"]: c for c in session.get("cameras", [])}
    if not cams:
        print(f"session {session.get('id')}: {session.get('state')} ({session.get('reason')})", file=out)
        return
    res = {n: Pose.from_quat(c["translation"], c["rotation"]) for n, c in cams.items()}
    acc = evaluate(res, truth)
    t = Table(title=f"session {session['id']}: {session['state']} ({session['reason']})")
    for col in ("camera", "position error m", "orientation error °", "std m", "std °", "observations", "converged"):
        t.add_column(col, justify="right")
    for n in sorted(cams, key=natural_key):
        c = cams[n]
        p, o, _, _ = acc.per_camera[n]
        t.add_row(n, f"{p:.4f}", f"{o:.3f}", f"{c['std_translation'] or 0:.4f}", f"{c['std_rotation'] or 0:.3f}",
                  str(c["observations"]), "yes" if c["converged"] else "no")
    Console(file=out, width=120).print(t)
    print(f"initial estimate: {init_err.summary()}", file=out)
    print(f"result:           {acc.summary()}", file=out)
    print(f"cycles: {session.get('cycles')}, converged at cycle {session.get('converged_cycle')}", file=out)
    scale = session.get("scale") or {}
    if scale.get("summary"):
        print(scale["summary"], file=out)
