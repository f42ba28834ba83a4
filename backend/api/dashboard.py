"""The operator dashboard: one page at `/`, its assets, and the camera files it draws.

Everything ships in the package (backend/static/): no CDN, the page works on networks
without internet. The page reads the service's public API (/status, /sessions,
/sessions/{id}, /sessions/{id}/history, /events, POST /sessions, POST /sessions/{id}/stop)
and one endpoint of its own, ``GET /dashboard/api/sessions/{id}/cameras``: the session's
initial estimate, reference and intrinsics, to draw frusta of the right shape.

Mount with ``app.include_router(dashboard.router)`` (docs/dashboard.md).
"""

from __future__ import annotations

from importlib import resources
from typing import Any

from fastapi import APIRouter, HTTPException
from fastapi.responses import HTMLResponse, Response

from ..cameras import CameraFileError, parse_extrinsics, parse_intrinsics
from .deps import ReadAuth, ServiceDep

router = APIRouter(tags=["dashboard"])

_STATIC = resources.files("backend") / "static"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png",
          ".ico": "image/x-icon"}
# Assets are looked up in this fixed list, never by joining a path from the request.
ASSETS = {p.name: p for p in _STATIC.iterdir() if p.is_file() and "." + p.name.rsplit(".", 1)[-1] in _TYPES}
_NO_CACHE = {"Cache-Control": "no-cache"}  # a service upgrade must not leave an old page behind


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
async def index() -> HTMLResponse:
    return HTMLResponse(ASSETS["index.html"].read_text(encoding="utf-8"), headers=_NO_CACHE)


@router.get("/dashboard/{name}", include_in_schema=False)
async def asset(name: str) -> Response:
    p = ASSETS.get(name)
    if p is None:
        raise HTTPException(404, f"no dashboard asset {name!r}")
    return Response(p.read_bytes(), media_type=_TYPES["." + name.rsplit(".", 1)[-1]], headers=_NO_CACHE)


@router.get("/dashboard/api/sessions/{sid}/cameras", dependencies=[ReadAuth],
            summary="a session's camera files, for drawing (dashboard)")
async def session_cameras(sid: str, service: ServiceDep) -> dict[str, Any]:
    """The initial estimate, the reference (null if none) and the intrinsics of a session
    as JSON: poses as `translation` (optical centre) and `rotation` (world_R_cam
    quaternion x, y, z, w); intrinsics as fx, fy, cx, cy at width × height."""
    service.store.load_record(sid)  # 404 for unknown or malformed ids
    d = service.store.dir(sid)
    out: dict[str, Any] = {"initial": None, "reference": None, "intrinsics": None}
    try:
        for key in ("initial", "reference"):
            p = d / f"{key}.yaml"
            if p.is_file():
                ext = parse_extrinsics(p.read_text(), f"session {sid} {key}.yaml")
                out[key] = {n: {"translation": e.pose.t.tolist(), "rotation": e.pose.quat.tolist()}
                            for n, e in ext.items()}
        p = d / "intrinsics.yaml"
        if p.is_file():
            out["intrinsics"] = {n: {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy,
                                     "width": i.resolution[0], "height": i.resolution[1]}
                                 for n, i in parse_intrinsics(p.read_text(), f"session {sid} intrinsics.yaml").items()}
    except (OSError, CameraFileError) as e:
        raise HTTPException(500, f"session {sid}: stored camera files are unreadable: {e}") from None
    return out
