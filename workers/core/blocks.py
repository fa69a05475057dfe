"""The blocks of a large map's reconstruction, adjusted in parallel ahead of the packing.

A map of more than :data:`~workers.core.geometry.reconstruct.MAX_BLOCK` images is adjusted
block by block (:func:`~workers.core.geometry.reconstruct.reconstruct_in_blocks`), each on
its own: about 70 ms an image of one core, over an hour for 50,000 images. Once the tie
points' pairs are matched (:mod:`.tiepairs`), a build writes each block's pairs and the
map's positions to disk (:func:`plan`), lets the engine's workers adjust the blocks
(:func:`adjust`, one file of results per block) and hands them to the packing
(:func:`load_results`), which adjusts only blocks whose inputs it does not find among them
(:func:`~workers.core.geometry.reconstruct.block_key`): the map comes out the same as when
one process adjusts every block.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .geometry.camera import Intrinsics
from .geometry.pairs import keep_some
from .geometry.reconstruct import BlockResult, adjust_block, block_key, block_pairs
from .tiepairs import read_results, save_results

PLAN_FILE = "blocks-plan.npz"
INPUT = "block-{:05d}-pairs.npz"
RESULT = "block-{:05d}.npz"
RESULTS_GLOB = "block-?????.npz"


def plan(folder: str | Path, verified, positions: np.ndarray, altitudes: np.ndarray,
         K0: Intrinsics, *, seed: int = 0) -> int:
    """Write what each block's adjustment needs into ``folder``; returns the number of
    blocks (0 for a map adjusted whole, which the packing does itself).

    ``verified`` are the map's verified pairs with all their tie points, in the order the
    geometry matches them; each keeps the tie points
    :func:`~workers.core.geometry.pairs.match_pairs` would keep with ``seed``. A pair
    missing here (an image without tie points, matched by the packing) shifts those draws:
    the packing then finds no block's inputs among the results and adjusts them all."""
    positions = np.asarray(positions, np.float64)
    pairs = keep_some(list(verified), np.random.default_rng(seed))
    blocks = block_pairs(pairs, positions)
    if len(blocks) < 2:
        return 0
    folder = Path(folder)
    np.savez(folder / PLAN_FILE, positions=positions,
             altitudes=np.asarray(altitudes, np.float64),
             intrinsics=np.array([K0.f, K0.cx, K0.cy]))
    for b, inside in enumerate(blocks):
        save_results([(p.a, p.b, p) for p in inside], folder / INPUT.format(b))
    return len(blocks)


def adjust(folder: str | Path, block: int) -> int:
    """Adjust one planned block (:func:`plan`) and write its result beside it; returns the
    number of cameras it placed. A result already there for the same inputs (a failed
    build's, by :func:`~workers.core.geometry.reconstruct.block_key`) is kept."""
    folder = Path(folder)
    with np.load(folder / PLAN_FILE) as z:
        positions, altitudes = z["positions"], z["altitudes"]
        K0 = Intrinsics(*(float(v) for v in z["intrinsics"]))
    inside = [p for _, _, p in read_results(folder / INPUT.format(block))]
    key = block_key(inside, positions, altitudes, K0)
    out = folder / RESULT.format(block)
    if out.is_file():
        # a failed build's result for exactly these inputs, kept for its retry
        with np.load(out) as z:
            if str(z["key"]) == key:
                return len(z["cameras"]) if bool(z["placed"]) else 0
    # one BLAS thread, as the packing adjusts with (build_geometry)
    with threadpool_limits(limits=1, user_api="blas"):
        res = adjust_block(inside, positions, altitudes, K0)
    tmp = out.with_name("." + out.name)  # outside the results' glob until whole
    if res is None:
        np.savez(tmp, key=np.array(key), placed=np.array(False))
    else:
        np.savez(tmp, key=np.array(key), placed=np.array(True), cameras=res.cameras,
                 rotations=res.rotations, centres=res.centres,
                 figures=np.array([res.focal, res.ground_alt, res.residual_px, res.gps_rms]))
    tmp.replace(out)
    return 0 if res is None else len(res.cameras)


def load_results(folder: str | Path) -> dict[str, BlockResult | None]:
    """Every block adjusted into ``folder`` (:func:`adjust`), by its inputs' key; None for a
    block that placed no camera."""
    out: dict[str, BlockResult | None] = {}
    for path in sorted(Path(folder).glob(RESULTS_GLOB)):
        with np.load(path) as z:
            key = str(z["key"])
            if not bool(z["placed"]):
                out[key] = None
                continue
            f, ground, residual, gps = (float(v) for v in z["figures"])
            out[key] = BlockResult(z["cameras"], z["rotations"], z["centres"], f, ground,
                                   residual, gps)
    return out
