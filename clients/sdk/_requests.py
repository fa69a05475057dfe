"""Each API route as a :class:`Call`: what to send, whether a retry is safe, how to read
the answer. Shared by the sync and async clients, which only differ in how they send."""

from __future__ import annotations

import json
import mimetypes
import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from os import PathLike
from pathlib import Path
from typing import Any

import httpx

from ._exceptions import APIError, ProblemKind, error_for_response
from ._models import (
    Coverage,
    FrameAccepted,
    Job,
    Localization,
    Map,
    MapImage,
    MapRevision,
    Pose,
    Route,
    Session,
    UploadResult,
    parse_message,
)

ImageSource = str | PathLike | bytes | tuple[str, bytes]
"""A file path, raw JPEG/PNG bytes, or ``(filename, bytes)``."""

RETRY_STATUSES = frozenset({429, 502, 503, 504})
WAIT_READ_TIMEOUT_S = 120.0
"""Read timeout of ``?wait=true`` frames: longer than the server's own wait (60 s)."""


def _none(response: httpx.Response) -> None:
    return None


def _model(cls) -> Callable[[httpx.Response], Any]:
    return lambda r: cls.model_validate(r.json())


def _models(cls) -> Callable[[httpx.Response], Any]:
    return lambda r: [cls.model_validate(item) for item in r.json()]


@dataclass(frozen=True)
class Call:
    """One request to the API.

    Attributes
    ----------
    idempotent : bool
        Sending it twice has the effect of sending it once, so it may be retried.
    token : str or None
        Credentials for this call instead of the client's admin key (a session token).
    accepted_seq : int or None
        A frame POST with an explicit ``seq``: a retry answered ``409 duplicate-seq``
        means an earlier attempt got through, so it counts as accepted.
    read_timeout : float or None
        A longer read timeout than the client's, for calls that wait on the server.
    """

    method: str
    path: str
    parse: Callable[[httpx.Response], Any] = _none
    params: dict[str, Any] | None = None
    json: Any = None
    data: dict[str, Any] | None = None
    files: list[tuple[str, tuple[str, bytes, str]]] | None = None
    content: bytes | None = None
    headers: dict[str, str] = field(default_factory=dict)
    idempotent: bool = False
    token: str | None = None
    accepted_seq: int | None = None
    read_timeout: float | None = None


@dataclass(frozen=True)
class RetryPolicy:
    """Exponential backoff with full jitter for idempotent calls.

    A call is retried on a connection failure (nothing was sent) and on 429/502/503/504;
    a ``Retry-After`` header, when given, replaces the computed delay (capped at
    ``max_delay``).
    """

    retries: int = 3
    backoff: float = 0.25
    max_delay: float = 8.0

    def delay(self, attempt: int, error: APIError | None = None,
              rng: random.Random | None = None) -> float:
        advised = error.body.get("retry_after") if error is not None else None
        if isinstance(advised, int | float) and advised >= 0:
            return min(float(advised), self.max_delay)
        cap = min(self.backoff * 2 ** attempt, self.max_delay)
        return (rng or random).uniform(0.5 * cap, cap)


def retryable(call: Call, error: Exception) -> bool:
    """Whether a failed attempt of ``call`` may be sent again."""
    if not call.idempotent:
        return False
    if isinstance(error, APIError):
        return error.status in RETRY_STATUSES
    # Connect failures mean the request never reached the server.
    return isinstance(error, httpx.ConnectError | httpx.ConnectTimeout | httpx.PoolTimeout)


def outcome(call: Call, response: httpx.Response, *, retried: bool) -> Any:
    """The parsed answer of a response, or raise its :class:`APIError`."""
    if response.is_success:
        return call.parse(response)
    error = error_for_response(response)
    if (retried and call.accepted_seq is not None and error.status == 409
            and error.kind == ProblemKind.DUPLICATE_SEQ):
        return FrameAccepted(seq=call.accepted_seq)
    raise error


# -- maps -------------------------------------------------------------------------------------

def create_map(name: str) -> Call:
    return Call("POST", "/v1/maps", _model(Map), json={"name": name})


