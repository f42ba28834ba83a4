"""Dependencies: the service, and the bearer token on state-changing (and protected) routes."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ..service import Service
from .errors import Unauthorized

_bearer = HTTPBearer(auto_error=False, description="the service's token (settings `token`)")


# async, though nothing here awaits: FastAPI runs a plain ``def`` dependency in its thread
# pool, two thread hand-offs per request, each waiting for the GIL behind a saturated
# service loop (bench/overload.py: /status p99).
async def get_service(request: Request) -> Service:
    return request.app.state.service


def _check(request: Request, cred: HTTPAuthorizationCredentials | None) -> None:
    token = request.app.state.settings.token_value()
    if token is None:
        return
    if cred is None:
        raise Unauthorized("this endpoint needs 'Authorization: Bearer <token>'")
    if not secrets.compare_digest(cred.credentials.encode(), token.encode()):
        raise Unauthorized("wrong token")


async def require_token(request: Request, cred: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    _check(request, cred)


async def require_read(request: Request, cred: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    if request.app.state.settings.protect_reads:
        _check(request, cred)


ServiceDep = Annotated[Service, Depends(get_service)]
WriteAuth = Depends(require_token)
ReadAuth = Depends(require_read)
