"""``/healthz`` (the process answers), ``/readyz`` (database and workers), ``/metrics``
(the admin key or ``VLOC_METRICS_TOKEN``)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from vloc.app.deps import Ctx, require_metrics
from vloc.app.problems import Problem, ProblemKind

router = APIRouter(tags=["health"])


@router.get("/healthz")
async def healthz() -> dict:
    """Liveness: the process answers (no dependency is checked)."""
    return {"status": "ok"}


@router.get("/readyz")
def readyz(ctx: Ctx) -> dict:
    """Readiness: the database answers and every worker is alive and not stalled; 503
    otherwise, naming what is not ready."""
    try:
        with ctx.db_engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # noqa: BLE001 - any failure means "not ready"
        raise Problem(503, f"database unreachable: {type(exc).__name__}",
                      kind=ProblemKind.NOT_READY) from None
    if not ctx.engine.alive():
        raise Problem(503, "worker processes are not all running, or one has not run for "
                      f"{ctx.settings.worker_stall_s:g} s", kind=ProblemKind.NOT_READY)
    return {"status": "ready", "database": ctx.db_engine.dialect.name,
            "workers": ctx.engine.n_workers}


@router.get("/metrics", include_in_schema=False, dependencies=[Depends(require_metrics)])
def metrics(ctx: Ctx) -> Response:
    m = ctx.metrics
    m.workers_alive.set(ctx.engine.alive_count())
    m.worker_restarts.set(ctx.engine.restarts)
    return Response(generate_latest(m.registry), media_type=CONTENT_TYPE_LATEST)
