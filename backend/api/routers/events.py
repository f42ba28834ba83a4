from __future__ import annotations

import asyncio
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse

from ...events import EventBus
from ...session import dumps_json
from ..deps import ReadAuth, ServiceDep

router = APIRouter(tags=["events"], dependencies=[ReadAuth])

KEEPALIVE = 15.0  # s between comment lines, so proxies keep the stream open

# what the service publishes; ``hello`` opens every stream
EventKind = Literal[tuple(sorted(EventBus.KINDS))]  # type: ignore[valid-type]


@router.get("/events", summary="live progress (server-sent events)",
            response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}},
                             "description": "events `hello` (current status), `status` (every second), "
                                            "`cycle` (after every cycle), `session` (state changes), `service`, "
                                            "`camera_moved` (the monitor flagged a converged camera), "
                                            "`camera_restarted` (a camera started over from a pose found elsewhere: "
                                            "a dispute adjustment or a re-localisation), `calibration` "
                                            "(a version was recorded by the monitor or activated), `hypotheses` "
                                            "(the persons of a cycle, for the dashboard)"}})
async def events(service: ServiceDep, request: Request,
                 kind: Annotated[list[EventKind] | None, Query(
                     description="only these kinds (repeatable; default all): a client waiting for alarms "
                                 "(`?kind=camera_moved&kind=calibration`) then loses none of them to the flood of "
                                 "`cycle` and `hypotheses`")] = None) -> StreamingResponse:
    """Server-sent events, one JSON object per `data:` line. A slow client loses its
    oldest events; `dropped` in the next event says how many."""
    kinds = frozenset(kind) if kind else None

    async def stream():
        async with service.events.subscribe(kinds) as q:
            yield _frame(0, "hello", service.status_brief())
            while True:
                try:
                    item = await asyncio.wait_for(q.get(), KEEPALIVE)
                except TimeoutError:
                    if await request.is_disconnected():
                        return
                    yield ": keepalive\n\n"
                    continue
                if item is None:  # the service is shutting down
                    return
                eid, kind, data = item
                if q.dropped:
                    data = {**data, "dropped": q.dropped}
                    q.dropped = 0
                yield _frame(eid, kind, data)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def _frame(eid: int, kind: str, data: dict) -> str:
    return f"id: {eid}\nevent: {kind}\ndata: {dumps_json(data)}\n\n"



