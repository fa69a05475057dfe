"""Per-keypoint arrays in chunks that revisions share: where chunks end, reading them as one
array, and revisions packed from earlier ones linking what did not change."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tests.core.test_mapdata import _geometry
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.rowchunks import ChunkedRows, chunk_bounds, load_chunked, save_chunked

NAMES = [f"IMG_{i:04d}.JPG" for i in range(400)]


def _runs(bounds: list[int], names: list[str]) -> list[tuple[str, ...]]:
    return [tuple(names[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def test_chunks_end_where_the_names_say_so_edits_move_only_their_own():
    bounds = chunk_bounds(NAMES, every=8)
    assert bounds[0] == 0 and bounds[-1] == len(NAMES)
    sizes = np.diff(bounds)
    assert sizes.min() >= 1 and sizes.max() <= 32  # four times `every` at most
    assert 25 <= len(sizes) <= 100  # about 400 / 8 chunks
    runs = _runs(bounds, NAMES)
    # appending images: only the last chunk changes
    grown = NAMES + [f"NEW_{i}.JPG" for i in range(20)]
    assert _runs(chunk_bounds(grown, every=8), grown)[:len(runs) - 1] == runs[:-1]
    # deleting one image: only the chunk that held it changes
    gone = NAMES[:150] + NAMES[151:]
    after = set(_runs(chunk_bounds(gone, every=8), gone))
    changed = [r for r in runs if r not in after]
    assert changed == [r for r in runs if NAMES[150] in r]
    assert chunk_bounds([], every=8) == [0, 0]


def test_a_run_of_names_none_of_which_ends_a_chunk_is_cut_every_four_times_as_many():
    plain = [n for n in NAMES if chunk_bounds([n, "pad"], every=8)[1] != 1][:70]
    assert len(plain) == 70
    assert np.diff(chunk_bounds(plain, every=8)).tolist() == [32, 32, 6]


def _reference_split(rng, sizes):
    rows = rng.normal(size=(sum(sizes), 3)).astype(np.float32)
    edges = np.concatenate([[0], np.cumsum(sizes)])
    return rows, ChunkedRows([rows[a:b] for a, b in zip(edges[:-1], edges[1:], strict=True)])


@pytest.mark.parametrize("sizes", [[7], [5, 0, 9, 3], [0, 4, 4, 0]])
def test_chunked_rows_read_as_the_one_array_they_were_cut_from(sizes):
    rng = np.random.default_rng(len(sizes))
    whole, chunked = _reference_split(rng, sizes)
    n = len(whole)
    assert (len(chunked), chunked.shape, chunked.dtype, chunked.ndim) == (n, (n, 3),
                                                                          np.float32, 2)
    np.testing.assert_array_equal(np.asarray(chunked), whole)
    for a in range(n + 1):
        for b in range(a, n + 2):
            np.testing.assert_array_equal(chunked[a:b], whole[a:b])
    np.testing.assert_array_equal(chunked[-3:], whole[-3:])
    picks = rng.integers(0, n, 20)
    np.testing.assert_array_equal(chunked[picks], whole[picks])
    np.testing.assert_array_equal(chunked[picks - n], whole[picks - n])
    for i in (0, n - 1, -1, np.int64(n // 2)):
        np.testing.assert_array_equal(chunked[i], whole[i])
    np.testing.assert_array_equal(chunked[np.zeros(0, np.int64)], whole[:0])
    np.testing.assert_array_equal(chunked[::2], whole[::2])
    np.testing.assert_array_equal(chunked[whole[:, 0] > 0], whole[whole[:, 0] > 0])
    with pytest.raises(IndexError):
        chunked[np.array([n])]


def test_rows_times_a_vector_are_the_one_array_s_product():
    rng = np.random.default_rng(4)
    whole, chunked = _reference_split(rng, [40, 0, 200, 17, 99])
    q = rng.normal(size=3).astype(np.float32)
    got = chunked @ q
    assert got.shape == (len(whole),) and got.dtype == np.float32
    # BLAS sums a row's products in an order that depends on where the row lies in the
    # matrix it was given: each chunk's rows exactly as that chunk alone gives them
    np.testing.assert_array_equal(got, np.concatenate([p @ q for p in chunked.parts]))
    np.testing.assert_allclose(got, whole @ q, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(ChunkedRows([whole]) @ q, whole @ q)
    np.testing.assert_allclose(chunked @ np.eye(3, dtype=np.float32), whole, rtol=1e-6)


def test_an_image_is_a_view_of_its_chunk():
    whole, chunked = _reference_split(np.random.default_rng(3), [4, 6])
    view = chunked[5:9]
    assert view.base is not None and np.shares_memory(view, chunked.parts[1])


def test_chunks_that_disagree_on_their_rows_are_refused(tmp_path):
    with pytest.raises(ValueError, match="disagree"):
        ChunkedRows([np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32)])
    offsets = np.array([0, 2, 5])
    chunks = save_chunked(tmp_path, "x", np.arange(10).reshape(5, 2), offsets, [0, 1, 2])
    chunks[1][1] = 4
    with pytest.raises(ValueError, match="holds 3 rows, not 4"):
        load_chunked(tmp_path, chunks)


def _map(n: int, rng, *, names=None) -> MapData:
    names = names or NAMES[:n]
    counts = rng.integers(0, 6, len(names))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    k = int(offsets[-1])
    return MapData(origin=GeoOrigin(42.0, -76.0, 300.0), names=tuple(names),
                   positions=np.column_stack([np.arange(len(names)) * 10.0,
                                              np.zeros(len(names))]),
                   altitudes=np.full(len(names), 310.0),
                   global_features={"wgoh": rng.random((len(names), 8)).astype(np.float32)},
                   sift_offsets=offsets,
                   sift_keypoints=(rng.random((k, 4)) * 300).astype(np.float32),
                   sift_descriptors=rng.integers(0, 255, (k, 128)).astype(np.uint8),
                   sift_keep=rng.random(k) > 0.3, orb_offsets=offsets,
                   orb_keypoints=(rng.random((k, 4)) * 300).astype(np.float32),
                   orb_descriptors=rng.integers(0, 255, (k, 32)).astype(np.uint8),
                   map_id="m", revision=1)


def _grown(before: MapData, added: int, rng) -> MapData:
    """``before`` with ``added`` images appended, its own rows untouched."""
    extra = _map(added, rng, names=[f"NEW_{i}.JPG" for i in range(added)])
    k = len(before.sift_descriptors)

    def cat(a, b):
        return np.concatenate([np.asarray(a), np.asarray(b)])

    return MapData(origin=before.origin, names=before.names + extra.names,
                   positions=cat(before.positions, extra.positions + [0.0, 50.0]),
                   altitudes=cat(before.altitudes, extra.altitudes),
                   global_features={"wgoh": cat(before.global_features["wgoh"],
                                                extra.global_features["wgoh"])},
                   sift_offsets=cat(before.sift_offsets[:-1], extra.sift_offsets + k),
                   sift_keypoints=cat(before.sift_keypoints, extra.sift_keypoints),
                   sift_descriptors=cat(before.sift_descriptors, extra.sift_descriptors),
                   sift_keep=cat(before.sift_keep, extra.sift_keep),
                   orb_offsets=cat(before.orb_offsets[:-1], extra.orb_offsets + k),
                   orb_keypoints=cat(before.orb_keypoints, extra.orb_keypoints),
                   orb_descriptors=cat(before.orb_descriptors, extra.orb_descriptors),
                   map_id="m", revision=2)


def _assert_same_map(got: MapData, want: MapData) -> None:
    assert got.names == want.names
    for i in range(len(want)):
        for g, w in ((got.sift(i), want.sift(i)), (got.orb(i), want.orb(i)),
                     (got.sift(i, reduced=True), want.sift(i, reduced=True))):
            np.testing.assert_array_equal(g.keypoints, w.keypoints)
            np.testing.assert_array_equal(g.descriptors, w.descriptors)
    np.testing.assert_array_equal(np.asarray(got.sift_keep), np.asarray(want.sift_keep))
    np.testing.assert_array_equal(got.global_features["wgoh"], want.global_features["wgoh"])


def _files(folder) -> dict[str, os.stat_result]:
    return {p.name: p.stat() for p in folder.iterdir()}


def test_a_revision_packed_from_an_earlier_one_links_the_chunks_it_left_alone(tmp_path):
    rng = np.random.default_rng(5)
    first = _map(300, rng)
    a = first.save(tmp_path / "1", chunk_images=16)
    second = _grown(MapData.load(a), 12, rng)
    b = second.save(tmp_path / "2", share=a, chunk_images=16)
    _assert_same_map(MapData.load(b), second)
    _assert_same_map(MapData.load(b, mmap=False), second)

    meta_a, meta_b = (json.loads((f / "meta.json").read_text()) for f in (a, b))
    files_b = _files(b)
    # the last image of the earlier revision still ends a chunk: the new ones start their own
    assert chunk_bounds(NAMES[:301], every=16)[-2] != 300
    old = len(meta_a["chunk_images"])
    assert old >= 10 and meta_b["chunk_images"][:old] == meta_a["chunk_images"]
    assert sum(meta_b["chunk_images"][old:]) == 12
    for stem in ("sift_keypoints", "sift_descriptors", "sift_keep", "orb_keypoints",
                 "orb_descriptors", "global_wgoh"):
        chunks_a = [name for name, _ in meta_a["chunks"][stem]]
        chunks_b = [name for name, _ in meta_b["chunks"][stem]]
        # the chunks of images the update left alone are the earlier revision's files
        assert chunks_b[:old] == chunks_a
        for name in chunks_a:
            assert os.path.samefile(a / name, b / name) and files_b[name].st_nlink == 2
        # those of the new images are new files
        for name in chunks_b[old:]:
            assert files_b[name].st_nlink == 1
    # files written whole are linked only where byte for byte the same
    assert files_b["meta.json"].st_nlink == 1 and files_b["positions.npy"].st_nlink == 1

    # the earlier revision can go; the later one keeps every file it needs
    for path in a.iterdir():
        path.unlink()
    a.rmdir()
    _assert_same_map(MapData.load(b), second)


def test_a_revision_that_lost_an_image_writes_only_the_chunk_that_held_it(tmp_path):
    rng = np.random.default_rng(9)
    first = _map(200, rng)
    a = first.save(tmp_path / "1", chunk_images=16)
    keep = [i for i in range(200) if i != 120]
    offsets = np.asarray(first.sift_offsets)
    rows = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in keep])
    counts = np.diff(offsets)[keep]
    new_offsets = np.concatenate([[0], np.cumsum(counts)])
    fewer = MapData(origin=first.origin, names=tuple(first.names[i] for i in keep),
                    positions=first.positions[keep], altitudes=first.altitudes[keep],
                    global_features={"wgoh": first.global_features["wgoh"][keep]},
                    sift_offsets=new_offsets, sift_keypoints=first.sift_keypoints[rows],
                    sift_descriptors=first.sift_descriptors[rows],
                    sift_keep=first.sift_keep[rows], orb_offsets=new_offsets,
                    orb_keypoints=first.orb_keypoints[rows],
                    orb_descriptors=first.orb_descriptors[rows], map_id="m", revision=2)
    b = fewer.save(tmp_path / "2", share=a, chunk_images=16)
    _assert_same_map(MapData.load(b), fewer)
    meta_a, meta_b = (json.loads((f / "meta.json").read_text()) for f in (a, b))
    at = int(np.searchsorted(np.cumsum(meta_a["chunk_images"]), 120, side="right"))
    expected = list(meta_a["chunk_images"])
    expected[at] -= 1
    assert meta_b["chunk_images"] == [n for n in expected if n]
    for stem in ("sift_descriptors", "orb_keypoints"):
        chunks_a = [name for name, _ in meta_a["chunks"][stem]]
        chunks_b = [name for name, _ in meta_b["chunks"][stem]]
        written = [name for name in chunks_b if (b / name).stat().st_nlink == 1]
        assert chunks_b == chunks_a[:at] + written + chunks_a[at + 1:]
        assert len(written) == 1


def test_saving_the_same_map_again_links_every_file_but_its_meta(tmp_path):
    rng = np.random.default_rng(6)
    data = _map(40, rng)
    data.geometry = None
    a = data.save(tmp_path / "1", chunk_images=4)
    again = MapData.load(a)
    again.revision = 2
    b = again.save(tmp_path / "2", share=a, chunk_images=4)
    unshared = sorted(n for n, s in _files(b).items() if s.st_nlink == 1)
    assert unshared == ["meta.json"]
    _assert_same_map(MapData.load(b), data)


def test_geometry_points_are_chunked_with_their_keypoints(tmp_path):
    from tests.core.test_mapdata import _map as small_map

    data = small_map(np.random.default_rng(0))
    data.geometry = _geometry(data)
    folder = data.save(tmp_path / "map", chunk_images=1)
    meta = json.loads((folder / "geometry.json").read_text())
    assert sorted(meta["point_chunks"]) == ["sift"]
    assert len(meta["point_chunks"]["sift"]) == len(json.loads(
        (folder / "meta.json").read_text())["chunks"]["sift_keypoints"])
    back = MapData.load(folder)
    np.testing.assert_array_equal(np.asarray(back.geometry.points["sift"]),
                                  data.geometry.points["sift"])
    rows = np.flatnonzero(np.isfinite(data.geometry.points["sift"][:, 0]))
    np.testing.assert_array_equal(back.geometry.points["sift"][rows],
                                  data.geometry.points["sift"][rows])


def test_a_revision_saved_in_one_file_per_array_still_loads(tmp_path):
    """Revisions packed before chunks: each per-keypoint array in one file."""
    rng = np.random.default_rng(7)
    data = _map(30, rng)
    folder = data.save(tmp_path / "old", chunk_images=4)
    meta = json.loads((folder / "meta.json").read_text())
    for stem, chunks in meta.pop("chunks").items():
        assert stem in ("sift_keypoints", "sift_descriptors", "sift_keep", "orb_keypoints",
                        "orb_descriptors", "global_wgoh")
        np.save(folder / f"{stem}.npy", np.concatenate([np.load(folder / n) for n, _ in chunks]))
        for name, _ in chunks:
            (folder / name).unlink()
    (folder / "meta.json").write_text(json.dumps(meta))
    back = MapData.load(folder)
    assert isinstance(back.sift_descriptors, np.memmap)
    _assert_same_map(back, data)


def test_a_save_that_died_leaves_nothing_the_next_one_trusts(tmp_path):
    rng = np.random.default_rng(8)
    data = _map(20, rng)
    folder = data.save(tmp_path / "map", chunk_images=4)
    chunk = json.loads((folder / "meta.json").read_text())["chunks"]["sift_descriptors"][0][0]
    (tmp_path / "again.tmp").mkdir()
    (tmp_path / "again.tmp" / chunk).write_bytes(b"half a chunk")
    _assert_same_map(MapData.load(data.save(tmp_path / "again", chunk_images=4)), data)
