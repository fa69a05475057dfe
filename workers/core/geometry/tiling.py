"""A map's reconstruction cut into tiles: which images COLMAP reconstructs together.

A map of up to :data:`MAX_TILE` images is reconstructed whole. A larger one is halved along
its longer side until each part is small enough, each part widened by :data:`TILE_MARGIN`
image spacings so that neighbouring tiles share cameras (:func:`plan_tiles`: a map built
again is cut where it was, the images added joining the tiles around them); each tile is
reconstructed and aligned to its own GPS (:func:`tile_models`, COLMAP through
:func:`.sfm.reconstruct_images`), and each image takes its pose from the tile whose centre it
is nearest. Tiles are independent, so the service reconstructs them on the engine's workers
(:mod:`workers.core.tiles`) and the packing takes up each one whose inputs hash to the same
:func:`tile_key`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..timings import Timings, stage
from .kept import KeptModels
from .models import Structure, TileModel, structure_of, tags
from .pairs import PairMatches
from .sfm import reconstruct_images, settings_key

MAX_TILE: int = 400
"""A map of more images is reconstructed in overlapping spatial tiles of at most this many
(:func:`spatial_tiles`), each on its own GPS: an incremental reconstruction's time grows
faster than its images."""

TILE_MARGIN: float = 3.0
"""Tiles overlap by this many median image spacings on each side."""

GROWTH_SLACK: float = 1.25
"""A tile kept from the map's last build is cut again only once images added to it make its
core more than this many times :data:`MAX_TILE` (:func:`plan_tiles`): a map cut into full
tiles can grow without moving their edges."""

NEW_TILE_SHARE: float = 0.125
"""Images added to a kept tile whose core they grow past :data:`GROWTH_SLACK` times the
limit make a tile of their own where they are at least this share of the limit
(:func:`plan_tiles`): 100 images added beside a 420-image tile of a synthetic survey were
reconstructed in two halves of the grown core from scratch, 262 s of the update's tiles;
fewer are too few to reconstruct apart."""

MIN_GROUP: int = 3
"""Fewest images left out of every tile's models that are reconstructed on their own
(:func:`left_out_models`): the mapper's smallest model (:mod:`.sfm`), and the fewest a
model can be aligned to its GPS with."""


def reconstruct(keypoints: Sequence[np.ndarray], pairs: list[PairMatches],
                positions: np.ndarray, altitudes: np.ndarray, focal_px: float | None, *,
                seed: int = 0, times: np.ndarray | None = None,
                known_tiles: dict[str, list[TileModel] | None] | None = None,
                kept: KeptModels | None = None,
                timings: Timings | None = None) -> Structure | None:
    """The map's cameras and 3-D points from its tie points and verified pairs.

    A map of more than :data:`MAX_TILE` images is reconstructed tile by tile
    (:func:`plan_tiles`), each tile's models aligned to their own GPS, and each image
    takes its pose from the tile whose centre it is nearest.

    Parameters
    ----------
    keypoints : sequence of (K_i, >=2) float arrays, one per map image
        Tie points, pixels at the working resolution in the first two columns.
    pairs : list of PairMatches
        Verified matches, indices into ``keypoints``.
    positions : (N, 2) float ndarray
        GPS east/north of the images.
    altitudes : (N,) float ndarray
        GPS altitudes, NaN where unknown.
    focal_px : float or None
        EXIF focal length at the working resolution; None where unknown.
    seed : int
        Seeds COLMAP and the alignment's RANSAC: the same inputs give the same map.
    times : (N,) float ndarray, optional
        Capture times (s, NaN unknown): the GPS altitudes may drift in time
        (:func:`.align.align_to_gps`).
    known_tiles : dict, optional
        Tiles reconstructed elsewhere (:func:`tile_models`), by :func:`tile_key`; the
        others are reconstructed here.
    kept : KeptModels, optional
        The models and tiles kept from the map's last build (:mod:`.kept`): the map is cut
        where it was (:func:`plan_tiles`), and a tile whose inputs changed grows from a kept
        model where it can; afterwards the store holds this build's.
    timings : dict, optional
        Receives the seconds of the left-out images' models (:func:`left_out_models`) as
        ``"geometry: cameras: left-out models"`` (:mod:`..timings`).

    Returns
    -------
    Structure or None
        None where fewer than three cameras are placed consistently with their GPS.
    """
    positions = np.asarray(positions, np.float64)
    gps = tags(positions, altitudes, times)
    if len(pairs) == 0 or len(positions) < 3:
        return None
    plan = map_tiles(positions, kept)
    tiles = [t.members for t in plan]
    if kept is not None:
        kept.save_tiles((t.core, t.members) for t in plan)
    found: list[tuple[np.ndarray, TileModel]] = []
    keys = []
    for tile in plan:
        inside = tile.members
        key = tile_key(inside, pairs, gps, focal_px, seed)
        keys.append(key)
        if known_tiles is not None and key in known_tiles:
            models = known_tiles[key]
        else:
            models = tile_models(keypoints, pairs, gps, focal_px, inside, seed=seed, key=key,
                                 kept=kept, core=tile.core)
        found += [(inside, m) for m in models or []]
    if not found:
        if kept is not None:
            kept.keep_only(keys)
        return None
    placed = _by_centrality(found, positions) if len(tiles) > 1 else [m for _, m in found]
    with stage(timings, "geometry: cameras: left-out models"):
        placed += left_out_models(keypoints, pairs, gps, focal_px, placed, seed=seed,
                                  known_tiles=known_tiles, kept=kept, keys=keys)
    if kept is not None:
        kept.keep_only(keys)
    return structure_of(placed, len(positions), gps)


def left_out_models(keypoints: Sequence[np.ndarray], pairs: list[PairMatches],
                    gps: np.ndarray, focal_px: float | None, models: list[TileModel], *,
                    seed: int = 0,
                    known_tiles: dict[str, list[TileModel] | None] | None = None,
                    kept: KeptModels | None = None, keys: list[str] | None = None,
                    ) -> list[TileModel]:
    """Models of the tied images that none of ``models`` places, reconstructed again on
    their own, each aligned to its own GPS.

    Where a survey turns, its images are banked and see the ground obliquely: they tie
    strongly to one another and weakly to the level images around them, and the mapper
    either leaves them out or, from a handful of chance matches across the fields, attaches
    them far from where they are (seneca-uav's IMG_0451-0456, 30 to 200 m off, dropped by
    the alignment). Reconstructed apart from the rest, the five that tie to one another make
    a model of their own that lies within 2.5 m of their GPS, and the frames over that turn
    register instead of falling back on a position between map images.

    The images left out are reconstructed group by group (:func:`tied_groups`): each group
    of at least three that their pairs tie together is a reconstruction of its own, as
    COLMAP would model it, its inputs keyed apart (:func:`tile_key`). A large map leaves
    images out here and there across its tiles; an update that adds images in one corner
    then reconstructs the groups there and takes up the others' kept models, where one
    run over all of them would have to start again whenever any of them changed.
    ``keypoints``, ``pairs`` and ``gps`` (:func:`tags`) are the whole map's; ``known_tiles``
    and ``kept`` as in :func:`reconstruct`; the keys of the groups' inputs are added to
    ``keys``.
    """
    placed = np.zeros(len(gps), bool)
    for m in models:
        placed[m.images] = True
    # a group's pairs are among these: each group's key and reconstruction look through
    # them, not through every pair of the map
    inner = [p for p in pairs if not (placed[p.a] or placed[p.b])]
    found: list[TileModel] = []
    for group in tied_groups(inner, ~placed):
        key = tile_key(group, inner, gps, focal_px, seed)
        if keys is not None:
            keys.append(key)
        if known_tiles is not None and key in known_tiles:
            found += list(known_tiles[key] or [])
        else:
            found += tile_models(keypoints, inner, gps, focal_px, group, seed=seed, key=key,
                                 kept=kept) or []
    return found


def tied_groups(pairs: list[PairMatches], among: np.ndarray, *,
                least: int = MIN_GROUP) -> list[np.ndarray]:
    """The groups of images ``among`` (a boolean mask over the map) that their pairs with
    one another tie together (connected components of the pair graph), of at least
    ``least`` images each (map indices, ascending), ordered by their first image."""
    among = np.asarray(among, bool)
    inner = [(p.a, p.b) for p in pairs if among[p.a] and among[p.b]]
    if not inner:
        return []
    ends = np.array(inner, np.int64)
    n = len(among)
    graph = coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    tied = np.zeros(n, bool)
    tied[ends.ravel()] = True
    groups = [np.flatnonzero(tied & (label == k)) for k in np.unique(label[tied])]
    return sorted((g for g in groups if len(g) >= least), key=lambda g: int(g[0]))


def tile_pairs(pairs: list[PairMatches], inside: np.ndarray) -> list[PairMatches]:
    """The pairs with both images in the tile ``inside`` (map indices), by (a, b)."""
    member = set(np.asarray(inside).tolist())
    return sorted((p for p in pairs if p.a in member and p.b in member),
                  key=lambda p: (p.a, p.b))


def tile_key(inside: np.ndarray, pairs: list[PairMatches], gps: np.ndarray,
             focal_px: float | None, seed: int) -> str:
    """What a tile's reconstruction depends on, hashed: its images, their tags (:func:`tags`),
    their pairs (:func:`tile_pairs`), the focal length, the seed, and the mapper's settings
    and COLMAP's version (:func:`.sfm.settings_key`). A tile reconstructed elsewhere
    (:mod:`workers.core.tiles`) is taken up where its key is the one the packing finds."""
    inside = np.ascontiguousarray(inside, np.int64)
    h = hashlib.sha1()
    h.update(settings_key().encode())
    h.update(inside.tobytes())
    h.update(np.ascontiguousarray(gps[inside], np.float64).tobytes())
    h.update(repr((None if focal_px is None else float(focal_px), int(seed))).encode())
    for p in tile_pairs(pairs, inside):
        h.update(np.array([p.a, p.b, p.config], np.int64).tobytes())
        h.update(np.ascontiguousarray(p.matches, np.int64).tobytes())
    return h.hexdigest()


def tile_models(keypoints: Sequence[np.ndarray], pairs: list[PairMatches], gps: np.ndarray,
                focal_px: float | None, inside: np.ndarray, *, seed: int = 0,
                key: str | None = None, kept: KeptModels | None = None,
                core: np.ndarray | None = None) -> list[TileModel] | None:
    """COLMAP's models of the tile ``inside`` (map indices), aligned to their GPS; their
    images are map indices. ``keypoints`` and ``gps`` (:func:`tags`) are the whole map's,
    read by index. With ``kept`` (and the tile's ``key``, :func:`tile_key`), the tile grows
    from a model kept from an earlier build where one fits (:meth:`.KeptModels.base_for`)
    and its model is kept for the next; ``core`` (map indices, the images the tile was cut
    for) says which of its new images judge the growth (:func:`.sfm.reconstruct_images`)."""
    inside = np.asarray(inside, np.int64)
    index = np.full(len(gps), -1)
    index[inside] = np.arange(len(inside))
    sub = [PairMatches(int(index[p.a]), int(index[p.b]), p.matches, p.config)
           for p in tile_pairs(pairs, inside)]
    if not sub:
        return None
    grow = {}
    if kept is not None and key is not None:
        tied = len({p.a for p in sub} | {p.b for p in sub})
        context = repr((settings_key(), None if focal_px is None else float(focal_px),
                        int(seed)))
        grow = {"names": [kept.names[i] for i in inside.tolist()], "context": context,
                "base": kept.base_for(inside, tied, context), "keep": kept.entry(key),
                "core": None if core is None else np.isin(inside, core)}
    models = reconstruct_images(_Subset(keypoints, inside), sub, gps[inside], focal_px, seed,
                                **grow)
    for m in models or []:
        m.images = inside[m.images]
    return models


def spatial_tiles(positions: np.ndarray, max_size: int) -> list[np.ndarray]:
    """Overlapping tiles of at most about ``max_size`` map images each (indices, ascending):
    the images halved along the longer side of their extent until each part is small
    enough, each part then widened by :data:`TILE_MARGIN` median spacings."""
    return [t.members for t in plan_tiles(positions, max_size)]


@dataclass(frozen=True)
class Tile:
    """A tile of the map's reconstruction: its ``core`` (the images it was cut for) and its
    ``members`` (the core widened by :data:`TILE_MARGIN` spacings), map indices ascending."""

    core: np.ndarray
    members: np.ndarray


def plan_tiles(positions: np.ndarray, max_size: int, *,
               previous: list[Tile] | None = None) -> list[Tile]:
    """The map's tiles: without ``previous``, its images halved along the longer side of
    their extent until each part holds at most ``max_size``, each part then widened.

    ``previous`` are the tiles of the map's last build, in today's map indices (images
    since deleted left out): each keeps its core and members, an added image joins the core
    of its nearest kept image (and the members of every tile whose widened core holds it),
    and only a core grown past :data:`GROWTH_SLACK` times ``max_size`` is cut again: where
    the added images that joined it are at least :data:`NEW_TILE_SHARE` of ``max_size``,
    they make tiles of their own (of at most ``max_size``) beside it, which then stays as it
    was; otherwise it is halved (to at most ``max_size``). So a tile that no added image
    reached keeps its inputs, and one that some reached keeps every image it had: its kept
    COLMAP model can take them in (:mod:`.kept`)."""
    positions = np.asarray(positions, np.float64)
    n = len(positions)
    if n <= max_size:
        return [Tile(np.arange(n), np.arange(n))]
    spacing, _ = cKDTree(positions).query(positions, k=2)
    margin = TILE_MARGIN * float(np.median(spacing[:, 1]))
    # (core, members kept, whether added images join those members)
    cores: list[tuple[np.ndarray, np.ndarray | None, bool]] = []
    old = [t for t in previous or [] if len(t.core)]
    if old:
        owner = np.full(n, -1)
        for k, t in enumerate(old):
            owner[t.core] = k
        added = owner < 0
        new = np.flatnonzero(added)
        if len(new):
            placed = np.flatnonzero(owner >= 0)
            _, nearest = cKDTree(positions[placed]).query(positions[new])
            owner[new] = owner[placed[nearest]]
        for k, t in enumerate(old):
            core = np.flatnonzero(owner == k)
            joined = core[added[core]]
            if len(core) <= GROWTH_SLACK * max_size:
                cores.append((core, t.members, True))
            elif len(joined) >= NEW_TILE_SHARE * max_size:
                # the added images make tiles of their own beside the kept one, which
                # stays as it was (its kept model is taken up): halving the grown core
                # would leave no kept model whole in either half, and both would be
                # reconstructed from scratch
                cores.append((core[~added[core]], t.members, False))
                cores += [(part, None, True) for part in _halve(positions, joined, max_size)]
            else:
                cores += [(part, None, True) for part in _halve(positions, core, max_size)]
    else:
        cores = [(part, None, True) for part in _halve(positions, np.arange(n), max_size)]
    tiles = []
    for core, kept, grows in cores:
        lo, hi = positions[core].min(axis=0) - margin, positions[core].max(axis=0) + margin
        inside = np.all((positions >= lo) & (positions <= hi), axis=1)
        if kept is not None:
            # a kept tile takes in added images only: its edges stay where they were
            inside &= added & grows
            inside[kept] = True
        inside[core] = True
        tiles.append(Tile(np.sort(core), np.flatnonzero(inside)))
    if len(tiles) == 1:
        return tiles
    # a small map's widened tiles may hold one another: each is reconstructed once
    sets = [set(t.members.tolist()) for t in tiles]
    return [t for k, t in enumerate(tiles)
            if not any(sets[k] < sets[j] or (sets[k] == sets[j] and j < k)
                       for j in range(len(tiles)) if j != k)]


def map_tiles(positions: np.ndarray, kept: KeptModels | None) -> list[Tile]:
    """The map's tiles of at most :data:`MAX_TILE` images (:func:`plan_tiles`), cut where
    the last build whose tiles ``kept`` holds cut them."""
    previous = None if kept is None else kept.tiles()
    return plan_tiles(positions, MAX_TILE,
                      previous=None if previous is None else [Tile(*t) for t in previous])


def _halve(positions: np.ndarray, part: np.ndarray, max_size: int) -> list[np.ndarray]:
    """``part`` (map indices) halved along the longer side of its extent until each piece
    holds at most ``max_size``."""
    parts, done = [part], []
    while parts:
        part = parts.pop()
        if len(part) <= max_size:
            done.append(part)
            continue
        xy = positions[part]
        axis = int(np.argmax(np.ptp(xy, axis=0)))
        order = part[np.argsort(xy[:, axis], kind="stable")]
        parts += [order[:len(order) // 2], order[len(order) // 2:]]
    return done


class _Subset(Sequence):
    """``items[index[k]]`` as item ``k``: a tile's view of the map's tie points."""

    def __init__(self, items: Sequence, index: np.ndarray) -> None:
        self._items, self._index = items, index

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, k: int):
        return self._items[int(self._index[k])]


def _by_centrality(found: list[tuple[np.ndarray, TileModel]],
                   positions: np.ndarray) -> list[TileModel]:
    """The tiles' models with each image kept only in the tile whose centre it is nearest
    (the tile reconstructed most of what surrounds it)."""
    best: dict[int, tuple[float, int]] = {}
    for k, (inside, m) in enumerate(found):
        centre = positions[inside].mean(axis=0)
        for i in m.images.tolist():
            d = float(np.hypot(*(positions[i] - centre)))
            if i not in best or d < best[i][0]:
                best[i] = (d, k)
    out = []
    for k, (_, m) in enumerate(found):
        keep = np.array([best[i][1] == k for i in m.images.tolist()], bool)
        if keep.sum() == 0:
            continue
        out.append(TileModel(m.images[keep], m.rotations[keep], m.centres[keep],
                             [o for o, y in zip(m.observations, keep, strict=True) if y],
                             [p for p, y in zip(m.points, keep, strict=True) if y],
                             m.camera, m.residual_px))
    return out
