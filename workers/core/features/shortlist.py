"""Place descriptors of a large map: a compact scan for the shortlist, exact scores on it.

A global step of the ``default`` configuration scores the frame against every map image: the
replacement particles start at the best-retrieved images, and the switching checks and the
SIFT candidates look at the best few. Scoring is one product with the map's (N, D) float32
descriptor matrix; at 50,000 images of 2,048-dimensional VLAD that reads 400 MB per step and
is bound by memory bandwidth, over 20 ms on one core. Every consumer uses only the top of the
ranking, so a large map keeps a second, compact copy of its descriptors: their coordinates
along the leading principal directions of the map's own descriptors (``CODE_DIMS`` of them).
The scan over those codes picks a shortlist (``SHORTLIST`` images), and the shortlist is
scored exactly with the full descriptors. Images outside it are left unscored.

The directions are the leading eigenvectors of the uncentred second-moment matrix of the
descriptors (Jegou and Chum, ECCV 2012, reduce VLAD by PCA the same way), so that
``codes @ (basis.T @ q)`` is the dot product of the descriptors projected onto that subspace:
close to the exact similarity for the images that look alike, which is what the shortlist
needs to hold. Maps of at most ``CODES_FROM`` images keep no codes and are scored exactly, as
before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CODES_FROM: int = 8192
"""Maps with more images than this keep shortlist codes (below it the exact product costs a
few milliseconds: 3 ms at 8,192 x 2,048 on one core)."""

CODE_DIMS: int = 128
"""Principal directions kept per code."""

SHORTLIST: int = 512
"""Map images rescored exactly per scan."""

FIT_SAMPLE: int = 20_000
"""Map descriptors the directions are estimated from (all of them on smaller maps)."""

_CHUNK = 8192  # rows projected at a time: no float64 copy of the whole matrix


@dataclass(frozen=True)
class PlaceCodes:
    """Compact codes of a map's place descriptors.

    Attributes
    ----------
    basis : (D, d) float32 ndarray
        Orthonormal columns: the leading principal directions.
    codes : (N, d) float32 ndarray
        Each map descriptor's coordinates along them.
    """

    basis: np.ndarray
    codes: np.ndarray

    def __post_init__(self) -> None:
        if self.basis.ndim != 2 or self.codes.ndim != 2 \
                or self.codes.shape[1] != self.basis.shape[1]:
            raise ValueError(f"codes {self.codes.shape} do not fit basis {self.basis.shape}")

    def __len__(self) -> int:
        return len(self.codes)

    @classmethod
    def fit(cls, descriptors: np.ndarray, *, dims: int = CODE_DIMS, sample: int = FIT_SAMPLE,
            seed: int = 0) -> PlaceCodes:
        """Principal directions of ``descriptors`` (N, D) and the codes of every row.

        The directions come from ``sample`` rows drawn without replacement (every row on a
        smaller map), fixed by ``seed``, so that a map packs to the same codes every time.
        """
        M = np.asarray(descriptors)
        n, d_full = M.shape
        dims = min(dims, d_full)
        if n > sample:
            rows = np.sort(np.random.default_rng(seed).choice(n, size=sample, replace=False))
        else:
            rows = np.arange(n)
        second = np.zeros((d_full, d_full))
        for a in range(0, len(rows), _CHUNK):
            part = np.asarray(M[rows[a:a + _CHUNK]], np.float64)
            second += part.T @ part
        _, vectors = np.linalg.eigh(second)  # ascending eigenvalues
        basis = np.ascontiguousarray(vectors[:, ::-1][:, :dims], np.float32)
        codes = np.empty((n, dims), np.float32)
        for a in range(0, n, _CHUNK):
            codes[a:a + _CHUNK] = np.asarray(M[a:a + _CHUNK], np.float32) @ basis
        return cls(basis, codes)

    def shortlist(self, query: np.ndarray, k: int | None = None) -> np.ndarray:
        """The ``k`` (:data:`SHORTLIST`) map images whose codes score highest against
        ``query`` (D,), ascending by index (every image when the map has no more)."""
        k = SHORTLIST if k is None else k
        n = len(self.codes)
        if k >= n:
            return np.arange(n)
        approx = self.codes @ (np.asarray(query, np.float32) @ self.basis)
        return np.sort(np.argpartition(-approx, k - 1)[:k])
