"""API errors: ``ApiError(status, code, message)`` and the handlers that turn every error into an ``Error`` body.

Request validation failures become 422 ``invalid_request`` with per-field details; anything unexpected becomes a
500 ``internal_error`` without internals (logged server-side).
"""

from __future__ import annotations

import logging

import redis
from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger(__name__)

HTTP_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
              405: "method_not_allowed", 409: "conflict", 413: "payload_too_large", 415: "unsupported_media_type",
              422: "invalid_request", 429: "quota_exceeded", 503: "unavailable"}


class ApiError(Exception):
    """An error with its HTTP status, stable code, message and optional headers (e.g. Retry-After)."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status, self.code, self.message, self.headers = status, code, message, headers or {}


def error_response(status: int, code: str, message: str, details=None, headers=None) -> JSONResponse:
    body = {"code": code, "message": message}
    if details is not None:
        body["details"] = details
    return JSONResponse(status_code=status, content=body, headers=headers)


def error_responses(*statuses: int) -> dict:
    """OpenAPI ``responses`` entries with the Error model for the given statuses."""
    from service.models import Error

    descriptions = {400: "Malformed request", 401: "Missing or unknown API key", 404: "No such resource for this "
                    "tenant", 409: "Conflict with the resource's state", 413: "Upload too large",
                    415: "Not a video / not multipart", 422: "Invalid request", 429: "Quota exceeded",
                    503: "A backend is unavailable"}
    return {s: {"model": Error, "description": descriptions.get(s, HTTP_CODES.get(s, "error"))} for s in statuses}


def allowed_methods(request: Request) -> list[str]:
    from starlette.routing import Match

    methods: set[str] = set()
    for route in request.app.routes:
        match, _ = route.matches({**request.scope, "method": "GET"})
        if match != Match.NONE or route.matches({**request.scope, "method": "POST"})[0] != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        details = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
                   for e in exc.errors()]
        first = details[0] if details else {"loc": [], "msg": "invalid request"}
        where = ".".join(str(x) for x in first["loc"] if x != "body") or "request"
        return error_response(422, "invalid_request", f"{where}: {first['msg']}", jsonable_encoder(details))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        code = HTTP_CODES.get(exc.status_code, "error")
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # every method of every route on this path, not only the first route's
            headers["Allow"] = ", ".join(allowed_methods(request))
        return error_response(exc.status_code, code, str(exc.detail), headers=headers or None)

    @app.exception_handler(redis.RedisError)
    async def _redis_down(request: Request, exc: redis.RedisError):
        log.warning("redis unavailable on %s %s: %s", request.method, request.url.path, exc)
        return error_response(503, "backend_unavailable", "the job store (Redis) is unavailable; retry shortly",
                              headers={"Retry-After": "5"})

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal_error", "internal error; the request id is in the server log")
