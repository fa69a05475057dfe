"""The reconstruction's tie-point pairs, matched in parallel ahead of the packing.

Matching the tie points of neighbouring map images (ratio test over three thousand SIFT
each, then COLMAP's two-view geometry; :func:`~workers.core.geometry.match_pair`) is much of
a map's geometry: about 75 ms a pair on one core. The pairs are independent, and each
one's RANSAC is seeded by its indices alone, so a build plans them (:func:`plan`), lets the
engine's workers match batches of them from the tie points on disk (:func:`match_batch`,
one file of results per batch) and hands the results to the packing
(:func:`load_results`), which matches only what is missing. The map comes out the same as
when one process matches every pair.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .geometry import PairMatches, match_pair, tie_pairs
from .mapbuild import TiePointFiles, load_tie_points, local_frame

RESULTS_GLOB = "pairs-*.npz"
FORMAT = 2
"""Version of the results files: 2 holds keypoint indices and two-view configurations; a
failed build's results of another version are matched again."""
PLAN_FILE = "pairs-plan.npy"
"""The image ids, in map order, that the pairs' indices refer to."""


def plan(lats, lons, alts) -> list[tuple[int, int]]:
    """The pairs (indices in map order) whose tie points the map's geometry matches: those
    :func:`~workers.core.mapbuild.assemble_map` would match for images at these positions."""
    _, xy, _ = local_frame(lats, lons, alts)
    return tie_pairs(xy)


def save_plan(folder: str | Path, image_ids: list[int]) -> None:
    """Record which images the pairs matched into ``folder`` index (:func:`load_results`).

    Results a failed build left in ``folder`` stay for its retry when they index the same
    images; under another plan their indices name other images, and they are removed."""
    folder = Path(folder)
    if (folder / PLAN_FILE).is_file() and not _planned_for(folder, image_ids):
        for path in folder.glob(RESULTS_GLOB):
            path.unlink()
    np.save(folder / PLAN_FILE, np.asarray(image_ids, np.int64))


def _planned_for(folder: Path, image_ids: list[int]) -> bool:
    """Whether ``folder``'s plan indexes exactly ``image_ids``."""
    plan_file = folder / PLAN_FILE
    return plan_file.is_file() and np.array_equal(np.load(plan_file),
                                                  np.asarray(image_ids, np.int64))


def match_batch(stems: dict[int, str], pairs: list[tuple[int, int]], out: str | Path, *,
                seed: int = 0) -> int:
    """Match ``pairs`` of map images from their tie points and write the results to ``out``
    (:func:`save_results`).

    ``stems[i]`` is where image ``i``'s tie points were written
    (:func:`~workers.core.mapbuild.save_tie_points`); a pair with an image whose tie points
    are missing is left out, for the packing to match from the image's stored SIFT.
    Returns the number of pairs that verified. Results already in ``out`` for exactly these
    pairs (a failed build's, under the same plan: :func:`save_plan`) are kept as they are.
    """
    out = Path(out)
    if out.is_file():
        present = {i: TiePointFiles.find(stem) is not None for i, stem in stems.items()}
        kept = read_results(out)
        if [(a, b) for a, b, _ in kept] == [(a, b) for a, b in pairs if present[a] and present[b]]:
            return sum(p is not None for _, _, p in kept)
    cache: dict[int, object] = {}

    def ties(i: int):
        if i not in cache:
            cache[i] = load_tie_points(stems[i])
        return cache[i]

    done: list[tuple[int, int, PairMatches | None]] = []
    for a, b in pairs:
        ta, tb = ties(a), ties(b)
        if ta is None or tb is None:
            continue
        done.append((a, b, match_pair(a, b, ta.keypoints, ta.descriptors, tb.keypoints,
                                      tb.descriptors, seed=seed)))
    save_results(done, out)
    return sum(p is not None for _, _, p in done)


def save_results(done: list[tuple[int, int, PairMatches | None]], out: str | Path) -> None:
    """Matched pairs as one ``.npz``: each pair tried, whether it verified, and the matched
    keypoint indices and two-view configuration of those that did. Written under a
    temporary name and renamed, so a file under ``out`` is always whole."""
    ok = [p for _, _, p in done if p is not None]
    arrays = {
        "format": np.array(FORMAT),
        "a": np.array([a for a, _, _ in done], np.int64),
        "b": np.array([b for _, b, _ in done], np.int64),
        "verified": np.array([p is not None for _, _, p in done], bool),
        "counts": np.array([len(p) for p in ok], np.int64),
        "matches": (np.concatenate([p.matches for p in ok]) if ok
                    else np.zeros((0, 2), np.int64)),
        "configs": np.array([p.config for p in ok], np.int64),
    }
    out = Path(out)
    tmp = out.with_name("." + out.name)  # outside the results' glob until whole
    np.savez(tmp, **arrays)
    tmp.replace(out)


def load_results(folder: str | Path, image_ids: list[int],
                 ) -> dict[tuple[int, int], PairMatches | None]:
    """Every pair matched into ``folder`` (:func:`match_batch`): (a, b) -> its tie points,
    None where it did not verify. Empty when the plan was made for other images than
    ``image_ids`` (the map changed in between; the packing then matches every pair)."""
    out: dict[tuple[int, int], PairMatches | None] = {}
    if not _planned_for(Path(folder), image_ids):
        return out
    for path in sorted(Path(folder).glob(RESULTS_GLOB)):
        for a, b, p in read_results(path):
            out[(a, b)] = p
    return out


def read_results(path: str | Path) -> list[tuple[int, int, PairMatches | None]]:
    """The pairs one file of :func:`save_results` holds, in its order; none from a file of
    another format."""
    with np.load(path) as z:
        if "format" not in z.files or int(z["format"]) != FORMAT:
            return []
        a, b, verified, counts = z["a"], z["b"], z["verified"], z["counts"]
        matches, configs = z["matches"], z["configs"]
    ends = np.concatenate([[0], np.cumsum(counts)])
    out: list[tuple[int, int, PairMatches | None]] = []
    k = 0
    for i, j, good in zip(a.tolist(), b.tolist(), verified.tolist(), strict=True):
        if good:
            out.append((i, j, PairMatches(i, j, matches[ends[k]:ends[k + 1]],
                                          int(configs[k]))))
            k += 1
        else:
            out.append((i, j, None))
    return out
