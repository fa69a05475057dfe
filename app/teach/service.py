"""Route maps: accept a taught sequence, build it in the workers, read it back."""

from __future__ import annotations

import asyncio
import logging
import uuid
from dataclasses import dataclass

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from vloc.app.background import BackgroundRunner
from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.engine import Engine, run_task
from vloc.app.maps.models import ImageSift, Map, MapImage
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.tasks import teach as tasks
from vloc.app.teach.models import Route, RouteArc, RouteImage, RouteNode, RouteStatus
from vloc.app.teach.odometry import OdometryRow
from vloc.app.teach.schemas import RouteDetail

log = logging.getLogger(__name__)

MAX_LISTED = 10
"""Filenames a problem lists before it says how many more there are."""


def route_params(params: dict | None) -> dict:
    """Complete :class:`~workers.core.navigation.RouteParams`, or a 422 naming the field."""
    from vloc.workers.core.navigation import RouteParams

    params = dict(params or {})
    known = set(RouteParams.__dataclass_fields__)
    if (unknown := sorted(set(params) - known)):
        raise Problem(422, f"params: unknown route parameter(s) {', '.join(unknown)}",
                      kind=ProblemKind.VALIDATION, errors=[{"loc": ["body", "params", unknown[0]],
                                                  "msg": "unknown parameter", "type": "extra"}])
    for key, value in params.items():
        if key == "node_variances":
            if not isinstance(value, bool):
                raise Problem(422, "params.node_variances: must be true or false",
                              kind=ProblemKind.VALIDATION)
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise Problem(422, f"params.{key}: must be a number", kind=ProblemKind.VALIDATION,
                          errors=[{"loc": ["body", "params", key], "msg": "must be a number",
                                   "type": "type"}])
    try:
        return RouteParams(**params).to_params()
    except ValueError as exc:
        raise Problem(422, f"params: {exc}", kind=ProblemKind.VALIDATION) from None


def create_route(db: Session, *, map_: Map, name: str, rows: list[OdometryRow],
                 params: dict) -> Route:
    """Store a taught sequence as a route to build.

    Every row must name one image of the map, and that image must have been built (its
    features extracted). Nothing is stored when a row fails.
    """
    images = list(db.execute(
        select(MapImage.filename, MapImage.id, ImageSift.image_id)
        .outerjoin(ImageSift, ImageSift.image_id == MapImage.id)
        .where(MapImage.map_id == map_.id)))
    by_name: dict[str, list[tuple[int, bool]]] = {}
    for filename, image_id, sift_id in images:
        by_name.setdefault(filename, []).append((image_id, sift_id is not None))
    missing = [r.filename for r in rows if r.filename not in by_name]
    if missing:
        listed = ", ".join(missing[:MAX_LISTED])
        more = f" and {len(missing) - MAX_LISTED} more" if len(missing) > MAX_LISTED else ""
        raise Problem(422, f"odometry: {len(missing)} row(s) name images this map does not "
                      f"have: {listed}{more}; upload them first", kind=ProblemKind.UNKNOWN_IMAGES,
                      missing=missing[:100])
    ambiguous = [r.filename for r in rows if len(by_name[r.filename]) > 1]
    if ambiguous:
        raise Problem(422, f"odometry: the map has several images named {ambiguous[0]}; "
                      "give the images distinct names", kind=ProblemKind.AMBIGUOUS_IMAGES,
                      ambiguous=ambiguous[:100])
    unbuilt = [r.filename for r in rows if not by_name[r.filename][0][1]]
    if unbuilt:
        raise Problem(409, f"{len(unbuilt)} image(s) of the route have no features yet "
                      f"(e.g. {unbuilt[0]}); build the map first", kind=ProblemKind.MAP_NOT_BUILT)
    route = Route(map_id=map_.id, name=name, status=RouteStatus.BUILDING, params=params,
                  n_images=len(rows))
    db.add(route)
    db.flush()
    for seq, r in enumerate(rows):
        db.add(RouteImage(route_id=route.id, seq=seq, image_id=by_name[r.filename][0][0],
                          filename=r.filename, odom_x=r.x, odom_y=r.y, odom_theta=r.theta,
                          lat=r.lat, lon=r.lon))
    db.commit()
    return route


def get_route(db: Session, *, map_: Map, route_id: str) -> Route:
    try:
        key = uuid.UUID(route_id)
    except ValueError:
        raise not_found("route", route_id) from None
    route = db.get(Route, key)
    if route is None or route.map_id != map_.id:
        raise not_found("route", route_id)
    return route


def list_routes(db: Session, *, map_: Map) -> list[Route]:
    return list(db.scalars(select(Route).where(Route.map_id == map_.id)
                           .order_by(Route.created_at)))


