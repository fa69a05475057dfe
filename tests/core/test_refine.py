"""Metric refinement: registration against a reconstructed map, interpolation without one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.core.geometry.scene import GROUND_ALT, HEIGHT, WIDTH, observe, survey, tilted_rotation
from vloc.clients.world.writer import generate_world
from vloc.workers.core.evaluation.experiment import load_experiment
from vloc.workers.core.features.orb import OrbFeatures
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.localisers.refine import (
    MIN_MATCHES,
    interpolate,
    rank_cloud_images,
    refine_orb,
    refine_sift,
)
from vloc.workers.core.localisers.scoring import sift_similarity
from vloc.workers.core.mapbuild import map_geometry
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import SiftFeatures


def _line_map(n: int = 4, spacing: float = 10.0) -> MapData:
    rng = np.random.default_rng(0)
    sift = [SiftFeatures(rng.uniform(0, 200, (20, 4)).astype(np.float32),
                         rng.integers(0, 256, (20, 128), dtype=np.uint8)) for _ in range(n)]
    return MapData.from_parts(origin=GeoOrigin(48.5, 9.0), names=[str(i) for i in range(n)],
                              positions=[[spacing * i, 0.0] for i in range(n)],
                              altitudes=np.zeros(n), global_features={}, sift=sift)


def test_interpolate_known_answers():
    data = _line_map()
    r = interpolate(data, np.array([1, 2]), np.array([3.0, 1.0]))
    assert r.kind == "interpolated" and r.images == (1, 2)
    np.testing.assert_allclose(r.xy, [12.5, 0.0])
    # spread sqrt((0.75 * 2.5^2 + 0.25 * 7.5^2) / 2) = 3.06 m, under a third of the spacing
    assert r.sigma == pytest.approx(10.0 / 3.0)
    r = interpolate(data, np.array([0, 3]), np.array([1.0, 1.0]))
    np.testing.assert_allclose(r.xy, [15.0, 0.0])
    assert r.sigma == pytest.approx(math.sqrt(15.0**2 / 2.0))
    assert r.heading_deg is None and r.inliers == 0


def test_interpolate_ignores_zero_scores():
    data = _line_map()
    r = interpolate(data, np.array([3, 0, 1]), np.array([2.0, 0.0, 2.0]))
    np.testing.assert_allclose(r.xy, [20.0, 0.0])
    assert r.images == (3, 1)
    assert interpolate(data, np.array([0, 1]), np.zeros(2)) is None


def test_rank_cloud_images_by_hand():
    # particles nearest images 7, 7, 2, 5, 2, 2 with log-likelihoods; shares by hand
    nearest = np.array([7, 7, 2, 5, 2, 2])
    log = np.append(np.log([0.5, 0.5, 0.1, 0.8, 0.1]), -np.inf)
    images, shares = rank_cloud_images(nearest, log)
    np.testing.assert_array_equal(images, [7, 5, 2])
    np.testing.assert_allclose(shares, np.array([1.0, 0.8, 0.2]) / 2.0)
    # equal shares: more particles first, then the lower index
    images, _ = rank_cloud_images(np.array([4, 1, 1, 9]), np.log([0.4, 0.2, 0.2, 0.4]))
    np.testing.assert_array_equal(images, [1, 4, 9])
    # no finite likelihood anywhere: the particles' share
    images, shares = rank_cloud_images(np.array([3, 3, 0]), np.full(3, -np.inf))
    np.testing.assert_array_equal(images, [3, 0])
    np.testing.assert_allclose(shares, [2 / 3, 1 / 3])


def test_rank_cloud_images_against_a_loop():
    rng = np.random.default_rng(5)
    nearest = rng.integers(0, 40, 500)
    log = rng.normal(-30.0, 8.0, 500)
    images, shares = rank_cloud_images(nearest, log)
    total = {}
    for i, lg in zip(nearest.tolist(), log.tolist(), strict=True):
        total[i] = total.get(i, 0.0) + math.exp(lg)
    norm = sum(total.values())
    expected = sorted(total, key=lambda i: -total[i])
    assert images.tolist() == expected
    np.testing.assert_allclose(shares, [total[i] / norm for i in expected], rtol=1e-9)


def _survey_map(with_geometry: bool):
    s = survey(np.random.default_rng(21), max_tilt_deg=8.0)
    data = MapData.from_parts(origin=GeoOrigin(48.5, 9.0),
                              names=[str(i) for i in range(len(s.centres))],
                              positions=s.positions, altitudes=s.altitudes, global_features={},
                              sift=[SiftFeatures(k, d) for k, d in
                                    zip(s.keypoints, s.image_descriptors, strict=True)])
    if with_geometry:
        data.geometry = map_geometry(data, focal_px=s.K.f)
        assert data.geometry is not None
    return s, data


@pytest.fixture(scope="module")
def surveyed_map():
    return _survey_map(with_geometry=True)


def _query(s, C, theta=0.8):
    R = tilted_rotation(theta, 5.0, 1.0)
    kp, desc, ids = observe(s.points, s.descriptors, R, C, s.K)
    shared = np.array([len(np.intersect1d(ids, p)) for p in s.point_ids], np.float64)
    ranked = np.argsort(-shared)
    return SiftFeatures(kp, desc), ranked, shared[ranked] / len(ids)


def test_refine_sift_registers_against_map_geometry(surveyed_map):
    s, data = surveyed_map
    C = np.array([25.0, 8.0, GROUND_ALT + 45.0])
    query, ranked, scores = _query(s, C)
    r = refine_sift(query, data, ranked, scores, frame_shape=(HEIGHT, WIDTH))
    assert r is not None and r.kind == "registered"
    assert np.linalg.norm(r.xy - C[:2]) < 0.5
    assert r.images == tuple(sorted(int(i) for i in ranked[:3]))  # max_images best
    assert r.heading_deg is not None and r.inliers >= 30


def test_refine_sift_without_geometry_interpolates():
    s, data = _survey_map(with_geometry=False)
    query, ranked, scores = _query(s, np.array([25.0, 8.0, GROUND_ALT + 45.0]))
    r = refine_sift(query, data, ranked, scores, frame_shape=(HEIGHT, WIDTH), max_images=2)
    assert r.kind == "interpolated" and r.images == tuple(int(i) for i in ranked[:2])
    w = scores[:2] / scores[:2].sum()
    np.testing.assert_allclose(r.xy, w @ s.positions[ranked[:2]])


def test_refine_sift_needs_matches(surveyed_map):
    s, data = surveyed_map
    query, ranked, scores = _query(s, np.array([25.0, 8.0, GROUND_ALT + 45.0]))
    shape = (HEIGHT, WIDTH)
    assert refine_sift(query, data, ranked, np.zeros(len(ranked)), frame_shape=shape) is None
    empty = SiftFeatures(np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8))
    assert refine_sift(empty, data, ranked, scores, frame_shape=shape) is None
    few = SiftFeatures(query.keypoints[: MIN_MATCHES - 1], query.descriptors[: MIN_MATCHES - 1])
    assert refine_sift(few, data, ranked, scores, frame_shape=shape) is None


# -- end to end on a rendered UAV world --------------------------------------------------------

@pytest.fixture(scope="module")
def uav_world(tmp_path_factory):
    """Two passes over one survey path at 30 m over 10 m hills: sunny builds the map,
    cloudy is queried.

    The hills are what lets the map find its camera: the world's JPEGs carry no focal
    length, and over flat land a nadir survey cannot tell the focal length from the height
    (:mod:`workers.core.geometry.sfm`): COLMAP settles at 796 px for the true 277, and the
    self-check refuses the geometry (4.3 m median error against a 2.8 m floor)."""
    folder = tmp_path_factory.mktemp("uav-world")
    generate_world(folder, kind="uav", seed=3, passes=["sunny", "cloudy"], frames=24,
                   altitude=30.0, gps_noise_m=0.0, supersample=1, relief_m=10.0)
    return load_experiment(folder, rule="pass", map_pass=1, query_pass=2)


def _ranked(query, data, candidates=None):
    idx = np.arange(len(data)) if candidates is None else np.asarray(candidates)
    scores = sift_similarity(query, data, idx, ratio=0.7, verify="homography")
    order = np.argsort(-scores, kind="stable")
    return idx[order], scores[order]


def test_uav_world_map_is_reconstructed(uav_world):
    geo = uav_world.map_data.geometry
    assert geo is not None
    assert geo.reconstructed.all()
    assert geo.residual_px < 1.0
    assert geo.gps_rms < 1.0  # the tags are exact
    assert geo.self_check["trusted"]
    assert geo.self_check["median_m"] < 0.5 < geo.self_check["floor_median_m"]
    altitudes = np.asarray(uav_world.map_data.altitudes)
    lo, hi = geo.altitude_range()
    assert lo < altitudes.min() and hi > altitudes.max()


def test_uav_world_frames_register_sub_metre(uav_world):
    data = uav_world.map_data
    errors = []
    for q, truth in zip(uav_world.queries, uav_world.truth, strict=True):
        sift, _ = q.sift()
        ranked, scores = _ranked(sift, data)
        r = refine_sift(sift, data, ranked, scores, frame_shape=q.frame.grey.shape[:2])
        if r is not None:
            assert r.kind == "registered"
            errors.append(float(np.linalg.norm(r.xy - truth)))
    n = len(uav_world.queries)
    assert len(errors) >= 0.75 * n
    assert np.median(errors) < 1.0
    assert np.percentile(errors, 90) < 3.0


def test_uav_world_without_geometry_interpolates_between_map_images(uav_world):
    # Two map images are too few to reconstruct: refinement falls back to a position
    # between the verified map images, weighted by their scores.
    full = uav_world.map_data
    truth = uav_world.truth
    k = len(uav_world.queries) // 2
    near = np.argsort(np.linalg.norm(full.positions - truth[k], axis=1))[:2]
    pair = MapData.from_parts(origin=full.origin, names=[full.names[i] for i in near],
                              positions=full.positions[near], altitudes=full.altitudes[near],
                              global_features={}, sift=[full.sift(int(i)) for i in near])
    assert map_geometry(pair) is None
    sift, _ = uav_world.queries[k].sift()
    ranked, scores = _ranked(sift, pair)
    assert (scores > 0).all()
    r = refine_sift(sift, pair, ranked, scores, frame_shape=uav_world.queries[k].frame.grey.shape)
    assert r is not None and r.kind == "interpolated"
    assert sorted(r.images) == [0, 1]
    w = scores / scores.sum()
    np.testing.assert_allclose(r.xy, w @ pair.positions[ranked])
    # between the two images, nearer the one that matched better
    a, b = pair.positions[ranked[0]], pair.positions[ranked[1]]
    t = float(np.dot(r.xy - a, b - a) / np.dot(b - a, b - a))
    assert 0.0 <= t <= 0.5
    assert np.linalg.norm(r.xy - truth[k]) <= np.linalg.norm(b - truth[k])


def test_uav_world_frames_register_with_orb(uav_world):
    """The global step's registration: ORB against the map's ORB 3-D points."""
    data = uav_world.map_data
    assert data.has_orb and "orb" in data.geometry.points
    errors = []
    for q, truth in zip(uav_world.queries, uav_world.truth, strict=True):
        near = np.argsort(np.linalg.norm(np.asarray(data.positions) - truth, axis=1))[:2]
        r = refine_orb(q.orb()[0], data, near, np.ones(2), frame_shape=q.frame.grey.shape)
        if r is not None:
            assert r.kind == "registered" and set(r.images) <= set(near.tolist())
            errors.append(float(np.linalg.norm(r.xy - truth)))
    assert len(errors) >= 0.75 * len(uav_world.queries)
    assert np.median(errors) < 1.0


def _orb_image(data, descriptors) -> int:
    """The map image whose ORB descriptors these are (what a matcher was handed)."""
    return next(i for i in range(len(data)) if data.orb(i).descriptors is descriptors
                or np.array_equal(data.orb(i).descriptors, descriptors))


def test_refine_orb_passes_over_images_that_match_thinly(uav_world, monkeypatch):
    """A map image giving fewer than ORB_FIRST_MATCHES ratio-test matches starts no pose:
    the next ranked image is tried instead, and where every one is that thin, nothing is
    registered."""
    from vloc.workers.core.localisers import refine as refine_module

    data = uav_world.map_data
    q, truth = uav_world.queries[3], uav_world.truth[3]
    near = np.argsort(np.linalg.norm(np.asarray(data.positions) - truth, axis=1))[:3]
    shape = q.frame.grey.shape
    alone = refine_orb(q.orb()[0], data, near[1:], np.ones(2), frame_shape=shape)
    assert alone is not None
    real, asked = refine_module.hamming_ratio_matches, []
    thin = {int(near[0])}

    def thinned(a, b, ratio):
        image = _orb_image(data, b)
        asked.append(image)
        m = real(a, b, ratio=ratio)
        return m[:refine_module.ORB_FIRST_MATCHES - 1] if image in thin else m

    monkeypatch.setattr(refine_module, "hamming_ratio_matches", thinned)
    # the nearest image thinned: the pose is the one the others give
    got = refine_orb(q.orb()[0], data, near, np.ones(3), frame_shape=shape)
    assert got is not None and int(near[0]) not in got.images
    np.testing.assert_allclose(got.xy, alone.xy)
    assert asked[0] == int(near[0])
    # every image thinned: each tried once, none registered
    thin.update(int(i) for i in near)
    asked.clear()
    assert refine_orb(q.orb()[0], data, near, np.ones(3), frame_shape=shape,
                      max_images=3) is None
    assert asked == [int(i) for i in near]


def test_refine_orb_tries_on_past_a_thin_registration(uav_world, monkeypatch):
    """A registration with fewer than ORB_SURE_INLIERS inliers is not the answer at once:
    the next images are tried, and the registration with the most inliers wins. One with
    that many is the answer at once, and nothing more is matched."""
    from vloc.workers.core.localisers import refine as refine_module

    data = uav_world.map_data
    q, truth = uav_world.queries[3], uav_world.truth[3]
    near = np.argsort(np.linalg.norm(np.asarray(data.positions) - truth, axis=1))[:3]
    shape = q.frame.grey.shape
    real, asked = refine_module.hamming_ratio_matches, []
    keep = refine_module.ORB_FIRST_MATCHES + 2  # enough to start a pose, too few to be sure

    def thinned(a, b, ratio):
        image = _orb_image(data, b)
        asked.append(image)
        m = real(a, b, ratio=ratio)
        return m[:keep] if image == int(near[0]) else m

    monkeypatch.setattr(refine_module, "hamming_ratio_matches", thinned)
    thin = refine_orb(q.orb()[0], data, near[:1], np.ones(1), frame_shape=shape)
    assert thin is not None and thin.kind == "registered"
    assert thin.inliers < refine_module.ORB_SURE_INLIERS
    asked.clear()
    got = refine_orb(q.orb()[0], data, near, np.ones(3), frame_shape=shape, max_images=3)
    assert got is not None and got.kind == "registered"
    assert asked[:2] == [int(near[0]), int(near[1])]
    assert got.inliers > thin.inliers and int(near[1]) in got.images
    assert np.linalg.norm(got.xy - truth) < 1.0
    # the old rule, the first registration the answer: the thin one, nothing else matched
    monkeypatch.setattr(refine_module, "ORB_SURE_INLIERS", 0)
    asked.clear()
    first = refine_orb(q.orb()[0], data, near, np.ones(3), frame_shape=shape, max_images=3)
    assert asked == [int(near[0])]
    np.testing.assert_allclose(first.xy, thin.xy)


def test_refine_orb_passes_over_images_the_reconstruction_left_out(uav_world):
    """An image without a camera pose has no 3-D points: it is not matched, and does not
    count against the images tried."""
    data = uav_world.map_data
    q, truth = uav_world.queries[3], uav_world.truth[3]
    near = np.argsort(np.linalg.norm(np.asarray(data.positions) - truth, axis=1))[:3]
    shape = q.frame.grey.shape
    want = refine_orb(q.orb()[0], data, near[1:], np.ones(2), frame_shape=shape,
                      max_images=1)
    geo = data.geometry
    saved = geo.centres
    centres = np.array(saved, copy=True)
    centres[near[0]] = np.nan
    geo.centres = centres
    try:
        got = refine_orb(q.orb()[0], data, near, np.ones(3), frame_shape=shape,
                         max_images=1)
    finally:
        geo.centres = saved
    assert want is not None and got is not None
    # the same matches; the view prior, worked out from the placed cameras, lost one
    np.testing.assert_allclose(got.xy, want.xy, atol=0.01)
    assert got.images == want.images


def test_refine_orb_needs_geometry_and_matches(uav_world):
    data = uav_world.map_data
    q = uav_world.queries[3]
    shape = q.frame.grey.shape
    # no map image scored: nothing to register against
    assert refine_orb(q.orb()[0], data, np.array([0, 1]), np.zeros(2), frame_shape=shape) is None
    assert refine_orb(OrbFeatures.empty(), data, np.array([0, 1]), np.ones(2),
                      frame_shape=shape) is None
    flat = MapData.from_parts(origin=data.origin, names=list(data.names),
                              positions=data.positions, altitudes=data.altitudes,
                              global_features={}, sift=[data.sift(i) for i in range(len(data))],
                              orb=[data.orb(i) for i in range(len(data))])
    assert flat.has_orb and flat.geometry is None
    assert refine_orb(q.orb()[0], flat, np.array([0, 1]), np.ones(2), frame_shape=shape) is None


def _without_pose(geo, image):
    """``geo`` with ``image`` left out of the reconstruction (restore with the result)."""
    saved = geo.centres
    centres = np.array(saved, copy=True)
    centres[image] = np.nan
    geo.centres = centres
    return saved


def test_refine_orb_places_a_frame_at_an_image_left_out(uav_world, monkeypatch):
    """A frame that overlaps a map image the reconstruction left out, beyond doubt, is
    placed at that image (as one image places it without geometry); a frame that does not,
    or overlaps it less than ORB_OVERLAP_INLIERS, gets nothing."""
    from vloc.workers.core.localisers import refine as refine_module

    data = uav_world.map_data
    q, truth = uav_world.queries[3], uav_world.truth[3]
    positions = np.asarray(data.positions)
    by_distance = np.argsort(np.linalg.norm(positions - truth, axis=1))
    near, far = int(by_distance[0]), int(by_distance[-1])
    shape = q.frame.grey.shape
    geo = data.geometry
    saved = _without_pose(geo, near)
    try:
        assert not geo.reconstructed[near]
        got = refine_orb(q.orb()[0], data, np.array([near]), np.ones(1), frame_shape=shape)
        assert got is not None and got.kind == "interpolated" and got.images == (near,)
        np.testing.assert_allclose(got.xy, positions[near])
        assert got.sigma == pytest.approx(data.median_spacing() / 3.0)
        assert got.heading_deg is None
        assert got.inliers >= refine_module.ORB_OVERLAP_INLIERS
        assert np.linalg.norm(got.xy - truth) < data.median_spacing()
        # the other end of the survey: no overlap
        saved_far = _without_pose(geo, far)
        try:
            assert refine_orb(q.orb()[0], data, np.array([far]), np.ones(1),
                              frame_shape=shape) is None
        finally:
            geo.centres = saved_far
        # an overlap short of the threshold places nothing
        monkeypatch.setattr(refine_module, "ORB_OVERLAP_INLIERS", got.inliers + 1)
        assert refine_orb(q.orb()[0], data, np.array([near]), np.ones(1),
                          frame_shape=shape) is None
    finally:
        geo.centres = saved


def test_refine_orb_places_a_frame_at_an_image_without_3d_points(uav_world):
    """A placed image whose keypoints the frame matched have too few 3-D points gives no
    pose: the frame is placed at it; with its points it registers as before."""
    data = uav_world.map_data
    q, truth = uav_world.queries[3], uav_world.truth[3]
    near = int(np.argmin(np.linalg.norm(np.asarray(data.positions) - truth, axis=1)))
    shape = q.frame.grey.shape
    geo = data.geometry
    registered = refine_orb(q.orb()[0], data, np.array([near]), np.ones(1), frame_shape=shape)
    assert registered is not None and registered.kind == "registered"
    saved = geo.points["orb"]
    points = np.array(saved, copy=True)
    offsets = np.asarray(data.orb_offsets)
    points[offsets[near]:offsets[near + 1]] = np.nan
    geo.points["orb"] = points
    try:
        got = refine_orb(q.orb()[0], data, np.array([near]), np.ones(1), frame_shape=shape)
    finally:
        geo.points["orb"] = saved
    assert got is not None and got.kind == "interpolated" and got.images == (near,)
    np.testing.assert_allclose(got.xy, np.asarray(data.positions)[near])


def test_the_hybrid_tries_a_global_step_after_every_sift_step(uav_world):
    """On a map whose global steps register and escalate, no SIFT step is followed by
    another by the spread alone: the next step starts global (``switching.decide``)."""
    from vloc.workers.core.localisers import make_localiser

    loc = make_localiser("hybrid", uav_world.map_data, {"config": "default"}, seed=0)
    assert loc.escalates
    sift_steps = 0
    for q in uav_world.queries:
        if loc.step(q).feature == "sift":
            sift_steps += 1
            assert loc.switch.next == "global"
    assert sift_steps >= 1  # the first step, at least
    off = make_localiser("hybrid", uav_world.map_data, {"config": "default", "escalate": False},
                         seed=0)
    assert not off.escalates
