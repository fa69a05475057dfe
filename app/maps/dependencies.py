"""Fetch-or-404 for maps."""

from __future__ import annotations

import asyncio
import uuid
from typing import Annotated

from fastapi import Depends

from vloc.app.deps import Ctx, DbSession
from vloc.app.engine import EngineClosed, WorkerDied, run_task
from vloc.app.maps.models import Map
from vloc.app.maps.service import Verifier
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.tasks.images import inspect_image

VERIFY_TIMEOUT_S = 120.0


def parse_id(value: str, what: str) -> uuid.UUID:
    """A UUID from a path segment; anything else is an id that does not exist."""
    try:
        return uuid.UUID(value)
    except ValueError:
        raise not_found(what, value) from None


def get_map(map_id: str, db: DbSession) -> Map:
    found = db.get(Map, parse_id(map_id, "map"))
    if found is None:
        raise not_found("map", map_id)
    return found


MapDep = Annotated[Map, Depends(get_map)]


async def get_verifier(ctx: Ctx) -> Verifier:
    """Full decoding of uploads, in the workers (never in the API process)."""
    engine, max_pixels = ctx.engine, ctx.settings.max_pixels

    async def verify(blobs: list[bytes]) -> list[str | None]:
        try:
            futures = [run_task(engine, inspect_image, blob, max_pixels=max_pixels)
                       for blob in blobs]
        except (WorkerDied, EngineClosed) as exc:
            raise Problem(503, f"image check unavailable: {exc}",
                          kind=ProblemKind.ENGINE_UNAVAILABLE) from None
        out: list[str | None] = []
        for fut in futures:
            try:
                await asyncio.wait_for(fut, VERIFY_TIMEOUT_S)
                out.append(None)
            except ValueError as exc:
                out.append(str(exc))
            except (WorkerDied, EngineClosed, TimeoutError) as exc:
                raise Problem(503, f"image check unavailable: {exc}",
                              kind=ProblemKind.ENGINE_UNAVAILABLE) from None
        return out

    return verify


ImageVerifier = Annotated[Verifier, Depends(get_verifier)]
