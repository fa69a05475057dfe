"""Route maps of a map (admin): create from a taught sequence, list, read, delete."""

from __future__ import annotations

import json

from fastapi import APIRouter, Depends, File, Form, Response, UploadFile

from vloc.app.deps import Ctx, DbSession, SettingsDep, require_admin
from vloc.app.maps.dependencies import MapDep
from vloc.app.problems import Problem, ProblemKind
from vloc.app.teach import service
from vloc.app.teach.odometry import parse_odometry
from vloc.app.teach.schemas import RouteDetail, RouteRead
from vloc.app.validation import check_text

router = APIRouter(prefix="/v1/maps/{map_id}/routes", tags=["routes"],
                   dependencies=[Depends(require_admin)])


@router.post("", status_code=202, response_model=RouteRead,
             responses={409: {"description": "The map's images are not built"},
                        413: {"description": "Too large"},
                        422: {"description": "Bad odometry, unknown images or parameters"}})
async def create_route(map_: MapDep, db: DbSession, ctx: Ctx, settings: SettingsDep,
                       response: Response,
                       odometry: UploadFile = File(description="CSV: filename, x, y, theta "
                                                               "[, lat, lon], in driving order"),
                       name: str = Form("route", min_length=1, max_length=200),
                       params: str | None = Form(None, description="JSON object of route "
                                                 "parameters (RouteParams)"),
                       max_step_m: float = Form(5.0, gt=0, le=1000, allow_inf_nan=False,
                                                description="Largest odometry step between "
                                                            "consecutive images")) -> RouteRead:
    """Teach a route: the map's images in driving order with their odometry. The route is
    partitioned into nodes, loops are closed and the nodes relaxed in the background;
    ``status`` turns ``ready`` (or ``failed``)."""
    check_text(name, "name")
    data = await odometry.read(settings.max_upload_bytes + 1)
    if len(data) > settings.max_upload_bytes:
        raise Problem(413, f"the odometry CSV exceeds {settings.max_upload_bytes} bytes",
                      kind=ProblemKind.TOO_LARGE)
    rows = parse_odometry(data, max_step_m=max_step_m)
    try:
        given = json.loads(params) if params else {}
    except json.JSONDecodeError as exc:
        raise Problem(422, f"params: not JSON ({exc.msg})", kind=ProblemKind.VALIDATION) from None
    if not isinstance(given, dict):
        raise Problem(422, "params: must be a JSON object", kind=ProblemKind.VALIDATION)
    route = service.create_route(db, map_=map_, name=name, rows=rows,
                                 params=service.route_params(given))
    ctx.routes.launch(route.id)
    response.headers["Location"] = f"/v1/maps/{map_.id}/routes/{route.id}"
    return RouteRead.model_validate(route)


@router.get("", response_model=list[RouteRead])
def list_routes(map_: MapDep, db: DbSession) -> list[RouteRead]:
    """The map's taught routes, with their build status."""
    return [RouteRead.model_validate(r) for r in service.list_routes(db, map_=map_)]


@router.get("/{route_id}", response_model=RouteDetail)
def get_route(route_id: str, map_: MapDep, db: DbSession) -> RouteDetail:
    """The route with its nodes, arcs and taught path."""
    return service.read_detail(db, route=service.get_route(db, map_=map_, route_id=route_id))


@router.delete("/{route_id}", status_code=204)
def delete_route(route_id: str, map_: MapDep, db: DbSession) -> Response:
    """Delete the route (its nodes, arcs and images); sessions following it keep the path
    they were given."""
    service.delete_route(db, route=service.get_route(db, map_=map_, route_id=route_id))
    return Response(status_code=204)
