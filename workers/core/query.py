"""A query frame with its features extracted on demand and cached.

A localiser asks for the features its step needs; the frame computes each at most once and
remembers how long that took, so an evaluation that replays the same frame through several
localisers pays the extraction once but still reports honest per-step times.
"""

from __future__ import annotations

import time

import numpy as np

from .features import extract_many
from .image import Frame
from .sift import SiftFeatures, extract_sift, reduce_with_previous


class QueryFrame:
    """One frame to localise.

    Parameters
    ----------
    frame : Frame
    captured_at : float or None
        Capture time, seconds since the epoch.
    key : hashable or None
        Identity of the frame for caches shared across runs (e.g. its index in a sequence).
    """

    def __init__(self, frame: Frame, captured_at: float | None = None, key=None) -> None:
        self.frame = frame
        self.captured_at = captured_at
        self.key = key
        self._global: dict[str, np.ndarray] = {}
        self._global_ms: dict[str, float] = {}
        self._sift: SiftFeatures | None = None
        self._sift_ms = 0.0
        self._reduced: dict = {}

    def global_features(self, names: tuple[str, ...]) -> tuple[dict[str, np.ndarray], float]:
        """The named global features and the milliseconds their extraction took."""
        missing = tuple(n for n in names if n not in self._global)
        if missing:
            t0 = time.perf_counter()
            got = extract_many(missing, self.frame)
            ms = (time.perf_counter() - t0) * 1e3
            for n in missing:
                self._global[n] = got[n]
                self._global_ms[n] = ms / len(missing)
        return {n: self._global[n] for n in names}, sum(self._global_ms[n] for n in names)

    def sift(self) -> tuple[SiftFeatures, float]:
        """All SIFT features of the frame and the milliseconds extraction took."""
        if self._sift is None:
            t0 = time.perf_counter()
            self._sift = extract_sift(self.frame.grey)
            self._sift_ms = (time.perf_counter() - t0) * 1e3
        return self._sift, self._sift_ms

    def reduced_sift(self, previous: SiftFeatures | None, prev_key=None, *, ratio: float,
                     min_keep: int) -> tuple[SiftFeatures, float]:
        """SIFT features kept by matching the previous frame (Weiss III), and the time."""
        full, ms = self.sift()
        if previous is None:
            return full, ms
        cache_key = (prev_key, ratio, min_keep) if prev_key is not None else None
        if cache_key is not None and cache_key in self._reduced:
            reduced, red_ms = self._reduced[cache_key]
        else:
            t0 = time.perf_counter()
            reduced = reduce_with_previous(full, previous, ratio=ratio, min_keep=min_keep)
            red_ms = (time.perf_counter() - t0) * 1e3
            if cache_key is not None:
                self._reduced[cache_key] = (reduced, red_ms)
        return reduced, ms + red_ms
