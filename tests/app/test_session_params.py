"""Session parameters at the edge: strict types and bounds, 422 naming the field, nothing
stored; and the edge's models agree with the core's lists and fields."""

from __future__ import annotations

import typing

import pytest

from tests.app.conftest import ADMIN, FAST, PROBLEM, snapshot
from vloc.app.sessions import params as edge

BAD_PARAMS = {
    "bool-for-int": ({"n_particles": True}, "params.n_particles"),
    "string-for-float": ({"pull": "a"}, "params.pull"),
    "string-for-level": ({"global_trust_level": "x"}, "params.global_trust_level"),
    "null-fraction": ({"replace_fraction": None}, "params.replace_fraction"),
    "list-for-config": ({"config": []}, "params.config"),
    "number-for-features": ({"global_features": 5}, "params.global_features"),
    "seed-past-int64": ({"seed": 2**63}, "params.seed"),
    "string-for-int": ({"n_particles": "60"}, "params.n_particles"),
    "unknown-feature": ({"global_features": ["wgoh", "sift"]}, "params.global_features"),
    "pull-of-one": ({"pull": 1.0}, "params.pull"),
    "unknown-key": ({"bogus": 1}, "params.bogus"),
    "zero-particles": ({"n_particles": 0}, "params.n_particles"),
    "int-for-refine": ({"refine": 1}, "params.refine"),
    "string-for-refine": ({"refine": "true"}, "params.refine"),
    "refine-outlier-of-one": ({"refine_outlier": 1.0}, "params.refine_outlier"),
    "zero-refine-outlier": ({"refine_outlier": 0.0}, "params.refine_outlier"),
    "string-for-refine-outlier": ({"refine_outlier": "0.1"}, "params.refine_outlier"),
}


@pytest.mark.parametrize("case", sorted(BAD_PARAMS))
def test_wrongly_typed_params_are_422_and_change_nothing(service, case):
    change, where = BAD_PARAMS[case]
    c = service.client
    before = snapshot(c)
    r = c.post("/v1/sessions", headers=ADMIN,
               json={"map_id": service.map_id, "params": {**FAST, **change}})
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM
    problem = r.json()
    assert problem["type"] == "urn:vloc:problem:validation"
    assert where in problem["detail"], problem["detail"]
    assert snapshot(c) == before


@pytest.mark.parametrize("body", [
    {"seed": 2**63}, {"seed": True}, {"seed": "5"}, {"mode": 5}, {"mode": "retrieval",
                                                                   "params": {"k": 3}},
    {"mode": "hierarchical", "params": {"k": 1.5}}, {"params": []}])
def test_bad_bodies_are_422(service, body):
    c = service.client
    before = snapshot(c)
    r = c.post("/v1/sessions", headers=ADMIN, json={"map_id": service.map_id} | body)
    assert r.status_code == 422 and r.json()["type"] == "urn:vloc:problem:validation", r.text
    assert snapshot(c) == before


def test_given_params_are_kept_and_the_rest_filled_in(service):
    c = service.client
    r = c.post("/v1/sessions", headers=ADMIN, json={
        "map_id": service.map_id, "mode": "sift",
        "params": {**FAST, "speed": None, "global_features": "wgoh", "motion_sigma": 3,
                   "seed": 2**63 - 1, "refine": True, "refine_outlier": 0.2}})
    assert r.status_code == 201, r.text
    got = r.json()
    assert got["seed"] == 2**63 - 1
    assert got["params"]["speed"] is None and got["params"]["global_features"] == ["wgoh"]
    assert got["params"]["motion_sigma"] == 3.0 and got["params"]["n_particles"] == 60
    assert got["params"]["config"] == "default"
    assert got["params"]["refine"] is True and got["params"]["refine_outlier"] == 0.2


