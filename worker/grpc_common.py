"""What every agg.v1 servicer shares: API-key auth from metadata and one mapping from errors to status codes.

Handlers raise; the ``unary`` / ``streaming`` decorators turn the exception into the status of the call:

=========================================  ===================
``RpcFailure(code, message)``              that code
``agg.scene.OutOfRange``                   OUT_OF_RANGE
``agg.scene.SceneRequestError``            INVALID_ARGUMENT (bad camera, pose, track id, output spec)
``worker.grpc_scenes.SceneLookupError``    NOT_FOUND (unknown, malformed or another tenant's scene)
``agg.scene.SceneNotReady``                FAILED_PRECONDITION (no checkpoint yet)
``agg.scene.SceneUnreadable``              UNAVAILABLE (checkpoint being replaced; retry)
Redis connection / timeout errors          UNAVAILABLE (job store unreachable; retry with backoff)
anything else                              INTERNAL (logged; the message says nothing more)
=========================================  ===================
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import grpc

from agg.scene import OutOfRange, SceneNotReady, SceneRequestError, SceneUnreadable
from worker.grpc_scenes import SceneLookupError

log = logging.getLogger(__name__)
Code = grpc.StatusCode


class RpcFailure(Exception):
    """Ends the call with ``code`` and ``message``."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code, self.message = code, message


def _store_errors() -> tuple[type[BaseException], ...]:
    errors: list[type[BaseException]] = [ConnectionError, TimeoutError]
    try:
        import redis

        errors += [redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, redis.exceptions.BusyLoadingError]
    except ImportError:  # a deployment without Redis has no job store to lose
        pass
    return tuple(errors)


STORE_ERRORS = _store_errors()


def status_of(exc: BaseException) -> tuple[grpc.StatusCode, str]:
    """(status code, client message) of an exception raised by a handler."""
    if isinstance(exc, RpcFailure):
        return exc.code, exc.message
    if isinstance(exc, OutOfRange):
        return Code.OUT_OF_RANGE, str(exc)
    if isinstance(exc, SceneRequestError):
        return Code.INVALID_ARGUMENT, str(exc)
    if isinstance(exc, SceneLookupError):
        return Code.NOT_FOUND, "scene not found"
    if isinstance(exc, SceneNotReady):
        return Code.FAILED_PRECONDITION, f"{exc}: the scene cannot be rendered before its first checkpoint"
    if isinstance(exc, SceneUnreadable):
        return Code.UNAVAILABLE, "the scene's checkpoint is being written; retry"
    if isinstance(exc, STORE_ERRORS):
        return Code.UNAVAILABLE, "the job store is unreachable; retry later"
    log.exception("internal error in a gRPC handler", exc_info=exc)
    return Code.INTERNAL, "internal error"


def unary(fn):
    """Decorator of a unary (or client-streaming) handler method: exceptions become statuses."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        try:
            return fn(self, request, context)
        except Exception as exc:  # noqa: BLE001  (mapped to a status; INTERNAL ones are logged)
            code, message = status_of(exc)
        context.abort(code, message)

    return wrapper


def streaming(fn):
    """Decorator of a server-streaming handler method (a generator): exceptions become statuses."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        try:
            yield from fn(self, request, context)
            return
        except Exception as exc:  # noqa: BLE001
            code, message = status_of(exc)
        context.abort(code, message)

    return wrapper


class Auth:
    """``authorization: Bearer KEY`` metadata -> tenant (``authenticate``), plus an optional rights check.

    ``authorize(tenant, key, action) -> bool`` (default: everything allowed) decides whether a valid key may do
    ``action``: "read" (Get/List/Watch), "render" or "cancel"; False answers PERMISSION_DENIED (e.g. a read-only
    key cancelling a job). It runs before any lookup, so it never reveals whether a resource exists.
    """

    ACTIONS = ("read", "render", "cancel")

    def __init__(self, authenticate: Callable[[str], str | None],
                 authorize: Callable[[str, str, str], bool] | None = None):
        self.authenticate, self.authorize = authenticate, authorize

    def tenant(self, context: grpc.ServicerContext, action: str) -> str:
        value = None
        for k, v in context.invocation_metadata() or ():
            if k.lower() == "authorization":
                value = v
        if not value:
            raise RpcFailure(Code.UNAUTHENTICATED, "missing 'authorization: Bearer <API key>' metadata")
        scheme, _, key = str(value).strip().partition(" ")
        key = key.strip()
        if scheme.lower() != "bearer" or not key:
            raise RpcFailure(Code.UNAUTHENTICATED, "malformed authorization metadata (want 'Bearer <API key>')")
        tenant = self.authenticate(key)
        if not tenant:
            raise RpcFailure(Code.UNAUTHENTICATED, "unknown API key")
        if self.authorize is not None and not self.authorize(tenant, key, action):
            raise RpcFailure(Code.PERMISSION_DENIED, f"this API key may not {action}")
        return tenant
