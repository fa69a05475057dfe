"""Data set folders: positions from EXIF or CSV, ordering, skipped files, splits."""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational as R

from vloc.workers.core.evaluation.datasets import (
    DatasetError,
    load_dataset,
    load_frames,
    positions_enu,
    read_image,
    split,
    split_alternate,
    split_by_pass,
)
from vloc.workers.core.exif import encode_jpeg_with_gps
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import load_frame

T0 = datetime(2024, 3, 1, 10, 0, 0)


def _pixels(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (60, 80, 3), dtype=np.uint8)


def _tagged(path: Path, seed: int, lat: float, lon: float, seconds: int | None,
            alt: float | None = 100.0) -> None:
    when = None if seconds is None else T0 + timedelta(seconds=seconds)
    path.write_bytes(encode_jpeg_with_gps(_pixels(seed), lat=lat, lon=lon, alt=alt,
                                          captured_at=when))


def _plain(path: Path, seed: int) -> None:
    ok, buf = cv2.imencode(path.suffix.lower(), _pixels(seed))
    assert ok
    path.write_bytes(buf.tobytes())


def _csv(path: Path, header: str, *rows: str) -> None:
    path.write_text("\n".join([header, *rows]) + "\n")


@pytest.fixture
def mixed(tmp_path: Path) -> Path:
    """images/ with mixed-case suffixes, a PNG positioned by CSV, and an unpositioned JPEG."""
    images = tmp_path / "images"
    images.mkdir()
    _tagged(images / "a.JPG", 1, 46.5, 6.6, seconds=20)
    _tagged(images / "b.jpeg", 2, 46.5001, 6.6001, seconds=10, alt=-4.0)
    _plain(images / "c.Png", 3)
    _plain(images / "d.jpg", 4)
    _tagged(images / "e.JpEg", 5, 46.5003, 6.6003, seconds=30)
    (images / "notes.txt").write_text("not an image")
    _plain(images / "._a.JPG", 6)
    _csv(tmp_path / "ground_truth.csv", "filename,pass,captured_at,lat,lon,alt_m",
         "a.JPG,1,2024-03-01T10:00:20,46.5,6.6,100.0",
         "b.jpeg,1,,46.5001,6.6001,",
         "c.Png,2,2024-03-01T10:00:25,46.5002,6.6002,99.5",
         "e.jpeg,2,2024-03-01T10:00:30,46.5003,6.6003,100")
    return tmp_path


def test_mixed_folder_positions_order_and_skips(mixed):
    ds = load_dataset(mixed)
    assert ds.image_dir == mixed / "images" and ds.csv_path.name == "ground_truth.csv"
    # capture order: b (10 s), a (20 s), c (25 s, from the CSV), e (30 s)
    assert [im.name for im in ds.images] == ["b.jpeg", "a.JPG", "c.Png", "e.JpEg"]
    by_name = {im.name: im for im in ds.images}
    assert [by_name[n].source for n in ("a.JPG", "b.jpeg", "c.Png")] == ["exif", "exif", "csv"]
    assert by_name["b.jpeg"].alt == pytest.approx(-4.0) and by_name["b.jpeg"].truth_alt is None
    assert (by_name["c.Png"].lat, by_name["c.Png"].lon, by_name["c.Png"].alt) \
        == (46.5002, 6.6002, 99.5)
    assert by_name["c.Png"].captured_at == T0 + timedelta(seconds=25)
    # e.JpEg is listed as e.jpeg: matched without regard to case
    assert by_name["e.JpEg"].pass_ == 2 and by_name["e.JpEg"].truth_lat == 46.5003
    assert ds.passes == {1: 2, 2: 2}
    assert len(ds.skipped) == 1 and ds.skipped[0][0] == "d.jpg"
    assert "no EXIF GPS" in ds.skipped[0][1]
    text = ds.summary()
    assert "4 images (3 positioned by EXIF, 1 by CSV), 1 skipped" in text
    assert "passes: 1 (2), 2 (2)" in text and "d.jpg" in text


def test_images_in_folder_itself_sorted_by_natural_name(tmp_path):
    _tagged(tmp_path / "IMG_10.jpg", 1, 10.0, 20.0, seconds=None)
    _tagged(tmp_path / "IMG_2.JPG", 2, 10.0, 20.001, seconds=None)
    _plain(tmp_path / "IMG_1.png", 3)
    _csv(tmp_path / "my_positions.csv", "Filename,Latitude,Longitude",
         "IMG_1.png,9.999,20.0")
    ds = load_dataset(tmp_path)
    assert ds.image_dir == tmp_path and ds.csv_path.name == "my_positions.csv"
    assert [im.name for im in ds.images] == ["IMG_1.png", "IMG_2.JPG", "IMG_10.jpg"]
    assert ds.passes == {} and ds.skipped == ()


