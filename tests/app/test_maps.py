"""Map routes against the real app: CRUD, upload validation, build and rebuild."""

from __future__ import annotations

import math
import struct
import uuid
import zlib
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import delete, select

from tests.app.conftest import (
    ADMIN,
    ADMIN_KEY,
    PROBLEM,
    UNKNOWN_ID,
    jpeg_files,
    snapshot,
    wait_job,
)
from tests.app.imagery import plain_jpeg, png, png_bomb
from tests.core.geometry.scene import similarity_residual
from tests.core.packing import assert_same_places
from vloc.app.engine import run_task
from vloc.app.jobs import service as job_service
from vloc.app.jobs.service import forget_reconstruction
from vloc.app.maps.codecs import decode_vocabulary
from vloc.app.maps.models import ImageGlobalFeature, ImageOrb, ImageSift, MapVocabulary
from vloc.app.tasks import build as build_tasks
from vloc.workers.core import geometry, tiepairs, tiles
from vloc.workers.core.carryover import MAX_DISTORTION_RISE
from vloc.workers.core.features import DESCRIPTOR_NAMES
from vloc.workers.core.features.descriptors import get_descriptor, local_vectors
from vloc.workers.core.features.distortion import image_distortion
from vloc.workers.core.features.orb import extract_orb
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.geometry import KeptModels, tie_reach, tiling
from vloc.workers.core.geometry.kept import read_order
from vloc.workers.core.image import load_frame
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import extract_sift


def new_map(client, name: str = "a map") -> str:
    r = client.post("/v1/maps", json={"name": name}, headers=ADMIN)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def corrupt_png() -> bytes:
    """A PNG whose header and chunk CRCs are valid but whose pixel stream is not zlib."""
    data = bytearray(png(size=(64, 48)))
    at = data.index(b"IDAT")
    length = struct.unpack(">I", data[at - 4:at])[0]
    body = bytes(range(7, 7 + length))
    data[at + 4:at + 4 + length] = body
    data[at + 4 + length:at + 8 + length] = struct.pack(">I", zlib.crc32(b"IDAT" + body))
    return bytes(data)


def test_create_read_list_delete(module_client):
    c = module_client
    r = c.post("/v1/maps", json={"name": "fields"}, headers=ADMIN)
    assert r.status_code == 201
    body = r.json()
    assert r.headers["location"] == f"/v1/maps/{body['id']}"
    assert (body["name"], body["status"], body["revision"], body["image_count"]) == \
        ("fields", "empty", 0, 0)
    assert body["extent"] is None and body["origin"] is None
    assert c.get(f"/v1/maps/{body['id']}", headers=ADMIN).json() == body
    assert body["id"] in {m["id"] for m in c.get("/v1/maps", headers=ADMIN).json()}
    assert c.delete(f"/v1/maps/{body['id']}", headers=ADMIN).status_code == 204
    r = c.get(f"/v1/maps/{body['id']}", headers=ADMIN)
    assert r.status_code == 404 and r.headers["content-type"] == PROBLEM


@pytest.mark.parametrize("name", ["", "x" * 201])
def test_bad_map_name_is_422(module_client, name):
    before = snapshot(module_client)
    r = module_client.post("/v1/maps", json={"name": name}, headers=ADMIN)
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "name"]
    assert snapshot(module_client) == before


ROUTES = [("post", "/v1/maps"), ("get", "/v1/maps"), ("get", "/v1/maps/{id}"),
          ("delete", "/v1/maps/{id}"), ("post", "/v1/maps/{id}/images"),
          ("get", "/v1/maps/{id}/images"), ("post", "/v1/maps/{id}/build"),
          ("get", "/v1/jobs/{id}")]


@pytest.mark.parametrize(("method", "path"), ROUTES)
def test_admin_routes_need_the_admin_key(module_client, method, path):
    c = module_client
    map_id = new_map(c)
    before = snapshot(c)
    url = path.format(id=map_id)
    r = getattr(c, method)(url)
    assert r.status_code == 401 and r.headers["content-type"] == PROBLEM
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert r.json()["type"] == "urn:vloc:problem:unauthenticated"
    for headers in ({"Authorization": "Bearer not-the-key"}, {"X-API-Key": "wrong"},
                    {"Authorization": f"Basic {ADMIN_KEY}"}):
        r = getattr(c, method)(url, headers=headers)
        assert r.status_code in (401, 403), (headers, r.status_code)
    assert snapshot(c) == before
    # The key also works as X-API-Key.
    assert c.get(f"/v1/maps/{map_id}", headers={"X-API-Key": ADMIN_KEY}).status_code == 200


@pytest.mark.parametrize(("method", "path"), [
    ("get", "/v1/maps/{id}"), ("delete", "/v1/maps/{id}"), ("get", "/v1/maps/{id}/images"),
    ("post", "/v1/maps/{id}/build"), ("get", "/v1/jobs/{id}")])
@pytest.mark.parametrize("ident", [UNKNOWN_ID, "not-a-uuid", "1"])
def test_unknown_ids_are_404(module_client, method, path, ident):
    before = snapshot(module_client)
    r = getattr(module_client, method)(path.format(id=ident), headers=ADMIN)
    assert r.status_code == 404 and r.json()["type"] == "urn:vloc:problem:not-found"
    assert ident in r.json()["detail"]
    assert snapshot(module_client) == before


