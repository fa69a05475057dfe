"""The reconstruction's tie-point pairs, matched in parallel ahead of the packing.

Matching the tie points of neighbouring map images (ratio test over three thousand SIFT
each, then COLMAP's two-view geometry; :func:`~workers.core.geometry.match_pair`) is much of
a map's geometry. The pairs are independent, and each one's RANSAC is seeded by its indices
alone, so a build plans them (:func:`plan`), lets the engine's workers match batches of them
from the tie points on disk (:func:`match_batch`, one file of results per batch) and hands
the results to the packing (:func:`load_results`), which matches only what is missing. The
map comes out the same as when one process matches every pair.

Results name the images they matched, so they outlive the build: a map keeps its tie points
and matched pairs, and a later build takes up every pair whose two images are both still in
the map (:func:`keep_valid`), at their places in the map's order now. Images added to a map
come after the others, so rebuilding it matches only the pairs the new images take part in;
deleting an image moves the images after it up the order, and their pairs are taken up
where they are now. Each result remembers the places its RANSAC was seeded at: a pair that
moved holds the matches a fresh build's seeding might not give, and a full rebuild
(:func:`forget_moved`) matches such pairs again, so that its map is a fresh build's.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from .geo import local_frame
from .geometry import PairMatches, match_pair, tie_pairs
from .tiepoints import load_tie_points

RESULTS_GLOB = "pairs-*.npz"
KEPT = "pairs-kept.npz"
"""The results earlier builds matched that still hold, gathered into one file."""
FORMAT = 4
"""Version of the results files, raised whenever what a pair's matching gives changes:
3 named the images (ids) and held keypoint indices and two-view configurations, matched
with :data:`~workers.core.geometry.pairs.TIE_RANSAC_TRIALS`; 4 the same, each pair's RANSAC
capped by the inlier ratio it could verify with (:func:`~workers.core.geometry.pairs.
ransac_floor`). Results of another version are matched again."""


def plan(lats, lons, alts, times=None, flights=None, *, kept=None) -> list[tuple[int, int]]:
    """The pairs (indices in map order) whose tie points the map's geometry matches: those
    :func:`~workers.core.mapbuild.assemble_map` would match for images at these positions,
    taken at these times (s, NaN unknown; None: none known) in these flights (names, None
    where not said), at the reach the map's store ``kept`` keeps where given
    (:class:`~workers.core.geometry.kept.KeptModels`)."""
    _, xy, _ = local_frame(lats, lons, alts)
    return tie_pairs(xy, None if times is None else np.asarray(times, np.float64), flights,
                     kept=kept)


def keep_valid(folder: str | Path, image_ids: list[int]) -> set[tuple[int, int]]:
    """Gather the results in ``folder`` that hold for a map whose images are ``image_ids``
    (in map order) into one file, delete the rest, and return the pairs they cover.

    A stored pair holds while both images it matched are in the map: it is taken up at
    their places now (a pair's matches index the images' own keypoints, which do not move),
    remembering the places it was seeded at (:func:`forget_moved`). Results of another
    format, and pairs of an image no longer in the map, go."""
    folder = Path(folder)
    where = {image_id: k for k, image_id in enumerate(image_ids)}
    files = sorted(folder.glob(RESULTS_GLOB))
    held: list[tuple[int, int, PairMatches | None, tuple[int, int]]] = []
    changed = False
    for path in files:
        found = _read(path)
        changed |= found is None                    # a file of another format
        for a, b, p, ids, seeded in found or []:
            placed = _place(ids, where)
            if placed is None:
                changed = True
                continue
            changed |= placed != (a, b)
            held.append((*placed, _at(p, placed), seeded))
    if changed or len(files) > 1 or (files and files[0].name != KEPT):
        held.sort(key=lambda r: (r[0], r[1]))
        save_results([r[:3] for r in held], folder / KEPT, image_ids=image_ids,
                     seeded=[r[3] for r in held])
        for path in files:
            if path.name != KEPT:
                path.unlink()
    return {(a, b) for a, b, _, _ in held}


def forget_moved(folder: str | Path) -> int:
    """Delete the results in ``folder`` of pairs that moved in the map's order since they
    were matched (:func:`keep_valid`), so that the next build matches them again, seeded
    where they are: a full rebuild's map is then a fresh build's. Returns how many went."""
    gone = 0
    for path in sorted(Path(folder).glob(RESULTS_GLOB)):
        found = _read(path)
        if found is None:
            continue
        stay = [r for r in found if (r[0], r[1]) == r[4]]
        if len(stay) < len(found):
            gone += len(found) - len(stay)
            # the ids the kept rows name, by their places (every results file names them)
            ids = {i: image_id for a, b, _, named, _ in stay if named is not None
                   for i, image_id in zip((a, b), named, strict=True)}
            save_results([r[:3] for r in stay], path, seeded=[r[4] for r in stay],
                         image_ids=ids if all(r[3] is not None for r in stay) else None)
    return gone


def _place(ids: tuple[int, int] | None, where: dict[int, int]) -> tuple[int, int] | None:
    """Where a stored pair of images ``ids`` is in the map now (``where``: image id -> map
    index); None where it named no images or one has left the map."""
    if ids is None or ids[0] not in where or ids[1] not in where:
        return None
    a, b = where[ids[0]], where[ids[1]]
    return (a, b) if a < b else None


def _at(p: PairMatches | None, placed: tuple[int, int]) -> PairMatches | None:
    """A stored pair's matches at the images' places now."""
    return None if p is None else PairMatches(placed[0], placed[1], p.matches, p.config)


def match_batch(stems: dict[int, str], pairs: list[tuple[int, int]], out: str | Path, *,
                image_ids: dict[int, int] | list[int], seed: int = 0) -> int:
    """Match ``pairs`` of map images from their tie points and write the results to ``out``
    (:func:`save_results`).

    ``stems[i]`` is where image ``i``'s tie points were written
    (:func:`~workers.core.tiepoints.save_tie_points`) and ``image_ids[i]`` the image's id; a
    pair with an image whose tie points are missing is left out, for the packing to match
    from the image's stored SIFT. Returns the number of pairs that verified.

    While a pair is being matched, a file beside ``out`` names it
    (:func:`crashed_pair`): COLMAP can bring the whole process down on a pair's matches
    (a segmentation fault in its two-view solvers), and the file then says which pair did.
    """
    cache: dict[int, object] = {}

    def ties(i: int):
        if i not in cache:
            cache[i] = load_tie_points(stems[i])
        return cache[i]

    marker = _marker(out)
    done: list[tuple[int, int, PairMatches | None]] = []
    for a, b in pairs:
        ta, tb = ties(a), ties(b)
        if ta is None or tb is None:
            continue
        marker.write_text(f"{image_ids[a]} {image_ids[b]}")
        done.append((a, b, match_pair(a, b, ta.keypoints, ta.descriptors, tb.keypoints,
                                      tb.descriptors, seed=seed)))
    save_results(done, out, image_ids=image_ids)
    marker.unlink(missing_ok=True)
    return sum(p is not None for _, _, p in done)


def crashed_pair(out: str | Path) -> tuple[int, int] | None:
    """The image ids of the pair :func:`match_batch` was matching into ``out`` when its
    process ended before finishing the batch (None where it finished, or never began one);
    the record is removed as it is read."""
    marker = _marker(out)
    try:
        a, b = (int(v) for v in marker.read_text().split())
    except (OSError, ValueError):
        return None
    marker.unlink(missing_ok=True)
    return a, b


def _marker(out: str | Path) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".matching")


def save_results(done: list[tuple[int, int, PairMatches | None]], out: str | Path, *,
                 image_ids: dict[int, int] | list[int] | None = None,
                 seeded: list[tuple[int, int]] | None = None) -> None:
    """Matched pairs as one ``.npz``: each pair tried, whether it verified, and the matched
    keypoint indices and two-view configuration of those that did; with ``image_ids``
    (index -> id), the ids of the images each pair matched; with ``seeded``, the places
    each pair was matched (and its RANSAC seeded) at, where not the ones it has now. Written
    under a temporary name and renamed, so a file under ``out`` is always whole."""
    ok = [p for _, _, p in done if p is not None]
    arrays = {
        "format": np.array(FORMAT),
        "a": np.array([a for a, _, _ in done], np.int64),
        "b": np.array([b for _, b, _ in done], np.int64),
        "verified": np.array([p is not None for _, _, p in done], bool),
        "counts": np.array([len(p) for p in ok], np.int64),
        "matches": (np.concatenate([p.matches for p in ok]) if ok
                    else np.zeros((0, 2), np.int64)).astype(np.int32),
        "configs": np.array([p.config for p in ok], np.int64),
    }
    if image_ids is not None:
        arrays["id_a"] = np.array([image_ids[a] for a, _, _ in done], np.int64)
        arrays["id_b"] = np.array([image_ids[b] for _, b, _ in done], np.int64)
    if seeded is not None:
        arrays["seed_a"] = np.array([a for a, _ in seeded], np.int64).reshape(-1)
        arrays["seed_b"] = np.array([b for _, b in seeded], np.int64).reshape(-1)
    out = Path(out)
    tmp = out.with_name("." + out.name)  # outside the results' glob until whole
    np.savez(tmp, **arrays)
    tmp.replace(out)


def load_results(folder: str | Path, image_ids: list[int],
                 ) -> dict[tuple[int, int], PairMatches | None]:
    """Every pair matched into ``folder`` (:func:`match_batch`) that holds for a map whose
    images are ``image_ids`` (:func:`keep_valid`): (a, b) -> its tie points, None where it
    did not verify."""
    where = {image_id: k for k, image_id in enumerate(image_ids)}
    out: dict[tuple[int, int], PairMatches | None] = {}
    for path in sorted(Path(folder).glob(RESULTS_GLOB)):
        for _, _, p, ids, _ in _read(path) or []:
            placed = _place(ids, where)
            if placed is not None:
                out[placed] = _at(p, placed)
    return out


def read_results(path: str | Path) -> list[tuple[int, int, PairMatches | None]]:
    """The pairs one file of :func:`save_results` holds, in its order; none from a file of
    another format."""
    return [(a, b, p) for a, b, p, _, _ in _read(path) or []]


_Row = tuple[int, int, PairMatches | None, tuple[int, int] | None, tuple[int, int]]
"""A stored pair: its places now, its matches (None: it did not verify), the ids of its
images (None in files that name none) and the places it was seeded at."""


def _read(path: str | Path) -> list[_Row] | None:
    """:func:`read_results` with each pair's image ids (None where the file names none) and
    the places it was seeded at; None for a file of another format, or one that is not a
    results file at all (its pairs are then matched again)."""
    try:
        with np.load(path) as z:
            if "format" not in z.files or int(z["format"]) != FORMAT:
                return None
            a, b, verified, counts = z["a"], z["b"], z["verified"], z["counts"]
            matches, configs = z["matches"].astype(np.int64), z["configs"]
            ids = list(zip(z["id_a"].tolist(), z["id_b"].tolist(), strict=True)) \
                if "id_a" in z.files else [None] * len(a)
            # results written before pairs moved with the map's order: seeded where they are
            seeded = list(zip(z["seed_a"].tolist(), z["seed_b"].tolist(), strict=True)) \
                if "seed_a" in z.files else list(zip(a.tolist(), b.tolist(), strict=True))
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
        return None
    ends = np.concatenate([[0], np.cumsum(counts)])
    out: list[_Row] = []
    k = 0
    for i, j, good, named, at in zip(a.tolist(), b.tolist(), verified.tolist(), ids, seeded,
                                     strict=True):
        if good:
            out.append((i, j, PairMatches(i, j, matches[ends[k]:ends[k + 1]],
                                          int(configs[k])), named, at))
            k += 1
        else:
            out.append((i, j, None, named, at))
    return out