def test_bad_cells_and_unreadable_files_are_skipped_with_reasons(tmp_path):
    _plain(tmp_path / "p.jpg", 1)
    _plain(tmp_path / "q.jpg", 2)
    _plain(tmp_path / "r.jpg", 3)
    (tmp_path / "s.jpg").write_bytes(b"garbage, not a JPEG")
    _tagged(tmp_path / "t.jpg", 4, 1.0, 2.0, seconds=0)
    _csv(tmp_path / "positions.csv", "filename,lat,lon,pass",
         "p.jpg,abc,2.0,1", "q.jpg,95.0,2.0,1", "r.jpg,1.0,2.0,first", "t.jpg,1.0,2.0,1")
    ds = load_dataset(tmp_path)
    assert [im.name for im in ds.images] == ["t.jpg"]
    reasons = dict(ds.skipped)
    assert "not numeric" in reasons["p.jpg"]
    assert "within +-90" in reasons["q.jpg"]
    assert "first" in reasons["r.jpg"]
    assert "unreadable image" in reasons["s.jpg"]


def test_malformed_exif_gps_falls_back_to_csv(tmp_path):
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = {1: "N", 2: (R(95, 1), R(0, 1), R(0, 1)),
                                  3: "E", 4: (R(1, 1), R(0, 1), R(0, 1))}
    for name in ("u.jpg", "v.jpg"):
        Image.new("RGB", (16, 8)).save(tmp_path / name, "JPEG", exif=exif.tobytes())
    _csv(tmp_path / "positions.csv", "filename,lat,lon", "u.jpg,12.0,13.0")
    ds = load_dataset(tmp_path)
    assert [(im.name, im.source, im.lat) for im in ds.images] == [("u.jpg", "csv", 12.0)]
    assert ds.skipped[0][0] == "v.jpg" and "malformed EXIF GPS" in ds.skipped[0][1]


def test_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_dataset(tmp_path / "nowhere")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="no .jpg/.jpeg/.png images"):
        load_dataset(tmp_path)
    _tagged(tmp_path / "a.jpg", 1, 1.0, 2.0, seconds=0)
    _csv(tmp_path / "one.csv", "filename,lat,lon")
    _csv(tmp_path / "two.csv", "filename,lat,lon")
    with pytest.raises(DatasetError, match="several CSV files"):
        load_dataset(tmp_path)
    _csv(tmp_path / "ground_truth.csv", "name,lat,lon", "a.jpg,1,2")
    with pytest.raises(DatasetError, match="no 'filename' column"):
        load_dataset(tmp_path)
    _csv(tmp_path / "ground_truth.csv", "filename,lat,lon", "a.jpg,1,2", "a.jpg,1,2")
    with pytest.raises(DatasetError, match="more than once"):
        load_dataset(tmp_path)
    with pytest.raises(FileNotFoundError, match="CSV file"):
        load_dataset(tmp_path, csv_path=tmp_path / "missing.csv")


def _line(tmp_path: Path, n: int, passes: list[int] | None) -> Path:
    for i in range(n):
        _tagged(tmp_path / f"f{i}.jpg", i, 30.0 + 1e-4 * i, -90.0, seconds=n - i)
    if passes is not None:
        _csv(tmp_path / "ground_truth.csv", "filename,pass",
             *[f"f{i}.jpg,{p}" for i, p in enumerate(passes)])
    return tmp_path


def test_alternate_split_in_capture_order(tmp_path):
    # capture times run backwards through the names: f4 is first
    ds = load_dataset(_line(tmp_path, 5, None))
    m, q = split_alternate(ds)
    assert [im.name for im in m] == ["f4.jpg", "f2.jpg", "f0.jpg"]
    assert [im.name for im in q] == ["f3.jpg", "f1.jpg"]
    assert split(ds, "alternate") == (m, q)
    with pytest.raises(DatasetError, match="no pass column"):
        split(ds, "pass")
    with pytest.raises(DatasetError, match="takes no map_pass"):
        split(ds, "alternate", map_pass=1)
    with pytest.raises(DatasetError, match="unknown split rule 'odd'.*pass, alternate"):
        split(ds, "odd")


def test_pass_split_and_its_errors(tmp_path):
    ds = load_dataset(_line(tmp_path, 6, [1, 1, 3, 3, 3, 1]))
    m, q = split(ds)
    assert [im.name for im in m] == ["f5.jpg", "f1.jpg", "f0.jpg"]
    assert [im.name for im in q] == ["f4.jpg", "f3.jpg", "f2.jpg"]
    assert split_by_pass(ds, 3, 1) == (q, m)
    with pytest.raises(DatasetError, match=r"pass 2 has no images; passes present: 1 \(3"):
        split_by_pass(ds, 1, 2)
    with pytest.raises(DatasetError, match="pass 1 is both a map pass and the query pass"):
        split_by_pass(ds, 1, 1)
    single = tmp_path / "single"
    single.mkdir()
    with pytest.raises(DatasetError, match="only pass 4"):
        split(load_dataset(_line(single, 2, [4, 4])))


