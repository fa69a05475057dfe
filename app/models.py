"""Every table, imported in one place for Alembic and ``Base.metadata``."""

from app.db import Base
from app.jobs.models import BuildJob
from app.maps.models import (
    ImageGlobalFeature,
    ImageOrb,
    ImageSift,
    Map,
    MapImage,
    MapVocabulary,
)
from app.routes.models import Route, RouteArc, RouteImage, RouteNode
from app.sessions.models import Frame, LocalisationSession, Pose

__all__ = ["Base", "BuildJob", "Frame", "ImageGlobalFeature", "ImageOrb", "ImageSift",
           "LocalisationSession", "Map", "MapImage", "MapVocabulary", "Pose", "Route", "RouteArc",
           "RouteImage", "RouteNode"]
