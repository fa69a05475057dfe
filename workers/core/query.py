"""A query frame with its features extracted on demand and cached.

A localiser asks for the features its step needs; the frame computes each at most once and
remembers how long that took, so an evaluation that replays the same frame through several
localisers pays the extraction once but still reports honest per-step times.

Place descriptors are computed against the map's vocabulary, which the caller passes; the
local features under them (ORB, SIFT) are extracted once per frame and shared, and their
extraction time is counted once per call however many descriptors use them.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from .features import DESCRIPTORS, extract_many
from .features.descriptors import describe, local_vectors
from .features.orb import OrbFeatures, extract_orb
from .features.vocabulary import Vocabulary
from .image import Frame
from .metadata import FrameMetadata
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
    metadata : FrameMetadata or None
        What the device's other sensors reported with the frame.
    """

    def __init__(self, frame: Frame, captured_at: float | None = None, key=None,
                 metadata: FrameMetadata | None = None) -> None:
        self.frame = frame
        self.captured_at = captured_at
        self.key = key
        self.metadata = metadata
        self._global: dict[str, np.ndarray] = {}
        self._global_ms: dict[str, float] = {}
        self._sift: SiftFeatures | None = None
        self._sift_ms = 0.0
        self._reduced: dict = {}
        self._orb: OrbFeatures | None = None
        self._orb_ms = 0.0
        self._local: dict[str, tuple[np.ndarray, float]] = {}
        self._described: dict[tuple[str, int], tuple[Vocabulary, np.ndarray, float]] = {}

    def global_features(self, names: tuple[str, ...],
                        vocabularies: Mapping[str, Vocabulary] | None = None, *,
                        sift_paid: bool = False) -> tuple[dict[str, np.ndarray], float]:
        """The named global features and the milliseconds their extraction took.

        Parameters
        ----------
        names : tuple of str
            Histogram features and place descriptors.
        vocabularies : mapping of str -> Vocabulary
            The map's vocabularies (:attr:`MapData.vocabularies`); needed for place
            descriptors.
        sift_paid : bool
            The caller already counts this frame's SIFT extraction (a SIFT step), so
            RootSIFT descriptors add only their own encoding time.

        Raises
        ------
        ValueError
            A place descriptor without its vocabulary (a map built without it).
        """
        hist = tuple(n for n in names if n not in DESCRIPTORS)
        missing = tuple(n for n in hist if n not in self._global)
        if missing:
            t0 = time.perf_counter()
            got = extract_many(missing, self.frame)
            ms = (time.perf_counter() - t0) * 1e3
            for n in missing:
                self._global[n] = got[n]
                self._global_ms[n] = ms / len(missing)
        out = {n: self._global[n] for n in hist}
        total = sum(self._global_ms[n] for n in hist)
        locals_used: set[str] = set()
        for name in names:
            if name not in DESCRIPTORS:
                continue
            vec, ms = self._descriptor(name, (vocabularies or {}).get(name))
            out[name] = vec
            total += ms
            locals_used.add(DESCRIPTORS[name].local)
        for local in locals_used:
            total += self._local_vectors(local)[1]
            if local == "rootsift" and not sift_paid:
                total += self.sift()[1]
            if local == "orb":
                total += self.orb()[1]
        return {n: out[n] for n in names}, total

    def orb(self) -> tuple[OrbFeatures, float]:
        """ORB features of the frame and the milliseconds extraction took."""
        if self._orb is None:
            t0 = time.perf_counter()
            self._orb = extract_orb(self.frame.grey)
            self._orb_ms = (time.perf_counter() - t0) * 1e3
        return self._orb, self._orb_ms

    def _local_vectors(self, local: str) -> tuple[np.ndarray, float]:
        """A descriptor's local vectors, and the ms of turning the features into them."""
        if local not in self._local:
            feats = {"orb": self.orb()[0]} if local == "orb" else {"sift": self.sift()[0]}
            t0 = time.perf_counter()
            vectors = local_vectors(local, **feats)
            self._local[local] = vectors, (time.perf_counter() - t0) * 1e3
        return self._local[local]

    def _descriptor(self, name: str, vocabulary: Vocabulary | None) -> tuple[np.ndarray, float]:
        """One place descriptor against a vocabulary, cached per vocabulary object."""
        if vocabulary is None:
            raise ValueError(f"the map has no vocabulary for the place descriptor {name!r}; "
                             "rebuild the map to train one")
        key = (name, id(vocabulary))
        hit = self._described.get(key)
        # the cache holds the vocabulary itself, so its id cannot be reused while cached
        if hit is None or hit[0] is not vocabulary:
            vectors, _ = self._local_vectors(DESCRIPTORS[name].local)
            t0 = time.perf_counter()
            vec = describe(DESCRIPTORS[name], vectors, vocabulary)
            hit = (vocabulary, vec, (time.perf_counter() - t0) * 1e3)
            self._described[key] = hit
        return hit[1], hit[2]

    @property
    def has_sift(self) -> bool:
        """Whether the frame's SIFT features have been extracted already."""
        return self._sift is not None

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