@pytest.mark.parametrize("backend", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_the_session_cap_is_429(tmp_path_factory, shots, backend):
    from tests.app.conftest import backend_client, build_map

    for c in backend_client(backend, tmp_path_factory, max_sessions=2):
        map_id = build_map(c, shots[0][:4])
        body = {"map_id": map_id, "params": FAST}
        assert [c.post("/v1/sessions", json=body, headers=ADMIN).status_code
                for _ in range(2)] == [201, 201]
        before = snapshot(c)
        r = c.post("/v1/sessions", json=body, headers=ADMIN)
        assert r.status_code == 429 and r.headers["content-type"] == PROBLEM
        assert r.json()["type"] == "urn:vloc:problem:too-many-sessions"
        assert r.json()["max_sessions"] == 2 and "retry-after" in r.headers
        assert snapshot(c) == before
        sid = c.get("/v1/sessions", headers=ADMIN).json()[0]["id"]
        assert c.delete(f"/v1/sessions/{sid}", headers=ADMIN).status_code == 204
        assert c.post("/v1/sessions", json=body, headers=ADMIN).status_code == 201


@pytest.mark.parametrize("backend", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_the_session_cap_holds_under_concurrent_creates(tmp_path_factory, shots, backend):
    from concurrent.futures import ThreadPoolExecutor

    from tests.app.conftest import backend_client, build_map

    for c in backend_client(backend, tmp_path_factory, max_sessions=5):
        map_id = build_map(c, shots[0][:4])
        body = {"map_id": map_id, "params": FAST}
        with ThreadPoolExecutor(20) as pool:
            replies = [pool.submit(c.post, "/v1/sessions", json=body, headers=ADMIN)
                       for _ in range(20)]
            codes = [r.result().status_code for r in replies]
        assert sorted(codes) == [201] * 5 + [429] * 15
        listed = c.get("/v1/sessions", headers=ADMIN).json()
        assert len(listed) == 5 and len(c.app.state.ctx.sessions) == 5


def _literal_values(annotation) -> set:
    return set(typing.get_args(annotation))


def test_the_edge_models_follow_the_core():
    from vloc.workers.core.features import ALL_FEATURE_NAMES
    from vloc.workers.core.localisers import MODES
    from vloc.workers.core.measures import MEASURES
    from vloc.workers.core.pf.config import (
        CONFIGS,
        PARAMS,
        REDUCTIONS,
        REPLACEMENTS,
        RESAMPLERS,
        VERIFICATIONS,
    )

    assert set(edge.FilterParams.model_fields) == \
        set(PARAMS) | {"config", "seed"}
    assert _literal_values(edge.FilterConfigName) == set(CONFIGS)
    assert _literal_values(edge.FeatureName) == set(ALL_FEATURE_NAMES)
    assert _literal_values(edge.MeasureName) == set(MEASURES)
    assert _literal_values(edge.Verification) == set(VERIFICATIONS)
    fields = edge.FilterParams.model_fields
    for name, allowed in (("replacement", REPLACEMENTS), ("sift_reduce", REDUCTIONS),
                          ("resampler", RESAMPLERS)):
        assert _literal_values(fields[name].annotation) == set(allowed), name
    assert set(edge.MODES) == set(MODES)


def _probes(param) -> list:
    """Values at and beside each of a parameter's bounds, and of the wrong type."""
    from vloc.workers.core.pf.params import MAX_GLOBAL_FEATURES

    if param.type is bool:
        return [True, False, 1, "true", None]
    if param.type is str:
        return [*param.names(), "nope", 1, None]
    if param.type is tuple:
        names = list(param.names())
        return [names[0], names[:2], [], ["nope"], names[:1] * (MAX_GLOBAL_FEATURES + 1), None]
    out: list = [True, "1", None, "auto", 1]
    for bound in param.bounds.values():
        if param.type is int:
            out += [int(bound) - 1, int(bound), int(bound) + 1]
        else:
            out += [bound * (1 - 1e-9) - 1e-12, float(bound), bound * (1 + 1e-9) + 1e-12]
    return out


@pytest.mark.parametrize("name", sorted(edge.PARAMS))
def test_the_api_and_the_core_take_the_same_values_of_each_filter_parameter(name):
    """The API's model is generated from the core's declaration: at every bound, and for
    every wrong type, the two agree on what a parameter takes."""
    import json

    import pydantic

    param = edge.PARAMS[name]
    for value in _probes(param):
        try:
            edge.FilterParams.model_validate_json(json.dumps({name: value}))
            api = True
        except pydantic.ValidationError:
            api = False
        try:
            param.check(name, value)
            core = True
        except ValueError:
            core = False
        assert api == core, (name, value, api)
