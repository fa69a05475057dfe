"""What every localiser shares: the interface, estimates in both frames, state packing."""

from __future__ import annotations

import io
import json
import time
from abc import ABC, abstractmethod
from dataclasses import fields

import numpy as np

from ..estimate import Estimate, Status
from ..geo import GeoOrigin
from ..image import Frame
from ..mapdata import MapData
from ..metadata import FrameMetadata
from ..query import QueryFrame

SPREAD_CANDIDATES = 5
"""Best candidates whose spread a single-frame localiser reports as its uncertainty."""


def check_param_keys(mode: str, params: dict, config_type) -> None:
    """Refuse parameters that are not fields of the mode's config dataclass."""
    allowed = {f.name for f in fields(config_type)}
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise ValueError(f"unknown parameter(s) for mode {mode!r}: {', '.join(unknown)}; "
                         f"valid: {', '.join(sorted(allowed))}")


def candidate_spread(map_xy: np.ndarray, idx: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Covariance (2, 2) of candidate positions weighted by their scores (normalised).

    Parameters
    ----------
    map_xy : (N, 2) float ndarray
    idx : (k,) int ndarray
        Candidate map images.
    score : (k,) float ndarray
        Their scores; negative scores count as zero, all zero as equal weights.
    """
    w = np.clip(score, 0.0, None)
    if w.sum() <= 0:
        w = np.ones_like(w)
    w = w / w.sum()
    pts = map_xy[idx]
    d = pts - w @ pts
    return (d * w[:, None]).T @ d


def as_query(frame: Frame | QueryFrame, captured_at: float | None,
             metadata: FrameMetadata | None = None) -> QueryFrame:
    if isinstance(frame, QueryFrame):
        if captured_at is not None:
            frame.captured_at = captured_at
        if metadata is not None:
            frame.metadata = metadata
        return frame
    return QueryFrame(frame, captured_at, metadata=metadata)


def reframe(source: GeoOrigin, target: GeoOrigin):
    """A function taking ``(n, 2)`` east/north metres in the local frame of ``source`` to
    those of the same places in the frame of ``target`` (identity for the same origin)."""
    def move(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if source == target or not len(xy):
            return xy.copy()
        lat, lon = source.to_wgs84(xy[:, 0], xy[:, 1])
        east, north = target.to_local(lat, lon)
        return np.column_stack([np.atleast_1d(east), np.atleast_1d(north)])

    return move


def pack_state(arrays: dict[str, np.ndarray], meta: dict) -> bytes:
    """Arrays and JSON metadata as one ``.npz`` byte string (exact, no pickle)."""
    buf = io.BytesIO()
    payload = dict(arrays)
    payload["__meta__"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(buf, **payload)
    return buf.getvalue()


def unpack_state(data: bytes) -> tuple[dict[str, np.ndarray], dict]:
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays.pop("__meta__").tobytes().decode())
    except Exception as exc:  # noqa: BLE001 - any failure means the blob is unusable
        raise ValueError(f"not a localiser state: {exc}") from exc
    return arrays, meta


class Localiser(ABC):
    """A localiser turns frames into estimates on one map.

    Subclasses implement :meth:`_step`, :meth:`_state`, :meth:`_load`, :meth:`reset` and
    :meth:`set_initial_pose`.
    """

    mode: str = ""
    moves_between_revisions = True
    """A localiser on another revision of the map takes up this one's state
    (:meth:`set_state`): a session can follow its map as it is rebuilt."""

    def __init__(self, map_data: MapData, params: dict, seed: int) -> None:
        self.map = map_data
        self.params = params
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.stats = {"steps": 0, "sift_steps": 0, "global_steps": 0}

    def step(self, frame: Frame | QueryFrame, *, captured_at: float | None = None,
             metadata: FrameMetadata | None = None) -> Estimate:
        """Localise one frame (``captured_at`` in seconds since the epoch, if known; the
        device's other sensors in ``metadata``, each used where the localiser can)."""
        query = as_query(frame, captured_at, metadata)
        t0 = time.perf_counter()
        est = self._step(query, t0)
        self.stats["steps"] += 1
        key = "sift_steps" if est.feature == "sift" else "global_steps"
        self.stats[key] += 1
        return est

    def _estimate(self, mean: np.ndarray, cov: np.ndarray, *, feature: str, next_feature: str,
                  measurement: str, n_particles: int, status: Status, processing_ms: float,
                  best_image: int, heading: tuple[float, float] | None = None) -> Estimate:
        lat, lon = self.map.origin.to_wgs84(mean[0], mean[1])
        return Estimate(
            x=float(mean[0]), y=float(mean[1]), lat=float(lat), lon=float(lon),
            sigma_x=float(np.sqrt(max(cov[0, 0], 0.0))),
            sigma_y=float(np.sqrt(max(cov[1, 1], 0.0))),
            cov=(float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 0]), float(cov[1, 1])),
            feature=feature, next_feature=next_feature, n_particles=n_particles,
            status=status, processing_ms=float(processing_ms), best_image=int(best_image),
            measurement=measurement,
            heading_deg=None if heading is None else float(heading[0]),
            heading_sigma_deg=None if heading is None else float(heading[1]))

    def get_state(self) -> bytes:
        """Everything needed to resume bit-for-bit, as bytes, with the map revision it was
        taken on (so that another revision of the same map can take it up)."""
        arrays, meta = self._state()
        origin = self.map.origin
        meta.update(mode=self.mode, seed=self.seed, stats=self.stats,
                    rng=self.rng.bit_generator.state, n_map=len(self.map),
                    map_id=self.map.map_id, revision=self.map.revision,
                    origin=[origin.lat, origin.lon, origin.alt])
        return pack_state(arrays, meta)

    def set_state(self, data: bytes) -> None:
        """Resume from :meth:`get_state`'s bytes.

        A state taken on another revision of this localiser's map (a map rebuilt or
        restored while a session ran on it) is carried over: its positions are moved from
        that revision's local frame into this one's, through WGS84; what it learnt of the
        frames (the particles' spread, the tracked velocity, the previous frame's features)
        is kept. Anything else (another mode, another map) is refused with ValueError.
        """
        arrays, meta = unpack_state(data)
        if meta.get("mode") != self.mode:
            raise ValueError("state belongs to another mode")
        if not self._same_revision(meta):
            if not self.map.map_id or meta.get("map_id") != self.map.map_id \
                    or meta.get("origin") is None:
                raise ValueError("state belongs to another map")
            arrays, meta = self._carried(arrays, meta,
                                         reframe(GeoOrigin(*meta["origin"]), self.map.origin))
        self.rng.bit_generator.state = meta["rng"]
        self.stats = dict(meta["stats"])
        self._load(arrays, meta)

    def _same_revision(self, meta: dict) -> bool:
        """Whether a state was taken on this localiser's own map revision (states from
        before revisions were recorded in them are judged by the map's size alone)."""
        if meta.get("n_map") != len(self.map):
            return False
        if meta.get("origin") is None:
            return True
        origin = self.map.origin
        return (meta.get("map_id"), meta.get("revision"), list(meta["origin"])) == (
            self.map.map_id, self.map.revision, [origin.lat, origin.lon, origin.alt])

    def _carried(self, arrays: dict[str, np.ndarray], meta: dict, to_here,
                 ) -> tuple[dict[str, np.ndarray], dict]:
        """A state of another revision of the map, its positions moved by ``to_here``
        (``(n, 2)`` east/north there -> here); the default has no positions to move."""
        return arrays, meta

    # -- subclass hooks -------------------------------------------------------------------

    @abstractmethod
    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        """Localise one frame; ``t0`` is when the step started (perf_counter)."""

    @abstractmethod
    def _state(self) -> tuple[dict[str, np.ndarray], dict]:
        """Subclass state as arrays and JSON-able metadata."""

    @abstractmethod
    def _load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        """Restore subclass state; the base restores rng and stats."""

    @abstractmethod
    def reset(self) -> None:
        """Forget everything learnt from earlier frames (global re-initialisation)."""

    @abstractmethod
    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        """Start from a known pose (east/north metres in the map frame)."""


class StatelessLocaliser(Localiser, ABC):
    """A localiser that keeps no belief between frames: each frame stands alone."""

    def _state(self) -> tuple[dict[str, np.ndarray], dict]:
        return {}, {}

    def _load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        return None  # nothing beyond the base's rng and statistics

    def reset(self) -> None:
        return None  # no belief to forget

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        return None  # each frame is localised on its own; a prior pose is not used
