"""A large map's reconstruction adjusted block by block apart from the packing: the same
cameras as when the packing adjusts every block itself (blocks of 4 cameras here)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core.geometry.scene import survey
from vloc.workers.core import blocks
from vloc.workers.core.geometry import build_geometry, match_pair, reconstruct, tie_pairs


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory):
    """An 8-image survey, its pairs matched once, and its two blocks adjusted apart."""
    s = survey(np.random.default_rng(7), rows=2, cols=4, max_tilt_deg=3.0)
    xy, alt = s.positions, np.asarray(s.altitudes)
    kp, desc = s.keypoints, s.image_descriptors
    pairs = {(a, b): match_pair(a, b, kp[a], desc[a], kp[b], desc[b]) for a, b in tie_pairs(xy)}
    folder = tmp_path_factory.mktemp("blocks")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reconstruct, "MAX_BLOCK", 4)
        n = blocks.plan(folder, [p for _, p in sorted(pairs.items()) if p is not None], xy,
                        alt, s.K)
        placed = [blocks.adjust(folder, b) for b in range(n)]
    return s, xy, alt, pairs, n, placed, blocks.load_results(folder)


@pytest.fixture
def counted(monkeypatch):
    """Blocks of 4 cameras, and the blocks adjusted in this process counted."""
    monkeypatch.setattr(reconstruct, "MAX_BLOCK", 4)
    calls = []
    real = reconstruct.adjust_block
    monkeypatch.setattr(reconstruct, "adjust_block",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


def test_blocks_adjusted_apart_give_the_cameras_of_one_process(surveyed, counted):
    s, xy, alt, pairs, n, placed, known = surveyed
    assert n == 2 and sum(placed) == len(xy)
    assert len(known) == 2 and all(r is not None for r in known.values())
    apart = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K, known_pairs=pairs,
                           known_blocks=known)
    assert counted == []
    here = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K, known_pairs=pairs)
    assert len(counted) == 2
    np.testing.assert_array_equal(apart.centres, here.centres)
    np.testing.assert_array_equal(apart.rotations, here.rotations)
    assert apart.intrinsics == here.intrinsics


def test_a_block_whose_inputs_changed_is_adjusted_again(surveyed, counted):
    s, xy, alt, pairs, n, placed, known = surveyed
    moved = alt.copy()
    moved[0] += 1.0      # one camera's altitude: its block's key changes, the other's not
    build_geometry(s.keypoints, s.image_descriptors, xy, moved, s.K, known_pairs=pairs,
                   known_blocks=known)
    assert counted == [1]


def test_a_map_adjusted_whole_plans_no_block(surveyed, tmp_path):
    s, xy, alt, pairs, *_ = surveyed
    assert blocks.plan(tmp_path, [p for p in pairs.values() if p is not None], xy, alt,
                       s.K) == 0
    assert blocks.load_results(tmp_path) == {}
