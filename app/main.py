"""The FastAPI application: ``create_app(settings)`` wires the domains, engine and database."""

from __future__ import annotations

import asyncio
import logging
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from vloc.app import logs, openapi, problems, ui
from vloc.app.config import Settings, ensure_admin_key, private_dir
from vloc.app.context import AppContext
from vloc.app.db import make_engine, make_session_factory
from vloc.app.edge import EdgeGate
from vloc.app.engine import engine_for
from vloc.app.health.router import router as health_router
from vloc.app.jobs.router import router as jobs_router
from vloc.app.jobs.service import BuildRunner, fail_interrupted
from vloc.app.localize.router import router as localize_router
from vloc.app.maps.router import router as maps_router
from vloc.app.metrics import Metrics, MetricsMiddleware
from vloc.app.security import hash_secret
from vloc.app.sessions.intake import FrameIntake
from vloc.app.sessions.registry import SessionRegistry
from vloc.app.sessions.router import router as sessions_router
from vloc.app.sessions.store import interrupt_left_queued
from vloc.app.stream.hub import LocalHub
from vloc.app.stream.router import router as stream_router
from vloc.app.teach.router import router as routes_router
from vloc.app.teach.service import RouteRunner, fail_interrupted_routes

log = logging.getLogger("vloc.app")

STREAMS_CLOSE_TIMEOUT_S = 5.0
SWEEP_INTERVAL_S = 30.0
SETTLE_INTERVAL_S = 1.0
FOLLOW_INTERVAL_S = 2.0
"""How often an API process reads the revisions of the maps its live sessions follow."""


def create_app(settings: Settings | None = None, *, configure_logging: bool = False) -> FastAPI:
    """Build the application; the engine and the database start with its lifespan."""
    settings = settings or Settings()
    if configure_logging:
        json_lines = settings.log_json if settings.log_json is not None \
            else not sys.stderr.isatty()
        logs.configure(settings.log_level, json_lines=json_lines, native=True)
    logs.redact_uvicorn()
    private_dir(settings.data_dir)
    db_engine = make_engine(settings.resolved_database_url)
    db_sessions = make_session_factory(db_engine)
    metrics = Metrics()
    engine = engine_for(settings)
    hub = _make_hub(settings)
    sessions = SessionRegistry(settings=settings, db_sessions=db_sessions, engine=engine,
                               hub=hub, metrics=metrics)
    intake = FrameIntake(sessions)
    engine.on_outcome = intake.outcomes.on_outcome
    ctx = AppContext(settings=settings, db_engine=db_engine, db_sessions=db_sessions,
                     admin_key_hash=hash_secret(ensure_admin_key(settings)), metrics=metrics,
                     engine=engine, hub=hub, sessions=sessions, intake=intake,
                     builds=BuildRunner(settings, db_sessions, engine, metrics,
                                        on_revised=intake.following.map_revised),
                     routes=RouteRunner(settings, db_sessions, engine))

    app = FastAPI(title="vloc", version="0.1.0", lifespan=_lifespan, docs_url=None,
                  redoc_url=None,
                  description="Visual localisation: where is the camera, from a map of "
                              "GPS-tagged images. Errors are RFC 9457 problem details.")
    app.state.ctx = ctx
    problems.install(app)
    for router in (health_router, maps_router, localize_router, routes_router, jobs_router,
                   sessions_router, stream_router):
        app.include_router(router)
    openapi.install(app)
    openapi.serve_docs(app)
    ui.install(app)
    app.add_middleware(EdgeGate)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(logs.RequestLogMiddleware)
    return app


def _make_hub(settings: Settings) -> LocalHub:
    if settings.redis_url:
        from vloc.app.stream.redis_hub import RedisHub

        return RedisHub(settings.redis_url)
    return LocalHub()


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    ctx: AppContext = app.state.ctx
    loop = asyncio.get_running_loop()
    await asyncio.to_thread(_prepare_database, ctx)
    await asyncio.to_thread(ctx.engine.start)
    ctx.intake.start(loop)
    ctx.builds.loop = loop
    ctx.routes.loop = loop
    await ctx.hub.start()
    # idle sessions released; sessions moved to the revision another API process built or
    # restored (this process tells its own at once); on a shared engine, the frames dead
    # API processes left queued reported
    sweeper = asyncio.create_task(_every(
        min(SWEEP_INTERVAL_S, ctx.settings.session_ttl_s / 4), ctx.sessions.expire_idle,
        "expiring idle sessions failed"))
    follower = asyncio.create_task(_every(
        FOLLOW_INTERVAL_S, ctx.intake.following.follow_maps,
        "moving sessions to their maps' new revisions failed"))
    settler = asyncio.create_task(_every(
        SETTLE_INTERVAL_S, ctx.intake.settle_gone,
        "settling the frames of dead API processes failed")) if ctx.engine.shared else None
    log.info("vloc ready", extra={"workers": ctx.engine.n_workers,
                                  "database": ctx.db_engine.dialect.name})
    try:
        yield
    finally:
        sweeper.cancel()
        follower.cancel()
        if settler is not None:
            settler.cancel()
        await ctx.builds.cancel_all()
        await ctx.routes.cancel_all()
        await ctx.intake.drain(ctx.settings.drain_timeout_s)
        await asyncio.to_thread(ctx.engine.close)
        await asyncio.to_thread(ctx.intake.stop)
        await asyncio.sleep(0)  # let the last publications run
        await ctx.hub.stop()
        ctx.db_engine.dispose()
        log.info("vloc stopped")


async def drain(app: FastAPI, timeout: float | None = None) -> None:
    """A graceful stop's first half, while connections are still open: refuse new frames,
    answer and store the frames already accepted (while the backlog shrinks, at most
    ``timeout``, by default ``VLOC_DRAIN_TIMEOUT_S``), let every stream send their
    messages, then close the streams with 1001 (going away)."""
    ctx: AppContext = app.state.ctx
    await ctx.intake.drain(ctx.settings.drain_timeout_s if timeout is None else timeout)
    if (left := ctx.intake.pending_total()):
        log.warning("closing the streams with %d frame(s) still unanswered", left)
    await ctx.hub.going_away(STREAMS_CLOSE_TIMEOUT_S)


async def _every(interval_s: float, work, failed: str) -> None:
    """Run ``work()`` every ``interval_s`` seconds until cancelled; a round that fails is
    logged (``failed``) and the next one tries again."""
    while True:
        await asyncio.sleep(interval_s)
        try:
            await work()
        except Exception:  # noqa: BLE001 - the next round tries again
            log.exception(failed)


def _prepare_database(ctx: AppContext) -> None:
    from vloc.app import migrate

    if ctx.settings.auto_migrate:
        migrate.upgrade(ctx.db_engine)
    with ctx.db_sessions() as db:
        if (n := fail_interrupted(db)):
            log.warning("marked %d interrupted build job(s) failed", n)
        if (n := fail_interrupted_routes(db)):
            log.warning("marked %d interrupted route build(s) failed", n)
        if (n := interrupt_left_queued(db, owner=ctx.settings.instance_name)):
            log.warning("%d frame(s) accepted before a stop were never answered; "
                        "reported as interrupted", n)
