from __future__ import annotations

import asyncio

from fastapi import APIRouter, Query, Response
from fastapi.responses import JSONResponse

from ..deps import ReadAuth, ServiceDep, WriteAuth
from ..schemas import SessionCreate, SessionDetail, SessionSummary
from .calibration import FORMAT_HELP, file_name, respond

router = APIRouter(prefix="/sessions", tags=["sessions"])

_ERRORS = {
    401: {"description": "missing or wrong bearer token"},
    404: {"description": "no such session"},
    409: {"description": "another session is running"},
    422: {"description": "the camera files, the config or the body are invalid; `detail` says where"},
}


@router.post("", status_code=201, response_model=SessionDetail, dependencies=[WriteAuth],
             summary="start a session", responses={k: _ERRORS[k] for k in (401, 409, 422)})
async def create(body: SessionCreate, service: ServiceDep, response: Response) -> dict:
    """Start a calibration session; 409 while another one runs. Answers with the new
    session (its `id`), in state `waiting_for_data`. Without an initial estimate (or with
    `distrust_initial`) it bootstraps first: `bootstrap` in the session shows the phase."""
    inputs, sources = await asyncio.to_thread(
        service.make_inputs,
        texts={"intrinsics": body.intrinsics_yaml, "initial": body.initial_yaml, "reference": body.reference_yaml},
        names={"intrinsics": body.intrinsics, "initial": body.initial, "reference": body.reference},
        config=body.config,
    )
    from ...live_bootstrap import LiveOptions

    d = await service.start_session(inputs=inputs, name=body.name, stop=body.stop, overrides=body.config,
                                    sources=sources, seed=body.seed,
                                    live=LiveOptions(tuple(body.person_height or ()), body.distrust_initial))
    response.headers["Location"] = f"/sessions/{d['id']}"
    return d


@router.get("", response_model=list[SessionSummary], dependencies=[ReadAuth], summary="all sessions, newest first")
async def list_sessions(service: ServiceDep) -> list[dict]:
    return await service.list_sessions()


@router.get("/{sid}", response_model=SessionDetail, dependencies=[ReadAuth], summary="one session",
            responses={404: _ERRORS[404]})
async def get(sid: str, service: ServiceDep) -> dict:
    """State (waiting_for_data → calibrating ⇄ converged → stopped | failed) with its
    reason, and per camera: observations, pose, std, change over the last cycles,
    converged flag."""
    return await service.session_view(sid)


@router.post("/{sid}/stop", response_model=SessionDetail, dependencies=[WriteAuth], summary="stop a session",
             responses={202: {"description": "stop started (wait=false)"}, 401: _ERRORS[401], 404: _ERRORS[404]})
async def stop(sid: str, service: ServiceDep,
               wait: bool = Query(True, description="answer when the final batch adjustment is done")) -> object:
    """Ends the session: the cycle in flight completes, the final batch adjustment runs
    (in the solver process), the result is written. Stopping a finished session returns it."""
    d = await service.stop_session(sid, wait=wait)
    if not wait and d.get("live"):
        return JSONResponse(SessionDetail.model_validate(d).model_dump(mode="json"), status_code=202)
    return d


@router.get("/{sid}/result", dependencies=[ReadAuth], summary="a session's calibration",
            response_model=None,
            responses={200: {"content": {"application/json": {}, "application/yaml": {}}}, 400: {"description": "unknown format"},
                       404: _ERRORS[404]})
async def result(sid: str, service: ServiceDep, format: str = Query("json", description=FORMAT_HELP)) -> Response:
    """The session's latest (or final) calibration."""
    body, media = await service.calibration_view(sid, format)
    return respond(body, media, file_name(f"extrcal-{sid}", format, media))


@router.get("/{sid}/history", dependencies=[ReadAuth], summary="per-cycle history",
            responses={404: _ERRORS[404]})
async def history(sid: str, service: ServiceDep,
                  since: int = Query(0, ge=0, description="only cycles after this one")) -> list[dict]:
    """One object per cycle: the cycle report, per-camera std/change/converged, accuracy
    against the reference when one was given."""
    return await service.history(sid, since)
