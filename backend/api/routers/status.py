from __future__ import annotations

from fastapi import APIRouter

from ..deps import ReadAuth, ServiceDep
from ..schemas import Status

router = APIRouter(tags=["status"], dependencies=[ReadAuth])


@router.get("/status", response_model=Status, summary="sensors, queues, cycles")
async def status(service: ServiceDep) -> dict:
    """Per sensor: online (liveliness), last seen, rate, latency (arrival − stamp), clock
    offset estimate, rejected messages by reason. Framesets accepted and rejected by
    reason, queue lengths and drops, cycle times, event-loop lag."""
    return service.status()
