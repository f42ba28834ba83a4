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
) -> None:
    """Run the live calibration service: Zenoh ingest, pipeline, REST API, sessions.

    Settings come from --config, EXTRCAL_* environment variables and these flags (highest).
    Sessions are started over HTTP (POST /sessions); see /docs for the API."""
    import asyncio
    import logging

    from .service import serve as run

    settings = _settings(config, http, zenoh_listen, zenoh_connect, zenoh_mode, site, state_dir, token, clock)
    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")

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
    from .demo import run_demo

    try:
        run_demo(speed=speed, duration=duration, http=http, persons=persons, translation=translation,
                 rotation=rotation, seed=seed, state_dir=state_dir, until_converged=until_converged)
    except (OSError, ValueError) as e:
        raise fail(str(e))
