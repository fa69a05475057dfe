"""A map packed into contiguous arrays, ready for the localisers.

A map is read once, packed here and shared read-only between worker processes: saved as a
folder of ``.npy`` files (:mod:`.mapfiles`), it loads with ``mmap_mode="r"`` so every process
maps the same pages. The per-keypoint arrays (SIFT's and ORB's keypoints and descriptors, the
reduction mask, the geometry's points) are saved in chunks of whole images that later
revisions share on disk, and load as :class:`~.rowchunks.ChunkedRows`, read like the arrays
below.

Arrays
------
positions : (N, 2) float64
    East/north metres of each map image in the map's local frame (:class:`GeoOrigin`).
altitudes : (N,) float64
global_features[name] : (N, D) float32
    One row per map image for each global feature.
sift_offsets : (N + 1,) int64
    Image ``i`` owns keypoint rows ``sift_offsets[i]:sift_offsets[i + 1]``.
sift_keypoints : (K, 4) float32
sift_descriptors : (K, 128) uint8
sift_keep : (K,) bool
    Keypoints kept by the neighbour reduction (Weiss III); all keypoints are stored so a
    localiser can choose to match against the full or the reduced set.
orb_offsets, orb_keypoints, orb_descriptors : (N + 1,) int64, (L, 4) float32, (L, 32) uint8
    The map images' ORB features, laid out as the SIFT ones; the cheap local features that
    register frames on global steps. None for maps packed before they were stored.
vocabularies[name] : Vocabulary
    The vocabulary of each place descriptor in ``global_features`` (trained on this map's
    own local features at build), saved as ``vocab_{name}_centroids.npy``,
    ``vocab_{name}_idf.npy`` and, where it projects the local vectors,
    ``vocab_{name}_projection.npy``, with its tree shape in ``meta.json``. Maps packed before place
    descriptors existed have none and load unchanged.
vocabulary_fits[name] : VocabularyFit
    How well each vocabulary fits the map's images: each image's distortion,
    ``vocab_{name}_fit.npy`` (N,) float32, whether it was trained on each,
    ``vocab_{name}_trained_on.npy`` (N,) bool, the trained images' mean and the revision
    that trained it in ``meta.json``; what an update reads to keep the vocabulary or train it
    again (:mod:`workers.core.carryover`). None recorded for maps packed before.
captured_at : (N,) float64
    Capture times of the map images in seconds since the epoch, NaN where unknown; the
    motion model derives the platform's typical speed from them.
flights : (N,) tuple of str or None, or None
    The flight (or pass) each map image was said to belong to, None where not said; in
    ``meta.json``, and only where some image has one (:mod:`workers.core.flights`). Images
    with none are grouped into flights by their capture times.
geometry : MapGeometry or None
    The map cameras reconstructed over the ground plane and the ground position of every
    stored keypoint (:mod:`workers.core.geometry`); None where the map is not a plane seen
    from above.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .features.distortion import VocabularyFit
from .features.orb import OrbFeatures
from .features.shortlist import PlaceCodes
from .features.vocabulary import Vocabulary
from .geo import GeoOrigin
from .geometry import MapGeometry
from .sift import SiftFeatures

CAPTURE_NEIGHBOURS: int = 32
"""Nearest map images among which an image's next capture on the same flight is sought.
Enough that a sparse flight's next frame is among them where it speeds up between frames
(on seneca-uav's map pass the nearest 8 miss it for 7 of the 70 images, the nearest 24 for
none); a parallel flight's frames hundreds of metres away are not."""