def test_upload_reads_gps_from_exif(module_client, shots):
    c = module_client
    map_id = new_map(c)
    maps = shots[0][:3]
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(maps), headers=ADMIN)
    assert r.status_code == 201, r.text
    accepted = r.json()["accepted"]
    assert r.json()["rejected"] == []
    assert [a["filename"] for a in accepted] == [s.name for s in maps]
    for a, s in zip(accepted, maps, strict=True):
        assert a["lat"] == pytest.approx(s.lat, abs=1e-9)
        assert a["lon"] == pytest.approx(s.lon, abs=1e-9)
        assert a["alt"] == pytest.approx(280.0)
        assert a["captured_at"].startswith(s.captured_at.strftime("%Y-%m-%dT%H:%M:%S"))
        assert (a["width"], a["height"], a["position_source"]) == (320, 240, "exif")
        assert a["byte_size"] == len(s.jpeg) and a["built_revision"] is None
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["image_count"], m["pending_images"], m["revision"]) == \
        ("unbuilt", 3, 3, 0)
    assert m["extent"]["min_lat"] == pytest.approx(min(s.lat for s in maps))
    assert m["extent"]["max_lon"] == pytest.approx(max(s.lon for s in maps))
    listed = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    assert listed == accepted


def test_single_file_with_form_position(module_client):
    c = module_client
    map_id = new_map(c)
    r = c.post(f"/v1/maps/{map_id}/images", headers=ADMIN,
               files=[("files", ("plain.jpg", plain_jpeg(), "image/jpeg"))],
               data={"lat": "41.5", "lon": "-83.25", "alt": "12",
                     "captured_at": "2024-01-02T03:04:05Z"})
    assert r.status_code == 201, r.text
    (a,) = r.json()["accepted"]
    assert (a["lat"], a["lon"], a["alt"], a["position_source"]) == (41.5, -83.25, 12.0, "form")
    assert a["captured_at"] == "2024-01-02T03:04:05Z"


