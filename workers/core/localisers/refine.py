"""Metric refinement: a frame's position from camera geometry, beyond the nearest map image.

Where the map has camera geometry (its structure from motion, see
:mod:`workers.core.geometry`), the frame's keypoints are matched to those of the few best
map images, each matched map keypoint sees a 3-D point, and a perspective-n-point solve
gives the frame's camera pose: a position in metres with its uncertainty, and the
camera's heading.

Where it has none (a map whose structure could not be recovered), the best verified map images vote for
the position with their match counts: a position between them rather than on one of them.
Where it has some but not where the frame is (an image the reconstruction left out, or one
whose keypoints it gave no 3-D points), a frame that overlaps that image beyond doubt is
placed at it the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..features.orb import OrbFeatures, hamming_ratio_matches
from ..geometry import Registration, register_against
from ..geometry.register import MIN_INLIERS
from ..mapdata import MapData
from ..sift import SiftFeatures, ratio_matches
from .scoring import verified_count

REFINE_RATIO: float = 0.8
"""Ratio test for the correspondences fed to the pose solver: its RANSAC removes outliers,
so the looser test of Lowe's paper keeps more true matches than the scoring's 0.7."""

ORB_REFINE_RATIO: float = 0.83
"""The ratio test for ORB's correspondences: Hamming distances between 256-bit descriptors
come in whole bits and crowd together, so a true match's second neighbour lies closer,
relative to the first, than with SIFT, and :data:`REFINE_RATIO` refuses more of the true
ones. On seneca-uav (pass 2 on pass 1, 5 starts) and lewis-uav (alternate split, 3 starts)
every ratio from 0.82 to 0.85 registered more global steps than 0.8 and gave both lower
errors (seneca hybrid mean 5.9-6.2 m against 6.4 m, SIFT on 25-26 % of steps against 32 %;
lewis 7.6-7.9 m against 8.2 m); from 0.87 the extra matches' outliers cost more than
they give."""

MIN_MATCHES: int = 8
"""A map image with fewer ratio-test matches adds nothing to the pose."""

ORB_FIRST_MATCHES: int = 30
"""A pose is started only from a map image that gives the frame at least this many ORB
ratio-test matches: the poses thinner matching gives are the ones 15-20 m off. On seneca-uav
(pass 2 on pass 1, 5 starts, one process, side by side) the hybrid's mean error fell from
6.3 to 5.6 m (median 3.6 to 3.2) against registering from any image; 45 gave 5.5 m with more
SIFT steps; 20 and 25 (with thin images passed over, below) 5.2-5.5 m. An image under it
is passed over for the next ranked one rather than ending the registration: on seneca-uav
the best-ranked image is often a look-alike 40-90 m off, or an image nearer the frame that
matches thinly, while the next one registers; SIFT steps fell from 31 % to 26 % of the
frames, the mean error 4.86 -> 4.94 m, lewis-uav unchanged."""

ORB_SURE_INLIERS: int = 40
"""A registration with this many inliers is the answer at once; a thinner one is kept while
the other images are tried, and the one with the most inliers is the answer. On seneca-uav
(pass 2 on pass 1, 5 starts) the ORB registrations with 15-25 inliers were the ones 10-18 m
off; those with 30 or more were within 11 m and mostly within 5. With the next images'
matches added, the frame registered from one image with 21 inliers at 15.8 m registers
with 34 at 6.4 m, the one with 17 at 10.0 m with 26 at 1.3 m. The hybrid's mean error fell
from 4.95 to 4.73 m (median 2.74 to 2.68 m), lewis-uav's stayed 5.51 m, the robot world's
fell from 0.51 to 0.43 m and the UAV worlds' moved by 0.1 m or less (flat 1.17 -> 1.09,
hills 1.09 -> 1.17, drifting altitude 1.12 -> 1.06), for 3-12 % more time a frame on
seneca-uav from the extra matching, in four side-by-side runs
(``bench/results/geometry.md``)."""

ORB_OVERLAP_INLIERS: int = 50
"""A global step that registers nowhere places the frame at a map image that cannot give it
a pose (the reconstruction left the image out, or gave fewer than
:data:`~workers.core.geometry.register.MIN_INLIERS` of the keypoints the frame matched a 3-D
point) where this many of their ORB ratio-test matches agree with one homography. Traced on
seneca-uav (pass 2 on pass 1, 5 starts) and lewis-uav (alternate split, 3 starts), the
frames over such images gave them 63 to 166 inliers at 1.5-6 m from the image; the
look-alikes 25-125 m off gave 10-25. Before, the step fell back on SIFT, whose registration
fails there too, so its fix was the same kind of position between images, for the SIFT
extraction's cost."""


