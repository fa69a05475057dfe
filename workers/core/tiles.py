"""The tiles of a large map's reconstruction, reconstructed in parallel ahead of the packing.

A map of more than :data:`~workers.core.geometry.tiling.MAX_TILE` images is reconstructed in
overlapping spatial tiles (:func:`~workers.core.geometry.tiling.plan_tiles`), each by COLMAP
on its own and aligned to its own GPS. Once the tie points' pairs are matched
(:mod:`.tiepairs`), a build writes each tile's pairs and what the tiles share to disk
(:func:`plan`), lets the engine's workers reconstruct the tiles (:func:`reconstruct`, one
file of results per tile, the tie points read from disk; each tile grows from the model kept
from the map's last build where one fits, :mod:`.geometry.kept`) and hands them to the packing
(:func:`load_results`), which reconstructs only tiles whose inputs it does not find among
them (:func:`~workers.core.geometry.tiling.tile_key`): the map comes out the same as when one
process reconstructs every tile.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .geometry import tiling
from .geometry.kept import KeptModels
from .geometry.models import TileModel, tags
from .geometry.pairs import PairMatches
from .geometry.tiling import tile_key, tile_models, tile_pairs
from .tiepairs import read_results, save_results
from .tiepoints import load_tie_points

PLAN_FILE = "tiles-plan.npz"
MODELS = "models"
"""The folder beside the plan where COLMAP's models are kept from build to build
(:mod:`.geometry.kept`); an image is named there by its tie points' file (its image id)."""
INPUT = "tile-{:05d}-pairs.npz"
RESULT = "tile-{:05d}.npz"
RESULTS_GLOB = "tile-?????.npz"


def plan(folder: str | Path, verified: list[PairMatches], positions: np.ndarray,
         altitudes: np.ndarray, focal_px: float | None, stems: list[str], *,
         times: np.ndarray | None = None, seed: int = 0) -> int:
    """Write what each tile's reconstruction needs into ``folder``; returns the number of
    tiles (0 for a map reconstructed whole, which the packing does itself).

    ``verified`` are the map's verified pairs (map indices), ``stems[i]`` where image
    ``i``'s tie points were written (:func:`~workers.core.tiepoints.save_tie_points`),
    ``times`` the capture times (s, NaN unknown)."""
    positions = np.asarray(positions, np.float64)
    folder = Path(folder)
    # cut where the map's last build cut it, as the packing will (tiling.reconstruct)
    kept = KeptModels(folder / MODELS, tuple(Path(s).name for s in stems))
    plan = tiling.map_tiles(positions, kept)
    tiles = [t.members for t in plan]
    _forget_tiles_from(folder, len(tiles) if len(tiles) > 1 else 0)
    if len(tiles) < 2:
        return 0
    np.savez(folder / PLAN_FILE, tags=tags(positions, altitudes, times),
             focal=np.array(np.nan if focal_px is None else float(focal_px)),
             seed=np.array(int(seed)), stems=np.array(stems, dtype=str),
             tiles=np.concatenate(tiles),
             offsets=np.concatenate([[0], np.cumsum([len(t) for t in tiles])]),
             cores=np.concatenate([t.core for t in plan]),
             core_offsets=np.concatenate([[0], np.cumsum([len(t.core) for t in plan])]))
    for k, inside in enumerate(tiles):
        save_results([(p.a, p.b, p) for p in tile_pairs(verified, inside)],
                     folder / INPUT.format(k))
    return len(tiles)


def _forget_tiles_from(folder: Path, n: int) -> None:
    """Delete the inputs and results in ``folder`` of tiles ``n`` and above: an earlier
    build's, of a plan with more tiles. (A tile below ``n`` whose inputs changed is
    reconstructed again over its result: :func:`reconstruct`.)"""
    for path in [*folder.glob(RESULTS_GLOB), *folder.glob(INPUT.replace("{:05d}", "?????"))]:
        if int(path.name[5:10]) >= n:
            path.unlink(missing_ok=True)