PAGE = 500
"""Items per page when the client reads a whole listing."""


def list_maps(*, offset: int = 0, limit: int | None = None) -> Call:
    return Call("GET", "/v1/maps", _models(Map), idempotent=True,
                params={"offset": offset, "limit": limit or PAGE})


def get_map(map_id: str) -> Call:
    return Call("GET", f"/v1/maps/{map_id}", _model(Map), idempotent=True)


def delete_map(map_id: str) -> Call:
    return Call("DELETE", f"/v1/maps/{map_id}", idempotent=True)


def list_images(map_id: str, *, offset: int = 0, limit: int | None = None) -> Call:
    """``offset`` is the id after which to list (the service pages by image id)."""
    return Call("GET", f"/v1/maps/{map_id}/images", _models(MapImage), idempotent=True,
                params={"after_id": offset, "limit": limit or PAGE})


def upload_images(map_id: str, images: Sequence[ImageSource], *, lat: float | None = None,
                  lon: float | None = None, alt: float | None = None,
                  captured_at: datetime | None = None, flight: str | None = None) -> Call:
    """Multipart ``files``; ``lat``/``lon`` (and ``alt``, ``captured_at``) for one file;
    ``flight`` for all of them."""
    files = [("files", _file_part(img, i)) for i, img in enumerate(images)]
    form = {k: str(v) for k, v in (("lat", lat), ("lon", lon), ("alt", alt),
                                   ("flight", flight)) if v is not None}
    if captured_at is not None:
        form["captured_at"] = captured_at.isoformat()
    return Call("POST", f"/v1/maps/{map_id}/images", _model(UploadResult), files=files,
                data=form or None)


def build_map(map_id: str, *, force: bool = False, full: bool = False) -> Call:
    def parse(r: httpx.Response) -> Job:
        body = r.json()
        return Job(id=str(body["job_id"]), map_id=str(map_id), status=body.get("status", ""))

    return Call("POST", f"/v1/maps/{map_id}/build", parse,
                params={k: "true" for k, v in (("force", force), ("full", full)) if v} or None)


def list_revisions(map_id: str) -> Call:
    return Call("GET", f"/v1/maps/{map_id}/revisions", _models(MapRevision), idempotent=True)


def restore_revision(map_id: str, revision: int) -> Call:
    # restoring the same revision twice leaves the map as once
    return Call("POST", f"/v1/maps/{map_id}/revisions/{int(revision)}/restore", _model(Map),
                idempotent=True)


def drop_revision(map_id: str, revision: int) -> Call:
    return Call("DELETE", f"/v1/maps/{map_id}/revisions/{int(revision)}", idempotent=True)


def get_job(job_id: str) -> Call:
    return Call("GET", f"/v1/jobs/{job_id}", _model(Job), idempotent=True)


# -- routes -----------------------------------------------------------------------------------

def create_route(map_id: str, odometry: bytes, *, name: str, params: dict[str, Any] | None,
                 max_step_m: float | None) -> Call:
    form: dict[str, Any] = {"name": name}
    if params:
        form["params"] = json.dumps(params)
    if max_step_m is not None:
        form["max_step_m"] = repr(float(max_step_m))
    return Call("POST", f"/v1/maps/{map_id}/routes", _model(Route), data=form,
                files=[("odometry", ("odometry.csv", odometry, "text/csv"))])


def get_route(map_id: str, route_id: str) -> Call:
    return Call("GET", f"/v1/maps/{map_id}/routes/{route_id}", _model(Route), idempotent=True)


def list_routes(map_id: str) -> Call:
    return Call("GET", f"/v1/maps/{map_id}/routes", _models(Route), idempotent=True)


# -- sessions ---------------------------------------------------------------------------------

def create_session(map_id: str, *, mode: str, params: dict[str, Any] | None,
                   seed: int | None, navigation: dict[str, Any] | None = None,
                   ttl_s: int | None = None, map_revision: int | None = None,
                   follow_map: bool | None = None) -> Call:
    body: dict[str, Any] = {"map_id": str(map_id), "mode": mode, "params": dict(params or {})}
    if seed is not None:
        body["seed"] = seed
    if map_revision is not None:
        body["map_revision"] = int(map_revision)
    if follow_map is not None:
        body["follow_map"] = bool(follow_map)
    if ttl_s is not None:
        body["ttl_s"] = int(ttl_s)
    if navigation is not None:
        body["navigation"] = navigation
    return Call("POST", "/v1/sessions", _model(Session), json=body)


