"""Test-only tasks and a trivial localiser for the engine tests (imported by the workers)."""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

import cv2
import numpy as np

from vloc.workers.core.estimate import Estimate, Status
from vloc.workers.engine import SessionSpec

COUNTING = "tests.engine.fakes:make_counting"
"""The factory of :class:`CountingLocaliser` sessions."""


def grey_png(level: int) -> bytes:
    """A small uniform PNG frame of grey ``level`` (the counting localiser's y)."""
    ok, buf = cv2.imencode(".png", np.full((24, 32), level, np.uint8))
    assert ok
    return buf.tobytes()


def counting_spec(session_id: str, **params) -> SessionSpec:
    """A session of the counting localiser, with no map."""
    return SessionSpec(session_id=session_id, map_id="", revision=0, map_folder="",
                       mode="count", params=params, seed=0, factory=COUNTING)


def square(x: int) -> int:
    return x * x


def fail(message: str) -> None:
    raise ValueError(message)


def pid() -> int:
    return os.getpid()


def loaded(modules: list[str]) -> list[bool]:
    """Whether each of ``modules`` is imported in the worker that runs this."""
    import sys

    return [name in sys.modules for name in modules]


def wait_for_file(path: str, timeout: float = 30.0) -> bool:
    """Hold the worker until ``path`` exists (lets a test queue work behind it)."""
    deadline = time.monotonic() + timeout
    while not Path(path).exists():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


class CountingLocaliser:
    """Counts its steps; x is the count, y the mean grey level of the last frame.

    Its whole state is the count, so a restored checkpoint shows in the next estimate; a
    session of it can move to another map revision (it has no map) with its count.
    """

    moves_between_revisions = True

    def __init__(self, offset: float = 0.0, step_s: float = 0.0) -> None:
        self.count = 0
        self.offset = offset
        self.step_s = step_s
        """Seconds each step takes (a slow localiser)."""
        self.stats = {"steps": 0}

    def step(self, frame, *, captured_at=None, metadata=None) -> Estimate:
        if float(frame.grey.mean()) > 250:
            raise RuntimeError("frame too bright for the fake")
        time.sleep(self.step_s)
        self.count += 1
        self.stats["steps"] = self.count
        x = float(self.count) + self.offset
        y = float(frame.grey.mean())
        return Estimate(x=x, y=y, lat=0.0, lon=0.0, sigma_x=1.0, sigma_y=1.0,
                        cov=(1.0, 0.0, 0.0, 1.0), feature="fake", next_feature="fake",
                        n_particles=1, status=Status.TRACKING, processing_ms=0.0)

    def get_state(self) -> bytes:
        return struct.pack("<q", self.count)

    def set_state(self, data: bytes) -> None:
        (self.count,) = struct.unpack("<q", data)

    def reset(self) -> None:
        self.count = 0

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        self.count = int(x)


def make_counting(mode: str, map_data, params: dict, *, seed: int) -> CountingLocaliser:
    if mode != "count":
        raise ValueError(f"unknown mode {mode!r}")
    return CountingLocaliser(offset=float(params.get("offset", 0.0)),
                             step_s=float(params.get("step_s", 0.0)))


def make_recording(mode: str, map_data, params: dict, *, seed: int) -> CountingLocaliser:
    """A counting localiser that keeps the map it was given, for the tests to inspect."""
    loc = CountingLocaliser()
    loc.map_data = map_data
    loc.seed = seed
    return loc


def make_map_probe(mode: str, map_data, params: dict, *, seed: int) -> CountingLocaliser:
    """A counting localiser whose ``stats`` tell how its process holds the map's arrays."""
    loc = CountingLocaliser()
    positions = map_data.positions
    base = positions
    while getattr(base, "base", None) is not None:
        base = base.base
    loc.stats = {"pid": os.getpid(), "n_images": len(map_data),
                 "writeable": bool(positions.flags.writeable),
                 "owns_data": bool(positions.flags.owndata),
                 "base": type(base).__module__ + "." + type(base).__name__}
    return loc


class GatedLocaliser(CountingLocaliser):
    """Steps only while the file ``gate`` exists: lets a test hold a frame in its worker."""

    def __init__(self, gate: str) -> None:
        super().__init__()
        self.gate = gate

    def step(self, frame, *, captured_at=None, metadata=None) -> Estimate:
        wait_for_file(self.gate, timeout=60.0)
        return super().step(frame, captured_at=captured_at, metadata=metadata)


def make_gated(mode: str, map_data, params: dict, *, seed: int) -> GatedLocaliser:
    return GatedLocaliser(params["gate"])
