"""Frame registration by 3-D PnP, on exact synthetic correspondences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.core.geometry.scene import (
    GROUND_ALT,
    HEIGHT,
    K_TRUE,
    WIDTH,
    level_rotation,
    tilt_deg,
    tilted_rotation,
)
from vloc.workers.core.geometry.camera import compass_heading_deg, project
from vloc.workers.core.geometry.register import MIN_INLIERS, register_frame

DOWN = (np.array([0.0, 0.0, -1.0]), 5.0)
"""The view prior of a nadir map: cameras look down, give or take 5 degrees."""

ALTITUDES = (GROUND_ALT - 20.0, GROUND_ALT + 150.0)


def _backproject(R, C, px, depth):
    """The 3-D points at ``depth`` (along the optical axis) behind pixels ``px`` of camera
    (R, C)."""
    rays = np.column_stack([(px[:, 0] - K_TRUE.cx) / K_TRUE.f,
                            (px[:, 1] - K_TRUE.cy) / K_TRUE.f, np.ones(len(px))])
    return C + (depth[:, None] * rays) @ R


def _on_ground(R, C, px, altitude=GROUND_ALT):
    """The points where the rays of pixels ``px`` meet the level ground at ``altitude``."""
    rays = np.column_stack([(px[:, 0] - K_TRUE.cx) / K_TRUE.f,
                            (px[:, 1] - K_TRUE.cy) / K_TRUE.f, np.ones(len(px))]) @ R
    t = (altitude - C[2]) / rays[:, 2]
    return C + t[:, None] * rays


def _survey_camera(rng: np.random.Generator, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A survey camera 60 m over the ground at the origin: a random heading, tilted
    ``tilt_deg`` from nadir towards a random direction (its rotation and centre)."""
    R = tilted_rotation(rng.uniform(0, 2 * np.pi), tilt_deg, rng.uniform(0, 2 * np.pi))
    return R, np.array([0.0, 0.0, GROUND_ALT + 60.0])


def _correspondences(rng, R, C, *, n=150, outliers=0.25, depth=(0.8, 1.0)):
    """n points seen by camera (R, C) anywhere in its image at depths ``depth`` (a range
    in metres), their exact pixels, a share of them mismatched to other points."""
    px = np.column_stack([rng.uniform(0, WIDTH - 1, n), rng.uniform(0, HEIGHT - 1, n)])
    pts = _backproject(R, C, px, rng.uniform(*depth, n))
    np.testing.assert_allclose(project(R, C, K_TRUE, pts), px, atol=1e-6)
    # a mismatch: the point another pixel, 20 to 150 px away, sees
    bad = rng.random(n) < outliers
    away = rng.uniform(20.0, 150.0, bad.sum())
    angle = rng.uniform(0.0, 2 * np.pi, bad.sum())
    other = px[bad] + np.column_stack([away * np.cos(angle), away * np.sin(angle)])
    pts[bad] = _backproject(R, C, other, rng.uniform(*depth, bad.sum()))
    image_of = rng.integers(0, 3, n) + 10 * bad  # the mismatches "come from" 10..12
    return px, pts, image_of, bad


NADIR = [(0, 0.0, 0.0, (50.0, 50.0)),        # flat ground, straight down
         (1, 123.0, 4.0, (35.0, 55.0)),      # hills and roofs under it
         (2, -70.0, 12.0, (30.0, 60.0)),
         (3, 200.0, 25.0, (40.0, 70.0))]     # oblique


@pytest.mark.parametrize(("seed", "theta_deg", "tilt", "depth"), NADIR)
def test_register_frame_recovers_a_known_pose_from_above(seed, theta_deg, tilt, depth):
    rng = np.random.default_rng(seed)
    R = tilted_rotation(math.radians(theta_deg), tilt, rng.uniform(0, 2 * np.pi))
    C = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), GROUND_ALT + 50.0])
    px, pts, image_of, bad = _correspondences(rng, R, C, depth=depth)
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES)
    assert reg is not None
    assert np.linalg.norm(reg.xy - C[:2]) < 0.01
    assert reg.height == pytest.approx(C[2], abs=0.01)
    d_heading = (reg.heading_deg - compass_heading_deg(R) + 180.0) % 360.0 - 180.0
    assert abs(d_heading) < 0.05
    assert reg.tilt_deg == pytest.approx(tilt_deg(R), abs=0.05)
    # every correspondence is judged under the solved pose: all the exact ones are in, and
    # no mismatch (they land tens of pixels off)
    assert reg.inliers == (~bad).sum()
    assert set(reg.images) == {0, 1, 2}
    assert 0.0 < reg.sigma < 3.0 and reg.heading_sigma_deg >= 0.5


