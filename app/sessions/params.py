"""The body of ``POST /v1/sessions``: a localiser mode and its parameters, strictly typed.

Each mode family has its own parameter model, picked by ``mode``: types are strict (``true``
is not a number, ``"5"`` is not an integer), numbers finite and within the core's bounds,
names from the core's lists, unknown keys refused. So a wrongly typed parameter is a 422
naming the field, never an error inside a worker or the database. A parameter left out
takes the value of the named configuration (``config``), which is why the fields have no
default of their own here. The core checks the whole set once more
(:func:`workers.core.localisers.validate_params`).
"""

from __future__ import annotations

import uuid
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag

SEED_BOUND = 2**63
"""Seeds are stored in a signed 64-bit column: below 2**63 (an exclusive bound, which a
JSON number states exactly where 2**63 - 1 is rounded up)."""

FilterConfigName = Literal["default", "weiss2008"]
FeatureName = Literal["grid_hist", "wgoh", "wgii", "wgii2", "wgii2_sparse", "hue_hist",
                      "vlad_orb", "vlad_rootsift", "bow_orb", "bow_rootsift"]
MeasureName = Literal["l1", "l2", "linf", "intersection", "bradley", "weiss"]
Verification = Literal["none", "homography", "fundamental"]


def _no_defaults(schema: dict) -> None:
    for prop in schema.get("properties", {}).values():
        prop.pop("default", None)


def _unset(**constraints):
    """A parameter that may be left out (the configuration's value), but not null."""
    return Field(None, **constraints)


class _Params(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False,
                              json_schema_extra=_no_defaults)

    seed: int = _unset(ge=0, lt=SEED_BOUND, description="Random seed (as the body's seed)")


class FilterParams(_Params):
    """Parameters of the particle filter (``hybrid``, ``global``, ``sift``); see
    :class:`workers.core.pf.config.FilterConfig` for their meaning."""

    config: FilterConfigName = _unset(description="Named base configuration")
    n_particles: int = _unset(ge=1, le=100_000)
    motion_sigma: float = _unset(gt=0, le=1e4, description="Metres per frame")
    speed: Annotated[float, Field(gt=0, le=1e4)] | Literal["auto"] | None = _unset(
        description='Metres per second, "auto" (from the map) or null')
    pull: float = _unset(ge=0, lt=1)
    global_power: float = _unset(gt=0, le=1e3)
    replace_fraction: float = _unset(ge=0, lt=1)
    replacement: Literal["uniform", "retrieval"] = _unset()
    d_global: float = _unset(gt=0, le=1e5, description="Metres")
    d_sift: float = _unset(gt=0, le=1e5, description="Metres")
    distance_scale: Annotated[float, Field(gt=0, le=1e5)] | None = _unset(
        description="Metres, or null")
    global_features: FeatureName | Annotated[list[FeatureName], Field(
        min_length=1, max_length=8)] = _unset()
    global_measure: MeasureName = _unset()
    sift_ratio: float = _unset(gt=0, lt=1)
    sift_verify: Verification = _unset()
    sift_reduce: Literal["both", "map", "query", "none"] = _unset()
    sift_power: float = _unset(gt=0, le=1e3)
    global_check: int = _unset(ge=0, le=1000)
    sift_candidates: int = _unset(ge=0, le=1000)
    global_trust: int = _unset(ge=0, le=1000)
    global_trust_level: float = _unset(ge=0, le=1)
    velocity: bool = _unset()
    resampler: Literal["multinomial", "systematic"] = _unset()
    refine: bool = _unset(description="Fuse a metric position solved against the best map "
                                      "images")
    refine_outlier: float = _unset(gt=0, lt=1, description="Probability that a refined "
                                                           "position is wrong")
    refine_inject: float = _unset(ge=0, lt=1, description="Share of the particles drawn "
                                                          "around a refined position")
    refine_global: bool = _unset(description="Register global steps with ORB against the "
                                             "map's geometry")
    refine_global_inliers: int = _unset(ge=4, le=10_000, description="Fewest pose inliers "
                                                                     "for a global step's fix")
    refine_gate: float = _unset(gt=0, le=1e3, description="A global step's fix counts "
                                                          "within this many cloud spreads")
    refine_sift_fallback: bool = _unset(description="Register a global step with SIFT "
                                                    "against the same map images when ORB "
                                                    "finds no fix")
    global_misses: int | None = _unset(ge=0, le=1000, description="Global steps in a row "
                                                                  "without a fix allowed")
    escalate: bool = _unset(description="Take back a global step without a fix and use "
                                        "SIFT for the frame")
    drift: bool = _unset(description="Move the cloud by the velocity tracked from fixes")


