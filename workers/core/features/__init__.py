"""Global image features: one fixed-length histogram vector per image, picked by name.

=================  ====  =====================================================  ===========
name               dim   definition                                             measure
=================  ====  =====================================================  ===========
``grid_hist``      128   Erhard et al. 4.1.1: 4x4 grid of 8-bin grey histograms  intersection
``wgoh``           128   Weiss et al. 2008 II-A (Bradley): gradient orientations weiss
``wgii``           128   Weiss et al. 2008 II-B: relational integral invariants  weiss
``wgii2``          256   Erhard et al. 4.1.3: two-kernel WGII                   l2
``wgii2_sparse``   256   ``wgii2`` on one pixel of every 2x2 block               l2
``hue_hist``        32   Li et al. eq. 4: chroma-weighted HSI hue histogram      l2
=================  ====  =====================================================  ===========

Every feature is a non-negative float32 vector summing to 1 (up to float32 rounding), or all
zeros when the image has nothing to count (a WGOH without gradients, a hue histogram without
colour); :mod:`workers.core.measures` re-normalises as each measure needs. The measure
column is the one the feature's source paper uses with it (Flyphone's best for
``grid_hist`` and ``wgii2``).

Each module also exposes the array-level function (``wgoh(grey)``, ``hue_hist(bgr)``, ...);
the registry wraps them as functions of a :class:`~workers.core.image.Frame`, and
:func:`extract_many` computes several features of one frame sharing the intermediate arrays
(the float grey image, the mirrored image of the WGII kernels, the dense invariant map that
``wgii2_sparse`` subsamples).

Place descriptors (``vlad_orb``, ``vlad_rootsift``, ``bow_orb``, ``bow_rootsift``) are global
features too, but over a vocabulary trained on each map's own local features (ORB,
RootSIFT); they live in :mod:`.descriptors` (:data:`DESCRIPTORS`) and are computed by
:class:`workers.core.query.QueryFrame` and :func:`workers.core.mapbuild.assemble_map`, which hold
the vocabulary. :data:`ALL_FEATURE_NAMES` lists both kinds, the names a configuration may use.
:func:`north_up` turns a frame north-up from its compass heading before description.

The package attributes ``grid_hist``, ``wgoh``, ``wgii`` and ``hue_hist`` are these functions,
which shadow the modules of the same name; reach a module's constants with
``from workers.core.features.wgii import EPS``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from ..image import Frame
from ._grid import FrameInputs
from .descriptors import DESCRIPTOR_NAMES, DESCRIPTORS, DescriptorSpec, get_descriptor
from .grid_hist import _grid_hist_inputs, grid_hist
from .heading import north_up
from .hue_hist import hue_hist
from .wgii import (
    _wgii2_inputs,
    _wgii2_sparse_inputs,
    _wgii_inputs,
    integral_invariant,
    wgii,
    wgii2,
    wgii2_sparse,
)
from .wgoh import _wgoh_inputs, wgoh

__all__ = [
    "ALL_FEATURE_NAMES",
    "DESCRIPTORS",
    "DESCRIPTOR_NAMES",
    "DescriptorSpec",
    "FEATURE_NAMES",
    "GLOBAL_FEATURES",
    "FeatureSpec",
    "extract",
    "extract_many",
    "get_descriptor",
    "get_feature",
    "grid_hist",
    "hue_hist",
    "integral_invariant",
    "north_up",
    "wgii",
    "wgii2",
    "wgii2_sparse",
    "wgoh",
]


@dataclass(frozen=True, slots=True)
class FeatureSpec:
    """A registered global feature.

    Attributes
    ----------
    name : str
    dim : int
        Length of the feature vector.
    fn : callable
        ``fn(frame: Frame) -> (dim,) float32 ndarray``.
    description : str
    measure : str
        Similarity measure the source paper pairs with the feature (a name in
        :data:`workers.core.measures.MEASURES`).
    """

    name: str
    dim: int
    fn: Callable[[Frame], np.ndarray]
    description: str
    measure: str
    _compute: Callable[[FrameInputs], np.ndarray] = field(repr=False, compare=False)


def _spec(name: str, dim: int, description: str, measure: str,
          compute: Callable[[FrameInputs], np.ndarray], *, colour: bool = False) -> FeatureSpec:
    if colour:
        def fn(frame: Frame) -> np.ndarray:
            return compute(FrameInputs(frame.grey, frame.colour))
    else:
        def fn(frame: Frame) -> np.ndarray:
            return compute(FrameInputs(frame.grey))
    fn.__name__ = name
    fn.__doc__ = f"{description} of a Frame: ({dim},) float32."
    return FeatureSpec(name, dim, fn, description, measure, compute)


def _hue_inputs(inputs: FrameInputs) -> np.ndarray:
    return hue_hist(inputs.colour)


GLOBAL_FEATURES: dict[str, FeatureSpec] = {
    s.name: s
    for s in (
        _spec("grid_hist", 128, "4x4 grid of Gaussian-weighted 8-bin grey histograms "
              "(Flyphone 4.1.1)", "intersection", _grid_hist_inputs),
        _spec("wgoh", 128, "weighted grid orientation histograms (Weiss 2008 II-A)",
              "weiss", _wgoh_inputs),
        _spec("wgii", 128, "weighted grid integral invariants, kernel (10,0)/(0,20) "
              "(Weiss 2008 II-B)", "weiss", _wgii_inputs),
        _spec("wgii2", 256, "two-kernel WGII (2,0)/(0,3) + (5,0)/(0,10) (Flyphone 4.1.3)",
              "l2", lambda inputs: _wgii2_inputs(inputs, 1)),
        _spec("wgii2_sparse", 256, "two-kernel WGII on one pixel of each 2x2 block "
              "(Flyphone 4.1.3, sparse)", "l2", _wgii2_sparse_inputs),
        _spec("hue_hist", 32, "chroma-weighted HSI hue histogram, 32 bins (Li eq. 4)", "l2",
              _hue_inputs, colour=True),
    )
}
"""Registered global features by name."""

FEATURE_NAMES: tuple[str, ...] = tuple(GLOBAL_FEATURES)
"""Names of the registered global features, in registry order."""

ALL_FEATURE_NAMES: tuple[str, ...] = FEATURE_NAMES + DESCRIPTOR_NAMES
"""Histogram features and place descriptors: every name a configuration may choose."""


def get_feature(name: str) -> FeatureSpec:
    """Look up a feature by name.

    Raises
    ------
    ValueError
        Unknown name; the message lists the valid ones.
    """
    try:
        return GLOBAL_FEATURES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown global feature {name!r}; valid names are "
                         f"{', '.join(FEATURE_NAMES)}") from None


def extract(name: str, frame: Frame) -> np.ndarray:
    """One global feature of a frame: ``(dim,) float32``."""
    return get_feature(name).fn(frame)


def extract_many(names: Iterable[str], frame: Frame) -> dict[str, np.ndarray]:
    """Several global features of one frame, sharing intermediate arrays.

    Parameters
    ----------
    names : iterable of str
    frame : Frame

    Returns
    -------
    features : dict
        ``name -> (dim,) float32 ndarray`` for each distinct name, in the order given.
    """
    specs = [get_feature(name) for name in dict.fromkeys(names)]
    inputs = FrameInputs(frame.grey, frame.colour)
    return {spec.name: spec._compute(inputs) for spec in specs}