@pytest.mark.parametrize(("seed", "look_deg"), [(4, 0.0), (5, 35.0), (6, 90.0)])
def test_register_frame_recovers_a_forward_looking_camera(seed, look_deg):
    # a walker's camera 1.6 m above the road looking along a street: points 3 to 40 m away
    rng = np.random.default_rng(seed)
    R = level_rotation(math.radians(look_deg + 20.0), pitch_deg=4.0)
    C = np.array([12.0, -3.0, GROUND_ALT + 1.6])
    px, pts, image_of, bad = _correspondences(rng, R, C, depth=(3.0, 40.0))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=(GROUND_ALT - 20.0,
                                                                     GROUND_ALT + 20.0))
    assert reg is not None
    assert np.linalg.norm(reg.xy - C[:2]) < 0.01
    assert reg.height == pytest.approx(C[2], abs=0.01)
    assert reg.tilt_deg == pytest.approx(94.0, abs=0.05)  # 4 degrees above the horizon
    assert reg.inliers == (~bad).sum()
    # a nadir map's prior refuses it: it looks nowhere near down
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                          view_prior=DOWN) is None


@pytest.mark.parametrize("seed", range(4))
def test_register_frame_finds_the_pose_among_as_many_mismatches(seed):
    # The RANSAC draws four correspondences (AP3P and one to choose among its solutions):
    # with half of them mismatched a sample is clean one time in 16, and among its 200
    # tries one is clean but for 2.5e-6.
    rng = np.random.default_rng(100 + seed)
    R, C = _survey_camera(rng, 6.0)
    px, pts, image_of, bad = _correspondences(rng, R, C, n=200, outliers=0.5,
                                              depth=(45.0, 62.0))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES)
    assert reg is not None
    # every exact correspondence is in; among 100 mismatches one may land within 4 px
    assert (~bad).sum() <= reg.inliers <= (~bad).sum() + 2
    assert np.linalg.norm(reg.xy - C[:2]) < 0.05


@pytest.mark.parametrize("seed", range(5))
def test_register_frame_with_a_view_prior_finds_the_pose_among_three_mismatches_in_four(seed):
    # A survey's frame starts from a two-point similarity across the viewing direction:
    # a clean sample one time in 16 at a quarter of inliers, where the four-point samples of
    # the pose RANSAC are clean one time in 256 (its 200 tries, alone, lose seed 3 here).
    rng = np.random.default_rng(200 + seed)
    R, C = _survey_camera(rng, 4.0)
    px, pts, image_of, bad = _correspondences(rng, R, C, n=200, outliers=0.75,
                                              depth=(52.0, 62.0))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                         view_prior=DOWN)
    assert reg is not None
    assert (~bad).sum() <= reg.inliers <= (~bad).sum() + 3
    assert np.linalg.norm(reg.xy - C[:2]) < 0.05
    assert reg.tilt_deg == pytest.approx(4.0, abs=0.1)


def _clustered(rng, R, C, n=60, noise_px=0.0):
    """n points of flat ground seen by camera (R, C) only in a 70x55 px patch near the
    frame's centre (textured ground in a field), their pixels with Gaussian noise."""
    px = np.column_stack([rng.uniform(115, 185, n), rng.uniform(103, 158, n)])
    pts = _on_ground(R, C, px)
    return px + rng.normal(0.0, noise_px, px.shape), pts, np.zeros(n, np.int64)


def test_register_frame_sigma_is_map_alignment_for_exact_data_spread_over_the_frame():
    rng = np.random.default_rng(9)
    R, C = tilted_rotation(0.3, 2.0, 0.0), np.array([0.0, 0.0, GROUND_ALT + 40.0])
    px, pts, image_of, _ = _correspondences(rng, R, C, outliers=0.0, depth=(35.0, 45.0))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES, base_sigma=2.0)
    # the solve's own uncertainty is small beside the map's alignment when the inliers
    # cover the frame
    assert 2.0 < reg.sigma < 2.05
    assert reg.heading_sigma_deg == pytest.approx(
        math.degrees(3.0 * 0.5 / K_TRUE.f / math.sqrt(reg.inliers)) + 0.5, abs=1e-6)