@dataclass
class MapData:
    origin: GeoOrigin
    names: tuple[str, ...]
    positions: np.ndarray
    altitudes: np.ndarray
    global_features: dict[str, np.ndarray]
    sift_offsets: np.ndarray
    sift_keypoints: np.ndarray
    sift_descriptors: np.ndarray
    map_id: str = ""
    revision: int = 0
    captured_at: np.ndarray | None = None
    flights: tuple[str | None, ...] | None = None
    sift_keep: np.ndarray | None = None
    geometry: MapGeometry | None = None
    vocabularies: dict[str, Vocabulary] = field(default_factory=dict)
    orb_offsets: np.ndarray | None = None
    orb_keypoints: np.ndarray | None = None
    orb_descriptors: np.ndarray | None = None
    place_codes: dict[str, PlaceCodes] = field(default_factory=dict)
    vocabulary_fits: dict[str, VocabularyFit] = field(default_factory=dict)
    _tree: cKDTree | None = field(default=None, repr=False, compare=False)
    _spacing: float | None = field(default=None, repr=False, compare=False)
    _steps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                          compare=False)

    def __post_init__(self) -> None:
        n = len(self.names)
        if self.positions.shape != (n, 2):
            raise ValueError(f"positions must be ({n}, 2), got {self.positions.shape}")
        if self.sift_offsets.shape != (n + 1,):
            raise ValueError("sift_offsets must have one more entry than there are images")
        for name, mat in self.global_features.items():
            if mat.ndim != 2 or mat.shape[0] != n:
                raise ValueError(f"global feature {name!r} must have {n} rows, got {mat.shape}")
        for name in self.vocabularies:
            if name not in self.global_features:
                raise ValueError(f"vocabulary {name!r} comes without its descriptor matrix")
        for name, fit in self.vocabulary_fits.items():
            if name not in self.vocabularies or fit.images.shape != (n,):
                raise ValueError(f"vocabulary fit {name!r} does not fit the map's images")
        for name, codes in self.place_codes.items():
            if name not in self.global_features or len(codes) != n \
                    or codes.basis.shape[0] != self.global_features[name].shape[1]:
                raise ValueError(f"shortlist codes {name!r} do not fit the descriptor matrix")
        if self.sift_keep is None:
            self.sift_keep = np.ones(len(self.sift_descriptors), dtype=bool)
        if self.sift_keep.shape != (len(self.sift_descriptors),):
            raise ValueError("sift_keep must have one entry per keypoint")
        if self.orb_offsets is not None and self.orb_offsets.shape != (n + 1,):
            raise ValueError("orb_offsets must have one more entry than there are images")
        if self.captured_at is None:
            self.captured_at = np.full(n, np.nan)
        self.captured_at = np.asarray(self.captured_at, np.float64)
        if self.captured_at.shape != (n,):
            raise ValueError(f"captured_at must be ({n},), got {self.captured_at.shape}")
        if self.flights is not None:
            self.flights = tuple(None if f is None else str(f) for f in self.flights)
            if len(self.flights) != n:
                raise ValueError(f"flights must have {n} entries, got {len(self.flights)}")
            if all(f is None for f in self.flights):
                self.flights = None

    def __len__(self) -> int:
        return len(self.names)

    @property
    def tree(self) -> cKDTree:
        """KD-tree over the map positions (nearest map image of each particle)."""
        if self._tree is None:
            self._tree = cKDTree(np.asarray(self.positions))
        return self._tree

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(min_east, min_north, max_east, max_north) in metres."""
        lo = self.positions.min(axis=0)
        hi = self.positions.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def sift(self, i: int, *, reduced: bool = False) -> SiftFeatures:
        """Keypoints of map image ``i``: all, or those kept by the neighbour reduction.

        The reduced set is gathered for this image alone: a reduced copy of the whole map
        would be private memory in every worker, where the packed arrays are shared pages.
        """
        a, b = int(self.sift_offsets[i]), int(self.sift_offsets[i + 1])
        kps, desc = self.sift_keypoints[a:b], self.sift_descriptors[a:b]
        if reduced:
            keep = np.asarray(self.sift_keep[a:b])
            return SiftFeatures(kps[keep], desc[keep])
        return SiftFeatures(kps, desc)

    @property
    def has_orb(self) -> bool:
        return self.orb_offsets is not None

    def keypoint_set(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """The keypoints of local-feature set ``kind`` (``"sift"``, ``"orb"``: the rows the
        geometry's ``points[kind]`` follow) and their offsets per image."""
        if kind == "sift":
            return self.sift_keypoints, self.sift_offsets
        if kind == "orb" and self.has_orb:
            return self.orb_keypoints, self.orb_offsets
        raise KeyError(f"the map holds no {kind!r} keypoints")

    def orb(self, i: int) -> OrbFeatures:
        """ORB features of map image ``i`` (the map must have them: :attr:`has_orb`)."""
        a, b = int(self.orb_offsets[i]), int(self.orb_offsets[i + 1])
        return OrbFeatures(self.orb_keypoints[a:b], self.orb_descriptors[a:b])

    def shortlist(self, query: dict[str, np.ndarray],
                  features: tuple[str, ...]) -> np.ndarray | None:
        """The map images worth scoring exactly for a frame's global features, ascending, or
        None where every image should be (a map without shortlist codes for ``features``).

        The codes of the first of ``features`` that has them pick the shortlist
        (:mod:`.features.shortlist`)."""
        for name in features:
            if name in self.place_codes:
                return self.place_codes[name].shortlist(query[name])
        return None

    def sift_counts(self) -> np.ndarray:
        return np.diff(self.sift_offsets)

    def typical_speed(self) -> float | None:
        """Median speed (m/s) from each timed map image to the next capture of its flight.

        Steps longer than five times the median gap are ignored: they are breaks between
        legs or flights, not motion.
        """
        dt, dist = self._capture_steps()
        if len(dt) < 2:
            return None
        keep = dt <= 5.0 * np.median(dt)
        return float(np.median(dist[keep] / dt[keep]))

    def typical_interval(self) -> float | None:
        """Median time (s) from each timed map image to the next capture of its flight."""
        dt, _ = self._capture_steps()
        return float(np.median(dt)) if len(dt) >= 2 else None

    def _capture_steps(self) -> tuple[np.ndarray, np.ndarray]:
        """Seconds and metres from each timed map image to the next capture of its flight.

        A map may join flights made at the same time (a survey split between several
        platforms): the next capture anywhere in the map then often belongs to another
        flight, hundreds of metres away, and the speed between the two is no platform's.
        The next capture of the same flight lies close by, so it is taken as the earliest
        later capture among the image's :data:`CAPTURE_NEIGHBOURS` nearest map images
        (found with the map's own KD-tree; untimed neighbours are no candidates). Images
        with no later capture near them (a flight's last) have no step. Computed once per
        map.
        """
        if self._steps is None:
            t = self.captured_at
            timed = np.flatnonzero(np.isfinite(t))
            if len(timed) < 2:
                self._steps = (np.empty(0), np.empty(0))
                return self._steps
            k = min(CAPTURE_NEIGHBOURS + 1, len(self))  # the image itself comes back too
            dist, near = self.tree.query(np.asarray(self.positions)[timed], k=k)
            with np.errstate(invalid="ignore"):  # NaN: an untimed neighbour
                later = t[near] - t[timed][:, None]
                later = np.where(later > 0, later, np.inf)
            nxt = np.argmin(later, axis=1)
            rows = np.arange(len(timed))
            dt, d = later[rows, nxt], dist[rows, nxt]
            has = np.isfinite(dt)
            self._steps = (dt[has], d[has])
        return self._steps

    def median_spacing(self) -> float:
        """Median distance from each map image to its nearest neighbour of the same flight
        (metres; :func:`workers.core.flights.flight_spacing`: a second flight over the same
        ground leaves it as it was).

        Computed once: refinement asks for it on every step of a map without geometry."""
        if self._spacing is None:
            from .flights import flight_spacing

            self._spacing = flight_spacing(np.asarray(self.positions), self.captured_at,
                                           self.flights)
        return self._spacing

    def flight_labels(self) -> np.ndarray:
        """Each image's flight, numbered in time order (-1: none);
        :func:`workers.core.flights.flight_labels`."""
        from .flights import flight_labels

        return flight_labels(self.captured_at, self.flights)

    @classmethod
    def from_parts(cls, *, origin: GeoOrigin, names, positions, altitudes,
                   global_features: dict[str, np.ndarray], sift: list[SiftFeatures],
                   map_id: str = "", revision: int = 0,
                   captured_at=None, flights=None,
                   sift_keep: list[np.ndarray] | None = None,
                   vocabularies: dict[str, Vocabulary] | None = None,
                   vocabulary_fits: dict[str, VocabularyFit] | None = None,
                   orb: list[OrbFeatures] | None = None) -> MapData:
        offsets, kps, desc = _concatenate(sift, 128)
        orb_parts = (None, None, None) if orb is None else _concatenate(orb, 32)
        return cls(origin=origin, names=tuple(names),
                   positions=np.asarray(positions, np.float64).reshape(-1, 2),
                   altitudes=np.asarray(altitudes, np.float64),
                   global_features={k: np.ascontiguousarray(v, np.float32)
                                    for k, v in global_features.items()},
                   sift_offsets=offsets, sift_keypoints=kps.astype(np.float32),
                   sift_descriptors=desc.astype(np.uint8), map_id=map_id, revision=revision,
                   captured_at=None if captured_at is None
                   else np.asarray(captured_at, np.float64),
                   flights=flights,
                   sift_keep=None if sift_keep is None or not sift
                   else np.concatenate(sift_keep).astype(bool),
                   vocabularies=dict(vocabularies or {}),
                   vocabulary_fits=dict(vocabulary_fits or {}), orb_offsets=orb_parts[0],
                   orb_keypoints=orb_parts[1], orb_descriptors=orb_parts[2])

    # -- persistence as a folder of .npy files (memory-mappable): :mod:`.mapfiles` --------

    def save(self, folder: str | Path, *, share: str | Path | None = None,
             chunk_images: int | None = None) -> Path:
        """Write the map to ``folder`` (:func:`.mapfiles.save_map`: atomic, its local
        features in chunks that a revision packed from ``share`` links where unchanged)."""
        from .mapfiles import save_map

        return save_map(self, folder, share=share, chunk_images=chunk_images)

    @classmethod
    def load(cls, folder: str | Path, *, mmap: bool = True) -> MapData:
        """The map saved in ``folder`` (:func:`.mapfiles.load_map`), memory-mapped by
        default."""
        from .mapfiles import load_map

        return load_map(folder, mmap=mmap)


def _concatenate(parts, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-image local features as (offsets, keypoints, descriptors) arrays."""
    counts = np.array([len(p) for p in parts], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    kps = (np.concatenate([p.keypoints for p in parts]) if parts
           else np.zeros((0, 4), np.float32))
    desc = (np.concatenate([p.descriptors for p in parts]) if parts
            else np.zeros((0, width), np.uint8))
    return offsets, kps.astype(np.float32), desc.astype(np.uint8)


KEPT_OPEN = 4
"""Packed revisions :func:`open_map` keeps loaded after their last user lets them go."""

_open: weakref.WeakValueDictionary[str, MapData] = weakref.WeakValueDictionary()
_kept: OrderedDict[str, MapData] = OrderedDict()
_open_lock = threading.Lock()


def open_map(folder: str | Path) -> MapData:
    """The packed revision in ``folder``, memory-mapped, loaded once per process.

    Every caller gets the same :class:`MapData` while any of them holds it (a worker's
    sessions, a one-shot localisation), and the :data:`KEPT_OPEN` last opened stay loaded
    after that: a packed revision never changes, and loading it again costs page-cache hits.
    """
    key = str(Path(folder))
    with _open_lock:
        data = _open.get(key)
        if data is None:
            data = MapData.load(key, mmap=True)
            _open[key] = data
        _kept[key] = data
        _kept.move_to_end(key)
        while len(_kept) > KEPT_OPEN:
            _kept.popitem(last=False)
    return data
