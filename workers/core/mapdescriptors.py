"""A map's place descriptors: their vocabularies trained on the map's images, or carried
over from its revision before while they still fit it, and every image described.

A descriptor's vocabulary needs every map image's local features at once
(:mod:`workers.core.features.descriptors`); a first build (and a full one) trains it, and
records how well it fits each image (:class:`~.features.distortion.VocabularyFit`), which
an update reads to keep it (:mod:`workers.core.carryover`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .carryover import CarriedDescriptor, Previous, carried_descriptors, merge_rows, still_fits
from .features.descriptors import (
    describe,
    get_descriptor,
    local_vectors,
    train_descriptor_vocabulary,
)
from .features.distortion import VocabularyFit, image_distortion
from .features.shortlist import PlaceCodes
from .features.vocabulary import Vocabulary


@dataclass(frozen=True, slots=True)
class TrainedDescriptor:
    """One place descriptor of a map: its vocabulary, how well that fits the map's
    images, their (N, dim) float32 descriptors, and what was carried over from the
    revision before (None where the vocabulary was trained)."""

    vocabulary: Vocabulary
    fit: VocabularyFit
    matrix: np.ndarray
    carried: CarriedDescriptor | None = None


def train_descriptors(features: list, names: tuple[str, ...], *,
                      seed: int = 0, revision: int = 0,
                      previous: Previous | None = None) -> dict[str, TrainedDescriptor]:
    """Train each place descriptor's vocabulary on the map images and describe them.

    Parameters
    ----------
    features : list of :class:`~.mapbuild.ImageFeatures`, one per map image
    names : tuple of str
        Place descriptors; those over ORB are skipped when an image has no ORB features.
    seed : int
        Each descriptor's vocabulary is trained with ``numpy.random.default_rng(seed)``.
    revision : int
        The revision being packed (a trained vocabulary's fit records it).
    previous : Previous, optional
        The revision before: its vocabularies are kept, with the kept images' descriptors,
        and only the added images described, while they still fit the map
        (:mod:`workers.core.carryover`).

    Returns
    -------
    dict name -> TrainedDescriptor
    """
    have_orb = all(f.orb is not None for f in features)
    wanted = tuple(n for n in names if have_orb or get_descriptor(n).local != "orb")
    if previous is not None:
        kept = _kept_descriptors(features, wanted, previous)
        if kept is not None:
            return kept
    vectors: dict[str, LocalVectors] = {}
    out = {}
    for name in wanted:
        spec = get_descriptor(name)
        if spec.local not in vectors:
            vectors[spec.local] = LocalVectors(features, spec.local)
        per_image = vectors[spec.local]
        vocab = train_descriptor_vocabulary(spec, per_image, rng=np.random.default_rng(seed))
        matrix, distortions = _describe(spec, vocab, per_image)
        out[name] = TrainedDescriptor(
            vocab, VocabularyFit(float(distortions.mean()), distortions, revision,
                                 np.ones(len(distortions), bool)), matrix)
    return out


def _describe(spec, vocabulary: Vocabulary, per_image) -> tuple[np.ndarray, np.ndarray]:
    """Each image's descriptor, (K, dim) float32, and its :func:`image_distortion`, (K,)
    float32, from one reading of its local vectors (ORB's are unpacked as they are read)."""
    rows, distortions = [], []
    for v in per_image:
        rows.append(describe(spec, v, vocabulary))
        distortions.append(image_distortion(vocabulary, v))
    matrix = np.stack(rows) if rows else np.zeros((0, spec.dim), np.float32)
    return matrix, np.array(distortions, np.float32)


def _kept_descriptors(features: list, names: tuple[str, ...],
                      previous: Previous) -> dict[str, TrainedDescriptor] | None:
    """The revision before's descriptors with the added images described against its
    vocabularies; None where one cannot be carried over or no longer fits the map."""
    carried = carried_descriptors(previous, names)
    if carried is None:
        return None
    added = [features[i] for i in previous.added]
    out = {}
    for name, c in carried.items():
        trained_on = merge_rows(previous.kept, c.fit.trained_on, np.zeros(len(added), bool))
        spec = get_descriptor(name)
        new, distortions = _describe(spec, c.vocabulary, LocalVectors(added, spec.local))
        fit = VocabularyFit(c.fit.trained, merge_rows(previous.kept, c.fit.images, distortions),
                            c.fit.revision, trained_on)
        if not still_fits(fit):
            return None
        out[name] = TrainedDescriptor(c.vocabulary, fit,
                                      merge_rows(previous.kept, c.rows, new), c)
    return out


class LocalVectors(Sequence):
    """The local vectors (:func:`~.features.descriptors.local_vectors`) of each map image,
    computed when read.

    Unpacked ORB bits are 256 float32 per keypoint, 400 kB an image: a large map's would
    not fit in memory at once, so training and describing read them image by image.
    """

    def __init__(self, features: list, local: str) -> None:
        self.features = features
        self.local = local

    def __len__(self) -> int:
        return len(self.features)

    def __getitem__(self, i: int) -> np.ndarray:
        f = self.features[i]
        return local_vectors(self.local, orb=f.orb, sift=f.sift)

    def counts(self) -> np.ndarray:
        """(N,) int: keypoints per image, without computing the vectors."""
        return np.array([len(f.orb) if self.local == "orb" else len(f.sift)
                         for f in self.features], np.int64)


def place_codes(trained: TrainedDescriptor, previous: Previous | None, *,
                seed: int = 0) -> PlaceCodes:
    """A descriptor's shortlist codes: the kept images' from the revision before with the
    added images' coded in its basis, where its vocabulary was carried over with codes;
    fitted afresh otherwise."""
    before = None if trained.carried is None else trained.carried.codes
    if before is None or previous is None:
        return PlaceCodes.fit(trained.matrix, seed=seed)
    added = np.asarray(trained.matrix[previous.added], np.float32) @ before.basis
    return PlaceCodes(before.basis, merge_rows(previous.kept, before.codes, added))
