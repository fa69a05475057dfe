"""Large unauthenticated bodies against a real server: answered 401 before they are read,
and the server's memory stays where it was."""

from __future__ import annotations

import re
import select
import socket
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

CHUNK = b"\0" * 65536
BODY_BYTES = 200 * 10**6
BODIES = 10
RSS_SLACK_BYTES = 50 * 2**20


def rss_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(re.search(r"VmRSS:\s+(\d+) kB", f.read()).group(1)) * 1024


def body_chunks(total: int, *, chunked: bool) -> Iterator[bytes]:
    """The body as a generator (in HTTP chunked framing when asked): the test never holds
    more than one chunk of it."""
    sent = 0
    while sent < total:
        n = min(len(CHUNK), total - sent)
        yield b"%x\r\n%s\r\n" % (n, CHUNK[:n]) if chunked else CHUNK[:n]
        sent += n


def post_unauthenticated(host: str, port: int, path: str, *, chunked: bool) -> tuple:
    """Send a 200 MB body, watching for the answer between chunks.

    Returns the answer (status line first) and how many body bytes went out before the
    server answered.
    """
    length = "Transfer-Encoding: chunked" if chunked else f"Content-Length: {BODY_BYTES}"
    head = (f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n"
            f"{length}\r\n\r\n").encode()
    answer, written = b"", 0
    with socket.create_connection((host, port), timeout=60) as sock:
        sock.sendall(head)
        chunks = body_chunks(BODY_BYTES, chunked=chunked)
        pending = next(chunks, b"")
        while True:
            readable, writable, _ = select.select([sock], [sock] if pending else [], [], 60)
            if readable:
                try:
                    data = sock.recv(65536)
                except ConnectionError:
                    break
                if not data:
                    break  # the server closed the connection after its answer
                answer += data
            elif writable:
                try:
                    written += sock.send(pending)
                except ConnectionError:
                    # The server answered and closed while this chunk was on its way; its
                    # reset can fail the send before select shows the answer, which is
                    # still in the receive queue.
                    answer += _rest(sock)
                    break
                pending = next(chunks, b"")
            else:
                break
    return answer, written


def _rest(sock: socket.socket) -> bytes:
    """What the peer sent before it reset the connection."""
    out = b""
    try:
        while data := sock.recv(65536):
            out += data
    except (ConnectionError, TimeoutError):
        pass
    return out


def test_unauthenticated_bodies_leave_the_servers_memory_alone(server):
    host, port = server.base_url.removeprefix("http://").split(":")
    # A first request warms up what any request loads, so the baseline includes it.
    post_unauthenticated(host, int(port), "/v1/maps", chunked=False)
    base = rss_bytes(server.process.pid)
    paths = ["/v1/maps", "/v1/maps/00000000-0000-0000-0000-000000000000/images"]
    with ThreadPoolExecutor(BODIES) as pool:
        results = list(pool.map(
            lambda i: post_unauthenticated(host, int(port), paths[i % 2], chunked=i % 3 == 0),
            range(BODIES)))
    after = rss_bytes(server.process.pid)
    for answer, written in results:
        assert answer.startswith(b"HTTP/1.1 401 "), answer[:200]
        assert b"urn:vloc:problem:unauthenticated" in answer
        assert written < BODY_BYTES // 10  # answered long before the end of the body
    assert after - base < RSS_SLACK_BYTES, (base, after)
    assert server.process.poll() is None
