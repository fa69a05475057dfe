"""Processes of the machine, as /proc shows them (Linux): for tests that kill servers."""

from __future__ import annotations

import os
import time

TIMEOUT = 30.0


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children first found through /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def running(pid: int) -> bool:
    """The process exists and is not a zombie waiting for a parent to reap it."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def wait_gone(pids: set[int], timeout: float = TIMEOUT) -> set[int]:
    """The processes of ``pids`` still running after ``timeout`` (polled)."""
    deadline = time.monotonic() + timeout
    while (left := {p for p in pids if running(p)}) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def children(pid: int) -> set[int]:
    """The processes whose parent is ``pid``."""
    return {p for p in descendants(pid) if parent(p) == pid}


def parent(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def pool_workers(server_pid: int) -> set[int]:
    """The engine's worker processes: the children of the server's forkserver."""
    forkservers = {p for p in children(server_pid) if "forkserver" in cmdline(p)}
    return {w for f in forkservers for w in children(f)}