def _truncated(shots):
    return shots[0][0].jpeg[: len(shots[0][0].jpeg) // 2]


BAD_UPLOADS = {
    # name: (files builder, form fields, status, reason of the (first) rejection)
    "no-gps": (lambda s: [("a.jpg", plain_jpeg())], {}, 422, "no-gps"),
    "nan-lat": (lambda s: [("a.jpg", plain_jpeg())], {"lat": "nan", "lon": "1"}, 422, None),
    "lat-out-of-range": (lambda s: [("a.jpg", plain_jpeg())], {"lat": "95", "lon": "1"},
                         422, None),
    "lon-out-of-range": (lambda s: [("a.jpg", plain_jpeg())], {"lat": "1", "lon": "-200"},
                         422, None),
    "infinite-alt": (lambda s: [("a.jpg", plain_jpeg())],
                     {"lat": "1", "lon": "1", "alt": "inf"}, 422, None),
    "lat-without-lon": (lambda s: [("a.jpg", plain_jpeg())], {"lat": "1"}, 422, None),
    "position-for-two-files": (lambda s: [("a.jpg", plain_jpeg()), ("b.jpg", png())],
                               {"lat": "1", "lon": "1"}, 422, None),
    "empty": (lambda s: [("a.jpg", b"")], {}, 422, "empty-image"),
    "not-an-image": (lambda s: [("a.txt", b"hello, world")], {}, 422, "bad-image"),
    "truncated": (lambda s: [("a.jpg", _truncated(s))], {}, 422, "truncated-image"),
    "corrupt-pixels": (lambda s: [("a.png", corrupt_png())], {"lat": "1", "lon": "1"},
                       422, "bad-image"),
    "decompression-bomb": (lambda s: [("a.png", png_bomb())], {"lat": "1", "lon": "1"},
                           413, "too-many-pixels"),
    "too-large": (lambda s: [("a.jpg", s[0][0].jpeg + b"\x00" * 1_000_000)], {}, 413,
                  "too-large"),
    "all-bad": (lambda s: [("a.jpg", b""), ("b.jpg", plain_jpeg())], {}, 422, "empty-image"),
}


@pytest.mark.parametrize("case", sorted(BAD_UPLOADS))
def test_rejected_upload_changes_nothing(module_client, shots, case):
    build, form, status, reason = BAD_UPLOADS[case]
    c = module_client
    map_id = new_map(c)
    before = snapshot(c)
    files = [("files", (name, data, "application/octet-stream")) for name, data in build(shots)]
    r = c.post(f"/v1/maps/{map_id}/images", files=files, data=form, headers=ADMIN)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    problem = r.json()
    assert problem["status"] == status and problem["detail"]
    if reason is not None:
        assert problem["rejected"][0]["reason"] == reason
    assert snapshot(c) == before


def test_missing_files_field_is_422(module_client):
    map_id = new_map(module_client)
    before = snapshot(module_client)
    r = module_client.post(f"/v1/maps/{map_id}/images", data={"lat": "1"}, headers=ADMIN)
    assert r.status_code == 422 and r.json()["type"] == "urn:vloc:problem:no-files"
    assert snapshot(module_client) == before


def test_partial_upload_keeps_the_good_files_and_reports_the_rest(module_client, shots):
    c = module_client
    map_id = new_map(c)
    good = shots[0][:2]
    files = [*jpeg_files(good), ("files", ("bare.jpg", plain_jpeg(), "image/jpeg")),
             ("files", ("again.jpg", good[0].jpeg, "image/jpeg"))]
    r = c.post(f"/v1/maps/{map_id}/images", files=files, headers=ADMIN)
    assert r.status_code == 201
    assert [a["filename"] for a in r.json()["accepted"]] == [s.name for s in good]
    assert {(x["filename"], x["reason"], x["status"]) for x in r.json()["rejected"]} == {
        ("bare.jpg", "no-gps", 422), ("again.jpg", "duplicate", 409)}
    # The same file again later is a duplicate of the stored one: 409, nothing stored.
    before = snapshot(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(good[:1]), headers=ADMIN)
    assert r.status_code == 409 and r.json()["rejected"][0]["reason"] == "duplicate"
    assert snapshot(c) == before


def test_build_then_add_images_and_rebuild(module_client, shots, monkeypatch):
    c = module_client
    ctx = c.app.state.ctx
    maps = shots[0]
    map_id = new_map(c)
    assert c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(maps[:6]),
                  headers=ADMIN).status_code == 201
    r = c.post(f"/v1/maps/{map_id}/build", headers=ADMIN)
    assert r.status_code == 202 and r.headers["location"] == f"/v1/jobs/{r.json()['job_id']}"
    job = wait_job(c, r.json()["job_id"])
    assert (job["status"], job["progress"], job["n_images"], job["n_extracted"],
            job["revision"], job["error"], job["stage"]) == ("done", 1.0, 6, 6, 1, None, "done")
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["revision"], m["pending_images"]) == ("ready", 1, 0)
    assert m["last_job_id"] == job["id"]
    # the revision says what its camera geometry gives, whatever became of it
    geometry = m["geometry"]
    assert geometry["images"] == 6 and geometry["status"] in ("accepted", "refused", "none")
    if geometry["status"] != "none":
        assert 0 < geometry["placed"] <= 6 and geometry["self_check"]["images"] > 0
        check = geometry["self_check"]
        # the whole map's figure counts the images no pose reaches at their nearest image:
        # never better than the registered images' own
        assert check["every_image_mean_m"] >= (check["mean_m"] or 0.0)
        assert 0.0 <= check["every_image_within_5m"] <= 1.0

    # The packed revision is the images' positions in a frame at their centroid.
    first = MapData.load(ctx.settings.packed_map_dir(map_id, 1))
    assert len(first) == 6 and first.revision == 1
    # the map keeps its tie points and matched pairs for the next build
    store = ctx.settings.tie_store_dir(map_id)
    tie_files = sorted(store.glob("*.kp.npy"))
    assert len(tie_files) == 6 and list(store.glob(tiepairs.RESULTS_GLOB))
    stamps = {p: p.stat().st_mtime_ns for p in tie_files}
    first_origin = m["origin"]
    # and the reach of its tie pairs, decided from the six images' spacing
    first_reach = KeptModels(store / tiles.MODELS, ()).reach()
    assert first_reach == tie_reach(first.positions, first.captured_at)
    origin = GeoOrigin(m["origin"]["lat"], m["origin"]["lon"], m["origin"]["alt"])
    images = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    assert origin.lat == pytest.approx(np.mean([i["lat"] for i in images]), abs=1e-12)
    for img in images:
        east, north = origin.to_local(img["lat"], img["lon"])
        assert (img["east"], img["north"]) == pytest.approx((float(east), float(north)),
                                                            abs=1e-6)
        assert img["built_revision"] == 1
    assert m["local_extent"]["min_east"] == pytest.approx(min(i["east"] for i in images))

    # The stored SIFT is the raw (unreduced) extraction of the image, bit for bit.
    with ctx.db_sessions() as db:
        stored = db.get(ImageSift, images[2]["id"])
        names = set(db.scalars(select(ImageGlobalFeature.name)
                               .where(ImageGlobalFeature.image_id == images[2]["id"])))
    reference = extract_sift(load_frame(maps[2].jpeg).grey)
    assert stored.n_keypoints == len(reference) > 0
    assert stored.descriptors == reference.descriptors.tobytes()
    assert np.frombuffer(stored.keypoints, "<f4").reshape(-1, 4).tolist() == \
        reference.keypoints.tolist()
    assert set(first.global_features) - set(DESCRIPTOR_NAMES) <= names
    # ORB is stored for the place descriptors' vocabularies, bit for bit too.
    with ctx.db_sessions() as db:
        orb = db.get(ImageOrb, images[2]["id"])
    ref_orb = extract_orb(load_frame(maps[2].jpeg).grey)
    assert orb.n_keypoints == len(ref_orb) > 0
    assert orb.descriptors == ref_orb.descriptors.tobytes()
    _assert_vocabularies_stored(ctx, map_id, 1, first)
    # The map keeps the reduced SIFT: never more than the raw keypoints.
    assert first.sift_counts()[2] <= stored.n_keypoints

    # Four more images: the map waits for a build; the rebuild extracts only those four.
    # (A failed build of an earlier version left its tie points beside its revision: the
    # rebuild deletes them.)
    left = ctx.settings.packed_map_dir(map_id, 2).with_name("rev-000002.ties")
    left.mkdir()
    (left / "7.kp.npy").write_bytes(b"")
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(maps[6:]), headers=ADMIN)
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["revision"], m["pending_images"]) == ("unbuilt", 1, 4)
    calls = []

    def recorded(engine, task, *args, **kwargs):
        calls.append((task.__name__, args))
        return run_task(engine, task, *args, **kwargs)

    monkeypatch.setattr(job_service, "run_task", recorded)
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    monkeypatch.undo()
    assert (job["status"], job["n_images"], job["revision"]) == ("done", 4, 2)
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["revision"], m["pending_images"], m["image_count"]) == \
        ("ready", 2, 0, 10)
    second = MapData.load(ctx.settings.packed_map_dir(map_id, 2))
    assert not left.exists()
    assert len(second) == 10 and list(second.names) == [s.name for s in maps]
    # Four images of ten: more than a fifth of the map was not trained on, and unlike the
    # first six's scenes they raise the distortion past its bound too: the vocabularies are
    # trained anew on all ten images (a fresh build's of the ten, compared below), and
    # revision 1 keeps its own.
    _assert_vocabularies_stored(ctx, map_id, 2, second)
    _assert_vocabularies_stored(ctx, map_id, 1, first)
    assert {f.revision for f in second.vocabulary_fits.values()} == {2}
    assert max(_rise(first, second, n) for n in DESCRIPTOR_NAMES) > MAX_DISTORTION_RISE
    assert not np.array_equal(first.vocabularies["bow_orb"].idf,
                              second.vocabularies["bow_orb"].idf)
    # Sessions on revision 1 keep their folder.
    assert len(MapData.load(ctx.settings.packed_map_dir(map_id, 1))) == 6
    images = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    # The update packs in the first build's frame: its six images keep their east and
    # north to the bit (a large map's untouched tiles keep their keys with them), and
    # the four new ones are placed in it.
    assert m["origin"] == first_origin
    assert not math.isclose(m["origin"]["lat"], np.mean([i["lat"] for i in images]),
                            abs_tol=1e-9)
    np.testing.assert_array_equal(second.positions[:6], first.positions)
    for img in images:
        east, north = origin.to_local(img["lat"], img["lon"])
        assert (img["east"], img["north"]) == pytest.approx((float(east), float(north)),
                                                            abs=1e-6)
    assert [i["built_revision"] for i in images] == [1] * 6 + [2] * 4
    # The rebuild took up the first build's tie points and pairs: it extracted the new
    # images' tie points and matched only the pairs they take part in...
    assert {p: p.stat().st_mtime_ns for p in tie_files} == stamps
    assert len(list(store.glob("*.kp.npy"))) == 10
    # (the engine was asked for the new images' alone)
    new_ids = {i["id"] for i in images[6:]}
    assert sorted(Path(args[1]).name for name, args in calls if name == "extract_ties") == \
        sorted(str(i) for i in new_ids)
    rematched = [(a, b) for path in store.glob(tiepairs.RESULTS_GLOB)
                 if path.name != tiepairs.KEPT for a, b, _ in tiepairs.read_results(path)]
    assert rematched and all(b >= 6 for _, b in rematched)
    # at the first build's reach, though the ten images' spacing is another
    assert KeptModels(store / tiles.MODELS, ()).reach() == first_reach
    assert tie_reach(second.positions, second.captured_at) != first_reach
    # ...and registered the new images into the COLMAP model the first build kept, whose
    # cameras stay where they were (tests/core/geometry/test_kept.py)
    models = store / tiles.MODELS
    if first.geometry is not None:
        assert second.geometry is not None
        (kept,) = [p for p in models.iterdir() if p.is_dir()]
        assert sorted(read_order(kept)) == sorted(str(i["id"]) for i in images)
        both = np.isfinite(first.geometry.centres[:, 0]) & \
            np.isfinite(second.geometry.centres[:6, 0])
        assert both.sum() >= 3
        assert similarity_residual(first.geometry.centres[both],
                                    second.geometry.centres[:6][both]) < 1e-3
    # A full rebuild reconstructs it whole: the map a build of all ten at once gives.
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", params={"full": "true"},
                             headers=ADMIN).json()["job_id"])
    assert (job["status"], job["n_images"], job["revision"], job["full"]) == \
        ("done", 0, 3, True)
    third = MapData.load(ctx.settings.packed_map_dir(map_id, 3))
    # a full build centres its frame on the images, as a fresh build does
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert math.isclose(m["origin"]["lat"], np.mean([i["lat"] for i in images]), abs_tol=1e-12)
    # and decides the reach of its tie pairs again
    assert KeptModels(store / tiles.MODELS, ()).reach() == \
        tie_reach(third.positions, third.captured_at)
    fresh_id = new_map(c)
    c.post(f"/v1/maps/{fresh_id}/images", files=jpeg_files(maps), headers=ADMIN)
    assert wait_job(c, c.post(f"/v1/maps/{fresh_id}/build", headers=ADMIN)
                    .json()["job_id"])["full"] is False
    fresh = MapData.load(ctx.settings.packed_map_dir(fresh_id, 1))
    # the vocabularies, descriptors and masks too (revision 2's, trained on the ten, also)
    for packed in (second, third):
        assert_same_places(packed, fresh)
    assert {f.revision for f in third.vocabulary_fits.values()} == {3}
    assert (third.geometry is None) == (fresh.geometry is None)
    if fresh.geometry is not None:
        np.testing.assert_array_equal(third.geometry.centres, fresh.geometry.centres)
        np.testing.assert_array_equal(third.geometry.points["sift"],
                                      fresh.geometry.points["sift"])
    # An image deleted: the next build grows the kept model without it, the others'
    # cameras where they were.
    gone = images[4]["id"]
    assert c.delete(f"/v1/maps/{map_id}/images/{gone}", headers=ADMIN).status_code == 204
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    assert (job["status"], job["revision"]) == ("done", 4)
    fourth = MapData.load(ctx.settings.packed_map_dir(map_id, 4))
    assert len(fourth) == 9 and gone not in {i["id"] for i in
                                             c.get(f"/v1/maps/{map_id}/images",
                                                   headers=ADMIN).json()}
    # The deletion leaves the vocabularies fitting the map: revision 3's are kept, with
    # the other nine images' descriptors and the masks of those whose neighbours stayed.
    rest = np.r_[0:4, 5:10]
    assert {f.revision for f in fourth.vocabulary_fits.values()} == {3}
    for name in DESCRIPTOR_NAMES:
        np.testing.assert_array_equal(fourth.vocabularies[name].centroids,
                                      third.vocabularies[name].centroids)
        np.testing.assert_array_equal(fourth.global_features[name],
                                      third.global_features[name][rest])
    _assert_vocabularies_stored(ctx, map_id, 4, fourth)
    if third.geometry is not None:
        assert fourth.geometry is not None
        (kept,) = [p for p in models.iterdir() if p.is_dir()]
        assert str(gone) not in read_order(kept) and len(read_order(kept)) == 9
        both = np.isfinite(third.geometry.centres[rest, 0]) & \
            np.isfinite(fourth.geometry.centres[:, 0])
        assert both.sum() >= 3
        # held, not reconstructed again: the same cameras to round-off
        assert similarity_residual(third.geometry.centres[rest][both],
                                    fourth.geometry.centres[both]) < 1e-6
    # and a full rebuild now is the map a fresh build of those nine gives, bit for bit:
    # the pairs that moved up the order are matched again where they are
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", params={"full": "true"},
                             headers=ADMIN).json()["job_id"])
    assert (job["status"], job["revision"]) == ("done", 5)
    fifth = MapData.load(ctx.settings.packed_map_dir(map_id, 5))
    nine_id = new_map(c)
    c.post(f"/v1/maps/{nine_id}/images", files=jpeg_files(maps[:4] + maps[5:]),
           headers=ADMIN)
    assert wait_job(c, c.post(f"/v1/maps/{nine_id}/build", headers=ADMIN)
                    .json()["job_id"])["status"] == "done"
    nine = MapData.load(ctx.settings.packed_map_dir(nine_id, 1))
    assert list(nine.names) == list(fifth.names)
    assert_same_places(fifth, nine)
    assert (fifth.geometry is None) == (nine.geometry is None)
    if nine.geometry is not None:
        np.testing.assert_array_equal(fifth.geometry.centres, nine.geometry.centres)
        np.testing.assert_array_equal(fifth.geometry.points["sift"],
                                      nine.geometry.points["sift"])