def test_a_map_of_several_passes(tmp_path):
    """A map of several flights: its images pass by pass in the order named, each pass in
    capture order; the query defaults to the first pass not in the map."""
    ds = load_dataset(_line(tmp_path, 8, [1, 2, 3, 1, 2, 3, 4, 2]))
    m, q = split(ds, map_pass=(2, 1))
    assert [im.pass_ for im in m] == [2, 2, 2, 1, 1]
    assert [im.name for im in m[:3]] == ["f7.jpg", "f4.jpg", "f1.jpg"]
    assert {im.pass_ for im in q} == {3}
    assert split(ds, map_pass=[1, 2], query_pass=4)[1] == [im for im in ds.images
                                                          if im.pass_ == 4]
    with pytest.raises(DatasetError, match="pass 2 is both"):
        split_by_pass(ds, (1, 2), 2)
    with pytest.raises(DatasetError, match="name each pass once"):
        split_by_pass(ds, (1, 1), 3)
    with pytest.raises(DatasetError, match="pass 5 has no images"):
        split_by_pass(ds, (1, 5), 3)


def test_positions_enu_known_answer_and_reference(tmp_path):
    ds = load_dataset(_line(tmp_path, 4, None))
    images = sorted(ds.images, key=lambda im: im.name)
    origin = GeoOrigin(images[0].lat, images[0].lon)
    xy = positions_enu(images, origin)
    assert xy.shape == (4, 2) and xy.dtype == np.float64
    # 1e-4 degrees of latitude at 30 N: pi/180 * M(30 deg) * 1e-4 with the WGS84 meridian
    # radius M = a(1-e^2)/(1-e^2 sin^2)^1.5 = 6351377 m: 11.0853 m north per step.
    a, e2 = 6378137.0, 6.69437999014e-3
    meridian = a * (1 - e2) / (1 - e2 * np.sin(np.radians(30)) ** 2) ** 1.5
    step = np.radians(1e-4) * meridian
    np.testing.assert_allclose(xy[:, 1], step * np.arange(4), atol=2e-3)
    np.testing.assert_allclose(xy[:, 0], 0.0, atol=1e-6)
    slow = np.array([[float(v) for v in origin.to_local(im.lat, im.lon)] for im in images])
    np.testing.assert_allclose(xy, slow, atol=1e-9)
    assert positions_enu([], origin).shape == (0, 2)


def test_load_frames_matches_one_by_one(mixed):
    ds = load_dataset(mixed)
    threaded = load_frames(list(ds.images), workers=3)
    single = load_frames(list(ds.images), size=(320, 240), workers=1)
    for im, a, b in zip(ds.images, threaded, single, strict=True):
        ref = load_frame(read_image(im))
        assert a.grey.shape == (240, 320) and a.colour.shape == (240, 320, 3)
        np.testing.assert_array_equal(a.colour, ref.colour)
        np.testing.assert_array_equal(b.grey, ref.grey)
    assert read_image(ds.images[0]) == ds.images[0].path.read_bytes()


@pytest.mark.dataset
def test_seneca_positions_and_pass_split(seneca_dir):
    ds = load_dataset(seneca_dir)
    assert len(ds) == 167 and ds.skipped == ()
    assert all(im.source == "exif" for im in ds.images)
    for im in ds.images:
        assert abs(im.lat - im.truth_lat) < 1e-6 and abs(im.lon - im.truth_lon) < 1e-6
    times = [im.captured_at for im in ds.images]
    assert times == sorted(times)
    m, q = split(ds, "pass", map_pass=1, query_pass=2)
    assert (len(m), len(q)) == (70, 97)
    assert (m[0].name, m[-1].name, q[0].name, q[-1].name) == \
        ("IMG_0446.jpg", "IMG_0515.jpg", "IMG_0516.jpg", "IMG_0612.jpg")
    # consecutive query images are about 32 m apart (data set README)
    xy = positions_enu(q, ds.origin())
    assert 25 < np.median(np.linalg.norm(np.diff(xy, axis=0), axis=1)) < 40


@pytest.mark.parametrize("build_seed", [0, 5])
def test_the_build_seed_reaches_the_map_build_and_the_photometric_seed_does_not(
        tmp_path, monkeypatch, build_seed):
    from vloc.workers.core.evaluation import experiment

    seen = {}

    class Built(Exception):
        pass

    def assemble(**kwargs):
        seen.update(kwargs)
        raise Built

    monkeypatch.setattr(experiment, "assemble_map", assemble)
    with pytest.raises(Built):
        experiment.load_experiment(_line(tmp_path, 6, None), rule="alternate", seed=3,
                                   geometry=False, build_seed=build_seed)
    assert seen["seed"] == build_seed and len(seen["names"]) == 3
