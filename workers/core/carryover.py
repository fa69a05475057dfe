"""A revision packed from the one before it: what an update of a map carries over.

A map that grows (images added, some deleted) is packed again as a new revision, its arrays
laid out afresh for the localisers. Most of what the packing works out for an image does not
change when images are added beside it or deleted elsewhere, and an update takes it from the
revision before (:class:`Previous`) instead of working it out again for every image:

* Its SIFT reduction mask (Weiss III: its keypoints that match one of its two GPS-nearest
  map images), where those are still its nearest: the mask a fresh build computes.
* The place descriptors' vocabularies, unless the images the map gained since they were
  trained measurably change them, and with them every kept image's descriptor row and
  shortlist code. How well a vocabulary fits the map is its distortion, the mean squared
  distance of each image's local vectors to their nodes a few dozen deep in its tree
  (:func:`~.features.distortion.image_distortion`), kept per image with the vocabulary
  (:class:`~.features.distortion.VocabularyFit`). A vocabulary is kept while the map's mean
  distortion stays within :data:`MAX_DISTORTION_RISE` of the trained images' mean and the
  images it was not trained on are at most :data:`MAX_UNTRAINED_SHARE` of the map's; past
  either, or where the revision before has no fit recorded, every vocabulary is trained
  again on every image, as a fresh build trains them.

A kept vocabulary is the one an earlier revision trained, so a map updated this way is not
the map a fresh build of the same images packs (its vocabularies, descriptors and codes
differ); a full rebuild is one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .features.distortion import VocabularyFit
from .features.shortlist import PlaceCodes
from .features.vocabulary import Vocabulary
from .mapdata import MapData
from .sift import reduction_neighbours

MAX_DISTORTION_RISE: float = 0.05
"""The most the map's mean distortion may rise (a fraction of the trained images') before
its vocabularies are trained again."""

MAX_UNTRAINED_SHARE: float = 0.2
"""The largest share of the map's images a kept vocabulary was not trained on. Past it (a
new flight of a fifth of the map, say) the vocabularies are trained again, however well
they fit: their words and their idf weights (counted over the trained images alone) then
miss too much of the map. On seneca-uav, pass 1 updated with the first half of pass 2 (41 %
of the map, another day) localised the second half 5.35 m off with pass 1's vocabularies
kept, 5.18 m with them trained again (the same cameras; `bench/results/update.md`)."""


@dataclass(frozen=True)
class Previous:
    """The revision an update packs from, and where each of the new revision's images lies
    in it.

    Attributes
    ----------
    data : MapData
        The revision before (memory-mapped is enough: rows are copied out of it).
    rows : (N,) int64 ndarray
        Each image of the new revision's row in ``data``; -1 for an image new to the map.
    """

    data: MapData
    rows: np.ndarray

    @classmethod
    def of(cls, data: MapData, before: Sequence, now: Sequence) -> Previous:
        """``data`` with the row of each of ``now`` (image identities, in the new
        revision's order) among ``before`` (``data``'s, in its order)."""
        if len(before) != len(data):
            raise ValueError(f"{len(before)} image identities for a revision of {len(data)}")
        at = {key: k for k, key in enumerate(before)}
        return cls(data, np.array([at.get(key, -1) for key in now], np.int64))

    @property
    def kept(self) -> np.ndarray:
        """Indices (in the new revision) of the images the revision before holds."""
        return np.flatnonzero(self.rows >= 0)

    @property
    def added(self) -> np.ndarray:
        """Indices (in the new revision) of the images new to the map."""
        return np.flatnonzero(self.rows < 0)


def known_masks(previous: Previous) -> dict[int, tuple[frozenset[int], np.ndarray]]:
    """The revision before's SIFT reduction masks by the new revision's image index, each
    with the images (new indices) it was matched against, for
    :func:`~.sift.reduction_masks`; an image whose neighbour there is not in the new
    revision (deleted) has none."""
    before = previous.data
    if before.sift_keep is None:
        return {}
    now = np.full(len(before), -1, np.int64)
    now[previous.rows[previous.kept]] = previous.kept
    offsets, keep = np.asarray(before.sift_offsets), before.sift_keep
    out = {}
    for row, near in enumerate(reduction_neighbours(np.asarray(before.positions))):
        i, mapped = int(now[row]), [int(now[j]) for j in near]
        if i >= 0 and min(mapped, default=0) >= 0:
            out[i] = frozenset(mapped), np.asarray(keep[offsets[row]:offsets[row + 1]])
    return out


def known_points(previous: Previous, kind: str, digests: np.ndarray, keypoints: np.ndarray,
                 offsets: np.ndarray) -> dict[int, np.ndarray]:
    """The revision before's 3-D points of local-feature set ``kind`` for each image (new
    index) whose structure digest (``digests``,
    :func:`~.geometry.mapgeometry.structure_digests`) and keypoints (``keypoints``, rows
    ``offsets[i]:offsets[i + 1]``) are the same there: worked out from the same inputs,
    they would come out the same (a tile no added image reached keeps its cameras and
    points to the bit). Nothing where that revision has no geometry, none of ``kind`` or
    no digests (packed before they were kept)."""
    before = previous.data
    geo = before.geometry
    if geo is None or geo.digests is None or kind not in geo.points:
        return {}
    old_kp, old_off = before.keypoint_set(kind)
    old_off, old_digests = np.asarray(old_off), np.asarray(geo.digests)
    out = {}
    for i in previous.kept:
        row = int(previous.rows[i])
        if not digests[i].any() or not np.array_equal(digests[i], old_digests[row]):
            continue
        a, b = int(offsets[i]), int(offsets[i + 1])
        c, d = int(old_off[row]), int(old_off[row + 1])
        if b - a == d - c and np.array_equal(keypoints[a:b], old_kp[c:d]):
            out[int(i)] = np.asarray(geo.points[kind][c:d], np.float32)
    return out


@dataclass(frozen=True)
class CarriedDescriptor:
    """A place descriptor taken up from the revision before: its vocabulary, fit and
    shortlist basis, and its rows for the kept images."""

    vocabulary: Vocabulary
    fit: VocabularyFit
    rows: np.ndarray
    """(N_kept, dim) float32, in the new revision's order of the kept images."""
    codes: PlaceCodes | None


