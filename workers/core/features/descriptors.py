"""Place descriptors: global vectors over a vocabulary trained on the map's own local features.

=================  ========  ========  ============================================  =====
name               local     encoding  vocabulary                                    dim
=================  ========  ========  ============================================  =====
``vlad_orb``       ORB       VLAD      64 principal components of the bits, 32       2048
                                       k-means words
``vlad_rootsift``  RootSIFT  VLAD      64 principal components, 64 k-means words     4096
``bow_orb``        ORB       BoW       k-majority tree, 8 x 8 x 8 x 8 = 4096 words   4096
``bow_rootsift``   RootSIFT  BoW       hierarchical k-means, 4096 words              4096
=================  ========  ========  ============================================  =====

Unlike the histogram features of :data:`~workers.core.features.GLOBAL_FEATURES`, a place
descriptor needs the map: its vocabulary is trained at map build on the local features of
the map images (:func:`train_descriptor_vocabulary`), stored with the map revision, and every
frame is described against it (:func:`describe`). Descriptors have unit L2 norm and are
compared by their dot product (:func:`workers.core.measures.descriptor_similarities`).

Why these vocabularies (seneca-uav, pass 2 against pass 1, recall@1 within 25 m, measured
while choosing them; the chosen ones' figures are in ``bench/results/place.md``): VLAD of ORB
around k-majority (binary) centres reached 0.34-0.52, around real-valued centres of the same
bit vectors 0.73-0.79, because the residual from a binary centre is itself a sparse bit
pattern that says little about the descriptor. Projecting the local vectors to 64 principal
components first (Jégou et al. 2012) keeps the recall (ORB: 0.75 at 2048 dimensions against
0.76 at 8192, means over five vocabulary seeds; RootSIFT: 0.80-0.82 at 4096 against 0.77 at
8192) and makes the map matrix two to four times smaller, and scoring a large map costs in
proportion to it. Bags of words need the finer partition a tree gives (4096 words: 0.73 for
ORB, against 0.61 with 256).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sift import SiftFeatures
from .bow import bow
from .orb import N_BITS, OrbFeatures, unpack_bits
from .rootsift import DIM as ROOTSIFT_DIM
from .rootsift import rootsift
from .vlad import vlad
from .vocabulary import Vocabulary, train_vocabulary

LOCAL_KINDS: tuple[str, ...] = ("orb", "rootsift")
"""Local features a place descriptor can be built on."""

_LOCAL_DIM = {"orb": N_BITS, "rootsift": ROOTSIFT_DIM}


@dataclass(frozen=True, slots=True)
class DescriptorSpec:
    """A registered place descriptor.

    Attributes
    ----------
    name : str
    local : {"orb", "rootsift"}
        The local feature it aggregates.
    encoding : {"vlad", "bow"}
    branching, depth : int
        Shape of the vocabulary tree (``branching ** depth`` words).
    binary : bool
        Train the vocabulary by k-majority on bits (ORB) rather than k-means.
    description : str
    components : int or None
        Project the local vectors to this many principal components before the vocabulary.
    """

    name: str
    local: str
    encoding: str
    branching: int
    depth: int
    binary: bool
    description: str
    components: int | None = None

    @property
    def n_words(self) -> int:
        return self.branching ** self.depth

    @property
    def dim(self) -> int:
        """Length of the descriptor vector."""
        if self.encoding == "vlad":
            return self.n_words * (self.components or _LOCAL_DIM[self.local])
        return self.n_words


DESCRIPTORS: dict[str, DescriptorSpec] = {
    s.name: s
    for s in (
        DescriptorSpec("vlad_orb", "orb", "vlad", 32, 1, False,
                       "VLAD of ORB bit vectors reduced to 64 principal components, 32 "
                       "k-means words, intra- and power-normalised", components=64),
        DescriptorSpec("vlad_rootsift", "rootsift", "vlad", 64, 1, False,
                       "VLAD of RootSIFT reduced to 64 principal components, 64 k-means "
                       "words, intra- and power-normalised", components=64),
        DescriptorSpec("bow_orb", "orb", "bow", 8, 4, True,
                       "tf-idf bag of ORB words, k-majority tree of 4096 words"),
        DescriptorSpec("bow_rootsift", "rootsift", "bow", 8, 4, False,
                       "tf-idf bag of RootSIFT words, k-means tree of 4096 words"),
    )
}
"""Registered place descriptors by name."""

DESCRIPTOR_NAMES: tuple[str, ...] = tuple(DESCRIPTORS)


def get_descriptor(name: str) -> DescriptorSpec:
    """Look up a place descriptor by name; ValueError listing the valid ones."""
    try:
        return DESCRIPTORS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown place descriptor {name!r}; valid names are "
                         f"{', '.join(DESCRIPTOR_NAMES)}") from None


def local_vectors(local: str, *, orb: OrbFeatures | None = None,
                  sift: SiftFeatures | None = None) -> np.ndarray:
    """The local feature vectors a descriptor aggregates.

    Parameters
    ----------
    local : {"orb", "rootsift"}
    orb : OrbFeatures, needed for ``"orb"``
    sift : SiftFeatures, needed for ``"rootsift"``

    Returns
    -------
    vectors : (K, 256) float32 0/1 bits for ORB, (K, 128) float32 RootSIFT
    """
    if local == "orb":
        if orb is None:
            raise ValueError("ORB features are needed for an ORB place descriptor")
        return unpack_bits(orb.descriptors)
    if local == "rootsift":
        if sift is None:
            raise ValueError("SIFT features are needed for a RootSIFT place descriptor")
        return rootsift(sift.descriptors)
    raise ValueError(f"unknown local feature {local!r}; valid: {', '.join(LOCAL_KINDS)}")


def train_descriptor_vocabulary(spec: DescriptorSpec, per_image: list[np.ndarray], *,
                                rng: np.random.Generator) -> Vocabulary:
    """Train the vocabulary of one descriptor on the map images' local vectors.

    Parameters
    ----------
    spec : DescriptorSpec
    per_image : list of (K_i, D) float32 ndarray
        :func:`local_vectors` of every map image.
    rng : numpy.random.Generator

    Returns
    -------
    Vocabulary
    """
    return train_vocabulary(per_image, branching=spec.branching, depth=spec.depth,
                            binary=spec.binary, rng=rng, components=spec.components)


def describe(spec: DescriptorSpec, vectors: np.ndarray, vocabulary: Vocabulary) -> np.ndarray:
    """One image's descriptor: ``(spec.dim,)`` float32, unit L2 norm (or all zeros).

    ``vectors`` are the image's :func:`local_vectors`; the vocabulary's projection, if any,
    is applied here.
    """
    word_dim = spec.components or _LOCAL_DIM[spec.local]
    if (vocabulary.n_words != spec.n_words or vocabulary.dim != _LOCAL_DIM[spec.local]
            or vocabulary.word_dim != word_dim):
        raise ValueError(f"vocabulary of {vocabulary.n_words} words of dimension "
                         f"{vocabulary.dim} -> {vocabulary.word_dim} does not fit {spec.name!r}")
    encode = vlad if spec.encoding == "vlad" else bow
    return encode(vocabulary.project(vectors), vocabulary)
