"""One error body everywhere: ``{"ok": false, "reason": ..., "message": ...}`` with a fitting status.

The reasons are the engine's ``Reason`` values plus the HTTP-only ones below,
so a PLC can branch on ``reason`` whatever produced the error.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.core.results import Reason

# every reason's HTTP status, where an error body carries it (tests/api/test_errors.py: all of Reason)
STATUS: dict[Reason, int] = {
    # the input cannot be solved: the request was understood, its content is unusable
    Reason.bad_input: 422,
    Reason.bad_image: 422,
    Reason.degenerate_geometry: 422,
    Reason.behind_camera: 422,
    Reason.no_convergence: 422,
    Reason.poor_motion: 422,
    # the cell's state does not allow it now
    Reason.too_few_targets: 409,
    Reason.not_calibrated: 409,
    Reason.not_solved: 409,
    Reason.robot_moving: 409,
    Reason.unsupported: 409,
    # the service cannot answer now; try again
    Reason.initializing: 503,
    Reason.camera_disconnected: 503,
    Reason.robot_disconnected: 503,
    Reason.stale: 503,
    Reason.storage_unavailable: 503,
    Reason.solver_unavailable: 503,
    Reason.busy: 503,
    Reason.timeout: 504,
    Reason.no_frame: 504,
    # the request itself
    Reason.unauthorized: 401,
    Reason.not_found: 404,
    Reason.method_not_allowed: 405,
    Reason.host_not_allowed: 400,
    Reason.origin_not_allowed: 403,
    Reason.body_too_large: 413,
    Reason.header_too_large: 431,
    Reason.http_error: 400,
}


class ApiError(Exception):
    def __init__(self, reason: Reason, message: str, status: int | None = None, **details: Any) -> None:
        super().__init__(message)
        self.reason, self.message, self.details = Reason(reason), message, details
        self.status = status or STATUS.get(self.reason, 400)


def body(reason: str, message: str, **details: Any) -> dict[str, Any]:
    return {"ok": False, "reason": str(reason), "message": message, **details}


def install(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, e: ApiError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if e.status == 401 else None
        return JSONResponse(body(e.reason, e.message, **e.details), status_code=e.status, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, e: RequestValidationError) -> JSONResponse:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc'] if p != 'body')}: {err['msg']}" for err in e.errors()
        )
        return JSONResponse(body(Reason.bad_input, f"invalid request: {problems}"), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, e: StarletteHTTPException) -> JSONResponse:
        reason = {404: Reason.not_found, 405: Reason.method_not_allowed}.get(e.status_code, Reason.http_error)
        return JSONResponse(body(reason, str(e.detail)), status_code=e.status_code)
