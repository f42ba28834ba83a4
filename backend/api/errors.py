"""Domain errors → HTTP status codes, in one place. Bad input is never a 500."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from ..cameras import CameraFileError
from ..config import ConfigError
from ..session import NotAvailable, SessionConflict, SessionInputError, SessionNotFound
from ..service import StorageError
from ..service_api import UnknownFormat

STATUS: dict[type[Exception], int] = {
    SessionNotFound: 404,
    NotAvailable: 404,
    SessionConflict: 409,
    SessionInputError: 422,
    CameraFileError: 422,
    ConfigError: 422,
    UnknownFormat: 400,
    StorageError: 503,
}


class Unauthorized(Exception):
    """Missing or wrong bearer token (401)."""


def install(app: FastAPI) -> None:
    for exc, code in STATUS.items():
        app.add_exception_handler(exc, _handler(code))
    app.add_exception_handler(Unauthorized, _unauthorized)
    app.add_exception_handler(RequestValidationError, _validation)


def _handler(code: int):
    async def handle(request: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=code)

    return handle


async def _unauthorized(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=401, headers={"WWW-Authenticate": "Bearer"})


async def _validation(request: Request, exc: Exception) -> JSONResponse:
    """One line per problem, naming where in the request it is."""
    assert isinstance(exc, RequestValidationError)
    problems = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err.get("loc", ()) if x != "body")
        msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")
        problems.append(f"{loc}: {msg}" if loc else msg)
    return JSONResponse({"detail": "; ".join(problems), "errors": [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg"))} for e in exc.errors()
    ]}, status_code=422)
