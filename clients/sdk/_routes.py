"""The routes both clients call the same way: one request each, built by
:mod:`._requests` and sent by the class's ``_call`` (blocking in :class:`Client`, a coroutine
in :class:`AsyncClient`, whose methods are then awaited). What differs between the two, the
sending, the waits, paging and the stream, stays in each class.

The return annotations are the blocking client's; :class:`AsyncClient` returns awaitables of
the same values.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime
from typing import Any

from . import _requests as rq
from ._models import (
    Coverage,
    FrameAccepted,
    FrameError,
    Job,
    Localization,
    Map,
    MapImage,
    MapRevision,
    Pose,
    Route,
    Session,
    UploadResult,
)
from ._requests import Call, ImageSource

SessionRef = Session | str
"""A session, or its id."""


def session_ref(session: SessionRef, token: str | None) -> tuple[str, str | None]:
    """``(id, token)``: an explicit token wins over the one a created Session carries."""
    if isinstance(session, Session):
        return session.id, token or session.token
    return str(session), token


class Routes(ABC):
    """The single-request methods of :class:`Client` and :class:`AsyncClient`."""

    @abstractmethod
    def _call(self, call: Call) -> Any:
        """Send one request and decode its answer (blocking, or a coroutine)."""

    @abstractmethod
    def _every(self, call: Callable[..., Call], *args) -> Any:
        """Every item of a paged listing, page by page."""

    def health(self) -> dict:
        """``GET /healthz``: the process answers."""
        return self._call(rq.healthz())

    def ready(self) -> dict:
        """``GET /readyz``: database and workers up (503 ServerError otherwise)."""
        return self._call(rq.readyz())

    def create_map(self, name: str) -> Map:
        return self._call(rq.create_map(name))

    def list_maps(self) -> list[Map]:
        """Every map (read page by page)."""
        return self._every(rq.list_maps)

    def get_map(self, map_id: str) -> Map:
        return self._call(rq.get_map(map_id))

    def delete_map(self, map_id: str) -> None:
        """Delete a map, its images and builds (409 while sessions use it)."""
        return self._call(rq.delete_map(map_id))

    def list_images(self, map_id: str) -> list[MapImage]:
        """Every image of the map, in id order (read page by page)."""
        return self._every(rq.list_images, map_id)

    def upload_images(self, map_id: str, images: Sequence[ImageSource], *,
                      lat: float | None = None, lon: float | None = None,
                      alt: float | None = None, captured_at: datetime | None = None,
                      flight: str | None = None) -> UploadResult:
        """Add JPEG/PNG images positioned by their EXIF GPS, or one image at ``lat``/``lon``;
        ``flight`` names the flight (or pass) they belong to, for a map of several.

        Files the server refuses are listed in ``rejected``; when none is accepted the
        call raises the problem (422, 413, 409...) instead.
        """
        return self._call(rq.upload_images(map_id, images, lat=lat, lon=lon, alt=alt,
                                           captured_at=captured_at, flight=flight))

    def build_map(self, map_id: str, *, force: bool = False, full: bool = False) -> Job:
        """Start a build of the images added since the last one; returns the queued job.
        ``force`` packs a new revision even when there is nothing new (else 409
        ``map-up-to-date``). The images added are registered into the map's camera
        geometry as it stands, and the map's place vocabularies kept while they fit it;
        ``full`` reconstructs the geometry whole and trains the vocabularies afresh
        instead (and implies ``force``)."""
        return self._call(rq.build_map(map_id, force=force, full=full))

    def list_revisions(self, map_id: str) -> list[MapRevision]:
        """The map's packed revisions, newest first."""
        return self._call(rq.list_revisions(map_id))

    def restore_revision(self, map_id: str, revision: int) -> Map:
        """Make ``revision`` the map's current revision again (new sessions use it; open
        ones that follow the map move to it); returns the map."""
        return self._call(rq.restore_revision(map_id, revision))

    def drop_revision(self, map_id: str, revision: int) -> None:
        """Delete a revision and its files (409 ``revision-current`` for the current one,
        ``revision-in-use`` while active sessions use it)."""
        return self._call(rq.drop_revision(map_id, revision))

    def get_job(self, job_id: str) -> Job:
        return self._call(rq.get_job(job_id))

    def create_session(self, map_id: str, *, mode: str = "hybrid",
                       params: dict[str, Any] | None = None,
                       seed: int | None = None,
                       navigation: dict[str, Any] | None = None,
                       ttl_s: int | None = None, map_revision: int | None = None,
                       follow_map: bool | None = None) -> Session:
        """Open a session on a built map; the returned Session carries its token.

        ``navigation`` (``route_id``, optionally ``from_node``, ``to_node`` and ``params``)
        makes the session follow a ready route: each pose then carries the path following.
        ``ttl_s``: seconds without a frame or keep-alive after which it expires (the
        server's default when None). The session follows the map to each new revision
        (between two frames, keeping its state) unless ``follow_map`` is False or it pins
        ``map_revision``, a recorded revision it then stays on.
        """
        return self._call(rq.create_session(map_id, mode=mode, params=params, seed=seed,
                                            navigation=navigation, ttl_s=ttl_s,
                                            map_revision=map_revision,
                                            follow_map=follow_map))

    def create_route(self, map_id: str, odometry: bytes, *, name: str = "route",
                     params: dict[str, Any] | None = None,
                     max_step_m: float | None = None) -> Route:
        """Teach a route: the odometry CSV (``filename, x, y, theta[, lat, lon]`` in driving
        order) of images the map already has, built; the route builds in the background."""
        return self._call(rq.create_route(map_id, odometry, name=name, params=params,
                                          max_step_m=max_step_m))

    def get_route(self, map_id: str, route_id: str) -> Route:
        """A route with its nodes, arcs and taught path."""
        return self._call(rq.get_route(map_id, route_id))

    def list_routes(self, map_id: str) -> list[Route]:
        return self._call(rq.list_routes(map_id))

    def list_sessions(self) -> list[Session]:
        """Every session (read page by page)."""
        return self._every(rq.list_sessions)

    def get_session(self, session: SessionRef, *, token: str | None = None) -> Session:
        return self._call(rq.get_session(*session_ref(session, token)))

    def delete_session(self, session: SessionRef, *, token: str | None = None) -> None:
        """Close a session; its open streams end."""
        return self._call(rq.delete_session(*session_ref(session, token)))

    def list_poses(self, session: SessionRef, *, after_seq: int | None = None,
                   limit: int = 1000, token: str | None = None) -> list[Pose | FrameError]:
        """Stored outcomes in sequence order, after ``after_seq``: the estimates, and a
        :class:`FrameError` for each frame that gave none."""
        return self._call(rq.list_poses(*session_ref(session, token), after_seq=after_seq,
                                        limit=limit))

    def send_frame(self, session: SessionRef, image: ImageSource, *, seq: int | None = None,
                   captured_at: datetime | float | str | None = None, wait: bool = False,
                   content_type: str | None = None, token: str | None = None,
                   metadata: Mapping[str, float | None] | None = None) -> FrameAccepted | Pose:
        """POST one frame; :class:`FrameAccepted` (its seq), or with ``wait`` the Pose.

        Give ``seq`` (increasing) to make the call safe to retry. ``captured_at`` is a
        datetime, an ISO 8601 string or seconds since the epoch. ``metadata`` holds the
        device's other sensor reports for this frame, by the names of
        :data:`FRAME_METADATA` (``{"heading_deg": 87.0, "gps_lat": ..., "gps_lon": ...}``);
        the server checks them (422 ``bad-metadata`` naming the field).
        """
        return self._call(rq.send_frame(*session_ref(session, token), image, seq=seq,
                                        captured_at=captured_at, wait=wait,
                                        content_type=content_type, metadata=metadata))

    def localize(self, map_id: str, image: ImageSource, *,
                 prior: tuple[float, float] | None = None,
                 prior_sigma_m: float | None = None, mode: str | None = None,
                 captured_at: datetime | float | str | None = None, seed: int | None = None,
                 metadata: Mapping[str, float | None] | None = None,
                 content_type: str | None = None) -> Localization:
        """Where was this one image taken? ``prior`` is (lat, lon) with ``prior_sigma_m``;
        ``mode`` is ``sift`` (the server's default), ``global`` or ``hybrid``."""
        return self._call(rq.localize(map_id, image, prior=prior, prior_sigma_m=prior_sigma_m,
                                      mode=mode, captured_at=captured_at, seed=seed,
                                      metadata=metadata, content_type=content_type))

    def coverage(self, lat: float, lon: float, *,
                 radius_m: float | None = None) -> list[Coverage]:
        """The built maps with an image within ``radius_m`` (server default 50 m)."""
        return self._call(rq.coverage(lat, lon, radius_m))

    def keep_alive(self, session: SessionRef, *, token: str | None = None) -> Session:
        """Restart the session's time to live."""
        return self._call(rq.keep_alive(*session_ref(session, token)))

    def reset_session(self, session: SessionRef, *, token: str | None = None) -> Session:
        """Global re-initialisation of the filter (after the frames already queued)."""
        return self._call(rq.reset_session(*session_ref(session, token)))

    def set_initial_pose(self, session: SessionRef, *, lat: float | None = None,
                         lon: float | None = None, x: float | None = None,
                         y: float | None = None, sigma: float = 5.0,
                         token: str | None = None) -> Session:
        """Restart the filter around ``lat``/``lon`` or map ``x``/``y`` (sigma metres)."""
        return self._call(rq.set_initial_pose(*session_ref(session, token), lat=lat, lon=lon,
                                              x=x, y=y, sigma=sigma))
