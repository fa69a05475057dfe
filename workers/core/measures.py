"""Histogram distance and similarity measures (Erhard et al. 4.2; Weiss et al. 2008 eq. 1).

One query vector is compared with a whole map matrix at once (one row per map image).

==================  =============================================  ==============  =======
measure             distance ``d(q, m)``                            normalisation   d_max
==================  =============================================  ==============  =======
``l1``              ``sum |q - m|``  (Flyphone eq. 2, p = 1)       L1              2
``l2``              ``sqrt(sum (q - m)^2)``  (eq. 2, p = 2)        L2              sqrt(2)
``linf``            ``max |q - m|``  (eq. 3)                       L1              1
``intersection``    ``1 - sum min(q, m)``  (Siggelkow; eq. 4)      L1              1
``bradley``         ``1 - q . m``  (eq. 5)                         L2              1
``weiss``           ``1 - sum min(q, m) / sum q``  (Weiss eq. 1)   none            1
==================  =============================================  ==============  =======

Normalisation (:func:`normalise`): Flyphone normalises each vector "according to the chosen
norm", L1 for the intersection and the Euclidean norm for Bradley's measure. So ``l1`` uses
L1 and ``l2`` and ``bradley`` use L2 (then ``l2`` and ``bradley`` rank alike:
``|q - m|^2 = 2 (1 - q . m)``). ``linf`` uses L1, not the max norm: scaling each vector to a
largest bin of 1 would let that single bin set the scale of the whole vector. ``weiss`` is
eq. 1 as printed, which normalises by the query's mass itself; the features of
:mod:`workers.core.features` already sum to 1, on which ``weiss`` equals ``intersection``.

Similarity (:func:`similarities`), the one rule for every measure: ``s = 1 - d / d_max``,
where ``d_max`` is the largest distance two non-negative vectors can have under the
measure's normalisation (the table). So ``s`` lies in [0, 1], is 1 for identical vectors and
decreases monotonically with the distance. For ``intersection`` and ``weiss`` ``s`` is the
intersection itself, for ``bradley`` the cosine ``q . m``, for ``l1`` it equals the
intersection too (``|q - m|_1 = 2 - 2 sum min(q, m)`` for vectors summing to 1).

Empty histograms: a vector without mass (all zeros, e.g. the WGOH of a flat image) carries no
evidence of place, so any pair involving one has distance ``d_max`` and similarity 0 under
every measure, itself included.

Inputs must be finite and non-negative (histograms); anything else is a ``ValueError``.

Place descriptors (:mod:`workers.core.features.descriptors`) are not histograms: they have
unit L2 norm and VLAD's components are signed. :func:`descriptor_similarities` compares them
by the one measure they are designed for, the cosine ``q . m``, and turns it into a
similarity by the same rule with ``d = 1 - q . m`` and ``d_max = 1``: ``s = max(q . m, 0)``.
Anti-correlated descriptors (negative cosine) say no more about place than unrelated ones, and
an all-zero descriptor (no local features) matches nothing.
"""

from __future__ import annotations

import numpy as np

MEASURES: tuple[str, ...] = ("l1", "l2", "linf", "intersection", "bradley", "weiss")
"""Names of the measures."""

NORMALISATION: dict[str, str | None] = {
    "l1": "l1", "l2": "l2", "linf": "l1", "intersection": "l1", "bradley": "l2",
    "weiss": None,
}
"""Norm each measure scales its inputs to (None: used as given)."""

D_MAX: dict[str, float] = {
    "l1": 2.0, "l2": float(np.sqrt(2.0)), "linf": 1.0, "intersection": 1.0, "bradley": 1.0,
    "weiss": 1.0,
}
"""Largest distance between two non-negative vectors under each measure's normalisation."""


def normalise(v: np.ndarray, measure: str) -> np.ndarray:
    """Scale a vector, or each row of a matrix, to the norm ``measure`` uses.

    Parameters
    ----------
    v : (D,) or (N, D) array_like, non-negative
    measure : str
        One of :data:`MEASURES`.

    Returns
    -------
    normalised : (D,) or (N, D) float64 ndarray
        Unit L1 or L2 norm along the last axis (``NORMALISATION``); rows without mass stay
        zero; ``weiss`` returns the values unchanged (as float64).
    """
    _check_measure(measure)
    v = np.array(v, dtype=np.float64)  # a copy: scaled in place below
    norm = NORMALISATION[measure]
    if norm is None:
        return v
    if norm == "l1":
        scale = np.abs(v).sum(axis=-1, keepdims=True)
    else:
        scale = np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    with np.errstate(divide="ignore"):
        inverse = np.where(scale > 0, 1.0 / scale, 0.0)
    v *= inverse
    return v


def distances(measure: str, q: np.ndarray, M: np.ndarray, *,
              normalised: bool = False) -> np.ndarray:
    """Distance of one query vector to every row of a map matrix.

    Parameters
    ----------
    measure : str
        One of :data:`MEASURES`.
    q : (D,) array_like
        Query feature, non-negative and finite.
    M : (N, D) array_like
        Map features, one row per map image, non-negative and finite.
    normalised : bool
        True when ``q`` and ``M`` already went through ``normalise(., measure)`` (e.g. a map
        matrix normalised once at load time); skips the normalisation.

    Returns
    -------
    d : (N,) float64 ndarray
        In ``[0, D_MAX[measure]]``; ``D_MAX`` for pairs involving an empty vector.

    Raises
    ------
    ValueError
        Unknown measure, shapes not ``(D,)`` and ``(N, D)``, NaN, infinite or negative values.
    """
    q, M = _check_inputs(measure, q, M)
    own = not normalised and NORMALISATION[measure] is not None
    if own:
        q, M = normalise(q, measure), normalise(M, measure)
    else:
        q, M = np.asarray(q, dtype=np.float64), np.asarray(M, dtype=np.float64)
    empty = ~M.any(axis=1)
    if not q.any():
        empty[:] = True
    # ``own``: M is this call's normalised copy and may be overwritten, which spares the
    # (N, D) temporary (at N = 400 that is a third of the time)
    d = _raw_distances(measure, q, M, overwrite=own)
    np.clip(d, 0.0, D_MAX[measure], out=d)  # float rounding only, e.g. a cosine of 1 + 1e-16
    d[empty] = D_MAX[measure]
    return d


