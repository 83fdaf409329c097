"""The worker process: an RQ worker on the job queue, a reaper thread, and (optionally) the gRPC servers.

The RQ worker forks one work horse per job attempt (``worker.jobs.run_job``); the engine module is imported
before forking so horses start at once. The reaper thread requeues jobs whose lease expired (a dead worker
anywhere in the deployment), every ``reap_interval_s``; several reapers are safe (WATCH/MULTI transactions).
"""

from __future__ import annotations

import importlib
import logging
import threading
from pathlib import Path

import redis
from rq import Queue, Worker

from service.config import ServiceConfig
from service.jobstore import JobStore
from worker import jobs as jobs_module

log = logging.getLogger(__name__)


class Reaper(threading.Thread):
    """Calls ``JobStore.reap()`` every ``interval_s`` until ``stop()``; Redis outages are logged and retried."""

    def __init__(self, store: JobStore, interval_s: float):
        super().__init__(daemon=True, name="agg-reaper")
        self.store, self.interval_s, self._stop_evt = store, interval_s, threading.Event()

    def run(self) -> None:
        while not self._stop_evt.wait(self.interval_s):
            try:
                self.store.reap()
            except redis.RedisError as exc:
                log.warning("reaper: %s", exc)
            except Exception:  # noqa: BLE001 - the reaper must outlive one bad job hash
                log.exception("reaper: unexpected error")

    def stop(self) -> None:
        self._stop_evt.set()


def preload_engine(spec: str) -> bool:
    """Import the engine module now (before forking); False when it is not importable yet."""
    try:
        importlib.import_module(spec.partition(":")[0])
        return True
    except ImportError as exc:
        log.warning("engine %s not importable (%s); jobs will fail until it is installed", spec, exc)
        return False


def start_grpc(port: int, host: str, authenticate, store: JobStore, device: str = "cpu"):
    """Build (``worker.grpc_server.build_server``, imported lazily) and start the gRPC servers over ``store``."""
    from worker.grpc_server import build_server

    server = build_server(port, authenticate=authenticate, jobs=store, host=host, device=device)
    server.start()
    return server


def run_worker(config: ServiceConfig, *, name: str | None = None, burst: bool = False, jobs: bool = True,
               grpc_port: int | None = None, grpc_host: str = "0.0.0.0", api_keys: Path | None = None,
               device: str = "cpu", preload: bool = True) -> int:
    """Run until stopped (SIGTERM/SIGINT: RQ's warm shutdown finishes the current attempt first)."""
    if not config.redis_url:
        raise SystemExit("agg worker: set --redis-url or AGG_REDIS_URL (workers share one Redis)")
    conn = redis.Redis.from_url(config.redis_url)
    conn.ping()
    settings = jobs_module.WorkerSettings(config=config)
    if name:
        settings.worker_name = name
    jobs_module.SETTINGS = settings
    store = JobStore.from_config(redis.Redis.from_url(config.redis_url), config)
    reaper = Reaper(store, config.reap_interval_s)
    reaper.start()
    grpc_server = None
    if grpc_port:
        from service.auth import KeyStore

        keys_file = api_keys or config.api_keys_file
        if not keys_file:
            raise SystemExit("agg worker: --grpc-port needs --api-keys (or AGG_API_KEYS)")
        grpc_server = start_grpc(grpc_port, grpc_host, KeyStore.from_file(keys_file).tenant_for, store, device)
        log.info("gRPC listening on %s:%d", grpc_host, grpc_port)
    try:
        if not jobs:
            if grpc_server is None:
                raise SystemExit("agg worker: --no-jobs without --grpc-port has nothing to do")
            grpc_server.wait_for_termination()
            return 0
        if preload:
            preload_engine(config.engine)
        queue = Queue(config.queue, connection=conn)
        worker = Worker([queue], connection=conn, name=name)
        log.info("worker %s consuming queue %r (engine %s)", worker.name, config.queue, config.engine)
        worker.work(burst=burst, with_scheduler=False, logging_level="INFO")
        return 0
    finally:
        reaper.stop()
        if grpc_server is not None:
            grpc_server.stop(grace=2)