def test_register_frame_sigma_grows_when_the_inliers_cluster():
    rng = np.random.default_rng(10)
    R, C = tilted_rotation(0.3, 2.0, 0.0), np.array([0.0, 0.0, GROUND_ALT + 70.0])
    px, pts, image_of = _clustered(rng, R, C)
    loose = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES)
    held = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                          view_prior=DOWN)
    assert loose is not None and held is not None
    # without the prior the tilt and the position trade off freely over a small patch
    assert loose.sigma > 5.0
    assert 2.0 < held.sigma < loose.sigma
    spread = register_frame(*_correspondences(rng, R, C, outliers=0.0, depth=(65.0, 75.0))[:3],
                            K_TRUE, altitude_range=ALTITUDES)
    assert spread.sigma < 2.1


@pytest.mark.parametrize("prior", [None, DOWN], ids=["no prior", "nadir prior"])
def test_register_frame_covariance_matches_a_monte_carlo_spread(prior):
    """The reported sigma against the spread of poses solved from noisy pixels (the slow
    obvious reference: solve many times). The sigma is linearised, so it is held to a factor
    of two."""
    rng = np.random.default_rng(11)
    R, C = tilted_rotation(1.1, 3.0, 0.7), np.array([10.0, -5.0, GROUND_ALT + 60.0])
    px0, pts, image_of = _clustered(rng, R, C, n=80)
    solved, sigmas = [], []
    for _ in range(150):
        px = px0 + rng.normal(0.0, 1.5, px0.shape)  # PIXEL_SIGMA
        reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                             base_sigma=0.0, view_prior=prior)
        solved.append(reg.xy)
        sigmas.append(reg.sigma)
    cov = np.cov(np.array(solved).T)
    largest = math.sqrt(float(np.linalg.eigvalsh(cov)[-1]))
    assert 0.5 * largest < np.median(sigmas) < 2.0 * largest


def test_register_frame_view_prior_keeps_clustered_inliers_from_a_false_tilt():
    errors = {"prior": [], "none": []}
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        R = tilted_rotation(rng.uniform(0, 2 * np.pi), 3.0, rng.uniform(0, 2 * np.pi))
        C = np.array([0.0, 0.0, GROUND_ALT + 70.0])
        px, pts, image_of = _clustered(rng, R, C, n=40, noise_px=1.5)
        for key, prior in (("prior", DOWN), ("none", None)):
            reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                                 view_prior=prior)
            errors[key].append(np.linalg.norm(reg.xy - C[:2]))
    # without the prior: metres of error from a false tilt; with it, what 40 noisy pixels
    # in a patch allow
    assert np.mean(errors["prior"]) < 0.5 * np.mean(errors["none"])
    assert np.mean(errors["prior"]) < 6.0


def test_register_frame_ignores_unknown_points():
    rng = np.random.default_rng(4)
    R, C = tilted_rotation(1.0, 3.0, 0.5), np.array([5.0, 5.0, GROUND_ALT + 30.0])
    px, pts, image_of, _ = _correspondences(rng, R, C, outliers=0.0, depth=(20.0, 32.0))
    pts[::3] = np.nan
    pts[1, 2] = np.nan  # one unknown coordinate is an unknown point
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES)
    assert reg is not None and np.linalg.norm(reg.xy - C[:2]) < 0.01
    assert reg.inliers == np.isfinite(pts).all(axis=1).sum()


def test_register_frame_rejects_too_few_correspondences():
    rng = np.random.default_rng(5)
    R, C = tilted_rotation(0.0, 2.0, 0.0), np.array([0.0, 0.0, GROUND_ALT + 40.0])
    px, pts, image_of, _ = _correspondences(rng, R, C, outliers=0.0, depth=(30.0, 42.0))
    k = MIN_INLIERS - 1
    assert register_frame(px[:k], pts[:k], image_of[:k], K_TRUE,
                          altitude_range=ALTITUDES) is None
    assert register_frame(px[:k + 1], pts[:k + 1], image_of[:k + 1], K_TRUE,
                          altitude_range=ALTITUDES) is not None
    # enough rows, but too few with a known point
    pts_nan = pts[:40].copy()
    pts_nan[k:] = np.nan
    assert register_frame(px[:40], pts_nan, image_of[:40], K_TRUE,
                          altitude_range=ALTITUDES) is None
    # enough rows, too few consistent ones: all but k given another's point
    px2, pts2, img2, _ = _correspondences(rng, R, C, n=60, outliers=0.0, depth=(30.0, 42.0))
    assert register_frame(px2, pts2, img2, K_TRUE, altitude_range=ALTITUDES) is not None
    pts2[k:] = np.roll(pts2[k:], 1, axis=0)
    assert register_frame(px2, pts2, img2, K_TRUE, altitude_range=ALTITUDES) is None


