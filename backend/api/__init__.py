"""The REST API of the live service: FastAPI app factory, routers per resource.

``create_app(settings, service)`` builds the app around a running ``Service``; with no
service it makes one and runs it with the app (``uvicorn --factory`` style use). The
OpenAPI schema at /openapi.json (browsable at /docs) is the API's documentation.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any, AsyncIterator

if TYPE_CHECKING:
    from fastapi import FastAPI

    from ..service import Service
    from ..settings import ServiceSettings

DESCRIPTION = """\
Live, marker-free extrinsic calibration of a camera network from person keypoints.

Sensors publish keypoint messages over Zenoh; a **session** turns them into camera poses.
Start one with `POST /sessions`, watch it with `GET /sessions/{id}` or the event stream
`GET /events`, stop it with `POST /sessions/{id}/stop`, fetch the result with
`GET /sessions/{id}/result` or the current calibration with `GET /calibration`.

**Convergence.** After every cycle each camera has a standard deviation (from the
filter's covariance) and a recent pose change over its last `refine.converged_cycles`
cycles. A camera is *converged* when it took part in at least that many cycles and both
its change and its std are within the thresholds below; a session is *converged* when
every camera that took part in a cycle is converged (cameras nobody saw are listed with
`cycles: 0` and do not hold it back). The thresholds are session `config` overrides;
their defaults in this build:

{thresholds}

**Authentication.** When the service has a token, state-changing endpoints (POST) need
`Authorization: Bearer <token>` (and read endpoints too with `protect_reads`).
"""


def create_app(settings: "ServiceSettings", service: "Service | None" = None) -> "FastAPI":
    from fastapi import FastAPI

    from . import errors
    from .routers import calibration, events, health, sessions, status

    lifespan = None
    if service is None:
        from ..service import Service

        own = Service(settings)

        @contextlib.asynccontextmanager
        async def lifespan(app: Any) -> AsyncIterator[None]:
            import asyncio

            task = asyncio.create_task(own.run())
            started = asyncio.ensure_future(own.started.wait())
            await asyncio.wait({task, started}, return_when=asyncio.FIRST_COMPLETED)
            if task.done():
                task.result()  # raises what stopped it
            try:
                yield
            finally:
                own.request_stop()
                await task

        service = own

    app = FastAPI(
        title="extrcal service",
        version="1",
        description=DESCRIPTION.replace("{thresholds}", _thresholds()),
        lifespan=lifespan,
        openapi_tags=[
            {"name": "sessions", "description": "calibration sessions: start, watch, stop, results"},
            {"name": "calibration", "description": "the current calibration"},
            {"name": "status", "description": "sensors, queues, cycles, health"},
            {"name": "events", "description": "live progress as server-sent events"},
        ],
    )
    app.state.service = service
    app.state.settings = settings
    errors.install(app)
    for r in (sessions, calibration, status, events, health):
        app.include_router(r.router)
    _optional_parts(app, service)
    return app


def _thresholds() -> str:
    """The engine's convergence settings, from its config model (always in step with it)."""
    from ..config import RefineConfig

    lines = []
    for name, f in RefineConfig.model_fields.items():
        if name.startswith("converged"):
            lines.append(f"- `refine.{name}` = {f.default}: {f.description or ''}")
    return "\n".join(lines)


def _optional_parts(app: "FastAPI", service: "Service") -> None:
    """The dashboard and Prometheus metrics, when this build has them."""
    import importlib

    def have(mod: str) -> bool:
        try:
            importlib.import_module(mod)
            return True
        except ModuleNotFoundError as e:
            if e.name != mod:
                raise  # the module is there but one of its imports is not: say so
            return False

    if have("backend.api.dashboard"):
        from . import dashboard

        app.include_router(dashboard.router)
    if have("backend.metrics"):
        from .. import metrics

        m = metrics.Metrics()
        metrics.mount(app, m, refresh=lambda: metrics.update_from_state(m, service.active_state(), service.status()))
        service.cycle_listeners.append(lambda sid, report, wall: metrics.observe_cycle(m, report, wall, session=sid))
        app.state.metrics = m
