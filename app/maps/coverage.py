"""Which built maps cover a position: those with a built image within a radius of it."""

from __future__ import annotations

import math
import uuid

from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from vloc.app.maps.models import Map, MapImage

EARTH_RADIUS_M = 6_371_008.8
"""Mean radius (IUGG): distances over a map's extent are far below its error."""


class Coverage(BaseModel):
    map_id: uuid.UUID
    name: str
    revision: int = Field(description="The revision a new session would use")
    distance_m: float = Field(description="From the position to the nearest built image")
    image_count: int = Field(description="Built images within the radius")


def covering_maps(db: Session, *, lat: float, lon: float, radius_m: float) -> list[Coverage]:
    """Built maps with an image of their current revision within ``radius_m`` of the
    position, nearest first."""
    dlat = math.degrees(radius_m / EARTH_RADIUS_M)
    dlon = dlat / max(math.cos(math.radians(lat)), 1e-6)
    rows = db.execute(
        select(Map.id, Map.name, Map.revision, MapImage.lat, MapImage.lon)
        .join(MapImage, MapImage.map_id == Map.id)
        .where(Map.revision > 0, MapImage.built_revision.is_not(None),
               MapImage.built_revision <= Map.revision,
               MapImage.lat.between(lat - dlat, lat + dlat),
               MapImage.lon.between(lon - dlon, lon + dlon))).all()
    found: dict[uuid.UUID, Coverage] = {}
    for map_id, name, revision, ilat, ilon in rows:
        d = haversine_m(lat, lon, ilat, ilon)
        if d > radius_m:
            continue
        seen = found.get(map_id)
        if seen is None:
            found[map_id] = Coverage(map_id=map_id, name=name, revision=revision,
                                     distance_m=d, image_count=1)
        else:
            found[map_id] = seen.model_copy(update={
                "distance_m": min(seen.distance_m, d), "image_count": seen.image_count + 1})
    return sorted(found.values(), key=lambda c: (c.distance_m, str(c.map_id)))


def haversine_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2.0 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))
