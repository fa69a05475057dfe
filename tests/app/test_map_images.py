"""Map image metadata at the edge (altitude, times, EXIF GPS) and deleting one image."""

from __future__ import annotations

import io
from datetime import UTC, datetime
from fractions import Fraction

import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational
from sqlalchemy import func, select, update

from tests.app.conftest import ADMIN, PROBLEM, jpeg_files, snapshot, wait_job
from tests.app.imagery import plain_jpeg
from tests.app.test_maps import new_map
from vloc.app.maps.models import ImageGlobalFeature, ImageSift, MapImage
from vloc.workers.core.exif import write_gps

BAD_FORMS = {
    "huge-alt": {"lat": "41", "lon": "-83", "alt": "1e308"},
    "alt-below-the-dead-sea": {"lat": "41", "lon": "-83", "alt": "-600"},
    "alt-above-10-km": {"lat": "41", "lon": "-83", "alt": "10000.5"},
    "nan-alt": {"lat": "41", "lon": "-83", "alt": "nan"},
    "far-future": {"lat": "41", "lon": "-83", "captured_at": "9999-12-31T23:59:59Z"},
    "before-1990": {"lat": "41", "lon": "-83", "captured_at": "1989-12-31T23:59:59Z"},
    "infinite-lon": {"lat": "41", "lon": "-inf"},
}


@pytest.mark.parametrize("case", sorted(BAD_FORMS))
def test_implausible_form_metadata_is_422_and_changes_nothing(module_client, case):
    c = module_client
    map_id = new_map(c)
    before = snapshot(c)
    r = c.post(f"/v1/maps/{map_id}/images", data=BAD_FORMS[case], headers=ADMIN,
               files=[("files", ("a.jpg", plain_jpeg(), "image/jpeg"))])
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM
    assert snapshot(c) == before