def list_sessions(*, offset: int = 0, limit: int | None = None) -> Call:
    return Call("GET", "/v1/sessions", _models(Session), idempotent=True,
                params={"offset": offset, "limit": limit or PAGE})


def next_offset(call: Callable[..., Call], items: list, offset: int) -> int:
    """Where the page after ``items`` starts: the last image id for images (listed by id),
    else the count so far."""
    return items[-1].id if call is list_images else offset + len(items)


def get_session(session_id: str, token: str | None) -> Call:
    return Call("GET", f"/v1/sessions/{session_id}", _model(Session), idempotent=True,
                token=token)


def delete_session(session_id: str, token: str | None) -> Call:
    return Call("DELETE", f"/v1/sessions/{session_id}", idempotent=True, token=token)


def list_poses(session_id: str, token: str | None, *, after_seq: int | None,
               limit: int) -> Call:
    params: dict[str, Any] = {"limit": limit}
    if after_seq is not None:
        params["after_seq"] = after_seq
    return Call("GET", f"/v1/sessions/{session_id}/poses",
                lambda r: [parse_message(item) for item in r.json()], params=params,
                idempotent=True, token=token)


FRAME_METADATA = ("heading_deg", "heading_accuracy_deg", "altitude_m", "gps_lat", "gps_lon",
                  "gps_accuracy_m", "velocity_east", "velocity_north")
"""The optional sensor reports a frame may carry (docs/api.md, "Frame metadata")."""

CapturedAt = datetime | float | str
"""A capture time: an aware datetime (a naive one is taken as UTC, as the server does), an
ISO 8601 string, or seconds since the epoch."""


def captured_at_param(captured_at: CapturedAt) -> str | float:
    """The wire form of a capture time; ValueError for a string that is not ISO 8601."""
    if isinstance(captured_at, datetime):
        return captured_at.isoformat()
    if isinstance(captured_at, str):
        try:
            datetime.fromisoformat(captured_at)
        except ValueError:
            raise ValueError(f"captured_at {captured_at!r} is not an ISO 8601 time") from None
        return captured_at
    if isinstance(captured_at, bool) or not isinstance(captured_at, int | float):
        raise TypeError("captured_at must be a datetime, an ISO 8601 string or seconds since "
                        f"the epoch, not {type(captured_at).__name__}")
    return float(captured_at)


def metadata_params(metadata: Mapping[str, float | None] | None) -> dict[str, float]:
    """The frame's metadata as query parameters; ValueError for a name the server does not
    know (it would otherwise be ignored silently)."""
    if not metadata:
        return {}
    unknown = sorted(set(metadata) - set(FRAME_METADATA))
    if unknown:
        raise ValueError(f"unknown frame metadata {unknown}; known: {', '.join(FRAME_METADATA)}")
    return {k: float(v) for k, v in metadata.items() if v is not None}


def send_frame(session_id: str, token: str | None, image: ImageSource, *,
               seq: int | None, captured_at: CapturedAt | None, wait: bool,
               content_type: str | None,
               metadata: Mapping[str, float | None] | None = None) -> Call:
    """The raw image as the body. With ``seq`` the server refuses a second copy, so the
    POST is safe to retry; without one it is not. ``metadata`` (:data:`FRAME_METADATA`)
    goes as query parameters."""
    name, data = _read_source(image, 0)
    params: dict[str, Any] = {}
    if seq is not None:
        params["seq"] = seq
    if captured_at is not None:
        value = captured_at_param(captured_at)
        params["captured_at"] = repr(value) if isinstance(value, float) else value
    params.update(metadata_params(metadata))
    if wait:
        params["wait"] = "true"

    def parse(r: httpx.Response) -> FrameAccepted | Pose:
        body = r.json()
        return Pose.model_validate(body) if body.get("type") == "pose" \
            else FrameAccepted.model_validate(body)

    ctype = content_type or image_content_type(data, name)
    return Call("POST", f"/v1/sessions/{session_id}/frames", parse, params=params,
                content=data, headers={"Content-Type": ctype}, idempotent=seq is not None,
                token=token, accepted_seq=seq if not wait else None,
                read_timeout=WAIT_READ_TIMEOUT_S if wait else None)


