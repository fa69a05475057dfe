"""The particle filter's flat parameters: their names and their validation.

Sessions and the command line name a filter's parameters by flat keys (``n_particles``,
``sift_ratio``, ``global_features`` ...). :data:`PARAMS` maps each to its part and field of
:class:`~.config.FilterConfig`, and :func:`check_params` validates a full set of them.
Every configuration is checked when it is made.
"""

from __future__ import annotations

import math

RESAMPLERS = ("multinomial", "systematic")
REPLACEMENTS = ("uniform", "retrieval")
VERIFICATIONS = ("none", "homography", "fundamental")
REDUCTIONS = ("both", "map", "query", "none")


PARAMS: dict[str, tuple[str | None, str]] = {
    "n_particles": (None, "n_particles"),
    "motion_sigma": ("motion", "sigma"),
    "speed": ("motion", "speed"),
    "pull": ("motion", "pull"),
    "global_power": ("measurement", "global_power"),
    "replace_fraction": ("reset", "fraction"),
    "replacement": ("reset", "replacement"),
    "d_global": ("switching", "d_global"),
    "d_sift": ("switching", "d_sift"),
    "distance_scale": ("measurement", "distance_scale"),
    "global_features": ("measurement", "global_features"),
    "global_measure": ("measurement", "global_measure"),
    "sift_ratio": ("sift", "ratio"),
    "sift_verify": ("sift", "verify"),
    "sift_reduce": ("sift", "reduce"),
    "sift_power": ("measurement", "sift_power"),
    "global_check": ("switching", "global_check"),
    "sift_candidates": ("sift", "candidates"),
    "global_trust": ("switching", "global_trust"),
    "global_trust_level": ("switching", "global_trust_level"),
    "velocity": ("motion", "velocity"),
    "drift": ("motion", "drift"),
    "resampler": (None, "resampler"),
    "refine": ("refine", "enabled"),
    "refine_outlier": ("refine", "outlier"),
    "refine_inject": ("refine", "inject"),
    "refine_global": ("refine", "on_global"),
    "refine_global_inliers": ("refine", "global_inliers"),
    "refine_gate": ("refine", "gate"),
    "refine_sift_fallback": ("refine", "sift_fallback"),
    "global_misses": ("switching", "global_misses"),
    "escalate": ("switching", "escalate"),
}
"""Flat parameter name -> (part of :class:`FilterConfig`, or None for its own field; field)."""


def check_params(c: dict) -> None:
    """Validate the flat parameters; the first problem found is the error."""
    def positive(name: str, value: float) -> None:
        if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")

    if not isinstance(c["n_particles"], int) or not 1 <= c["n_particles"] <= 100_000:
        raise ValueError(f"n_particles must be an integer in 1..100000, got {c['n_particles']!r}")
    for name in ("motion_sigma", "global_power", "d_global", "d_sift", "sift_ratio",
                 "sift_power"):
        positive(name, c[name])
    for name in ("global_check", "sift_candidates", "global_trust"):
        value = c[name]
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= 1000:
            raise ValueError(f"{name} must be an integer in 0..1000, got {value!r}")
    if c["distance_scale"] is not None:
        positive("distance_scale", c["distance_scale"])
    if c["speed"] is not None and c["speed"] != "auto":
        positive("speed", c["speed"])
    if not 0.0 <= c["global_trust_level"] <= 1.0:
        raise ValueError(f"global_trust_level must be in [0, 1], got {c['global_trust_level']!r}")
    for name in ("refine", "refine_global", "drift", "velocity", "escalate",
                 "refine_sift_fallback"):
        if not isinstance(c[name], bool):
            raise ValueError(f"{name} must be true or false, got {c[name]!r}")
    inliers = c["refine_global_inliers"]
    if not isinstance(inliers, int) or isinstance(inliers, bool) or not 4 <= inliers <= 10_000:
        raise ValueError(f"refine_global_inliers must be an integer in 4..10000, got {inliers!r}")
    positive("refine_gate", c["refine_gate"])
    misses = c["global_misses"]
    if misses is not None and (not isinstance(misses, int) or isinstance(misses, bool)
                               or not 0 <= misses <= 1000):
        raise ValueError(f"global_misses must be null or an integer in 0..1000, got {misses!r}")
    if not 0.0 < c["refine_outlier"] < 1.0:
        raise ValueError(f"refine_outlier must be in (0, 1), got {c['refine_outlier']!r}")
    if not 0.0 <= c["refine_inject"] < 1.0:
        raise ValueError(f"refine_inject must be in [0, 1), got {c['refine_inject']!r}")
    if not 0.0 <= c["pull"] < 1.0:
        raise ValueError(f"pull must be in [0, 1), got {c['pull']!r}")
    if not 0.0 <= c["replace_fraction"] < 1.0:
        raise ValueError(f"replace_fraction must be in [0, 1), got {c['replace_fraction']!r}")
    if c["sift_ratio"] >= 1.0:
        raise ValueError(f"sift_ratio must be below 1, got {c['sift_ratio']!r}")
    for name, allowed in (("replacement", REPLACEMENTS), ("sift_verify", VERIFICATIONS),
                          ("sift_reduce", REDUCTIONS), ("resampler", RESAMPLERS)):
        if c[name] not in allowed:
            raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {c[name]!r}")
    if not c["global_features"]:
        raise ValueError("global_features must name at least one feature")
    from ..features import ALL_FEATURE_NAMES
    from ..measures import MEASURES
    for name in c["global_features"]:
        if name not in ALL_FEATURE_NAMES:
            raise ValueError(f"unknown global feature {name!r}; valid: "
                             f"{', '.join(ALL_FEATURE_NAMES)}")
    if c["global_measure"] not in MEASURES:
        raise ValueError(f"unknown measure {c['global_measure']!r}; valid: {', '.join(MEASURES)}")
