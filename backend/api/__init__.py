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
Every accepted calibration is a version (`GET /calibrations`); `POST
/calibrations/{v}/activate` rolls back to one.

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
    from .routers import calibration, calibrations, events, health, sessions, status

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
    app.add_middleware(BodyLimit, limit=MAX_BODY)
    errors.install(app)
    for r in (sessions, calibration, calibrations, status, events, health):
        app.include_router(r.router)
    _optional_parts(app, service)
    return app


def _read_protected(inner: Any, app: "FastAPI") -> Any:
    """An ASGI endpoint behind the read token (``protect_reads``), like the API's reads."""
    import secrets

    class Endpoint:  # a class instance: Starlette serves it as an ASGI app, not as a request handler
        async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
            settings = app.state.settings
            token = settings.token_value()
            if settings.protect_reads and token is not None:
                got = dict(scope.get("headers", ())).get(b"authorization", b"")
                if not secrets.compare_digest(got, b"Bearer " + token.encode()):
                    body = b'{"detail": "this endpoint needs \'Authorization: Bearer <token>\'"}'
                    await send({"type": "http.response.start", "status": 401, "headers": [
                        (b"content-type", b"application/json"), (b"www-authenticate", b"Bearer"),
                        (b"content-length", str(len(body)).encode())]})
                    await send({"type": "http.response.body", "body": body})
                    return
            await inner(scope, receive, send)

    return Endpoint()


MAX_BODY = 8 * 1024 * 1024  # bytes: camera files of a few hundred cameras fit many times over


class BodyLimit:
    """413 for request bodies over ``limit`` bytes, by Content-Length or while streaming
    (chunked uploads have none): an oversized upload must not fill the service's memory."""

    def __init__(self, app: Any, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        cl = next((v for k, v in scope.get("headers", ()) if k == b"content-length"), None)
        if cl is not None:
            try:
                n = int(cl)
            except ValueError:
                return await self._refuse(send, "Content-Length is not a number")
            if n > self.limit:
                return await self._refuse(send, f"request body of {n} bytes is over the limit of {self.limit}")
        elif scope.get("method") in ("POST", "PUT", "PATCH"):  # chunked: read up to the limit here, then hand it on
            chunks, seen, more = [], 0, True
            while more:
                msg = await receive()
                if msg["type"] != "http.request":
                    return  # the client went away
                chunks.append(msg.get("body", b""))
                seen += len(chunks[-1])
                more = msg.get("more_body", False)
                if seen > self.limit:
                    return await self._refuse(send, f"request body over the limit of {self.limit} bytes")
            body, sent = b"".join(chunks), False

            async def replay() -> Any:
                nonlocal sent
                if not sent:
                    sent = True
                    return {"type": "http.request", "body": body, "more_body": False}
                return await receive()

            return await self.app(scope, replay, send)
        await self.app(scope, receive, send)

    @staticmethod
    async def _refuse(send: Any, why: str) -> None:
        import json

        body = json.dumps({"detail": f"{why}: send smaller camera files (or name files configured on the "
                                     f"server in camera_files)"}).encode()
        status = 413 if "limit" in why else 400
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


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
        from starlette.routing import Route

        scrape = metrics.asgi_app(m, lambda: metrics.update_from_state(m, service.active_state(), service.status()))
        # not metrics.mount(): with protect_reads the scrape needs the token as well (Prometheus
        # sends it with `authorization: {credentials: ...}`); sensor names and progress are reads
        app.router.routes.append(Route("/metrics", endpoint=_read_protected(scrape, app), methods=["GET", "HEAD"],
                                       include_in_schema=False))
        service.cycle_listeners.append(lambda sid, report, wall: metrics.observe_cycle(m, report, wall, session=sid))
        app.state.metrics = m
