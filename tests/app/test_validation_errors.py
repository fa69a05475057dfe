"""Validation errors name what the client sent: no wrapper it never wrote (a union's tag),
a suggestion for a misspelt name, and the documented kind of an upload without files."""

from __future__ import annotations

import pytest

from tests.app.conftest import ADMIN, PROBLEM


@pytest.fixture
def map_id(client) -> str:
    return client.post("/v1/maps", json={"name": "validation"}, headers=ADMIN).json()["id"]


def test_a_misspelt_parameter_is_located_as_sent_with_a_suggestion(client, map_id):
    r = client.post("/v1/sessions", headers=ADMIN,
                    json={"map_id": map_id, "params": {"n_particle": 5}})
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    body = r.json()
    assert body["detail"].startswith("body.params.n_particle: ")
    assert body["detail"].endswith("did you mean n_particles?")
    assert body["errors"][0]["loc"] == ["body", "params", "n_particle"]
    assert body["errors"][0]["suggestion"] == "n_particles"


def test_another_modes_parameter_gets_no_suggestion_of_itself(client, map_id):
    r = client.post("/v1/sessions", headers=ADMIN,
                    json={"map_id": map_id, "mode": "retrieval", "params": {"n_particles": 5}})
    assert r.status_code == 422
    assert r.json()["errors"][0]["loc"] == ["body", "params", "n_particles"]
    assert "did you mean" not in r.json()["detail"]


def test_a_wrong_type_deep_in_the_body_is_located_as_sent(client, map_id):
    r = client.post("/v1/sessions", headers=ADMIN,
                    json={"map_id": map_id, "mode": "sift", "params": {"n_particles": "9"}})
    assert r.status_code == 422
    assert r.json()["detail"].startswith("body.params.n_particles: ")


@pytest.mark.parametrize("form", [None, {"lat": "41.0", "lon": "-83.0"}])
def test_an_upload_without_files_is_no_files(client, map_id, form):
    r = client.post(f"/v1/maps/{map_id}/images", data=form, headers=ADMIN)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == "urn:vloc:problem:no-files"
