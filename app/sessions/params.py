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


class RetrievalParams(_Params):
    """Flyphone retrieval: the nearest map image under one feature and measure."""

    feature: FeatureName = _unset()
    measure: MeasureName = _unset()


class HierarchicalParams(_Params):
    """Li et al.: hue-histogram candidates, then SIFT against each."""

    k: int = _unset(ge=1, le=1000)
    sift_ratio: float = _unset(gt=0, lt=1)
    sift_verify: Verification = _unset()


class _SessionCreate(BaseModel):
    map_id: uuid.UUID
    seed: int | None = Field(None, ge=0, lt=SEED_BOUND, strict=True,
                             description="Random seed (or params.seed); random when unset")

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
