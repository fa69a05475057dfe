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

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, create_model

from vloc.workers.core.features import ALL_FEATURE_NAMES
from vloc.workers.core.measures import MEASURES
from vloc.workers.core.modes import FILTER_MODES, MODES
from vloc.workers.core.pf.params import MAX_GLOBAL_FEATURES, PARAMS, VERIFICATIONS, Param

SEED_BOUND = 2**63
"""Seeds are stored in a signed 64-bit column: below 2**63 (an exclusive bound, which a
JSON number states exactly where 2**63 - 1 is rounded up)."""

FilterConfigName = Literal["default", "weiss2008"]
FeatureName = Literal[ALL_FEATURE_NAMES]
MeasureName = Literal[MEASURES]
Verification = Literal[VERIFICATIONS]


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


def _filter_field(param: Param) -> tuple[object, object]:
    """The pydantic (annotation, field) of one declared filter parameter."""
    doc = {"description": param.doc} if param.doc else {}
    if param.type is tuple:
        return FeatureName | Annotated[list[FeatureName], Field(
            min_length=1, max_length=MAX_GLOBAL_FEATURES)], _unset(**doc)
    if param.type is str:
        return Literal[param.names()], _unset(**doc)
    if param.type is float and param.nullable:
        number = Annotated[float, Field(**param.bounds)]
        annotation = number | Literal["auto"] | None if param.auto else number | None
        return annotation, _unset(**doc)
    annotation = param.type | None if param.nullable else param.type
    return annotation, _unset(**param.bounds, **doc)


FilterParams = create_model(
    "FilterParams", __base__=_Params, __module__=__name__,
    __doc__="""Parameters of the particle filter (``hybrid``, ``global``, ``sift``); see
    :class:`workers.core.pf.config.FilterConfig` for their meaning.""",
    config=(FilterConfigName, _unset(description="Named base configuration")),
    **{name: _filter_field(param) for name, param in PARAMS.items()})
"""Generated from the core's declarations (:data:`workers.core.pf.params.PARAMS`): the
names, types and bounds the core checks, strictly typed and with nothing left to default."""


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

    map_revision: int | None = Field(
        None, ge=1, strict=True,
        description="Localise against this revision of the map (one of its recorded "
                    "revisions whose files are kept) and stay on it; the map's current "
                    "revision when unset")
    follow_map: bool | None = Field(
        None, strict=True,
        description="Move to the map's new revision, between two frames and with the "
                    "filter's state, whenever the map is rebuilt or restored: true by "
                    "default; false stays on the revision the session starts on, as does "
                    "a session given map_revision or a route to follow")
    ttl_s: int | None = Field(None, ge=10, strict=True,
                              description="Seconds without a frame or keep-alive after which "
                                          "the session expires; the server's default "
                                          "(VLOC_SESSION_TTL_S) when unset")

    def given_params(self) -> dict:
        """The parameters the client gave (the configuration fills in the others)."""
        return self.params.model_dump(exclude_unset=True)


class FilterSessionCreate(_SessionCreate):
    mode: Literal[FILTER_MODES] = "hybrid"
    params: FilterParams = Field(default_factory=FilterParams)


class RetrievalSessionCreate(_SessionCreate):
    mode: Literal["retrieval"]
    params: RetrievalParams = Field(default_factory=RetrievalParams)


class HierarchicalSessionCreate(_SessionCreate):
    mode: Literal["hierarchical"]
    params: HierarchicalParams = Field(default_factory=HierarchicalParams)


_FAMILY = {mode: "filter" for mode in FILTER_MODES} | {"retrieval": "retrieval",
                                                         "hierarchical": "hierarchical"}


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