def test_forget_reconstruction_keeps_the_tie_points_and_pairs(tmp_path):
    (tmp_path / "7.kp.npy").write_bytes(b"k")
    (tmp_path / "pairs-000000.npz").write_bytes(b"p")
    (tmp_path / tiles.PLAN_FILE).write_bytes(b"plan")
    (tmp_path / "tile-00003.npz").write_bytes(b"t")
    (tmp_path / tiles.MODELS / "abc").mkdir(parents=True)
    (tmp_path / tiles.MODELS / "abc" / "order.txt").write_text("7\n")
    forget_reconstruction(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == \
        ["7.kp.npy", "pairs-000000.npz", tiles.PLAN_FILE]
    forget_reconstruction(tmp_path / "absent")  # a map never built: nothing to forget

def _rise(before: MapData, after: MapData, name: str) -> float:
    """How far ``before``'s vocabulary ``name`` would have risen in distortion over the
    images of ``after`` (a map of ``before``'s images and more, in the same order)."""
    vocab, fit = before.vocabularies[name], before.vocabulary_fits[name]
    local = get_descriptor(name).local
    added = [image_distortion(vocab, local_vectors(local, orb=after.orb(i), sift=after.sift(i)))
             for i in range(len(before), len(after))]
    return float(np.mean(np.r_[fit.images, added]) / fit.trained - 1.0)


def _assert_vocabularies_stored(ctx, map_id: str, revision: int, packed: MapData) -> None:
    """The database holds the packed revision's vocabularies, bit for bit."""
    with ctx.db_sessions() as db:
        rows = {v.name: v for v in db.scalars(select(MapVocabulary).where(
            MapVocabulary.map_id == uuid.UUID(map_id), MapVocabulary.revision == revision))}
        assert set(rows) == set(DESCRIPTOR_NAMES) == set(packed.vocabularies)
        for name, row in rows.items():
            vocab = decode_vocabulary(branching=row.branching, depth=row.depth,
                                      binary=row.binary, dim=row.dim, centroids=row.centroids,
                                      idf=row.idf, projection=row.projection)
            np.testing.assert_array_equal(vocab.centroids, packed.vocabularies[name].centroids)
            np.testing.assert_array_equal(vocab.idf, packed.vocabularies[name].idf)
            assert vocab.binary == packed.vocabularies[name].binary
            if packed.vocabularies[name].projection is None:
                assert vocab.projection is None
            else:
                np.testing.assert_array_equal(vocab.projection,
                                              packed.vocabularies[name].projection)


def test_images_extracted_before_orb_are_extracted_again(module_client, shots):
    c = module_client
    ctx = c.app.state.ctx
    map_id = new_map(c)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:3]), headers=ADMIN)
    wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    images = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    with ctx.db_sessions() as db:  # as a map built before ORB features were stored
        db.execute(delete(ImageOrb).where(ImageOrb.image_id == images[1]["id"]))
        db.commit()
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    assert (job["status"], job["n_images"], job["revision"]) == ("done", 1, 2)
    with ctx.db_sessions() as db:
        assert db.get(ImageOrb, images[1]["id"]) is not None
    assert set(MapData.load(ctx.settings.packed_map_dir(map_id, 2)).vocabularies) == \
        set(DESCRIPTOR_NAMES)


