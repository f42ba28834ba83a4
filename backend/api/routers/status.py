from __future__ import annotations

import json

from fastapi import APIRouter, Request, Response

from ..deps import ReadAuth, ServiceDep
from ..schemas import Status

router = APIRouter(tags=["status"], dependencies=[ReadAuth])


@router.get("/status", response_model=Status, summary="sensors, queues, cycles")
async def status(service: ServiceDep, request: Request) -> Response:
    """Per sensor: online (liveliness), last seen, rate, latency (arrival − stamp), clock
    offset estimate, rejected messages by reason. Framesets accepted and rejected by
    reason, queue lengths and drops, cycle times, event-loop lag. Answered within tens of
    milliseconds even when the service is overloaded: then it is the status the service
    last published (at most about a second old; ``as_of`` says when it was made)."""
    d = await service.status_view()
    # under overload the same snapshot is served many times: serialise it once
    cached = getattr(request.app.state, "status_json", None)
    if cached is None or cached[0] is not d:
        cached = request.app.state.status_json = (d, json.dumps(d, separators=(",", ":")).encode())
    return Response(cached[1], media_type="application/json")