def read_detail(db: Session, *, route: Route) -> RouteDetail:
    nodes = db.scalars(select(RouteNode).where(RouteNode.route_id == route.id)
                       .order_by(RouteNode.idx))
    arcs = db.scalars(select(RouteArc).where(RouteArc.route_id == route.id)
                      .order_by(RouteArc.idx))
    images = db.scalars(select(RouteImage).where(RouteImage.route_id == route.id)
                        .order_by(RouteImage.seq))
    return RouteDetail.model_validate({
        **{k: getattr(route, k) for k in RouteDetail.model_fields
           if k not in ("nodes", "arcs", "images")},
        "nodes": list(nodes), "arcs": list(arcs), "images": list(images)})


def delete_route(db: Session, *, route: Route) -> None:
    """Delete a route; 409 while it builds. Sessions that follow it keep their copy of the
    path."""
    if route.status == RouteStatus.BUILDING:
        raise Problem(409, "the route is being built", kind=ProblemKind.ROUTE_BUSY)
    db.delete(route)
    db.commit()


def navigation_path(db: Session, *, map_id: uuid.UUID, route_id: uuid.UUID,
                    from_node: int | None, to_node: int | None) -> dict:
    """The part of a ready route a session follows: ``points`` (the taught path, (N, 2)
    east/north), ``thetas`` (headings), ``nodes`` (the node of each point), ``names`` (the
    taught images' file names, which the worker finds in the map) and ``route_id``.

    Raises 404 for a route of another map, 409 for a route that is not ready, 422 for
    nodes the route does not have or in the wrong order.
    """
    route = db.get(Route, route_id)
    if route is None or route.map_id != map_id:
        raise Problem(404, f"route {route_id} does not exist on this map", kind=ProblemKind.NOT_FOUND)
    if route.status != RouteStatus.READY:
        raise Problem(409, f"route {route_id} is {route.status}, not ready",
                      kind=ProblemKind.ROUTE_NOT_READY)
    rows = db.execute(select(RouteImage.x, RouteImage.y, RouteImage.theta, RouteImage.node,
                             RouteImage.filename)
                      .where(RouteImage.route_id == route_id).order_by(RouteImage.seq)).all()
    last = route.n_nodes - 1
    lo = 0 if from_node is None else from_node
    hi = last if to_node is None else to_node
    for field, value in (("from_node", lo), ("to_node", hi)):
        if not 0 <= value <= last:
            raise Problem(422, f"navigation.{field}: the route has nodes 0 to {last}",
                          kind=ProblemKind.VALIDATION)
    if lo >= hi:
        raise Problem(422, "navigation: from_node must come before to_node",
                      kind=ProblemKind.VALIDATION)
    kept = [r for r in rows if lo <= r.node <= hi]
    return {"route_id": str(route_id), "points": [[r.x, r.y] for r in kept],
            "thetas": [r.theta for r in kept], "nodes": [r.node for r in kept],
            "names": [r.filename for r in kept]}


def fail_interrupted_routes(db: Session) -> int:
    """Routes left building by a stopped server never finish: mark them failed."""
    n = db.execute(update(Route).where(Route.status == RouteStatus.BUILDING).values(
        status=RouteStatus.FAILED, error="interrupted by a server restart")).rowcount
    db.commit()
    return n or 0


@dataclass(eq=False)
class RouteRunner(BackgroundRunner):
    """Builds routes on the event loop, the workers doing the numerics."""

    settings: Settings
    db_sessions: sessionmaker[Session]
    engine: Engine
    loop: asyncio.AbstractEventLoop | None = None

    task_name = "route"

    async def run(self, route_id: uuid.UUID) -> None:
        try:
            await run_task(self.engine, tasks.build_route,
                           self.settings.resolved_database_url, str(route_id))
        except asyncio.CancelledError:
            await asyncio.to_thread(self._fail, route_id, "cancelled by shutdown")
            raise
        except Exception as exc:  # noqa: BLE001 - the route records the failure
            log.exception("route %s failed to build", route_id)
            await asyncio.to_thread(self._fail, route_id, f"{type(exc).__name__}: {exc}")

    def _fail(self, route_id: uuid.UUID, error: str) -> None:
        with self.db_sessions() as db:
            db.execute(update(Route).where(Route.id == route_id).values(
                status=RouteStatus.FAILED, error=error[:2000], built_at=utcnow()))
            db.commit()


def count_routes(db: Session, *, map_id: uuid.UUID) -> int:
    return db.scalar(select(func.count(Route.id)).where(Route.map_id == map_id)) or 0