def test_build_conflicts(module_client, shots, hold_worker):
    c = module_client
    empty = new_map(c)
    before = snapshot(c)
    r = c.post(f"/v1/maps/{empty}/build", headers=ADMIN)
    assert r.status_code == 409 and r.json()["type"] == "urn:vloc:problem:map-empty"
    assert snapshot(c) == before

    map_id = new_map(c)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:2]), headers=ADMIN)
    hold_worker()  # the build below waits behind it
    job_id = c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"]
    before = snapshot(c)
    assert c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).status_code == 409
    r = c.delete(f"/v1/maps/{map_id}", headers=ADMIN)
    assert r.status_code == 409 and r.json()["type"] == "urn:vloc:problem:map-busy"
    assert c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["status"] == "building"
    assert snapshot(c) == before
    assert c.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()["status"] in ("queued", "running")


@pytest.mark.parametrize("name", ["nul\x00name", "line\nbreak", "\x7f", "tab\there"])
def test_map_name_with_control_characters_is_422(module_client, name):
    def map_ids():  # (builds of earlier tests may still change the maps' status)
        return [m["id"] for m in module_client.get("/v1/maps", headers=ADMIN).json()]

    before = map_ids()
    r = module_client.post("/v1/maps", json={"name": name}, headers=ADMIN)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
    assert map_ids() == before