@dataclass(frozen=True)
class Refinement:
    """A position measurement from local-feature geometry.

    Attributes
    ----------
    xy : (2,) float ndarray
        East/north (m).
    sigma : float
        Standard deviation per axis (m).
    kind : {"registered", "interpolated"}
        Camera-geometry pose, or a match-weighted position between map images.
    heading_deg, heading_sigma_deg : float or None
        Compass bearing of the image's top edge and its standard deviation, where the
        geometry gives them.
    inliers : int
    images : tuple of int
        Map images that contributed.
    """

    xy: np.ndarray
    sigma: float
    kind: str
    heading_deg: float | None = None
    heading_sigma_deg: float | None = None
    inliers: int = 0
    images: tuple[int, ...] = ()

    @classmethod
    def from_registration(cls, reg: Registration) -> Refinement:
        return cls(np.asarray(reg.xy, np.float64), float(reg.sigma), "registered",
                   float(reg.heading_deg), float(reg.heading_sigma_deg), int(reg.inliers),
                   reg.images)


def refine_sift(query: SiftFeatures, map_data: MapData, ranked: np.ndarray,
                scores: np.ndarray, *, frame_shape: tuple[int, int],
                max_images: int = 3) -> Refinement | None:
    """Refine with SIFT: register against the best-scored map images.

    Parameters
    ----------
    query : SiftFeatures
        The frame's (full) SIFT features.
    map_data : MapData
    ranked : (k,) int ndarray
        Map images, best first (e.g. by verified SIFT similarity).
    scores : (k,) float ndarray
        Their scores; images scoring zero are not used.
    frame_shape : (height, width)
    max_images : int
        Map images to match against.

    Returns
    -------
    Refinement or None
        Registered where the map's camera geometry gives a pose, else interpolated
        between the images; None when too few matches.
    """
    ranked, scores = _best(ranked, scores, max_images)
    if len(query) == 0 or len(ranked) == 0:
        return None
    q_desc = np.asarray(query.descriptors, dtype=np.float32)
    matches = _matches(ranked, np.asarray(map_data.sift_offsets),
                       lambda i: ratio_matches(q_desc, map_data.sift(i).descriptors,
                                               ratio=REFINE_RATIO))
    if not matches:
        return None
    if map_data.geometry is not None:
        reg = register_against(map_data.geometry, "sift", np.asarray(query.keypoints),
                               matches, frame_shape=frame_shape)
        if reg is not None:
            return Refinement.from_registration(reg)
    # no geometry, or none where the frame is (images the reconstruction left out, too
    # few 3-D points): a position between the images it matched
    return interpolate(map_data, ranked, scores)


def refine_orb(query: OrbFeatures, map_data: MapData, ranked: np.ndarray,
               scores: np.ndarray, *, frame_shape: tuple[int, int],
               max_images: int = 2, min_inliers: int = MIN_MATCHES) -> Refinement | None:
    """Refine with ORB: register against the 3-D points of the best-ranked map images.

    The cheap counterpart of :func:`refine_sift` for global steps: binary descriptors
    matched by Hamming distance, the same pose solver. Of the ranked images, those the
    reconstruction placed (the others have no 3-D points) are tried one at a time, best
    first, at most ``max_images`` of them: the pose starts from the first that gives at
    least :data:`ORB_FIRST_MATCHES` matches (an image thinner than that is passed over),
    each later image adds its matches, and the first registration with at least
    :data:`ORB_SURE_INLIERS` inliers is the answer, else the one with the most inliers of at
    least ``min_inliers``. The first usable image alone usually suffices, and matching is
    most of the cost.

    Where none registers with ``min_inliers``, the best ``max_images`` ranked images that
    cannot give the frame a pose are looked at (:func:`_overlap_fix`): the frame is placed
    at the first one it overlaps beyond doubt. Nothing weaker counts: a position between
    images the frame merely resembles is what the global similarities already say.

    Parameters are those of :func:`refine_sift`, with the frame's ORB features.
    """
    geometry = map_data.geometry
    if geometry is None or "orb" not in geometry.points or not map_data.has_orb:
        return None
    ranked = np.asarray(ranked, np.int64)
    scores = np.asarray(scores)
    if len(query) == 0:
        return None
    offsets = np.asarray(map_data.orb_offsets)
    found: dict[int, np.ndarray] = {}

    def matched(image: int) -> np.ndarray:
        """The frame's ratio-test matches into ``image``, each image matched once."""
        if image not in found:
            found[image] = hamming_ratio_matches(query.descriptors,
                                                 map_data.orb(image).descriptors,
                                                 ratio=ORB_REFINE_RATIO)
        return found[image]

    placed = geometry.reconstructed[ranked]
    tried, _ = _best(ranked[placed], scores[placed], max_images)
    matches: list[tuple[int, np.ndarray, np.ndarray]] = []
    reg = best = None
    for image in tried.tolist():
        more = _matches(np.array([image]), offsets, matched)
        if not matches and (not more or len(more[0][1]) < ORB_FIRST_MATCHES):
            continue  # too thin to start a pose from (ORB_FIRST_MATCHES)
        if not more:
            continue
        matches += more
        # no three-point rescue where a survey's similarity start finds no consensus: of
        # the 90 such ORB registrations of seneca-uav (87) and the relief world (3) none
        # gave a fix, at 4 ms each; the two frames it rescues on the relief world are
        # SIFT registrations, which keep it
        reg = register_against(geometry, "orb", np.asarray(query.keypoints), matches,
                               frame_shape=frame_shape, rescue=False)
        if reg is not None and reg.inliers >= min_inliers:
            if reg.inliers >= ORB_SURE_INLIERS:
                return Refinement.from_registration(reg)
            if best is None or reg.inliers > best.inliers:
                best = reg  # thin: the next image may register the frame better
    if best is not None:
        return Refinement.from_registration(best)
    overlap = _overlap_fix(query, map_data, _best(ranked, scores, max_images)[0], matched)
    if overlap is not None:
        return overlap
    return None if reg is None else Refinement.from_registration(reg)


