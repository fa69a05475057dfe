"""Prometheus metrics, in a registry of the application's own (tests build many apps)."""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from starlette.types import ASGIApp, Message, Receive, Scope, Send

_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.015, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5,
                    5, 10)


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.http_requests = Counter(
            "vloc_http_requests", "HTTP requests by route and status",
            ["method", "route", "status"], registry=r)
        self.http_seconds = Histogram(
            "vloc_http_request_seconds", "HTTP request handling time", ["method", "route"],
            buckets=_LATENCY_BUCKETS, registry=r)
        self.frames_accepted = Counter(
            "vloc_frames_accepted", "Frames accepted for processing", registry=r)
        self.frames_rejected = Counter(
            "vloc_frames_rejected", "Frames refused before processing", ["reason"], registry=r)
        self.frames_processed = Counter(
            "vloc_frames_processed", "Frames that gave an estimate", ["feature"], registry=r)
        self.frames_failed = Counter(
            "vloc_frames_failed", "Accepted frames that gave no estimate", ["kind"], registry=r)
        self.frame_latency = Histogram(
            "vloc_frame_latency_seconds", "Frame arrival to estimate back in the API",
            buckets=_LATENCY_BUCKETS, registry=r)
        self.step_seconds = Histogram(
            "vloc_step_seconds", "Localiser step time in the worker", ["feature"],
            buckets=_LATENCY_BUCKETS, registry=r)
        self.live_sessions = Gauge(
            "vloc_live_sessions", "Sessions open in the engine", registry=r)
        self.stream_subscribers = Gauge(
            "vloc_stream_subscribers", "Open pose-stream WebSockets", registry=r)
        self.workers_alive = Gauge(
            "vloc_workers_alive", "Engine worker processes alive", registry=r)
        self.worker_restarts = Gauge(
            "vloc_worker_restarts", "Worker processes replaced since start", registry=r)
        self.build_jobs = Counter(
            "vloc_build_jobs", "Finished map build jobs", ["status"], registry=r)
        self.session_moves = Counter(
            "vloc_session_moves", "Sessions moved to their map's new revision, or kept where "
            "they were when the move failed", ["outcome"], registry=r)


class MetricsMiddleware:
    """Counts and times HTTP requests by route template (never by raw path: ids vary)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.metrics.http_requests.labels(scope["method"], template, str(status)).inc()
            self.metrics.http_seconds.labels(scope["method"], template).observe(
                time.perf_counter() - t0)