def test_a_frame_that_pillow_cannot_identify_has_a_clean_detail(module_client):
    map_id = new_map(module_client)
    r = module_client.post(f"/v1/maps/{map_id}/images", headers=ADMIN, data={
        "lat": "41", "lon": "-83"}, files=[("files", ("x.jpg", b"\xff\xd8\xff" + bytes(300),
                                                     "image/jpeg"))])
    assert r.status_code == 422 and "object at 0x" not in r.text


def test_tie_points_are_extracted_to_files_and_unreadable_images_say_so(tmp_path, shots):
    from vloc.app.tasks.build import extract_ties
    from vloc.workers.core.tiepoints import extract_tie_points, load_tie_points

    image = tmp_path / "map.jpg"
    image.write_bytes(shots[0][0].jpeg)
    assert extract_ties(str(image), str(tmp_path / "1")) == len(load_tie_points(tmp_path / "1"))
    want = extract_tie_points(shots[0][0].jpeg)
    np.testing.assert_array_equal(load_tie_points(tmp_path / "1").descriptors, want.descriptors)
    # a missing or undecodable file: no tie points, the stored SIFT ties the image
    assert extract_ties(str(tmp_path / "gone.jpg"), str(tmp_path / "2")) == -1
    (tmp_path / "bad.jpg").write_bytes(b"not an image")
    assert extract_ties(str(tmp_path / "bad.jpg"), str(tmp_path / "3")) == -1
    assert load_tie_points(tmp_path / "2") is None and load_tie_points(tmp_path / "3") is None


def _built_six_image_map(c, shots) -> tuple[str, str, dict[int, str]]:
    """A map of six images built through the API: its id, the database URL and each image's
    file by image id."""
    from vloc.app.maps.models import MapImage
    from vloc.app.maps.service import image_path

    ctx = c.app.state.ctx
    map_id = new_map(c)
    assert c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:6]),
                  headers=ADMIN).status_code == 201
    assert wait_job(c, c.post(f"/v1/maps/{map_id}/build",
                              headers=ADMIN).json()["job_id"])["status"] == "done"
    with ctx.db_sessions() as db:
        files = {img.id: str(image_path(ctx.settings, img)) for img in db.scalars(
            select(MapImage).where(MapImage.map_id == uuid.UUID(map_id)))}
    return map_id, ctx.settings.resolved_database_url, files


