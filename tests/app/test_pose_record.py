"""The pose record: one mapping from the core's estimate to the schema, the table, the
stream and the client; the fields a positioning client expects, against the real app."""

from __future__ import annotations

import math
import uuid
import warnings
from datetime import UTC, datetime

import pytest

from tests.app.conftest import ADMIN
from tests.app.test_frames import settled
from tests.app.test_sessions import open_stream, post_frame
from vloc.app.sessions import pose
from vloc.app.sessions.models import Pose
from vloc.app.sessions.schemas import PoseEstimate
from vloc.clients.sdk import Pose as ClientPose
from vloc.workers.core.accuracy import horizontal_accuracy
from vloc.workers.core.estimate import Estimate, Status
from vloc.workers.core.metadata import FrameMetadata


def test_every_stored_field_has_its_column_and_every_estimate_field_reaches_the_pose():
    columns = set(Pose.__table__.columns.keys())
    for name in pose.stored_fields():
        wanted = set(pose.COV_COLUMNS) if name == "cov" else {name}
        assert wanted <= columns, name
    estimate_fields = set(Estimate.__dataclass_fields__) - {"best_image"}
    assert estimate_fields <= set(PoseEstimate.model_fields)
    # the client reads every field the server sends
    assert set(PoseEstimate.model_fields) | {"geopose"} == set(ClientPose.model_fields)


def _context(**change) -> pose.FrameContext:
    values = dict(session_id=str(uuid.uuid4()), seq=3, map_id=str(uuid.uuid4()),
                  map_revision=2, map_folder="", captured_at=None,
                  received_at=datetime(2026, 1, 2, tzinfo=UTC), metadata=None, decode_ms=1.5,
                  latency_ms=20.0)
    return pose.FrameContext(**values | change)


def _estimate(**change) -> Estimate:
    values = dict(x=3.0, y=-4.0, lat=41.0, lon=-83.0, sigma_x=2.0, sigma_y=2.0,
                  cov=(4.0, 0.0, 0.0, 4.0), feature="sift", next_feature="global",
                  n_particles=60, status=Status.TRACKING, processing_ms=30.0, best_image=1,
                  measurement="sift+registered", heading_deg=None, heading_sigma_deg=None,
                  metadata_used="", gps_gate="")
    return Estimate(**values | change)


def _pose(estimate: Estimate, ctx: pose.FrameContext | None = None) -> PoseEstimate:
    return pose.from_estimate(estimate, ctx or _context(), bound_m=25.0,
                              converged_before=False)[0]


NAVIGATION = {"state": {"x": 1.0, "y": 2.0, "theta": 0.5, "v": 1.0, "omega": 0.0},
              "command": {"v": 1.0, "omega": 0.1}, "reference": {"x": 1.0, "y": 2.1, "theta": 0.4},
              "cross_track": -0.1, "heading_error": 0.1, "curvature": 0.0, "node": 4,
              "progress": 12.5, "length": 40.0, "arrived": False, "fused": True, "views": 2}


@pytest.mark.parametrize("change", [
    {},
    {"heading_deg": 30.0, "heading_sigma_deg": 2.0, "gps_gate": "used"},
    {"status": Status.LOST, "cloud": ((1.0, 2.0), (3.5, -4.25)), "best_image": -1},
    {"navigation": NAVIGATION, "measurement": "", "metadata_used": "heading+altitude"},
])
def test_the_assembled_pose_is_what_validation_makes(change):
    """A pose is assembled from typed values, not validated (:func:`pose.from_estimate`):
    its JSON is the JSON of the same fields validated by the schema, and reads back as
    the same pose."""
    ctx = _context(captured_at=datetime(2026, 1, 2, 3, 4, 5, 678000, tzinfo=UTC),
                   metadata=FrameMetadata(heading_deg=80.0, altitude_m=120.0))
    made, row = pose.from_estimate(_estimate(**change), ctx, bound_m=25.0,
                                   converged_before=False)
    fields = {name: getattr(made, name) for name in PoseEstimate.model_fields}
    fields["navigation"] = change.get("navigation")
    validated = PoseEstimate.model_validate(fields)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a value not of its field's type warns when dumped
        text = made.model_dump_json()
    assert text == validated.model_dump_json()
    assert PoseEstimate.model_validate_json(text) == validated
    assert row == pose.to_row(validated)


def test_row_round_trip_keeps_every_field():
    msg, row = pose.from_estimate(_estimate(heading_deg=30.0, heading_sigma_deg=2.0,
                                            gps_gate="used"), _context(),
                                  bound_m=25.0, converged_before=False)
    stored = Pose(session_id=msg.session_id, seq=msg.seq, **row)
    back = pose.from_row(stored, map_id=msg.map_id, map_revision=msg.map_revision)
    assert back.model_dump(mode="json") == msg.model_dump(mode="json")