def reconstruct(folder: str | Path, tile: int) -> int:
    """Reconstruct one planned tile (:func:`plan`) and write its models beside it; returns
    the number of cameras it placed. A result already there for the same inputs (a failed
    build's, by :func:`~workers.core.geometry.tiling.tile_key`) is kept."""
    folder = Path(folder)
    with np.load(folder / PLAN_FILE) as z:
        gps = z["tags"]
        focal = float(z["focal"])
        seed, stems = int(z["seed"]), [str(s) for s in z["stems"]]
        inside = z["tiles"][z["offsets"][tile]:z["offsets"][tile + 1]]
        # a plan written before tiles carried their cores: every image judges the growth
        core = z["cores"][z["core_offsets"][tile]:z["core_offsets"][tile + 1]] \
            if "cores" in z.files else None
    focal_px = None if not np.isfinite(focal) else focal
    pairs = [p for _, _, p in read_results(folder / INPUT.format(tile)) if p is not None]
    key = tile_key(inside, pairs, gps, focal_px, seed)
    out = folder / RESULT.format(tile)
    if out.is_file():
        found = _read(out)
        if found is not None and found[0] == key:
            return sum(len(m.images) for m in found[1] or [])
    # one BLAS thread, as the packing reconstructs with (build_geometry)
    kept = KeptModels(folder / MODELS, tuple(Path(s).name for s in stems))
    with threadpool_limits(limits=1, user_api="blas"):
        models = tile_models(_TiePoints(stems), pairs, gps, focal_px, inside, seed=seed,
                             key=key, kept=kept, core=core)
    _write(out, key, models)
    return sum(len(m.images) for m in models or [])


def load_results(folder: str | Path) -> dict[str, list[TileModel] | None]:
    """Every tile reconstructed into ``folder`` (:func:`reconstruct`), by its inputs' key;
    None for a tile that placed no camera."""
    out: dict[str, list[TileModel] | None] = {}
    for path in sorted(Path(folder).glob(RESULTS_GLOB)):
        found = _read(path)
        if found is not None:
            out[found[0]] = found[1]
    return out


class _TiePoints(Sequence):
    """Each image's tie-point keypoints, read from disk when indexed."""

    def __init__(self, stems: list[str]) -> None:
        self._stems = stems

    def __len__(self) -> int:
        return len(self._stems)

    def __getitem__(self, i: int) -> np.ndarray:
        tie = load_tie_points(self._stems[i])
        if tie is None:
            raise FileNotFoundError(f"tie points of map image {i} missing at {self._stems[i]}")
        return tie.keypoints


def _write(out: Path, key: str, models: list[TileModel] | None) -> None:
    arrays: dict[str, np.ndarray] = {"key": np.array(key), "models": np.array(
        0 if models is None else len(models))}
    for j, m in enumerate(models or []):
        arrays |= {
            f"m{j}_images": m.images, f"m{j}_rotations": m.rotations,
            f"m{j}_centres": m.centres, f"m{j}_camera": m.camera,
            f"m{j}_residual": np.array(m.residual_px),
            f"m{j}_counts": np.array([len(o) for o in m.observations], np.int64),
            f"m{j}_observations": (np.concatenate(m.observations) if m.observations
                                   else np.zeros(0, np.int64)),
            f"m{j}_points": (np.concatenate(m.points) if m.points else np.zeros((0, 3))),
        }
    tmp = out.with_name("." + out.name)  # outside the results' glob until whole
    np.savez(tmp, **arrays)
    tmp.replace(out)


def _read(path: Path) -> tuple[str, list[TileModel] | None] | None:
    with np.load(path) as z:
        if "key" not in z.files:
            return None
        key, n = str(z["key"]), int(z["models"])
        models = []
        for j in range(n):
            ends = np.concatenate([[0], np.cumsum(z[f"m{j}_counts"])])
            obs, pts = z[f"m{j}_observations"], z[f"m{j}_points"]
            models.append(TileModel(
                z[f"m{j}_images"], z[f"m{j}_rotations"], z[f"m{j}_centres"],
                [obs[a:b] for a, b in zip(ends[:-1], ends[1:], strict=True)],
                [pts[a:b] for a, b in zip(ends[:-1], ends[1:], strict=True)],
                z[f"m{j}_camera"], float(z[f"m{j}_residual"])))
    return key, (models or None)
