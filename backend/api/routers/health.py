from __future__ import annotations

from fastapi import APIRouter

from ..deps import ServiceDep
from ..schemas import Health

router = APIRouter(tags=["status"])


@router.get("/healthz", response_model=Health, summary="liveness of the service")
async def healthz(service: ServiceDep) -> Health:
    """200 while the service runs; no authentication (for probes)."""
    s = service.active
    return Health(ok=service.started.is_set(), session=s.record.id if s else None,
                  state=s.record.state.value if s else None)