def _overlap_fix(query: OrbFeatures, map_data: MapData, images: np.ndarray,
                 matched) -> Refinement | None:
    """The frame placed at the first of ``images`` that cannot give it a pose and that it
    overlaps beyond doubt (:data:`ORB_OVERLAP_INLIERS`), as :func:`interpolate` places it
    at one image; None where there is none.

    An image cannot give the frame a pose where the reconstruction left it out, or where
    fewer than :data:`~workers.core.geometry.register.MIN_INLIERS` of the keypoints the
    frame matched in it have 3-D points (the image's own tie points were few and no plane
    stood in for them). ``matched(image)`` gives the frame's ORB ratio-test matches."""
    geometry = map_data.geometry
    offsets = np.asarray(map_data.orb_offsets)
    for image in np.asarray(images, np.int64).tolist():
        m = matched(image)
        if len(m) < ORB_FIRST_MATCHES:
            continue
        if geometry.reconstructed[image]:
            points = np.asarray(geometry.points["orb"][m[:, 1] + int(offsets[image])])
            if int(np.isfinite(points).all(axis=1).sum()) >= MIN_INLIERS:
                continue  # it could give a pose, and gave none
        inliers = verified_count(query, map_data.orb(image), m, "homography")
        if inliers >= ORB_OVERLAP_INLIERS:
            placed = interpolate(map_data, np.array([image]), np.array([1.0]))
            return replace(placed, inliers=inliers)
    return None


def rank_cloud_images(nearest: np.ndarray, log: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map images under a particle cloud, by their share of the posterior.

    Each particle stands for the map image nearest it; an image's share is the sum of the
    likelihood of its particles (weights are uniform after resampling, so this is the
    posterior). The share weighs how many particles the motion put near an image as well as
    how similar the frame looks to it: on seneca-uav, ranking by similarity alone put an
    image ORB registers against first less often, and steps fell back on SIFT on 25 % of
    the frames instead of 20 %.

    Parameters
    ----------
    nearest : (m,) int ndarray
        Each particle's nearest map image.
    log : (m,) float ndarray
        Each particle's log-likelihood under the frame's measurement.

    Returns
    -------
    images : (k,) int ndarray
        The distinct images in ``nearest``, largest share first (ties: more particles
        first, then lower index).
    shares : (k,) float ndarray
        Their shares, summing to one; where no particle has a finite likelihood, the share
        of particles.
    """
    nearest = np.asarray(nearest, np.int64)
    log = np.asarray(log, np.float64)
    images, inverse, counts = np.unique(nearest, return_inverse=True, return_counts=True)
    top = np.max(log) if len(log) else -np.inf
    weights = np.exp(log - top) if np.isfinite(top) else np.ones(len(nearest))
    mass = np.bincount(inverse, weights=weights, minlength=len(images))
    order = np.lexsort((images, -counts, -mass))
    return images[order], mass[order] / mass.sum()


def _best(ranked: np.ndarray, scores: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``k`` ranked images that scored above zero, with their scores."""
    positive = np.asarray(scores) > 0
    return (np.asarray(ranked)[positive][:k],
            np.asarray(scores, np.float64)[positive][:k])


def _matches(images: np.ndarray, offsets: np.ndarray,
             match) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(image, frame rows, global map rows)`` for each image with enough matches."""
    out = []
    for i in images.tolist():
        m = match(int(i))
        if len(m) >= MIN_MATCHES:
            out.append((int(i), m[:, 0], m[:, 1] + int(offsets[int(i)])))
    return out


def interpolate(map_data: MapData, images: np.ndarray, scores: np.ndarray) -> Refinement | None:
    """A position between the best verified map images, weighted by their scores.

    The uncertainty is the weighted spread of the images about that position, floored at a
    third of the map's spacing: with one dominant image the frame is near it, not on it.
    """
    scores = np.asarray(scores, np.float64)
    ok = scores > 0
    if not ok.any():
        return None
    xy = np.asarray(map_data.positions)[np.asarray(images)[ok]]
    w = scores[ok] / scores[ok].sum()
    mean = w @ xy
    spread = math.sqrt(float(w @ np.sum((xy - mean) ** 2, axis=1)) / 2.0)
    sigma = max(spread, map_data.median_spacing() / 3.0)
    return Refinement(mean, sigma, "interpolated",
                      images=tuple(int(i) for i in np.asarray(images)[ok]))
