"""The blocking client: :class:`Client`."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import httpx

from . import _requests as rq
from ._exceptions import JobFailed, TransportError, VlocError, WaitTimeout
from ._models import Job, Route
from ._requests import Call, RetryPolicy
from ._routes import Routes, SessionRef, session_ref
from ._stream import Connect, PoseStream, websockets_connect

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT = httpx.Timeout(30.0, connect=5.0)

def resolve_settings(base_url: str | None, admin_key: str | None) -> tuple[str, str | None]:
    """Explicit values, else ``VLOC_URL`` / ``VLOC_ADMIN_KEY``, else the local default."""
    url = base_url or os.environ.get("VLOC_URL") or DEFAULT_URL
    key = admin_key if admin_key is not None else os.environ.get("VLOC_ADMIN_KEY") or None
    return url.rstrip("/"), key


def stream_url(base_url: str, session_id: str) -> str:
    scheme, sep, rest = base_url.partition("://")
    ws_scheme = {"http": "ws", "https": "wss"}.get(scheme, scheme)
    return f"{ws_scheme}{sep}{rest}/v1/sessions/{session_id}/stream"


def auth_headers(token: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


class Client(Routes):
    """A blocking client for every route of the vloc API.

    Parameters
    ----------
    base_url : str, optional
        Server address; default ``$VLOC_URL``, else ``http://127.0.0.1:8000``.
    admin_key : str, optional
        For the admin routes (maps, jobs, creating sessions); default ``$VLOC_ADMIN_KEY``.
        Session routes use the session's token when one is known, else this key.
    timeout : float or httpx.Timeout
    retry : RetryPolicy or int
        Backoff for idempotent calls (GET, DELETE, frames with an explicit ``seq``); an
        int is the number of retries.
    transport : httpx.BaseTransport, optional
        Where requests go instead of the network (``httpx.MockTransport``, a WSGI/ASGI
        transport).
    http : httpx.Client, optional
        An HTTP client to send through instead of one of our own (Starlette's
        ``TestClient`` for the in-process app); the caller closes it.
    ws_connect : Connect, optional
        Opens the pose stream's WebSocket; default the ``websockets`` library.

    Examples
    --------
    >>> with Client("http://127.0.0.1:8000", admin_key="...") as vloc:  # doctest: +SKIP
    ...     m = vloc.create_map("campus")
    ...     vloc.upload_images(m.id, sorted(Path("photos").glob("*.jpg")))
    ...     vloc.wait_for_job(vloc.build_map(m.id).id)
    """

    def __init__(self, base_url: str | None = None, *, admin_key: str | None = None,
                 timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
                 retry: RetryPolicy | int = 3, transport: httpx.BaseTransport | None = None,
                 http: httpx.Client | None = None, ws_connect: Connect | None = None,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if base_url is None and http is not None and str(http.base_url):
            base_url = str(http.base_url)
        self.base_url, self.admin_key = resolve_settings(base_url, admin_key)
        self.retry = retry if isinstance(retry, RetryPolicy) else RetryPolicy(retries=retry)
        self._owns_http = http is None
        self._http = http or httpx.Client(base_url=self.base_url, timeout=timeout,
                                          transport=transport)
        self._timeout = timeout if isinstance(timeout, httpx.Timeout) else httpx.Timeout(timeout)
        self._ws_connect = ws_connect or websockets_connect()
        self._sleep = sleep

    # -- plumbing ---------------------------------------------------------------------------

    def _url(self, path: str) -> str:
        return path if str(self._http.base_url) else f"{self.base_url}{path}"

    def _send(self, call: Call) -> httpx.Response:
        headers = {**auth_headers(call.token or self.admin_key), **call.headers}
        timeout: httpx.Timeout | object = self._timeout
        if not self._owns_http:
            timeout = httpx.USE_CLIENT_DEFAULT  # a caller's client keeps its own timeouts
        elif call.read_timeout is not None:
            timeout = httpx.Timeout(self._timeout.connect, read=call.read_timeout,
                                    write=self._timeout.write, pool=self._timeout.pool)
        try:
            return self._http.request(call.method, self._url(call.path), params=call.params,
                                      json=call.json, data=call.data, files=call.files,
                                      content=call.content, headers=headers, timeout=timeout)
        except httpx.TransportError as exc:
            raise TransportError(f"{call.method} {call.path}: {type(exc).__name__}: "
                                 f"{exc or 'no answer'}") from exc

    def _call(self, call: Call) -> Any:
        attempt = 0
        while True:
            try:
                return rq.outcome(call, self._send(call), retried=attempt > 0)
            except VlocError as error:
                cause = error.__cause__ if isinstance(error, TransportError) else error
                if attempt >= self.retry.retries or not rq.retryable(call, cause):
                    raise
                self._sleep(self.retry.delay(attempt, None if cause is not error else error))
                attempt += 1

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Any other route, with the client's credentials; errors raised as for the rest.

        ``kwargs`` go to :meth:`httpx.Client.request`.
        """
        headers = {**auth_headers(self.admin_key), **kwargs.pop("headers", {})}
        try:
            response = self._http.request(method, self._url(path), headers=headers, **kwargs)
        except httpx.TransportError as exc:
            raise TransportError(f"{method} {path}: {type(exc).__name__}: {exc}") from exc
        return rq.outcome(Call(method, path, lambda r: r), response, retried=False)

    def close(self) -> None:
        if self._owns_http:
            self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- health -----------------------------------------------------------------------------

    def wait_ready(self, timeout: float = 60.0, *, interval: float = 0.2) -> dict:
        """Poll ``/readyz`` until it answers 200; :class:`WaitTimeout` after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self._call(rq.Call("GET", "/readyz", lambda r: r.json()))
            except VlocError as exc:
                if time.monotonic() >= deadline:
                    raise WaitTimeout(f"{self.base_url} not ready within {timeout:g} s: "
                                      f"{exc}") from exc
            self._sleep(interval)

    # -- maps -------------------------------------------------------------------------------

    def wait_for_job(self, job_id: str, timeout: float = 600.0, *,
                     on_progress: Callable[[Job], None] | None = None,
                     poll_interval: float = 0.5) -> Job:
        """Poll a job until it is done.

        Parameters
        ----------
        on_progress : callable, optional
            Called with the job after every poll (``job.progress`` in [0, 1]).

        Raises
        ------
        JobFailed
            The job ended ``failed``.
        WaitTimeout
            Still not finished after ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        while True:
            job = self.get_job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job.status == "failed":
                raise JobFailed(job)
            if job.status == "done":
                return job
            if time.monotonic() >= deadline:
                raise WaitTimeout(f"job {job_id} still {job.status} after {timeout:g} s "
                                  f"({100 * job.progress:.0f} %)")
            self._sleep(poll_interval)

    # -- sessions ---------------------------------------------------------------------------

    def wait_for_route(self, map_id: str, route_id: str, timeout: float = 600.0, *,
                       poll_interval: float = 0.5) -> Route:
        """Poll a route until it is built.

        Raises
        ------
        VlocError
            The route ended ``failed`` (its error in the message).
        WaitTimeout
            Still building after ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        while True:
            route = self.get_route(map_id, route_id)
            if route.status == "failed":
                raise VlocError(f"route {route_id} failed to build: {route.error}")
            if route.status == "ready":
                return route
            if time.monotonic() >= deadline:
                raise WaitTimeout(f"route {route_id} still {route.status} after {timeout:g} s")
            self._sleep(poll_interval)

    def _every(self, call: Callable[..., rq.Call], *args) -> list:
        found, offset = [], 0
        while True:
            page = self._call(call(*args, offset=offset))
            found += page
            if len(page) < rq.PAGE:
                return found
            offset = rq.next_offset(call, page, offset)

    def stream(self, session: SessionRef, *, token: str | None = None,
               timeout: float | None = None) -> PoseStream:
        """Open the session's pose stream (returns once the server's hello has arrived).

        Raises Unauthorized / Forbidden / NotFound when the server refuses it.
        """
        sid, tok = session_ref(session, token)
        conn = self._ws_connect(stream_url(self.base_url, sid),
                                auth_headers(tok or self.admin_key))
        return PoseStream(conn, timeout=timeout)
