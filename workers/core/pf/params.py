"""The particle filter's flat parameters, each declared once: its name, where it lives in
:class:`~.config.FilterConfig`, the values it takes and what it means.

Sessions and the command line name a filter's parameters by flat keys (``n_particles``,
``sift_ratio``, ``global_features`` ...). :data:`PARAMS` declares each (:class:`Param`);
:func:`check_params` validates a full set of them against those declarations, and the API's
request model is generated from them (``app.sessions.params.FilterParams``), so the two
accept the same values. Every configuration is checked when it is made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RESAMPLERS = ("multinomial", "systematic")
REPLACEMENTS = ("uniform", "retrieval")
VERIFICATIONS = ("none", "homography", "fundamental")
REDUCTIONS = ("both", "map", "query", "none")
POINT_ESTIMATES = ("mean", "cluster")
MAX_GLOBAL_FEATURES = 8
"""The most global features one configuration combines."""


@dataclass(frozen=True, slots=True)
class Param:
    """One flat parameter of the filter.

    Attributes
    ----------
    part : str or None
        The part of :class:`~.config.FilterConfig` that holds it, None for its own field.
    field : str
        Its field there.
    type : {bool, int, float, str, tuple}
        What it takes: ``str`` one of ``choices``; ``tuple`` a global feature's name or a
        list of 1 to :data:`MAX_GLOBAL_FEATURES` of them.
    ge, gt, le, lt : float or None
        Bounds of a number.
    choices : tuple of str
        The names a ``str`` parameter takes ("measures" and "features" are the core's lists
        of similarity measures and global features, looked up when needed).
    nullable : bool
        None is a value too.
    auto : bool
        ``"auto"`` is a value too.
    doc : str
        What it means, where the name alone does not say it.
    """

    part: str | None
    field: str
    type: type
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[str, ...] | str = ()
    nullable: bool = False
    auto: bool = False
    doc: str = ""

    @property
    def bounds(self) -> dict[str, float]:
        """The bounds that are set, by name (``ge``, ``gt``, ``le``, ``lt``)."""
        return {k: v for k in ("ge", "gt", "le", "lt") if (v := getattr(self, k)) is not None}

    def names(self) -> tuple[str, ...]:
        """The names a ``str`` or ``tuple`` parameter takes."""
        if self.choices == "measures":
            from ..measures import MEASURES
            return MEASURES
        if self.choices == "features":
            from ..features import ALL_FEATURE_NAMES
            return ALL_FEATURE_NAMES
        return self.choices

    def check(self, name: str, value) -> None:
        """ValueError naming the parameter when ``value`` is not one it takes."""
        if (value is None and self.nullable) or (value == "auto" and self.auto):
            return
        problem = {bool: self._bool, str: self._name, tuple: self._features,
                   int: self._integer}.get(self.type, self._number)(name, value)
        if problem:
            raise ValueError(problem)

    def _within(self, value: float) -> bool:
        return ((self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                and (self.le is None or value <= self.le)
                and (self.lt is None or value < self.lt))

    def _bool(self, name: str, value) -> str | None:
        if not isinstance(value, bool):
            return f"{name} must be true or false, got {value!r}"
        return None

    def _name(self, name: str, value) -> str | None:
        if value in self.names():
            return None
        if self.choices == "measures":
            return f"unknown measure {value!r}; valid: {', '.join(self.names())}"
        return f"{name} must be one of {', '.join(self.names())}; got {value!r}"

    def _features(self, name: str, value) -> str | None:
        names = [value] if isinstance(value, str) else value
        if not names:
            return f"{name} must name at least one feature"
        if len(names) > MAX_GLOBAL_FEATURES:
            return f"{name} must name at most {MAX_GLOBAL_FEATURES} features, got {len(names)}"
        for feature in names:
            if feature not in self.names():
                return (f"unknown global feature {feature!r}; valid: "
                        f"{', '.join(self.names())}")
        return None

    def _integer(self, name: str, value) -> str | None:
        if isinstance(value, int) and not isinstance(value, bool) and self._within(value):
            return None
        null = "null or " if self.nullable else ""
        return f"{name} must be {null}an integer in {self.ge}..{self.le}, got {value!r}"

    def _number(self, name: str, value) -> str | None:
        number = (isinstance(value, int | float) and not isinstance(value, bool)
                  and math.isfinite(value))
        if number and self._within(value):
            return None
        if self.gt == 0:  # a positive quantity, with a ceiling
            if not number or value <= 0:
                return f"{name} must be a positive number, got {value!r}"
            if self.lt is not None:
                return f"{name} must be below {self.lt:g}, got {value!r}"
            return f"{name} must be at most {self.le:g}, got {value!r}"
        low = f"[{self.ge:g}" if self.ge is not None else f"({self.gt:g}"
        high = f"{self.le:g}]" if self.le is not None else f"{self.lt:g})"
        return f"{name} must be in {low}, {high}, got {value!r}"


_COUNT = {"type": int, "ge": 0, "le": 1000}

PARAMS: dict[str, Param] = {
    "n_particles": Param(None, "n_particles", int, ge=1, le=100_000),
    "motion_sigma": Param("motion", "sigma", float, gt=0, le=1e4, doc="Metres per frame"),
    "speed": Param("motion", "speed", float, gt=0, le=1e4, nullable=True, auto=True,
                   doc='Metres per second, "auto" (from the map) or null'),
    "pull": Param("motion", "pull", float, ge=0, lt=1),
    "global_power": Param("measurement", "global_power", float, gt=0, le=1e3),
    "replace_fraction": Param("reset", "fraction", float, ge=0, lt=1),
    "replacement": Param("reset", "replacement", str, choices=REPLACEMENTS),
    "d_global": Param("switching", "d_global", float, gt=0, le=1e5, doc="Metres"),
    "d_sift": Param("switching", "d_sift", float, gt=0, le=1e5, doc="Metres"),
    "distance_scale": Param("measurement", "distance_scale", float, gt=0, le=1e5,
                            nullable=True, doc="Metres, or null"),
    "global_features": Param("measurement", "global_features", tuple, choices="features"),
    "global_measure": Param("measurement", "global_measure", str, choices="measures"),
    "sift_ratio": Param("sift", "ratio", float, gt=0, lt=1),
    "sift_verify": Param("sift", "verify", str, choices=VERIFICATIONS),
    "sift_reduce": Param("sift", "reduce", str, choices=REDUCTIONS),
    "sift_power": Param("measurement", "sift_power", float, gt=0, le=1e3),
    "global_check": Param("switching", "global_check", **_COUNT),
    "sift_candidates": Param("sift", "candidates", **_COUNT),
    "global_trust": Param("switching", "global_trust", **_COUNT),
    "global_trust_level": Param("switching", "global_trust_level", float, ge=0, le=1),
    "velocity": Param("motion", "velocity", bool),
    "drift": Param("motion", "drift", bool,
                   doc="Move the cloud by the velocity tracked from fixes"),
    "resampler": Param(None, "resampler", str, choices=RESAMPLERS),
    "point_estimate": Param(None, "point_estimate", str, choices=POINT_ESTIMATES,
                            doc="The position reported: the weighted mean of the whole cloud, "
                                "or of its heaviest cluster where it holds most of the "
                                "weight"),
    "refine": Param("refine", "enabled", bool,
                    doc="Fuse a metric position solved against the best map images"),
    "refine_outlier": Param("refine", "outlier", float, gt=0, lt=1,
                            doc="Probability that a refined position is wrong"),
    "refine_inject": Param("refine", "inject", float, ge=0, lt=1,
                           doc="Share of the particles drawn around a refined position"),
    "refine_global": Param("refine", "on_global", bool,
                           doc="Register global steps with ORB against the map's geometry"),
    "refine_global_inliers": Param("refine", "global_inliers", int, ge=4, le=10_000,
                                   doc="Fewest pose inliers for a global step's fix"),
    "refine_gate": Param("refine", "gate", float, gt=0, le=1e3,
                         doc="A global step's fix counts within this many cloud spreads"),
    "refine_sift_fallback": Param("refine", "sift_fallback", bool,
                                  doc="Register a global step with SIFT against the same map "
                                      "images when ORB finds no fix"),
    "global_misses": Param("switching", "global_misses", int, ge=0, le=1000, nullable=True,
                           doc="Global steps in a row without a fix allowed"),
    "escalate": Param("switching", "escalate", bool,
                      doc="Take back a global step without a fix and use SIFT for the frame"),
}
"""Flat parameter name -> its declaration, in the order :meth:`FilterConfig.to_params`
lists them."""


def check_params(c: dict) -> None:
    """Validate a full set of flat parameters; the first problem found is the error."""
    for name, param in PARAMS.items():
        param.check(name, c[name])