def test_register_frame_rejects_an_implausible_pose():
    rng = np.random.default_rng(6)
    R, C = tilted_rotation(0.7, 3.0, 2.0), np.array([1.0, 2.0, GROUND_ALT + 40.0])
    px, pts, image_of, _ = _correspondences(rng, R, C, depth=(30.0, 45.0))
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES) is not None
    # the camera is 40 m up; altitudes that leave it out, above or below
    above, below = (GROUND_ALT + 60.0, GROUND_ALT + 150.0), (GROUND_ALT, GROUND_ALT + 30.0)
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=above) is None
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=below) is None
    # a camera looking 40 degrees from down: within five sigmas of a 10 degree prior,
    # not of a 5 degree one
    steep = tilted_rotation(0.7, 40.0, 2.0)
    px, pts, image_of, _ = _correspondences(rng, steep, C, depth=(30.0, 45.0))
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                          view_prior=DOWN) is None
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                         view_prior=(DOWN[0], 10.0))
    assert reg is not None and reg.tilt_deg == pytest.approx(40.0, abs=0.5)


@pytest.mark.parametrize("seed", range(3))
def test_register_frame_survives_a_consensus_of_two_points_seen_many_times(seed):
    # Map keypoints of several images share a 3-D point, so a frame's keypoints may match
    # the same few points many times over (a build's uav-drift world met this). Here every
    # correspondence sees one of two points (to a micrometre): OpenCV's SQPnP, given the
    # similarity's consensus, fails an assertion ("num_null_vectors") instead of returning
    # no pose. That start is then passed over like one that found nothing; the three-point
    # start, with the view prior, may still place the camera, and then where it is.
    rng = np.random.default_rng(seed)
    R = tilted_rotation(0.3, 0.0, 1.0)
    C = np.array([10.0, -5.0, GROUND_ALT + 50.0])
    two = _on_ground(R, C, np.array([[100.0, 80.0], [220.0, 150.0]]))
    pts = np.repeat(two, 12, axis=0) + rng.normal(0.0, 1e-6, (24, 3))
    px = project(R, C, K_TRUE, pts)
    image_of = rng.integers(0, 3, len(px))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                         view_prior=DOWN)
    assert reg is None or (np.linalg.norm(reg.xy - C[:2]) < 0.1
                           and reg.height == pytest.approx(C[2], abs=0.1))


@pytest.mark.parametrize("seed", range(3))
def test_register_frame_rescues_a_survey_frame_the_similarity_cannot_start(seed):
    """Points 5 to 60 m under a survey camera (towers over a street, 60 m up) bend the
    two-point similarity start past any consensus: the three-point poses find the camera,
    unless no rescue is asked for. Where the similarity holds, the rescue changes
    nothing."""
    rng = np.random.default_rng(300 + seed)
    R, C = _survey_camera(rng, 3.0)
    px, pts, image_of, _ = _correspondences(rng, R, C, n=40, outliers=0.0,
                                            depth=(5.0, 60.0))
    reg = register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                         view_prior=DOWN)
    assert reg is not None and reg.inliers == len(px)
    assert np.linalg.norm(reg.xy - C[:2]) < 0.05
    assert register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                          view_prior=DOWN, rescue=False) is None
    # the same camera over level ground: the similarity starts it either way
    px, pts, image_of, _ = _correspondences(rng, R, C, n=80, outliers=0.25,
                                            depth=(58.0, 62.0))
    found = [register_frame(px, pts, image_of, K_TRUE, altitude_range=ALTITUDES,
                            view_prior=DOWN, rescue=rescue) for rescue in (True, False)]
    assert found[0] is not None and found[1] is not None
    np.testing.assert_array_equal(found[0].xy, found[1].xy)
    assert found[0].inliers == found[1].inliers
