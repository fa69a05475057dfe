"""A map built from image files another map holds links that map's tie points instead of
extracting them again: the same files on disk, the same map, and each map still whole when
the other is deleted."""

from __future__ import annotations

import os
import uuid

import numpy as np
from sqlalchemy import select

from tests.app.conftest import ADMIN, build_map, wait_job
from vloc.app.maps.models import MapImage
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.core.tiepoints import TiePointFiles, link_tie_points, save_tie_points


def _tie_files(client, map_id: str) -> dict[str, str]:
    """The map's tie-point keypoint files, by image file hash."""
    ctx = client.app.state.ctx
    with ctx.db_sessions() as db:
        rows = db.execute(select(MapImage.file_hash, MapImage.id)
                          .where(MapImage.map_id == uuid.UUID(map_id))).all()
    folder = ctx.settings.tie_store_dir(map_id)
    return {h: str(folder / f"{image_id}{TiePointFiles.SUFFIXES[0]}") for h, image_id in rows}


def test_a_second_map_of_the_same_files_links_their_tie_points(client, shots):
    first = build_map(client, shots[0][:8], name="first")
    second = build_map(client, shots[0][2:], name="second")
    a, b = _tie_files(client, first), _tie_files(client, second)
    shared = set(a) & set(b)
    assert len(shared) == 6 and len(b) == 8
    for h in shared:
        assert os.path.samefile(a[h], b[h])
        assert os.path.samefile(a[h].replace(".kp.", ".desc."), b[h].replace(".kp.", ".desc."))
    for h in set(b) - shared:  # its own images: extracted, its own files
        assert os.stat(b[h]).st_nlink == 1
    kept = {h: np.load(b[h]).copy() for h in b}
    revision = client.get(f"/v1/maps/{second}", headers=ADMIN).json()["revision"]

    assert client.delete(f"/v1/maps/{first}", headers=ADMIN).status_code == 204
    for h, keypoints in kept.items():
        assert os.stat(b[h]).st_nlink == 1
        np.testing.assert_array_equal(np.load(b[h]), keypoints)
    # and the second map builds again, whole, from what it holds
    job = client.post(f"/v1/maps/{second}/build?full=true", headers=ADMIN).json()["job_id"]
    assert wait_job(client, job)["status"] == "done"
    assert client.get(f"/v1/maps/{second}", headers=ADMIN).json()["revision"] == revision + 1


def _features(n: int, seed: int) -> SiftFeatures:
    rng = np.random.default_rng(seed)
    return SiftFeatures(rng.random((n, 4), dtype=np.float32),
                        rng.integers(0, 256, (n, 128), dtype=np.uint8))


def test_linking_tie_points_takes_complete_ones_only(tmp_path):
    source, stem = tmp_path / "7", tmp_path / "other" / "3"
    stem.parent.mkdir()
    assert link_tie_points(source, stem) == -1
    # descriptors alone: an extraction that died before its keypoints were renamed in
    desc = tmp_path / f"7{TiePointFiles.SUFFIXES[1]}"
    np.save(desc, np.zeros((2, 128), np.uint8))
    assert link_tie_points(source, stem) == -1
    assert TiePointFiles.find(stem) is None
    tie = _features(40, 1)
    save_tie_points(tie, source)
    assert link_tie_points(source, stem) == 40
    linked = TiePointFiles.find(stem)
    np.testing.assert_array_equal(linked.keypoints, tie.keypoints)
    np.testing.assert_array_equal(linked.descriptors, tie.descriptors)
    assert not list(stem.parent.glob(".*"))  # no temporary names left behind
