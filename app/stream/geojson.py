"""Pose messages as GeoJSON features, for viewers that read GeoJSON (the ``vloc.geojson``
subprotocol of the stream).

A pose becomes a ``Feature`` whose geometry is the estimate in WGS84 (``[lon, lat]``, RFC
7946 order) and whose properties carry the rest: the position in the map's frame, the
covariance and spreads, the heading where known, the step's kind and timings, and the
particle sample in the map's east/north metres (``cloud``). Every other message is sent
as it is.
"""

from __future__ import annotations

GEOJSON_SUBPROTOCOL = "vloc.geojson"

_GEOMETRY_KEYS = ("type", "lat", "lon")


def as_feature(message: dict) -> dict:
    """The GeoJSON ``Feature`` of a ``pose`` message; any other message unchanged."""
    if message.get("type") != "pose":
        return message
    properties = {k: v for k, v in message.items() if k not in _GEOMETRY_KEYS}
    properties["message"] = "pose"
    return {"type": "Feature", "id": message["seq"],
            "geometry": {"type": "Point", "coordinates": [message["lon"], message["lat"]]},
            "properties": properties}
