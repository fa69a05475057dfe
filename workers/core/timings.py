"""Where a build's time goes: named stages, each with its wall and CPU seconds.

A packing records its stages in one dict (``build_timings.json`` beside the revision). A
name ``"X: Y"`` is a part of stage ``X``, timed inside it: the parts say where the stage's
time went and are not to be added to it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

Timings = dict[str, tuple[float, float]]
"""Stage name -> (wall s, CPU s of this process)."""


@contextmanager
def stage(timings: Timings | None, name: str) -> Iterator[None]:
    """Add the block's (wall, CPU) seconds to ``timings[name]``; CPU is this process's.
    With ``timings`` None nothing is recorded."""
    if timings is None:
        yield
        return
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        before = timings.get(name, (0.0, 0.0))
        timings[name] = (before[0] + time.perf_counter() - wall,
                         before[1] + time.process_time() - cpu)


def top_level(timings: dict) -> dict:
    """The stages of ``timings`` that are not parts of another (``"X: Y"``): those that add
    up to the whole."""
    return {name: v for name, v in timings.items() if ": " not in name}
