"""The gRPC server of a worker: agg.v1 RenderService, SceneService and JobService, grpc.health.v1 and server
reflection, on one port (docs/API_GRPC.md).

``build_server(...)`` returns an unstarted ``grpc.Server``; ``server.bound_port`` is the port it bound (useful
with ``port=0``) and ``server.health`` its health servicer. Renders come from an LRU cache of loaded scenes that
reloads a scene when its checkpoint file changes, so a scene still training serves its latest checkpoint.

    server = build_server(50051, "/data/scenes", authenticate=keys.tenant_for, scene_tenant=store.scene_tenant,
                          jobs=store)
    server.start(); server.wait_for_termination()
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from concurrent import futures
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from worker.grpc_catalog import SceneServicer
from worker.grpc_common import Auth
from worker.grpc_jobs import JobServicer
from worker.grpc_proto import SERVICE_NAMES, job_pb2_grpc, render_pb2_grpc, scene_pb2_grpc
from worker.grpc_render import RenderLimits, RenderServicer
from worker.grpc_scenes import SceneCache, SceneResolver

log = logging.getLogger(__name__)


def build_server(port: int = 0, scene_dir: str | Path | Callable[[str], Path] | None = None,
                 authenticate: Callable[[str], str | None] | None = None,
                 scene_tenant: Callable[[str], str | None] | None = None, jobs=None, *,
                 host: str = "127.0.0.1", max_message_mb: int = 64, cache_size: int = 4, device: str = "cpu",
                 authorize: Callable[[str, str, str], bool] | None = None,
                 list_scenes: Callable[[str], Iterable[str]] | None = None, limits: RenderLimits | None = None,
                 max_workers: int = 8, watch_poll_ms: int = 1000) -> grpc.Server:
    """An unstarted server with every agg.v1 service, health and reflection, listening on ``host:port``.

    Args:
        port: TCP port (0 picks a free one; read ``server.bound_port``).
        scene_dir: the scenes' root folder (``root/<scene_id>``) or a resolver ``scene_id -> folder`` (default:
            ``jobs.scene_dir``).
        authenticate: API key -> tenant, or None for an unknown key (``service.auth.KeyStore.tenant_for``).
        scene_tenant: scene id -> owning tenant or None (default: ``jobs.scene_tenant``).
        jobs: the job store (``service.jobstore.JobStore``); without it JobService is not served.
        host: bind address ("0.0.0.0" / "[::]" for every interface).
        max_message_mb: send and receive message limit (the answer-size check of renders uses it too).
        cache_size: loaded scenes kept (LRU).
        device: torch device scenes are loaded on ("cpu", or e.g. "cuda:0" on a GPU worker).
        authorize: optional ``(tenant, key, action) -> bool`` rights check ("read", "render", "cancel"); False
            answers PERMISSION_DENIED.
        list_scenes: tenant -> its scene ids for ListScenes (default: the scenes of ``jobs.list(tenant)``, else a
            scan of the root folder filtered by ``scene_tenant``).
        limits: per-request render limits (``RenderLimits``; its max_message_bytes follows max_message_mb).
        max_workers: handler threads (concurrent calls).
        watch_poll_ms: WatchJob's blocking read of the event stream, before it re-checks the job state.
    """
    if authenticate is None:
        raise TypeError("build_server needs authenticate (API key -> tenant)")
    if scene_dir is None and jobs is not None:
        scene_dir = jobs.scene_dir
    if scene_tenant is None and jobs is not None:
        scene_tenant = jobs.scene_tenant
    if scene_dir is None or scene_tenant is None:
        raise TypeError("build_server needs scene_dir and scene_tenant (or a jobs store that provides them)")
    if list_scenes is None and jobs is not None:
        def list_scenes(tenant: str) -> list[str]:
            return [j["scene_id"] for j in jobs.list(tenant) if j.get("scene_id")]

    max_bytes = int(max_message_mb) << 20
    base = limits or RenderLimits()
    limits = RenderLimits(base.max_cameras, base.max_pixels, base.max_steps, max_bytes)
    auth = Auth(authenticate, authorize)
    resolver = SceneResolver(scene_dir, scene_tenant)
    cache = SceneCache(cache_size, device)

    server = grpc.server(futures.ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix="agg-grpc"),
                         options=[("grpc.max_send_message_length", max_bytes),
                                  ("grpc.max_receive_message_length", max_bytes),
                                  ("grpc.so_reuseport", 0)])
    render_pb2_grpc.add_RenderServiceServicer_to_server(RenderServicer(auth, resolver, cache, limits), server)
    scene_pb2_grpc.add_SceneServiceServicer_to_server(SceneServicer(auth, resolver, cache, list_scenes), server)
    names = [n for n in SERVICE_NAMES if n != "agg.v1.JobService"]
    if jobs is not None:
        job_pb2_grpc.add_JobServiceServicer_to_server(JobServicer(auth, jobs, watch_poll_ms), server)
        names.append("agg.v1.JobService")

    health_servicer = health.HealthServicer(experimental_non_blocking=True)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    for name in ["", *names]:
        health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    reflection.enable_server_reflection([*names, health.SERVICE_NAME, reflection.SERVICE_NAME], server)

    bound = server.add_insecure_port(f"{host}:{int(port)}")
    if not bound:
        raise OSError(f"could not bind gRPC to {host}:{port}")
    server.bound_port, server.health, server.scene_cache = bound, health_servicer, cache
    log.info("agg.v1 gRPC services %s on %s:%d", names, host, bound)
    return server
