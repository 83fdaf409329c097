"""Prometheus metrics of the API: request counts and latencies per route, uploads, jobs, queue gauges.

Each app has its own ``CollectorRegistry`` (several apps in one process, as in the tests, do not clash). Queue
gauges are read from Redis at scrape time.
"""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily


class QueueCollector:
    """agg_queue_depth, agg_jobs_running, agg_redis_up from the job store at scrape time."""

    def __init__(self, store):
        self.store = store

    def collect(self):
        up = GaugeMetricFamily("agg_redis_up", "1 when Redis answered the last scrape")
        depth = GaugeMetricFamily("agg_queue_depth", "jobs waiting in the RQ queue")
        running = GaugeMetricFamily("agg_jobs_running", "jobs holding a worker lease")
        try:
            depth.add_metric([], self.store.queue_depth())
            running.add_metric([], self.store.running_count())
            up.add_metric([], 1)
            yield depth
            yield running
        except Exception:  # noqa: BLE001 - a scrape must not fail because Redis is down
            up.add_metric([], 0)
        yield up


class Metrics:
    def __init__(self, store=None):
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("agg_http_requests", "HTTP requests", ["method", "route", "status"], registry=r)
        self.latency = Histogram("agg_http_request_seconds", "HTTP request latency (to the end of the response "
                                 "body)", ["route"], registry=r,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60))
        self.upload_bytes = Counter("agg_upload_bytes", "bytes of accepted video uploads", registry=r)
        self.upload_rejected = Counter("agg_uploads_rejected", "refused uploads", ["code"], registry=r)
        self.jobs_submitted = Counter("agg_jobs_submitted", "jobs queued", ["preset"], registry=r)
        self.renders = Counter("agg_renders", "HTTP renders", ["status"], registry=r)
        if store is not None:
            r.register(QueueCollector(store))


class MetricsMiddleware:
    """Pure ASGI middleware (streaming responses such as SSE pass through untouched)."""

    def __init__(self, app, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        start, status = time.perf_counter(), [500]

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            self.metrics.requests.labels(scope["method"], path, str(status[0])).inc()
            self.metrics.latency.labels(path).observe(time.perf_counter() - start)