def test_pairs_matched_by_the_workers_are_not_matched_again_and_change_nothing(
        module_client, shots, tmp_path, monkeypatch):
    """The build's pair phase (a plan, then batches on the workers) hands the packing every
    pair it needs: packed with them, no pair is matched in the packing, and the map is the
    map the packing builds by matching them all itself."""
    from vloc.app.tasks import build as tasks
    from vloc.workers.core.geometry import pairs

    map_id, url, files = _built_six_image_map(module_client, shots)
    ties = tmp_path / "ties"
    ties.mkdir()
    for image_id, path in files.items():
        assert tasks.extract_ties(path, tasks.tie_stem(ties, image_id)) > 0
    plan = tasks.plan_tie_pairs(url, map_id, str(ties))
    assert plan["image_ids"] == sorted(files) and len(plan["pairs"]) >= 5
    ids = plan["image_ids"]
    for k, pair in enumerate(plan["pairs"]):
        tasks.match_tie_pairs(str(ties), {i: ids[i] for i in pair}, [pair], k)
    assert len(list(ties.glob(tiepairs.RESULTS_GLOB))) == len(plan["pairs"])

    matched_here = []
    real = pairs.match_pair
    monkeypatch.setattr(pairs, "match_pair",
                        lambda *a, **k: matched_here.append(a[:2]) or real(*a, **k))
    tasks.pack_map(url, map_id, 90, str(tmp_path / "apart"), image_files=files,
                   tie_dir=str(ties), lens_files=[files[i] for i in ids[:2]])
    assert matched_here == []
    tasks.pack_map(url, map_id, 91, str(tmp_path / "here"), image_files=files,
                   lens_files=[files[i] for i in ids[:2]])
    assert sorted(matched_here) == sorted(tuple(p) for p in plan["pairs"])
    apart, here = MapData.load(tmp_path / "apart"), MapData.load(tmp_path / "here")
    assert apart.geometry is not None and here.geometry is not None
    np.testing.assert_array_equal(apart.geometry.centres, here.geometry.centres)
    np.testing.assert_array_equal(apart.geometry.points["sift"], here.geometry.points["sift"])
    assert apart.geometry.self_check == here.geometry.self_check
    np.testing.assert_array_equal(apart.positions, here.positions)


def test_a_rebuild_takes_up_what_an_earlier_build_left(module_client, shots, tmp_path,
                                                       monkeypatch):
    """A map's store of tie points and pairs outlives its builds (a failed one's too): the
    next build's tie points and pairs found there are not computed again, and those an
    older results format or a deleted image have made stale are."""
    from vloc.app.tasks import build as tasks
    from vloc.workers.core import tiepoints

    map_id, url, files = _built_six_image_map(module_client, shots)
    ties = tmp_path / "ties"
    ties.mkdir()

    def attempt():
        counts = [tasks.extract_ties(path, tasks.tie_stem(ties, image_id))
                  for image_id, path in sorted(files.items())]
        plan = tasks.plan_tie_pairs(url, map_id, str(ties))
        ids, pairs = plan["image_ids"], plan["pairs"]
        batches = [pairs[k:k + 2] for k in range(0, len(pairs), 2)]
        for k, b in enumerate(batches):
            tasks.match_tie_pairs(str(ties), {i: ids[i] for p in b for i in p}, b, k)
        found = tiepairs.load_results(ties, ids)
        return counts, plan["planned"], len(pairs), {k: p is not None for k, p in found.items()}

    counts, planned, matched, first = attempt()
    assert min(counts) > 0 and matched == planned == len(first) and any(first.values())
    kept = list(ties.glob("*.kp.npy"))
    stamps = {p: p.stat().st_mtime_ns for p in kept}

    calls = {"tie": 0, "pair": 0}

    def counted(name, real):
        def call(*a, **k):
            calls[name] += 1
            return real(*a, **k)
        return call

    monkeypatch.setattr(tiepoints, "extract_tie_points",
                        counted("tie", tiepoints.extract_tie_points))
    monkeypatch.setattr(tiepairs, "match_pair", counted("pair", tiepairs.match_pair))
    assert attempt() == (counts, planned, 0, first)
    assert calls == {"tie": 0, "pair": 0}
    assert {p: p.stat().st_mtime_ns for p in kept} == stamps
    assert [p.name for p in ties.glob(tiepairs.RESULTS_GLOB)] == [tiepairs.KEPT]

    # results the plane geometry's build left (pixels and homographies, no format) are
    # matched again, to the same pairs
    with np.load(ties / tiepairs.KEPT) as z:
        a, b = z["a"], z["b"]
    np.savez(ties / tiepairs.KEPT, a=a, b=b, verified=np.zeros(len(a), bool),
             counts=np.zeros(0, np.int64), pa=np.zeros((0, 2)), pb=np.zeros((0, 2)),
             homographies=np.zeros((0, 3, 3)))
    assert attempt() == (counts, planned, planned, first) and calls["pair"] == planned
    assert [p.name for p in ties.glob(tiepairs.RESULTS_GLOB)] != [tiepairs.KEPT]
    assert tiepairs.keep_valid(ties, sorted(files)) == set(first)
    assert [p.name for p in ties.glob(tiepairs.RESULTS_GLOB)] == [tiepairs.KEPT]
    # the map's first image deleted: the others move up the map's order and their pairs
    # are taken up where they are now, only pairs new to the plan are matched, and the
    # deleted image's tie points go
    gone = min(files)
    assert module_client.delete(f"/v1/maps/{map_id}/images/{gone}",
                                headers=ADMIN).status_code == 204
    del files[gone]
    _, again, rematched, found = attempt()
    assert again > rematched and again > 0 and calls["pair"] == planned + rematched
    assert len(found) == again
    assert not list(ties.glob(f"{gone}.*"))
    # a full rebuild forgets the pairs that moved: they are matched again, seeded where
    # they are, as a fresh build of these images would match them
    forget_reconstruction(ties)
    _, again_full, rematched_full, found_full = attempt()
    assert again_full == again and rematched_full == again - rematched > 0
    assert found_full.keys() == found.keys()
    # every file was written under a temporary name and renamed: none is left half written
    assert not list(ties.glob(".*"))


