"""Every table, imported in one place for Alembic and ``Base.metadata``."""

from vloc.app.db import Base
from vloc.app.jobs.models import BuildJob
from vloc.app.maps.models import (
    ImageGlobalFeature,
    ImageOrb,
    ImageSift,
    Map,
    MapImage,
    MapVocabulary,
)
from vloc.app.sessions.models import Frame, LocalisationSession, Pose
from vloc.app.teach.models import Route, RouteArc, RouteImage, RouteNode

__all__ = ["Base", "BuildJob", "Frame", "ImageGlobalFeature", "ImageOrb", "ImageSift",
           "LocalisationSession", "Map", "MapImage", "MapVocabulary", "Pose", "Route", "RouteArc",
           "RouteImage", "RouteNode"]
