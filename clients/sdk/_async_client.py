"""The asyncio client: :class:`AsyncClient`, the same calls as :class:`Client`, awaited."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

import httpx

from . import _requests as rq
from ._client import (
    DEFAULT_TIMEOUT,
    SessionRef,
    auth_headers,
    resolve_settings,
    session_ref,
    stream_url,
)
from ._exceptions import JobFailed, TransportError, VlocError, WaitTimeout
from ._models import Job
from ._requests import Call, RetryPolicy
from ._routes import Routes
from ._stream import AsyncConnect, AsyncPoseStream, async_websockets_connect


class AsyncClient(Routes):
    """An asyncio client for every route of the vloc API.

    Parameters are those of :class:`~clients.sdk.Client`; ``transport`` takes an
    ``httpx.AsyncBaseTransport`` (``httpx.ASGITransport(app=...)`` for the in-process app)
    and ``ws_connect`` an :data:`AsyncConnect`.
    """

    def __init__(self, base_url: str | None = None, *, admin_key: str | None = None,
                 timeout: float | httpx.Timeout = DEFAULT_TIMEOUT,
                 retry: RetryPolicy | int = 3,
                 transport: httpx.AsyncBaseTransport | None = None,
                 http: httpx.AsyncClient | None = None,
                 ws_connect: AsyncConnect | None = None,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep) -> None:
        if base_url is None and http is not None and str(http.base_url):
            base_url = str(http.base_url)
        self.base_url, self.admin_key = resolve_settings(base_url, admin_key)
        self.retry = retry if isinstance(retry, RetryPolicy) else RetryPolicy(retries=retry)
        self._owns_http = http is None
        self._http = http or httpx.AsyncClient(base_url=self.base_url, timeout=timeout,
                                               transport=transport)
        self._timeout = timeout if isinstance(timeout, httpx.Timeout) else httpx.Timeout(timeout)
        self._ws_connect = ws_connect or async_websockets_connect()
        self._sleep = sleep

    # -- plumbing ---------------------------------------------------------------------------

    def _url(self, path: str) -> str:
        return path if str(self._http.base_url) else f"{self.base_url}{path}"

    async def _send(self, call: Call) -> httpx.Response:
        headers = {**auth_headers(call.token or self.admin_key), **call.headers}
        timeout: httpx.Timeout | object = self._timeout
        if not self._owns_http:
            timeout = httpx.USE_CLIENT_DEFAULT  # a caller's client keeps its own timeouts
        elif call.read_timeout is not None:
            timeout = httpx.Timeout(self._timeout.connect, read=call.read_timeout,
                                    write=self._timeout.write, pool=self._timeout.pool)
        try:
            return await self._http.request(
                call.method, self._url(call.path), params=call.params, json=call.json,
                data=call.data, files=call.files, content=call.content, headers=headers,
                timeout=timeout)
        except httpx.TransportError as exc:
            raise TransportError(f"{call.method} {call.path}: {type(exc).__name__}: "
                                 f"{exc or 'no answer'}") from exc

    async def _call(self, call: Call) -> Any:
        attempt = 0
        while True:
            try:
                return rq.outcome(call, await self._send(call), retried=attempt > 0)
            except VlocError as error:
                cause = error.__cause__ if isinstance(error, TransportError) else error
                if attempt >= self.retry.retries or not rq.retryable(call, cause):
                    raise
                await self._sleep(self.retry.delay(attempt,
                                                   None if cause is not error else error))
                attempt += 1

    async def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Any other route, with the client's credentials; errors raised as for the rest."""
        headers = {**auth_headers(self.admin_key), **kwargs.pop("headers", {})}
        try:
            response = await self._http.request(method, self._url(path), headers=headers,
                                                **kwargs)
        except httpx.TransportError as exc:
            raise TransportError(f"{method} {path}: {type(exc).__name__}: {exc}") from exc
        return rq.outcome(Call(method, path, lambda r: r), response, retried=False)

    async def aclose(self) -> None:
        if self._owns_http:
            await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    # -- health -----------------------------------------------------------------------------

    async def wait_ready(self, timeout: float = 60.0, *, interval: float = 0.2) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            try:
                return await self._call(rq.Call("GET", "/readyz", lambda r: r.json()))
            except VlocError as exc:
                if time.monotonic() >= deadline:
                    raise WaitTimeout(f"{self.base_url} not ready within {timeout:g} s: "
                                      f"{exc}") from exc
            await self._sleep(interval)

    # -- maps -------------------------------------------------------------------------------

    async def wait_for_job(self, job_id: str, timeout: float = 600.0, *,
                           on_progress: Callable[[Job], None] | None = None,
                           poll_interval: float = 0.5) -> Job:
        """As :meth:`Client.wait_for_job`."""
        deadline = time.monotonic() + timeout
        while True:
            job = await self.get_job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job.status == "failed":
                raise JobFailed(job)
            if job.status == "done":
                return job
            if time.monotonic() >= deadline:
                raise WaitTimeout(f"job {job_id} still {job.status} after {timeout:g} s "
                                  f"({100 * job.progress:.0f} %)")
            await self._sleep(poll_interval)

    # -- sessions ---------------------------------------------------------------------------

    async def _every(self, call: Callable[..., rq.Call], *args) -> list:
        found, offset = [], 0
        while True:
            page = await self._call(call(*args, offset=offset))
            found += page
            if len(page) < rq.PAGE:
                return found
            offset = rq.next_offset(call, page, offset)

    async def stream(self, session: SessionRef, *, token: str | None = None,
                     timeout: float | None = None) -> AsyncPoseStream:
        """Open the pose stream (``async with await client.stream(s) as poses``)."""
        sid, tok = session_ref(session, token)
        conn = await self._ws_connect(stream_url(self.base_url, sid),
                                      auth_headers(tok or self.admin_key))
        return await AsyncPoseStream.open(conn, timeout=timeout)
