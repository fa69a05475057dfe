"""A large map's reconstruction adjusted block by block apart from the packing: the same
cameras as when the packing adjusts every block itself."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core.geometry.scene import survey
from vloc.workers.core import blocks
from vloc.workers.core.geometry import build_geometry, reconstruct, tie_reach
from vloc.workers.core.geometry.reconstruct import match_pairs


@pytest.fixture(scope="module")
def surveyed():
    s = survey(np.random.default_rng(7), rows=2, cols=8, max_tilt_deg=3.0)
    return s, s.positions, np.asarray(s.altitudes)


@pytest.fixture
def small_blocks(monkeypatch):
    monkeypatch.setattr(reconstruct, "MAX_BLOCK", 8)


def _planned(s, xy, alt, folder):
    pairs = match_pairs(s.keypoints, s.image_descriptors, xy, max_distance=tie_reach(xy))
    return blocks.plan(folder, pairs, xy, alt, s.K)


def test_blocks_adjusted_apart_give_the_cameras_of_one_process(surveyed, small_blocks,
                                                                tmp_path, monkeypatch):
    s, xy, alt = surveyed
    here = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K)
    assert here is not None
    n = _planned(s, xy, alt, tmp_path)
    assert n == 2
    placed = [blocks.adjust(tmp_path, b) for b in range(n)]
    assert sum(placed) == len(xy)
    known = blocks.load_results(tmp_path)
    assert len(known) == 2 and all(r is not None for r in known.values())

    adjusted_here = []
    real = reconstruct.adjust_block
    monkeypatch.setattr(reconstruct, "adjust_block",
                        lambda *a, **k: adjusted_here.append(1) or real(*a, **k))
    apart = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K,
                           known_blocks=known)
    assert adjusted_here == []
    np.testing.assert_array_equal(apart.centres, here.centres)
    np.testing.assert_array_equal(apart.rotations, here.rotations)
    assert apart.intrinsics == here.intrinsics


def test_a_block_whose_inputs_changed_is_adjusted_again(surveyed, small_blocks, tmp_path,
                                                        monkeypatch):
    s, xy, alt = surveyed
    for b in range(_planned(s, xy, alt, tmp_path)):
        blocks.adjust(tmp_path, b)
    known = blocks.load_results(tmp_path)
    moved = alt.copy()
    moved[0] += 1.0      # one camera's altitude: its block's key changes, the other's not
    calls = []
    real = reconstruct.adjust_block
    monkeypatch.setattr(reconstruct, "adjust_block",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    build_geometry(s.keypoints, s.image_descriptors, xy, moved, s.K, known_blocks=known)
    assert calls == [1]


def test_a_map_adjusted_whole_plans_no_block(surveyed, tmp_path):
    s, xy, alt = surveyed
    assert _planned(s, xy, alt, tmp_path) == 0
    assert blocks.load_results(tmp_path) == {}