def test_the_altitude_bounds_are_inclusive(module_client):
    c = module_client
    map_id = new_map(c)
    for alt in ("-500", "10000"):
        r = c.post(f"/v1/maps/{map_id}/images", data={"lat": "41", "lon": "-83", "alt": alt},
                   files=[("files", (f"{alt}.jpg", plain_jpeg(level=100 + int(alt) // 500), "image/jpeg"))],
                   headers=ADMIN)
        assert r.status_code == 201, r.text


def _exif_jpeg(gps: dict) -> bytes:
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = gps
    out = io.BytesIO()
    Image.new("RGB", (64, 48), (120, 80, 40)).save(out, "JPEG", exif=exif)
    return out.getvalue()


def _r(x) -> IFDRational:
    f = Fraction(x).limit_denominator(10_000)
    return IFDRational(f.numerator, f.denominator)


@pytest.mark.parametrize(("data", "reason"), [
    (_exif_jpeg({1: "N", 2: (_r(41), _r(60), _r(0)), 3: "W", 4: (_r(83), _r(0), _r(0))}),
     "bad-gps"),
    (_exif_jpeg({1: "N", 2: (_r(41), _r(1), _r(61)), 3: "W", 4: (_r(83), _r(0), _r(0))}),
     "bad-gps"),
    (write_gps(plain_jpeg(), lat=41.0, lon=-83.0, alt=20_000.0), "bad-gps"),
])
def test_implausible_exif_gps_is_422(module_client, data, reason):
    c = module_client
    map_id = new_map(c)
    before = snapshot(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=[("files", ("a.jpg", data, "image/jpeg"))],
               headers=ADMIN)
    assert r.status_code == 422 and r.json()["rejected"][0]["reason"] == reason, r.text
    assert snapshot(c) == before


def test_an_exif_time_from_an_unset_clock_is_dropped(module_client):
    c = module_client
    map_id = new_map(c)
    data = write_gps(plain_jpeg(level=77), lat=41.0, lon=-83.0,
                     captured_at=datetime(1980, 1, 1, tzinfo=UTC))
    r = c.post(f"/v1/maps/{map_id}/images", files=[("files", ("a.jpg", data, "image/jpeg"))],
               headers=ADMIN)
    assert r.status_code == 201, r.text
    assert r.json()["accepted"][0]["captured_at"] is None


# -- DELETE /v1/maps/{id}/images/{image_id} -------------------------------------------------

def _build(c, map_id: str) -> dict:
    r = c.post(f"/v1/maps/{map_id}/build", headers=ADMIN)
    assert r.status_code == 202, r.text
    return wait_job(c, r.json()["job_id"])


def _features_of(c, image_id: int) -> int:
    with c.app.state.ctx.db_sessions() as db:
        return sum(db.scalar(select(func.count()).select_from(t).where(t.image_id == image_id))
                   for t in (ImageGlobalFeature, ImageSift))


def test_delete_one_image_and_build_again(module_client, shots):
    c = module_client
    map_id = new_map(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:4]), headers=ADMIN)
    images = r.json()["accepted"]
    assert _build(c, map_id)["status"] == "done"
    victim = images[1]
    files_dir = c.app.state.ctx.settings.images_dir(map_id)
    assert _features_of(c, victim["id"]) > 1  # global features and SIFT
    assert any(p.name.startswith(victim["file_hash"]) for p in files_dir.iterdir())

    r = c.delete(f"/v1/maps/{map_id}/images/{victim['id']}", headers=ADMIN)
    assert r.status_code == 204
    left = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    assert [i["id"] for i in left] == [i["id"] for i in images if i["id"] != victim["id"]]
    assert _features_of(c, victim["id"]) == 0
    assert not any(p.name.startswith(victim["file_hash"]) for p in files_dir.iterdir())
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["image_count"], m["revision"]) == ("unbuilt", 3, 1)

    job = _build(c, map_id)
    assert job["status"] == "done" and job["revision"] == 2
    assert c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["status"] == "ready"


def test_deleting_an_unknown_image_is_404_and_changes_nothing(module_client, shots):
    c = module_client
    map_id = new_map(c)
    other = new_map(c)
    r = c.post(f"/v1/maps/{other}/images", files=jpeg_files(shots[0][:1]), headers=ADMIN)
    foreign = r.json()["accepted"][0]["id"]
    before = snapshot(c)
    for url, status in ((f"/v1/maps/{map_id}/images/{foreign}", 404),
                        (f"/v1/maps/{map_id}/images/999999999", 404),
                        ("/v1/maps/00000000-0000-0000-0000-000000000000/images/1", 404),
                        (f"/v1/maps/{map_id}/images/{2**63}", 422),
                        (f"/v1/maps/{map_id}/images/abc", 422)):
        r = c.delete(url, headers=ADMIN)
        assert r.status_code == status and r.headers["content-type"] == PROBLEM, url
    assert c.delete(f"/v1/maps/{other}/images/{foreign}").status_code == 401
    assert snapshot(c) == before


def test_deleting_the_image_that_breaks_builds_lets_the_map_build(module_client, shots):
    """A row stored before the edge checked altitudes (alt 1e308) fails every build; once
    it is deleted the map builds."""
    c = module_client
    map_id = new_map(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:3]), headers=ADMIN)
    bad = r.json()["accepted"][2]["id"]
    with c.app.state.ctx.db_sessions() as db:
        db.execute(update(MapImage).where(MapImage.id == bad).values(alt=1e308))
        db.commit()
    assert _build(c, map_id)["status"] == "failed"
    assert c.delete(f"/v1/maps/{map_id}/images/{bad}", headers=ADMIN).status_code == 204
    job = _build(c, map_id)
    assert job["status"] == "done", job
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["image_count"]) == ("ready", 2)


def test_the_last_image_deleted_leaves_an_empty_map(module_client, shots):
    c = module_client
    map_id = new_map(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:1]), headers=ADMIN)
    image_id = r.json()["accepted"][0]["id"]
    assert c.delete(f"/v1/maps/{map_id}/images/{image_id}", headers=ADMIN).status_code == 204
    assert c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["status"] == "empty"
    assert c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).status_code == 409