def test_heading_altitude_and_geopose_are_never_invented():
    msg = _pose(_estimate())
    assert (msg.heading_deg, msg.heading_sigma_deg, msg.heading_source, msg.altitude_m) == \
        (None, None, None, None)
    assert msg.geopose is None  # GeoPose Basic needs a height: none without an altitude
    assert msg.horizontal_accuracy_m == pytest.approx(2.0 * math.sqrt(-2 * math.log(0.32)))
    # the frame's own heading and altitude are reported back, marked as the device's
    device = _pose(_estimate(), _context(metadata=FrameMetadata(heading_deg=90.0,
                                                               altitude_m=212.5)))
    assert (device.heading_deg, device.heading_source, device.altitude_m) == \
        (90.0, "device", 212.5)
    q = device.geopose.quaternion
    # heading east (90 deg) is yaw 0 in East-North-Up: the identity rotation
    assert (q.x, q.y, q.z, q.w) == pytest.approx((0.0, 0.0, 0.0, 1.0))
    geometry = _pose(_estimate(heading_deg=0.0, heading_sigma_deg=3.0),
                     _context(metadata=FrameMetadata(heading_deg=90.0, altitude_m=10.0)))
    q = geometry.geopose.quaternion
    assert geometry.heading_source == "geometry" and geometry.heading_deg == 0.0
    # north is yaw +90 deg about Up
    assert (q.z, q.w) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))


def test_poses_name_the_map_and_its_matched_image(service, shots):
    c = service.client
    sid, auth = service.new_session()
    images = {i["id"]: i["filename"] for i in
              c.get(f"/v1/maps/{service.map_id}/images", headers=ADMIN).json()}
    revision = c.get(f"/v1/maps/{service.map_id}", headers=ADMIN).json()["revision"]
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        for q in shots[1][:4]:
            assert post_frame(c, sid, q.jpeg, auth).status_code == 202
        streamed = [ws.receive_json() for _ in range(4)]
    settled(c, sid, auth)  # the stream runs ahead of the database
    stored = c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    # the particle sample and the order of answers go out on the stream only
    assert all(p["cloud"] for p in streamed)
    assert [p.get("prev_seq") for p in streamed] == [None, 0, 1, 2]
    assert stored == [{k: v for k, v in p.items() if k != "prev_seq"} | {"cloud": []}
                      for p in streamed]
    for p in streamed:
        assert p["map_id"] == service.map_id and p["map_revision"] == revision
        assert p["image_id"] in images and images[p["image_id"]] == p["image_filename"]
        assert p["horizontal_accuracy_m"] == pytest.approx(horizontal_accuracy(p["cov"]))
        assert p["geopose"] is None  # no altitude sent
        assert p["converged"] == (p["status"] == "tracking"
                                  and p["horizontal_accuracy_m"] <= 25.0)
        assert "best_image" not in p
        ClientPose.model_validate(p)


def test_initialising_until_converged_and_again_after_a_reset(service, shots):
    c = service.client
    settings = c.app.state.ctx.settings
    sid, auth = service.new_session()
    jpeg = shots[1][0].jpeg
    saved = settings.converged_accuracy_m
    try:
        settings.converged_accuracy_m = 1e-9  # nothing converges
        first = post_frame(c, sid, jpeg, auth, wait="true").json()
        assert (first["status"], first["converged"]) == ("initialising", False)
        settings.converged_accuracy_m = 1e9   # every tracking estimate converges
        second = post_frame(c, sid, jpeg, auth, wait="true").json()
        assert second["converged"] == (second["status"] == "tracking")
        if second["converged"]:
            settings.converged_accuracy_m = 1e-9
            third = post_frame(c, sid, jpeg, auth, wait="true").json()
            assert third["status"] in ("tracking", "lost") and not third["converged"]
            assert c.post(f"/v1/sessions/{sid}/reset", headers=auth).status_code == 200
            fourth = post_frame(c, sid, jpeg, auth, wait="true").json()
            assert fourth["status"] == "initialising"
    finally:
        settings.converged_accuracy_m = saved


def test_an_object_field_is_streamed_not_stored(monkeypatch):
    """A field such as a particle-cloud sample goes out on the stream without a column."""
    from pydantic import create_model

    extended = create_model("Extended", __base__=PoseEstimate,
                            particles=(list[list[float]] | None, None))
    monkeypatch.setattr(pose, "PoseEstimate", extended)
    assert "particles" not in pose.stored_fields()
    assert {c.name for c in pose.pose_columns()} == set(Pose.__table__.columns.keys()) - {
        "id", "session_id", "seq", "map_revision"}
