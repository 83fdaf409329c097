"""The FastAPI application: ``create_app(config, keystore)``; ``app_from_env()`` for ``uvicorn --factory``.

Routers: ``routes_jobs`` (uploads, listing, SSE, cancel) and ``routes_scenes`` (metadata, graph, artifacts,
renders). ``/healthz`` (the process answers), ``/readyz`` (Redis answers) and ``/metrics`` (Prometheus) need no
key. While it runs, the app also requeues jobs whose worker lease expired (same reaper as the workers).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

import redis
import redis.asyncio as aioredis
from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service import __doc__ as SERVICE_DOC  # noqa: N812
from service.auth import KeyStore
from service.config import ServiceConfig
from service.errors import install_handlers
from service.jobstore import JobStore
from service.metrics import Metrics, MetricsMiddleware
from service.models import Health, Ready
from service.routes_jobs import router as jobs_router
from service.routes_jobs import upload_schema
from service.routes_scenes import router as scenes_router
from service.scenes import SceneCache

log = logging.getLogger(__name__)

API_VERSION = "1.0.0"


async def _reaper(store: JobStore, interval_s: float) -> None:
    while True:
        await asyncio.sleep(interval_s)
        try:
            await run_in_threadpool(store.reap)
        except redis.RedisError as exc:
            log.warning("reaper: %s", exc)
        except Exception:  # noqa: BLE001 - keep reaping
            log.exception("reaper: unexpected error")


def create_app(config: ServiceConfig, keystore: KeyStore, *, reaper: bool = True, sse_block_ms: int = 5000) -> FastAPI:
    """The API for ``config`` (``redis_url`` required) authenticating with ``keystore``."""
    if not config.redis_url:
        raise ValueError("ServiceConfig.redis_url is required")
    client = redis.Redis.from_url(config.redis_url, socket_timeout=30, health_check_interval=30)
    store = JobStore.from_config(client, config)
    metrics = Metrics(store)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        config.uploads_dir.mkdir(parents=True, exist_ok=True)
        config.scenes_dir.mkdir(parents=True, exist_ok=True)
        app.state.aredis = aioredis.Redis.from_url(config.redis_url, socket_timeout=30, health_check_interval=30)
        task = asyncio.create_task(_reaper(store, config.reap_interval_s)) if reaper else None
        try:
            yield
        finally:
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            await app.state.aredis.aclose()
            client.close()

    app = FastAPI(title="AGG service", version=API_VERSION, lifespan=lifespan,
                  description=(SERVICE_DOC or "") + "\n\nUpload a driving video, follow the reconstruction, download "
                  "the 4D Gaussian scene and render new views. Every /v1 route needs `Authorization: Bearer KEY`; "
                  "ids of other tenants answer 404. Errors have the body `{code, message}`.")
    app.state.config, app.state.keystore, app.state.store, app.state.metrics = config, keystore, store, metrics
    app.state.scene_cache = SceneCache(config.render_cache_size)
    app.state.sse_block_ms = sse_block_ms
    install_handlers(app)
    app.include_router(jobs_router)
    app.include_router(scenes_router)
    app.add_middleware(MetricsMiddleware, metrics=metrics)

    @app.get("/healthz", response_model=Health, tags=["ops"], summary="The process answers")
    def healthz() -> Health:
        return Health()

    @app.get("/readyz", response_model=Ready, tags=["ops"], summary="Redis answers (503 otherwise)",
             responses={503: {"model": Ready, "description": "Redis is unreachable"}})
    def readyz():
        try:
            store.r.ping()
            return Ready(status="ready", redis=True, queue_depth=store.queue_depth())
        except redis.RedisError:
            return JSONResponse(Ready(status="unavailable", redis=False).model_dump(), status_code=503)

    @app.get("/metrics", tags=["ops"], summary="Prometheus metrics", response_class=Response,
             responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                              "description": "Prometheus text format"}})
    def prometheus_metrics(request: Request) -> Response:
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    _patch_openapi(app, config)
    return app


def _patch_openapi(app: FastAPI, config: ServiceConfig) -> None:
    """Add the hand-written multipart body of POST /v1/jobs to the generated schema."""
    from fastapi.openapi.utils import get_openapi

    def openapi():
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        op = schema["paths"]["/v1/jobs"]["post"]
        op.update(upload_schema(config.presets, config.max_frames_limit))
        app.openapi_schema = schema
        return schema

    app.openapi = openapi


def app_from_env() -> FastAPI:
    """``uvicorn --factory service.app:app_from_env``: config from AGG_* variables, keys from AGG_API_KEYS."""
    logging.basicConfig(level=logging.INFO)
    config = ServiceConfig.from_env()
    if not config.api_keys_file:
        raise SystemExit("set AGG_API_KEYS to a file of 'tenant:key' lines")
    return create_app(config, KeyStore.from_file(config.api_keys_file))
