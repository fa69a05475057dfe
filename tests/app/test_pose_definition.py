"""One definition of the fields that say how a pose was found: the schema's descriptions
(also the OpenAPI description's) and docs/api.md's table say the same words, and poses keep
to them: a GeoPose only with a height, and feature and measurement never at odds."""

from __future__ import annotations

import re

import pytest

from tests.app.test_sessions import post_frame
from tests.conftest import REPO_ROOT
from vloc.app.sessions.schemas import PoseEstimate

API_MD = (REPO_ROOT / "docs" / "api.md").read_text()
DEFINED = ("feature", "next_feature", "measurement", "geopose")


def _plain(text: str) -> str:
    text = re.sub(r"\s+", " ", text.replace("`", "")).strip().rstrip(".")
    return text[:1].lower() + text[1:]


def _api_md_row(name: str) -> str:
    (row,) = [line for line in API_MD.splitlines() if line.startswith(f"| `{name}` |")]
    return row.split("|")[2]


@pytest.mark.parametrize("name", DEFINED)
def test_api_md_and_the_schema_define_the_field_alike(name):
    fields = PoseEstimate.model_fields | PoseEstimate.model_computed_fields
    assert _plain(_api_md_row(name)) == _plain(fields[name].description)


def test_the_openapi_description_carries_the_same_definitions(client):
    schema = client.get("/openapi.json").json()["components"]["schemas"]["PoseEstimate"]
    for name in DEFINED:
        assert _plain(schema["properties"][name]["description"]) == \
            _plain(_api_md_row(name)), name


def test_poses_keep_to_the_definitions(service, shots):
    c = service.client
    sid, auth = service.new_session(mode="hybrid")
    poses = [post_frame(c, sid, q.jpeg, auth, wait="true").json() for q in shots[1][:6]]
    with_height = post_frame(c, sid, shots[1][6].jpeg, auth, wait="true",
                             altitude_m="212.5").json()
    for p in poses:
        kinds = set(p["measurement"].split("+")) - {""}
        assert kinds <= {"sift", "global", "registered", "interpolated"}, p["measurement"]
        assert len(kinds & {"sift", "global"}) <= 1
        assert p["feature"] in ("sift", "global") and p["next_feature"] in ("sift", "global")
        if p["feature"] == "global":  # global features only: no SIFT weighed it
            assert "sift" not in kinds
        assert p["geopose"] is None  # no altitude: no GeoPose, rather than a made-up height
    assert with_height["geopose"]["position"] == {"lat": with_height["lat"],
                                                  "lon": with_height["lon"], "h": 212.5}
