"""Building a taught route, run by the engine's workers (:func:`vloc.app.engine.run_task`):
read the taught sequence and its images' features, partition, close loops, relax, store
nodes, arcs and the taught path.

The route is aligned to the map's frame by the images' positions of the map's last build
(``east``/``north``), or by the GPS given with the odometry where those are missing.
"""

from __future__ import annotations

import math
import uuid

import numpy as np
from sqlalchemy import delete, select

from vloc.app.db import utcnow
from vloc.app.maps.codecs import decode_sift, decode_vector
from vloc.app.maps.models import ImageGlobalFeature, ImageSift, Map, MapImage
from vloc.app.tasks.database import sessions
from vloc.app.teach.models import Route, RouteArc, RouteImage, RouteNode, RouteStatus


def build_route(database_url: str, route_id: str) -> dict:
    """Build one stored route; returns its node and loop counts."""
    from vloc.workers.core.geo import GeoOrigin
    from vloc.workers.core.image import WORK_SIZE
    from vloc.workers.core.navigation import RouteParams
    from vloc.workers.core.navigation import build_route as build
    from vloc.workers.core.navigation.routemap import sift_verifier, yaw_from_views
    from vloc.workers.core.navigation.visual import camera_matrix

    rid = uuid.UUID(route_id)
    with sessions(database_url)() as db:
        route = db.get(Route, rid)
        params = RouteParams(**route.params)
        rows = db.execute(
            select(RouteImage, MapImage, ImageSift, ImageGlobalFeature)
            .join(MapImage, MapImage.id == RouteImage.image_id)
            .join(ImageSift, ImageSift.image_id == MapImage.id)
            .join(ImageGlobalFeature, (ImageGlobalFeature.image_id == MapImage.id)
                  & (ImageGlobalFeature.name == "hue_hist"))
            .where(RouteImage.route_id == rid).order_by(RouteImage.seq)).all()
        if len(rows) != route.n_images:
            raise ValueError(f"{route.n_images - len(rows)} image(s) of the route were deleted "
                             "or have no features")
        m = db.get(Map, route.map_id)
        origin = None if m.origin_lat is None else GeoOrigin(m.origin_lat, m.origin_lon,
                                                             m.origin_alt or 0.0)
        odometry = np.array([[r.odom_x, r.odom_y, r.odom_theta] for r, _, _, _ in rows])
        hue = np.stack([decode_vector(f.data) for _, _, _, f in rows]).astype(np.float64)
        sift = [decode_sift(s.n_keypoints, s.keypoints, s.descriptors) for _, _, s, _ in rows]
        positions = np.full((len(rows), 2), np.nan)
        for k, (r, img, _, _) in enumerate(rows):
            if img.east is not None:
                positions[k] = (img.east, img.north)
            elif r.lat is not None and origin is not None:
                positions[k] = origin.to_local(r.lat, r.lon)
        seqs = [r.seq for r, _, _, _ in rows]
    # the hue histograms are compared as Li eq. 5 compares them: unit vectors, Euclidean
    hue /= np.maximum(np.linalg.norm(hue, axis=1, keepdims=True), 1e-12)
    K = camera_matrix(WORK_SIZE[0], WORK_SIZE[1], params.hfov_deg)
    result = build(odometry, hue, np.array([len(s) for s in sift]),
                   verify=sift_verifier(sift), relative_yaw=yaw_from_views(sift, K),
                   positions=positions, params=params)
    length = float(np.sum(np.hypot(*np.diff(result.path[:, :2], axis=0).T)))
    with sessions(database_url)() as db, db.begin():
        for table in (RouteNode, RouteArc):
            db.execute(delete(table).where(table.route_id == rid))
        ends = list(result.node_images[1:] - 1) + [len(seqs) - 1]
        for k, (first, last) in enumerate(zip(result.node_images, ends, strict=True)):
            o, p = result.node_odometry[k], result.node_poses[k]
            db.add(RouteNode(route_id=rid, idx=k, first_seq=seqs[first], last_seq=seqs[last],
                             odom_x=o[0], odom_y=o[1], odom_theta=o[2], x=p[0], y=p[1],
                             theta=p[2], variance=float(result.node_variances[k])))
        n_odometry = len(result.arcs) - result.loop_arcs
        for k, arc in enumerate(result.arcs):
            db.add(RouteArc(route_id=rid, idx=k, node_a=arc.a, node_b=arc.b, dx=arc.dx,
                            dy=arc.dy, dtheta=arc.dtheta, variance=arc.variance,
                            kind=("odometry" if k < n_odometry else "loop")))
        images = {r.seq: r for r in db.scalars(select(RouteImage)
                                               .where(RouteImage.route_id == rid))}
        for k, seq in enumerate(seqs):
            row = images[seq]
            row.node = int(result.image_nodes[k])
            row.x, row.y = float(result.path[k, 0]), float(result.path[k, 1])
            row.theta = float(math.remainder(result.path[k, 2], 2 * math.pi))
        route = db.get(Route, rid)
        route.status, route.error, route.built_at = RouteStatus.READY, None, utcnow()
        route.n_nodes, route.n_loops = len(result.node_images), result.loop_arcs
        route.length_m, route.sweeps = length, result.sweeps
    return {"nodes": len(result.node_images), "loops": result.loop_arcs}