def carried_descriptors(previous: Previous, names: Sequence[str],
                        ) -> dict[str, CarriedDescriptor] | None:
    """What the revision before holds of each place descriptor in ``names`` for the kept
    images, or None where it cannot be carried over: a descriptor or its fit missing (the
    revision was packed before fits were recorded, or without that descriptor), or the
    images its vocabulary was not trained on, the added ones with them, more than
    :data:`MAX_UNTRAINED_SHARE` of the new revision's."""
    before = previous.data
    rows = previous.rows[previous.kept]
    out = {}
    for name in names:
        vocab, fit = before.vocabularies.get(name), before.vocabulary_fits.get(name)
        if vocab is None or fit is None or name not in before.global_features:
            return None
        trained_on = (np.ones(len(rows), bool) if fit.trained_on is None
                      else np.asarray(fit.trained_on, bool)[rows])
        untrained = len(rows) - int(trained_on.sum()) + len(previous.added)
        if untrained > MAX_UNTRAINED_SHARE * len(previous.rows):
            return None
        codes = before.place_codes.get(name)
        out[name] = CarriedDescriptor(
            vocab, VocabularyFit(fit.trained, np.asarray(fit.images)[rows], fit.revision,
                                 trained_on),
            np.asarray(before.global_features[name])[rows],
            None if codes is None else PlaceCodes(np.asarray(codes.basis),
                                                  np.asarray(codes.codes)[rows]))
    return out


def still_fits(fit: VocabularyFit) -> bool:
    """Whether a vocabulary with this fit (its images now the new revision's) is kept."""
    return fit.rise() <= MAX_DISTORTION_RISE and fit.untrained_share() <= MAX_UNTRAINED_SHARE


def merge_rows(kept: np.ndarray, kept_rows: np.ndarray, added_rows: np.ndarray) -> np.ndarray:
    """The new revision's rows: ``kept_rows`` at the indices ``kept``, ``added_rows`` at
    the others, in order."""
    n = len(kept_rows) + len(added_rows)
    out = np.empty((n, *kept_rows.shape[1:]), np.result_type(kept_rows, added_rows))
    mask = np.zeros(n, bool)
    mask[kept] = True
    out[mask], out[~mask] = kept_rows, added_rows
    return out
