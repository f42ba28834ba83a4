from __future__ import annotations

from fastapi import APIRouter, Query
from fastapi.responses import JSONResponse, Response

from ..deps import ReadAuth, ServiceDep
from ..schemas import Calibration

router = APIRouter(tags=["calibration"], dependencies=[ReadAuth])

FORMAT_HELP = ("json (default), yaml (the FORMATS.md extrinsics with per-camera std), or an export "
               "format of `extrcal export` (ais, opencv, pose2sim, kalibr, colmap...) when available")


def respond(body: object, media_type: str, filename: str | None = None) -> Response:
    if isinstance(body, dict):
        return JSONResponse(body)
    headers = {"Content-Disposition": f'attachment; filename="{filename}"'} if filename else None
    return Response(body, media_type=media_type, headers=headers)


def file_name(stem: str, fmt: str, media_type: str) -> str | None:
    if fmt == "json":
        return None
    ext = {"application/yaml": "yaml", "application/zip": "zip", "application/toml": "toml",
           "application/json": "json"}.get(media_type.split(";")[0], "txt")
    return f"{stem}.{ext}" if fmt in ("yaml", "ais") else f"{stem}-{fmt}.{ext}"


@router.get("/calibration", response_model=Calibration, summary="the current calibration",
            responses={200: {"content": {"application/yaml": {}}}})
async def calibration(service: ServiceDep, format: str = Query("json", description=FORMAT_HELP)) -> Response:
    """The running session's latest estimate, or the last finished session's result."""
    body, media = await service.calibration_view(None, format)
    return respond(body, media, file_name("calibration", format, media))
