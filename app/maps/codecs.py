"""The byte layouts of features as the maps' tables store them (:mod:`app.maps.models`):
little-endian float32 vectors, keypoints and centroids, uint8 descriptors.

The build tasks (:mod:`app.tasks`) write them and read them back in the workers.
"""

from __future__ import annotations

import numpy as np

from vloc.workers.core.features.orb import OrbFeatures
from vloc.workers.core.features.vocabulary import Vocabulary
from vloc.workers.core.sift import SiftFeatures


def encode_vector(vec: np.ndarray) -> bytes:
    """(D,) float32 -> little-endian bytes."""
    return np.ascontiguousarray(vec, dtype="<f4").tobytes()


def decode_vector(data: bytes) -> np.ndarray:
    return np.frombuffer(data, dtype="<f4").astype(np.float32)


def encode_local(features: SiftFeatures | OrbFeatures) -> tuple[bytes, bytes]:
    """Keypoints (K, 4) float32 and descriptors (K, B) uint8 -> little-endian bytes."""
    kps = np.ascontiguousarray(features.keypoints, dtype="<f4").reshape(-1, 4)
    desc = np.ascontiguousarray(features.descriptors, dtype=np.uint8)
    return kps.tobytes(), desc.tobytes()


def _decode_local(n: int, keypoints: bytes, descriptors: bytes, width: int):
    kps = np.frombuffer(keypoints, dtype="<f4").astype(np.float32).reshape(n, 4)
    return kps, np.frombuffer(descriptors, dtype=np.uint8).reshape(n, width)


def decode_sift(n: int, keypoints: bytes, descriptors: bytes) -> SiftFeatures:
    """The inverse of :func:`encode_local` for SIFT (128-byte descriptors)."""
    return SiftFeatures(*_decode_local(n, keypoints, descriptors, 128))


def decode_orb(n: int, keypoints: bytes, descriptors: bytes) -> OrbFeatures:
    """The inverse of :func:`encode_local` for ORB (32-byte descriptors)."""
    return OrbFeatures(*_decode_local(n, keypoints, descriptors, 32))


def encode_vocabulary(vocab: Vocabulary) -> tuple[bytes, bytes, bytes | None]:
    """Centroids (n_nodes, P), idf (n_words,) and projection (P + 1, D) or None, float32
    little-endian -> bytes."""
    projection = None if vocab.projection is None \
        else np.ascontiguousarray(vocab.projection, dtype="<f4").tobytes()
    return (np.ascontiguousarray(vocab.centroids, dtype="<f4").tobytes(),
            np.ascontiguousarray(vocab.idf, dtype="<f4").tobytes(), projection)


def decode_vocabulary(*, branching: int, depth: int, binary: bool, dim: int,
                      centroids: bytes, idf: bytes, projection: bytes | None) -> Vocabulary:
    """The inverse of :func:`encode_vocabulary`; ``dim`` is D, the local vectors' length."""
    idf_arr = np.frombuffer(idf, dtype="<f4").astype(np.float32)
    n_nodes = sum(branching ** level for level in range(1, depth + 1))
    c = np.frombuffer(centroids, dtype="<f4").astype(np.float32).reshape(n_nodes, -1)
    p = None if projection is None \
        else np.frombuffer(projection, dtype="<f4").astype(np.float32).reshape(-1, dim)
    return Vocabulary(c, branching, depth, binary, idf_arr, p)
