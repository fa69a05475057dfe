"""A large synthetic UAV survey for ``bench_large_map.py``, generated tile by tile.

One world of the generator keeps its whole ground texture in memory (about 3.5 GB for a
1,000-frame survey at 40 m), so a survey of tens of thousands of frames is laid out as a
grid of tiles: each tile is a world of its own (its own seed and scene) whose local frame
is moved to its place in the grid through the geographic origin it is written with. The
tiles' lawnmower surveys sit side by side, one lane spacing apart, and together cover a few
square kilometres. Tile 0 is flown a second time under another light: the query pass.

A tile is finished when its ``world.json`` exists, so an interrupted generation resumes
at the first unfinished tile.

Usage (normally through ``bench_large_map.py``)::

    .venv/bin/python bench/large_map_world.py WORK_DIR [--images 50000]
"""

from __future__ import annotations

from _common import one_thread, repo_on_path

one_thread()

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

repo_on_path()

from vloc.clients.world import DEFAULT_ORIGIN, generate_world, uav  # noqa: E402
from vloc.workers.core.geo import GeoOrigin  # noqa: E402

TILE_FRAMES = 1000
"""Frames per tile: the largest survey whose world fits comfortably in memory."""
ALTITUDE_M = 40.0
SPACING_M = 6.0
"""Mean metres between frames: 6 m/s at one frame per second, 87 % forward overlap at 40 m."""
MAP_PASS = "sunny"
QUERY_PASS = "cloudy"


@dataclass(frozen=True)
class Layout:
    """Where the tiles of a survey of ``images`` frames lie.

    Attributes
    ----------
    images : int
        Map frames wanted; the last tile may hold more than needed.
    tile_frames : int
    columns, rows : int
        The tile grid, filled row by row from the south-west.
    pitch : (float, float)
        Metres between tile centres, east and north.
    """

    images: int
    tile_frames: int
    columns: int
    rows: int
    pitch: tuple[float, float]

    @property
    def tiles(self) -> int:
        return math.ceil(self.images / self.tile_frames)

    def offset(self, tile: int) -> tuple[float, float]:
        """(east, north) metres of tile ``tile``'s centre from the survey's origin."""
        col, row = tile % self.columns, tile // self.columns
        return ((col - (self.columns - 1) / 2) * self.pitch[0],
                (row - (self.rows - 1) / 2) * self.pitch[1])

    def origin(self, tile: int) -> GeoOrigin:
        lat, lon = (float(v) for v in DEFAULT_ORIGIN.to_wgs84(*self.offset(tile)))
        return GeoOrigin(lat, lon, DEFAULT_ORIGIN.alt)

    @property
    def extent_m(self) -> tuple[float, float]:
        return self.columns * self.pitch[0], self.rows * self.pitch[1]


def layout_for(images: int, tile_frames: int = TILE_FRAMES) -> Layout:
    """A near-square grid of tiles for a survey of ``images`` frames."""
    frames = min(tile_frames, images)
    tiles = math.ceil(images / frames)
    route = uav.survey_route(frames * SPACING_M, ALTITUDE_M, uav.PITCH_DEG)
    lo, hi = route.points.min(axis=0), route.points.max(axis=0)
    lane = 0.6 * uav.footprint_width(ALTITUDE_M)
    pitch = (float(hi[0] - lo[0] + lane), float(hi[1] - lo[1] + lane))
    columns = max(1, round(math.sqrt(tiles * pitch[1] / pitch[0])))
    return Layout(images, frames, columns, math.ceil(tiles / columns), pitch)


def tile_dir(work: Path, tile: int) -> Path:
    return work / "world" / f"tile_{tile:03d}"


def generate(work: Path, layout: Layout, *, seed: int = 0, log=print) -> float:
    """Generate every unfinished tile; returns the seconds spent."""
    spent = 0.0
    for tile in range(layout.tiles):
        if tile_done(work, tile):
            continue
        t0 = time.perf_counter()
        generate_tile(work, layout, tile, seed=seed)
        spent += time.perf_counter() - t0
        log(f"tile {tile + 1}/{layout.tiles} generated in {time.perf_counter() - t0:.0f} s")
    return spent


def generate_tile(work: Path, layout: Layout, tile: int, *, seed: int = 0) -> None:
    """Generate tile ``tile`` (its world seeded ``seed + tile``), whatever is there."""
    passes = [MAP_PASS, QUERY_PASS] if tile == 0 else [MAP_PASS]
    generate_world(tile_dir(work, tile), kind="uav", seed=seed + tile, passes=passes,
                   frames=layout.tile_frames, route_length=layout.tile_frames * SPACING_M,
                   altitude=ALTITUDE_M, origin=layout.origin(tile), overwrite=True)


def tile_done(work: Path, tile: int) -> bool:
    return (tile_dir(work, tile) / "world.json").is_file()


def map_images(work: Path, tile: int) -> list[Path]:
    """The map pass's image files of one finished tile, in flight order."""
    folder = tile_dir(work, tile)
    with (folder / "ground_truth.csv").open(newline="", encoding="utf-8") as f:
        return [folder / "images" / r["filename"] for r in csv.DictReader(f) if r["pass"] == "1"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="work directory (the world goes in world/)")
    parser.add_argument("--images", type=int, default=50_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    import cv2

    cv2.setNumThreads(1)
    layout = layout_for(args.images)
    print(f"{layout.tiles} tiles of {layout.tile_frames} frames, {layout.columns} x "
          f"{layout.rows} grid, {layout.extent_m[0]:.0f} x {layout.extent_m[1]:.0f} m", flush=True)
    generate(args.work, layout, seed=args.seed, log=lambda s: print(s, flush=True))


if __name__ == "__main__":
    main()
