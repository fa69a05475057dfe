"""Localisers: a session picks one by name (DESIGN section 4); the names and what each does
are in :mod:`workers.core.modes`."""

from __future__ import annotations

from ..mapdata import MapData
from ..modes import FILTER_MODES, MODES
from ..pf.config import config_from_params
from .base import Localiser, pack_state, unpack_state
from .filtering import FilterLocaliser
from .hierarchical import HierarchicalConfig, HierarchicalLocaliser
from .retrieval import RetrievalConfig, RetrievalLocaliser


def validate_params(mode: str, params: dict | None = None) -> dict:
    """Check a mode's parameters and return them complete, with defaults filled in.

    The filter modes take flat :class:`~workers.core.pf.config.FilterConfig` parameters
    over a named ``config``; ``retrieval`` and ``hierarchical`` the fields of
    :class:`.RetrievalConfig` and :class:`.HierarchicalConfig`. A ``seed`` entry (int) is
    accepted by every mode and passed through.

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
        out = {"config": name, **config_from_params(params).to_params()}
    elif mode == "retrieval":
        out = RetrievalConfig.from_params(params).to_params()
    else:
        out = HierarchicalConfig.from_params(params).to_params()
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