def similarities(measure: str, q: np.ndarray, M: np.ndarray, *,
                 normalised: bool = False) -> np.ndarray:
    """Similarity ``1 - d / d_max`` of one query vector to every row of a map matrix.

    Parameters and errors as :func:`distances`.

    Returns
    -------
    s : (N,) float64 ndarray
        In [0, 1]; 1 for identical (non-empty) vectors, 0 for pairs involving an empty one.
    """
    return 1.0 - distances(measure, q, M, normalised=normalised) / D_MAX[measure]


def weiss_similarity(q_wgoh: np.ndarray, M_wgoh: np.ndarray, q_wgii: np.ndarray,
                     M_wgii: np.ndarray) -> np.ndarray:
    """Weiss et al. 2008 II-C: ``s_WGOH * s_WGII``, each the normalised intersection (eq. 1).

    Parameters
    ----------
    q_wgoh : (D1,) array_like
    M_wgoh : (N, D1) array_like
    q_wgii : (D2,) array_like
    M_wgii : (N, D2) array_like

    Returns
    -------
    s : (N,) float64 ndarray in [0, 1]
    """
    n1, n2 = np.shape(M_wgoh)[:1], np.shape(M_wgii)[:1]
    if n1 != n2:
        raise ValueError(f"WGOH and WGII map matrices must have the same number of rows, "
                         f"got {n1} and {n2}")
    return similarities("weiss", q_wgoh, M_wgoh) * similarities("weiss", q_wgii, M_wgii)


def descriptor_similarities(q: np.ndarray, M: np.ndarray,
                            idx: np.ndarray | None = None) -> np.ndarray:
    """Similarity ``max(q . m, 0)`` of a place descriptor to map descriptors.

    The map matrix is used in place (no copy, no per-call validation: it was checked when the
    map was packed), so scoring a frame against a large map is one matrix-vector product.

    Parameters
    ----------
    q : (D,) float ndarray
        Query descriptor, unit L2 norm or zero, finite.
    M : (N, D) float32 ndarray
        Map descriptors, one row per map image, unit L2 norm or zero.
    idx : (k,) int ndarray, optional
        Score only these map images (all when None).

    Returns
    -------
    s : (k,) or (N,) float64 ndarray in [0, 1]
    """
    q = np.asarray(q, dtype=np.float32)
    if q.ndim != 1 or M.ndim != 2 or M.shape[1] != q.shape[0]:
        raise ValueError(f"expected a (D,) query and an (N, D) map matrix, got {q.shape} "
                         f"and {M.shape}")
    if not np.isfinite(q).all():
        raise ValueError("query descriptor contains NaN or infinite values")
    if idx is None:
        s = M @ q
    else:
        idx = np.asarray(idx, dtype=np.intp)
        # a few rows: gather them; most of the map: one product over all rows is cheaper
        s = M[idx] @ q if 4 * len(idx) < len(M) else (M @ q)[idx]
    return np.clip(s.astype(np.float64), 0.0, 1.0)


def _raw_distances(measure: str, q: np.ndarray, M: np.ndarray, *,
                   overwrite: bool) -> np.ndarray:
    if measure == "bradley":
        return 1.0 - M @ q
    out = M if overwrite else None
    if measure in ("intersection", "weiss"):
        common = np.minimum(M, q, out=out).sum(axis=1)
        if measure == "weiss":
            mass = q.sum()
            return 1.0 - (common / mass if mass > 0 else common)
        return 1.0 - common
    diff = np.subtract(M, q, out=out)
    if measure == "l2":
        return np.sqrt(np.einsum("ij,ij->i", diff, diff))
    np.abs(diff, out=diff)
    if measure == "l1":
        return diff.sum(axis=1)
    return diff.max(axis=1, initial=0.0)  # linf


def _check_measure(measure: str) -> None:
    if measure not in MEASURES:
        raise ValueError(f"unknown similarity measure {measure!r}; valid measures are "
                         f"{', '.join(MEASURES)}")


def _check_inputs(measure: str, q, M) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes and values; returns the arrays unconverted (no copy)."""
    _check_measure(measure)
    q, M = np.asarray(q), np.asarray(M)
    if q.ndim != 1 or M.ndim != 2 or M.shape[1] != q.shape[0]:
        raise ValueError(f"expected a (D,) query and an (N, D) map matrix, got {q.shape} "
                         f"and {M.shape}")
    for name, a in (("query", q), ("map", M)):
        if a.dtype.kind not in "iuf":
            raise ValueError(f"{name} features must be real numbers, got {a.dtype}")
        if a.size == 0:
            continue
        lo, hi = a.min(), a.max()  # NaN propagates into both: two fast passes check all
        if np.isnan(lo) or np.isnan(hi):
            raise ValueError(f"{name} features contain NaN")
        if np.isinf(hi):
            raise ValueError(f"{name} features contain infinite values")
        if lo < 0:
            raise ValueError(f"{name} features must be non-negative histograms")
    return q, M
