"""Checks on packed maps that tests of the core and of the service share."""

from __future__ import annotations

import numpy as np

from vloc.workers.core.features import DESCRIPTOR_NAMES
from vloc.workers.core.mapdata import MapData


def assert_same_places(packed: MapData, fresh: MapData) -> None:
    """``packed`` holds the place vocabularies, descriptors, vocabulary fits and SIFT masks
    of ``fresh``, a fresh packing of the same images, bit for bit."""
    np.testing.assert_array_equal(packed.sift_keep, fresh.sift_keep)
    for name in DESCRIPTOR_NAMES:
        np.testing.assert_array_equal(packed.vocabularies[name].centroids,
                                      fresh.vocabularies[name].centroids)
        np.testing.assert_array_equal(packed.global_features[name],
                                      fresh.global_features[name])
        np.testing.assert_array_equal(packed.vocabulary_fits[name].images,
                                      fresh.vocabulary_fits[name].images)
