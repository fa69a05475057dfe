"""Localisers: a session picks one by name (DESIGN section 4).

=============  ==============================================================
mode           behaviour
=============  ==============================================================
hybrid         particle filter switching between global features and SIFT
global, sift   particle filter with one feature type only (Weiss's baselines)
hierarchical   Li: hue-histogram top-k candidates, then SIFT against each
retrieval      Flyphone: nearest map image under a chosen feature and measure
=============  ==============================================================
"""

from __future__ import annotations

from ..features import ALL_FEATURE_NAMES
from ..mapdata import MapData
from ..pf.config import VERIFICATIONS, config_from_params
from ..similarity import MEASURES
from .base import Localiser, pack_state, unpack_state
from .filtering import FilterLocaliser
from .retrieval import HierarchicalLocaliser, RetrievalLocaliser

MODES = ("hybrid", "global", "sift", "hierarchical", "retrieval")
FILTER_MODES = ("hybrid", "global", "sift")

_RETRIEVAL_DEFAULTS = {"feature": "wgoh", "measure": "bradley"}
_HIERARCHICAL_DEFAULTS = {"k": 5, "sift_ratio": 0.8, "sift_verify": "none"}


def _check_keys(mode: str, params: dict, allowed: dict) -> None:
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise ValueError(f"unknown parameter(s) for mode {mode!r}: {', '.join(unknown)}; "
                         f"valid: {', '.join(sorted(allowed))}")


def validate_params(mode: str, params: dict | None = None) -> dict:
    """Check a mode's parameters and return them complete, with defaults filled in.

    A ``seed`` entry (int) is accepted by every mode and passed through.

    Raises
    ------
    ValueError
        Unknown mode, unknown parameter or a value out of range.
    """
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; valid: {', '.join(MODES)}")
    params = dict(params or {})
    seed = params.pop("seed", None)
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if mode in FILTER_MODES:
        name = params.get("config", "default")
        out = {"config": name, **config_from_params(params).to_dict()}
    elif mode == "retrieval":
        _check_keys(mode, params, _RETRIEVAL_DEFAULTS)
        out = {**_RETRIEVAL_DEFAULTS, **params}
        if out["feature"] not in ALL_FEATURE_NAMES:
            raise ValueError(f"unknown feature {out['feature']!r}; "
                             f"valid: {', '.join(ALL_FEATURE_NAMES)}")
        if out["measure"] not in MEASURES:
            raise ValueError(f"unknown measure {out['measure']!r}; valid: {', '.join(MEASURES)}")
    else:
        _check_keys(mode, params, _HIERARCHICAL_DEFAULTS)
        out = {**_HIERARCHICAL_DEFAULTS, **params}
        k = out["k"]
        if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 1000:
            raise ValueError(f"k must be an integer in 1..1000, got {k!r}")
        r = out["sift_ratio"]
        if not isinstance(r, int | float) or not 0 < r < 1:
            raise ValueError(f"sift_ratio must be in (0, 1), got {r!r}")
        if out["sift_verify"] not in VERIFICATIONS:
            raise ValueError(f"sift_verify must be one of {', '.join(VERIFICATIONS)}")
    if seed is not None:
        out["seed"] = seed
    return out


def make_localiser(mode: str, map_data: MapData, params: dict | None = None, *,
                   seed: int = 0) -> Localiser:
    """Build a localiser on a map. ``params`` are checked by :func:`validate_params`."""
    if len(map_data) == 0:
        raise ValueError("the map has no images")
    p = validate_params(mode, params)
    p.pop("seed", None)
    if mode in FILTER_MODES:
        return FilterLocaliser(map_data, p, seed, mode)
    if mode == "retrieval":
        return RetrievalLocaliser(map_data, p, seed)
    return HierarchicalLocaliser(map_data, p, seed)


__all__ = ["FILTER_MODES", "MODES", "Localiser", "make_localiser", "pack_state",
           "unpack_state", "validate_params"]
