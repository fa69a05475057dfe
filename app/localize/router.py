"""``POST /v1/maps/{map_id}/localize`` (admin): where was this one image taken?"""

from __future__ import annotations

import asyncio
import time
from datetime import datetime
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, Query, Request

from vloc.app.deps import Ctx, require_admin
from vloc.app.engine import EngineClosed, WorkerDied, run_task
from vloc.app.imagecheck import check_image, kind_of_content_type
from vloc.app.limits import read_body
from vloc.app.localize.schemas import Localization
from vloc.app.localize.service import DEFAULT_PRIOR_SIGMA_M, check_prior
from vloc.app.maps.dependencies import MapDep
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions.admission import revision_missing
from vloc.app.sessions.dependencies import FrameMetadataDep
from vloc.app.sessions.pose import pose_fields
from vloc.app.sessions.schemas import MAX_INITIAL_SIGMA_M, InitialPose
from vloc.app.sessions.service import check_initial_pose, map_frame
from vloc.app.tasks import localize as tasks
from vloc.app.validation import check_captured_at
from vloc.workers.core.localisers import validate_params
from vloc.workers.core.modes import FILTER_MODES

ONE_STEP_MODES = tuple(reversed(FILTER_MODES))
"""The particle filter's modes, as this route has always listed them: its default (sift)
first."""

router = APIRouter(prefix="/v1/maps", tags=["maps"], dependencies=[Depends(require_admin)])


@router.post("/{map_id}/localize", response_model=Localization,
             responses={409: {"description": "The map has not been built (map-not-built)"},
                        413: {"description": "Body or image too large"},
                        415: {"description": "Not image/jpeg or image/png"},
                        422: {"description": "Corrupt image, bad prior (bad-prior, "
                                             "bad-initial-pose) or metadata (bad-metadata)"},
                        503: {"description": "The map's files are missing, or the engine "
                                             "is unavailable"},
                        504: {"description": "No answer within VLOC_FRAME_WAIT_TIMEOUT_S"}},
             openapi_extra={"requestBody": {"required": True, "content": {
                 "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
                 "image/png": {"schema": {"type": "string", "format": "binary"}}}}})
async def localize_image(
    request: Request, map_: MapDep, ctx: Ctx, metadata: FrameMetadataDep,
    mode: Literal[ONE_STEP_MODES] = Query(
        "sift", description="The measurement of the one filter step"),
    prior_lat: float | None = Query(None, ge=-90, le=90, allow_inf_nan=False,
                                    description="Prior position, WGS84; with prior_lon"),
    prior_lon: float | None = Query(None, ge=-180, le=180, allow_inf_nan=False),
    prior_sigma_m: float | None = Query(
        None, gt=0, le=MAX_INITIAL_SIGMA_M, allow_inf_nan=False,
        description=f"Its standard deviation, metres (default {DEFAULT_PRIOR_SIGMA_M:g})"),
    captured_at: datetime | None = Query(None, description="ISO 8601 or seconds since the "
                                                           "epoch; echoed"),
    seed: int = Query(0, ge=0, lt=2**63, description="Random seed of the filter step"),
) -> Localization:
    """Where was this image taken? One image (the raw body), answered synchronously.

    Without a prior the filter starts over the whole map; with one (``prior_lat``,
    ``prior_lon``, ``prior_sigma_m``) around it. The frame metadata query parameters of
    ``POST /v1/sessions/{id}/frames`` are accepted too. Nothing is stored.
    """
    t0 = time.perf_counter()
    declared = kind_of_content_type(request.headers.get("content-type"))
    if declared is None:
        raise Problem(415, "send the image as the raw body with Content-Type image/jpeg or "
                      "image/png", kind=ProblemKind.UNSUPPORTED_MEDIA_TYPE)
    captured = check_captured_at(captured_at)
    prior = check_prior(prior_lat, prior_lon, prior_sigma_m)
    if map_.revision == 0:
        raise Problem(409, "the map has not been built yet; POST /v1/maps/{id}/build",
                      kind=ProblemKind.MAP_NOT_BUILT)
    map_id, revision = str(map_.id), map_.revision
    folder = str(ctx.settings.packed_map_dir(map_id, revision))
    if not Path(folder).is_dir():
        raise revision_missing(map_id, revision)
    if prior is not None:
        frame = await asyncio.to_thread(map_frame, folder, map_id, revision)
        check_initial_pose(frame, InitialPose(lat=prior[0], lon=prior[1], sigma=prior[2]))
    data = await read_body(request, ctx.settings.max_frame_bytes)
    check_image(data, max_pixels=ctx.settings.max_pixels, declared=declared)
    try:
        params = validate_params(mode, {})
    except ValueError as exc:  # the server's own defaults: not the caller's fault
        raise Problem(500, str(exc), kind=ProblemKind.BAD_PARAMS) from None
    params.pop("seed", None)
    try:
        result = await asyncio.wait_for(run_task(
            ctx.engine, tasks.localize_image, folder, data, mode=mode, params=params,
            seed=seed, prior=prior, metadata=metadata, max_pixels=ctx.settings.max_pixels),
            ctx.settings.frame_wait_timeout_s)
    except TimeoutError:
        raise Problem(504, "no answer within "
                      f"{ctx.settings.frame_wait_timeout_s:g} s", kind=ProblemKind.ESTIMATE_TIMEOUT) \
            from None
    except ValueError as exc:
        raise Problem(422, str(exc), kind=ProblemKind.BAD_IMAGE) from None
    except (KeyError, RuntimeError, WorkerDied, EngineClosed) as exc:
        raise Problem(503, f"the engine could not localise the image: {exc}",
                      kind=ProblemKind.ENGINE_UNAVAILABLE) from None
    fields = pose_fields(result["estimate"], map_id=map_.id, map_revision=revision,
                         map_folder=folder, metadata=metadata,
                         decode_ms=result["decode_ms"],
                         bound_m=ctx.settings.converged_accuracy_m, converged_before=False)
    return Localization(**fields, captured_at=captured,
                        latency_ms=(time.perf_counter() - t0) * 1e3)