def test_images_uploaded_as_named_flights_keep_them_and_the_self_check_reports_each(
        module_client, shots):
    """A morning and a dusk survey of the same ground, uploaded as two named flights (the
    map images and the frames between them): each image says its flight, and the built
    map's self-check gives each flight's figures under its name."""
    c = module_client
    map_id = new_map(c, "two flights")
    noon, dusk = shots
    for flight, flown in (("noon", noon), ("dusk", dusk)):
        r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(flown),
                   data={"flight": f"  {flight} "}, headers=ADMIN)
        assert r.status_code == 201 and not r.json()["rejected"], r.text
        assert {i["flight"] for i in r.json()["accepted"]} == {flight}
    listed = c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()
    assert [i["flight"] for i in listed] == ["noon"] * len(noon) + ["dusk"] * len(dusk)
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    assert job["status"] == "done", job
    geometry = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["geometry"]
    assert geometry["status"] == "accepted", geometry
    flights = geometry["self_check"]["flights"]
    # numbered in the order flown: the frames were taken after the map images
    assert [(f["flight"], f["name"]) for f in flights] == [(0, "noon"), (1, "dusk")]
    assert sum(f["images"] for f in flights) == geometry["self_check"]["images"]
    assert all(0.0 <= f["registered"] <= 1.0 for f in flights)


@pytest.mark.parametrize("flight, status, kind", [
    ("   ", 422, "bad-text"), ("a\x00b", 422, "bad-text"), ("x" * 65, 422, "validation")],
    ids=["blank", "nul", "too-long"])
def test_a_bad_flight_name_is_refused_and_nothing_stored(module_client, shots, flight, status,
                                                         kind):
    c = module_client
    map_id = new_map(c, "bad flight")
    before = snapshot(c)
    r = c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:2]),
               data={"flight": flight}, headers=ADMIN)
    assert r.status_code == status and r.json()["type"].endswith(kind), r.text
    assert snapshot(c) == before


def test_the_tiles_take_only_the_pairs_the_build_planned(module_client, shots, monkeypatch):
    """The map's store may hold verified pairs an earlier build planned and this one does
    not (a full build decides the pairs' reach again from the images' spacing): the tiles
    leave them out, as the packing does, so that the packing finds the tiles the workers
    reconstructed by their key."""
    c = module_client
    ctx = c.app.state.ctx
    map_id = new_map(c)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0]), headers=ADMIN)
    assert wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN)
                    .json()["job_id"])["status"] == "done"
    url, store = ctx.settings.resolved_database_url, ctx.settings.tie_store_dir(map_id)
    images = build_tasks._read_images(url, map_id)
    stored = {pair for pair, p in tiepairs.load_results(store, [i["id"] for i in images])
              .items() if p is not None}
    # this build plans fewer pairs than the one that matched the store's
    monkeypatch.setattr(geometry, "TIE_NEIGHBOURS", 2)
    planned = set(tiepairs.plan([i["lat"] for i in images], [i["lon"] for i in images],
                                [i["alt"] for i in images],
                                [i["captured_at"] for i in images]))
    assert stored - planned
    monkeypatch.setattr(tiling, "MAX_TILE", 3)
    monkeypatch.setattr(tiling, "TILE_MARGIN", 0.5)
    n = build_tasks.plan_tiles(url, map_id, str(store))
    assert n > 1
    in_tiles = {(p.a, p.b) for k in range(n)
                for _, _, p in tiepairs.read_results(store / tiles.INPUT.format(k))}
    assert in_tiles and in_tiles <= planned & stored
    # the tiles are planned in the frame the packing packs in (an update's is the current
    # revision's, not the images' centroid), so that the packing finds them by their key
    o = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["origin"]
    frame = GeoOrigin(o["lat"] + 1e-4, o["lon"], o["alt"])
    assert build_tasks.plan_tiles(url, map_id, str(store), origin=frame) > 1
    east, north = frame.to_local([i["lat"] for i in images],
                                             [i["lon"] for i in images])
    np.testing.assert_allclose(np.load(store / tiles.PLAN_FILE)["tags"][:, :2],
                               np.column_stack([east, north]), atol=1e-9)
