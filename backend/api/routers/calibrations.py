"""Calibration versions: the history of accepted calibrations, and rollback."""

from __future__ import annotations

from fastapi import APIRouter, Body, Query
from fastapi.responses import Response

from ..deps import ReadAuth, ServiceDep, WriteAuth
from ..schemas import Activate, Calibration, CalibrationVersion
from .calibration import FORMAT_HELP, file_name, respond

router = APIRouter(prefix="/calibrations", tags=["calibration"])

_404 = {404: {"description": "no such version"}}


@router.get("", response_model=list[CalibrationVersion], dependencies=[ReadAuth],
            summary="all calibration versions, newest first")
async def list_versions(service: ServiceDep) -> list[dict]:
    """Every accepted calibration: a session that stopped with a result, or an activation
    (a copy of an older version). `active` marks the one GET /calibration serves."""
    return await service.list_versions()


@router.get("/{v}", response_model=Calibration, dependencies=[ReadAuth], summary="one calibration version",
            responses={200: {"content": {"application/yaml": {}}}, 400: {"description": "unknown format"}, **_404})
async def get_version(v: int, service: ServiceDep, format: str = Query("json", description=FORMAT_HELP)) -> Response:
    body, media = await service.version_view(v, format)
    return respond(body, media, file_name(f"calibration-v{v}", format, media))


@router.post("/{v}/activate", response_model=CalibrationVersion, dependencies=[WriteAuth],
             summary="make a version the active calibration",
             responses={401: {"description": "missing or wrong bearer token"}, **_404})
async def activate(v: int, service: ServiceDep, body: Activate | None = Body(None)) -> dict:
    """Records a new version, a copy of version `v`, and makes it active: GET /calibration
    serves it (unless a session runs) and it is published on `extrcal/<site>/calibration`.
    Survives restarts. Answers with the new version's metadata."""
    return await service.activate_version(v, body.reason if body else None)