class RetrievalParams(_Params):
    """Flyphone retrieval: the nearest map image under one feature and measure."""

    feature: FeatureName = _unset()
    measure: MeasureName = _unset()


class HierarchicalParams(_Params):
    """Li et al.: hue-histogram candidates, then SIFT against each."""

    k: int = _unset(ge=1, le=1000)
    sift_ratio: float = _unset(gt=0, lt=1)
    sift_verify: Verification = _unset()


class NavigationParams(BaseModel):
    """Path following (Li et al.); see :class:`workers.core.navigation.FollowerConfig`."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False,
                              json_schema_extra=_no_defaults)

    alpha: float = _unset(gt=0, le=100, description="Natural frequency per metre: "
                                                    "k2 = alpha^2, k3 = 2 xi alpha")
    xi: float = _unset(gt=0, le=10, description="Damping (1/sqrt(2) in the paper)")
    v_max: float = _unset(gt=0, le=100, description="Forward speed, m/s")
    w_max: float = _unset(gt=0, le=100, description="Largest turn rate, rad/s")
    dt: float = _unset(gt=0, le=3600, description="Seconds between frames without "
                                                  "capture times")
    arrive_tolerance: float = _unset(gt=0, le=1000, description="Metres before the end")
    command_sigma_v: float = _unset(gt=0, le=100)
    command_sigma_w: float = _unset(gt=0, le=100)
    heading_sigma: float = _unset(gt=0, le=10, description="Radians")
    gate: bool = _unset(description="Reject fixes far from the filter's prediction")
    visual: bool = _unset(description="Heading and bearings from the frame's relative pose "
                                      "to the taught images behind the best one")
    hfov_deg: float = _unset(ge=1, le=179, description="The robot camera's horizontal "
                                                       "field of view")
    views: int = _unset(ge=0, le=20, description="Taught images looked at for bearings")


class NavigationCreate(BaseModel):
    """Follow a ready route of the session's map, all of it or from one node to another."""

    model_config = ConfigDict(strict=True, extra="forbid")

    route_id: uuid.UUID = Field(strict=False)
    from_node: int | None = Field(None, ge=0, le=1_000_000)
    to_node: int | None = Field(None, ge=0, le=1_000_000)
    params: NavigationParams = Field(default_factory=NavigationParams)


class _SessionCreate(BaseModel):
    map_id: uuid.UUID
    seed: int | None = Field(None, ge=0, lt=SEED_BOUND, strict=True,
                             description="Random seed (or params.seed); random when unset")
    navigation: NavigationCreate | None = Field(
        None, description="Follow a route: each pose then carries the path following")

    ttl_s: int | None = Field(None, ge=10, strict=True,
                              description="Seconds without a frame or keep-alive after which "
                                          "the session expires; the server's default "
                                          "(VLOC_SESSION_TTL_S) when unset")

    def given_params(self) -> dict:
        """The parameters the client gave (the configuration fills in the others)."""
        return self.params.model_dump(exclude_unset=True)


class FilterSessionCreate(_SessionCreate):
    mode: Literal["hybrid", "global", "sift"] = "hybrid"
    params: FilterParams = Field(default_factory=FilterParams)


class RetrievalSessionCreate(_SessionCreate):
    mode: Literal["retrieval"]
    params: RetrievalParams = Field(default_factory=RetrievalParams)


class HierarchicalSessionCreate(_SessionCreate):
    mode: Literal["hierarchical"]
    params: HierarchicalParams = Field(default_factory=HierarchicalParams)


MODES = ("hybrid", "global", "sift", "hierarchical", "retrieval")
_FAMILY = {"hybrid": "filter", "global": "filter", "sift": "filter",
           "retrieval": "retrieval", "hierarchical": "hierarchical"}


def _family(value) -> str | None:
    mode = value.get("mode", "hybrid") if isinstance(value, dict) \
        else getattr(value, "mode", None)
    return _FAMILY.get(mode) if isinstance(mode, str) else None


SessionCreate = Annotated[
    Annotated[FilterSessionCreate, Tag("filter")]
    | Annotated[RetrievalSessionCreate, Tag("retrieval")]
    | Annotated[HierarchicalSessionCreate, Tag("hierarchical")],
    Discriminator(_family, custom_error_type="bad_mode",
                  custom_error_message=f"mode must be one of {', '.join(MODES)}")]
"""The body of ``POST /v1/sessions``; ``mode`` (default ``hybrid``) picks the model."""