def localize(map_id: str, image: ImageSource, *, prior: tuple[float, float] | None,
             prior_sigma_m: float | None, mode: str | None,
             captured_at: CapturedAt | None, seed: int | None,
             metadata: Mapping[str, float | None] | None,
             content_type: str | None) -> Call:
    """One image, answered synchronously; safe to retry (nothing is stored)."""
    name, data = _read_source(image, 0)
    params: dict[str, Any] = metadata_params(metadata)
    if prior is not None:
        params["prior_lat"], params["prior_lon"] = float(prior[0]), float(prior[1])
    if prior_sigma_m is not None:
        params["prior_sigma_m"] = float(prior_sigma_m)
    if mode is not None:
        params["mode"] = mode
    if seed is not None:
        params["seed"] = int(seed)
    if captured_at is not None:
        value = captured_at_param(captured_at)
        params["captured_at"] = repr(value) if isinstance(value, float) else value
    return Call("POST", f"/v1/maps/{map_id}/localize", _model(Localization), params=params,
                content=data, headers={"Content-Type": content_type
                                       or image_content_type(data, name)},
                idempotent=True, read_timeout=WAIT_READ_TIMEOUT_S)


def coverage(lat: float, lon: float, radius_m: float | None) -> Call:
    params: dict[str, Any] = {"lat": lat, "lon": lon}
    if radius_m is not None:
        params["radius_m"] = radius_m
    return Call("GET", "/v1/maps/coverage", _models(Coverage), params=params, idempotent=True)


def keep_alive(session_id: str, token: str | None) -> Call:
    return Call("POST", f"/v1/sessions/{session_id}/keepalive", _model(Session), token=token,
                idempotent=True)


def reset_session(session_id: str, token: str | None) -> Call:
    return Call("POST", f"/v1/sessions/{session_id}/reset", _model(Session), token=token)


def set_initial_pose(session_id: str, token: str | None, *, lat: float | None,
                     lon: float | None, x: float | None, y: float | None,
                     sigma: float) -> Call:
    body = {k: v for k, v in (("lat", lat), ("lon", lon), ("x", x), ("y", y))
            if v is not None}
    body["sigma"] = sigma
    return Call("POST", f"/v1/sessions/{session_id}/initial-pose", _model(Session),
                json=body, token=token)


# -- health -----------------------------------------------------------------------------------

def readyz() -> Call:
    return Call("GET", "/readyz", lambda r: r.json(), idempotent=True)


def healthz() -> Call:
    return Call("GET", "/healthz", lambda r: r.json(), idempotent=True)


# -- helpers ----------------------------------------------------------------------------------

def image_content_type(data: bytes, name: str = "") -> str:
    """``image/jpeg`` or ``image/png`` from the magic bytes, else from the file name."""
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    guessed, _ = mimetypes.guess_type(name)
    return guessed or "application/octet-stream"


def image_bytes(image: ImageSource) -> bytes:
    """The bytes of an image given as a path, bytes or ``(name, bytes)``."""
    return _read_source(image, 0)[1]


def _read_source(image: ImageSource, index: int) -> tuple[str, bytes]:
    if isinstance(image, bytes | bytearray | memoryview):
        return f"image-{index}", bytes(image)
    if isinstance(image, tuple):
        name, data = image
        return str(name), bytes(data)
    if not isinstance(image, str | PathLike):
        raise TypeError("an image is a path, bytes or (name, bytes), not "
                        f"{type(image).__name__}")
    path = Path(image)
    return path.name, path.read_bytes()


def _file_part(image: ImageSource, index: int) -> tuple[str, bytes, str]:
    name, data = _read_source(image, index)
    return name, data, image_content_type(data, name)
