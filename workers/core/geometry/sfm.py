"""The map's structure from motion: COLMAP's incremental mapper over the map's own tie points.

The map's tie points (:func:`workers.core.tiepoints.extract_tie_points`) and the verified
matches between GPS-neighbouring images (:mod:`.pairs`) go into a COLMAP database, the way
hloc feeds its features and matches, and COLMAP's incremental mapper
(:func:`pycolmap.incremental_mapping`) recovers the cameras and the 3-D points they see, in
one or several models, each then brought onto the images' GPS (:mod:`.models`). Nothing
assumes a ground plane: nadir, oblique and street-level maps take the same path.

One camera model serves the map: SIMPLE_RADIAL (a focal length and one radial term; the
principal point at the image centre), started from the EXIF focal length. Over flat ground
a nadir survey cannot tell the focal length from the height (seneca-uav's mapper, free to
refine it, settles at 349 px for the EXIF's 222 and places the cameras 73 m from their GPS),
while an oblique survey over buildings needs it refined (lewis-uav: 233 px for the EXIF's
224). So the mapper runs with the intrinsics refined, and where the focal length it finds
strays from the EXIF's by more than :data:`MAX_FOCAL_CHANGE` or fewer than
:data:`GOOD_SHARE` of the images end up consistent with their GPS, it runs again with them
held, and the run that places more cameras consistently wins.

Coordinates: the project's pixels are at the working resolution with 0 at the centre of the
first pixel (OpenCV's convention); COLMAP's put 0.5 there. The database holds pixels scaled
by :data:`~.models.COLMAP_SCALE` (the tie points' own resolution), so that COLMAP's thresholds in
pixels mean what its defaults intend.

This module runs COLMAP on one set of images (:func:`reconstruct_images`); :mod:`.models`
joins the aligned models into the map's cameras, and :mod:`.tiling` decides which sets: a
small map whole, a large one in overlapping spatial tiles.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..image import WORK_SIZE
from .camera import DEFAULT_HFOV_DEG, focal_from_fov
from .kept import load_models, read_inputs, save_models
from .models import (
    COLMAP_SCALE,
    GPS_SIGMA_H,
    GPS_SIGMA_V,
    TileModel,
    align_models,
    placed_images,
)
from .pairs import PairMatches

MAX_FOCAL_CHANGE: float = 0.15
"""A refined focal length further than this (relative) from the EXIF's is distrusted."""

GOOD_SHARE: float = 0.6
"""A run that places fewer than this share of the images consistently with their GPS is
tried again with the intrinsics held."""

MIN_POSE_INLIERS: int = 15
"""Fewest 2D-3D inliers with which the mapper registers an image (COLMAP's default: 30)."""

MIN_POSE_INLIER_RATIO: float = 0.5
"""Least share of inliers the mapper's registrations assume an image's correspondences hold
(COLMAP's ``abs_pose_min_inlier_ratio``, 0.25 by default), which caps their RANSAC trials.
COLMAP 4 registers an image whose points are not yet triangulated from its 2D-2D
correspondences instead (its structure-less fallback), with an expensive minimal solver: at
a quarter, a few such attempts took 33 s of the seneca-uav map's 38 s of mapping. At a half
the mapper places the same images (63 and 6 in two models) in 21 s, and the hybrid's error
on seneca-uav is as before or better; lewis-uav's map and errors are unchanged. Without the
fallback at all, lewis-uav places 21 images instead of 23 and its hybrid takes SIFT on 24 %
of its steps instead of 19 %."""

LARGE_MODEL: int = 150
"""A reconstruction of more images than this runs its bundle adjustments lighter, as COLMAP's
FAQ advises for large collections (:data:`LARGE_BA`): its global adjustments, over every
camera, otherwise follow each tenth of growth and come to dominate its time (a 200-image tile
of a synthetic survey: 169 s of one core with COLMAP's defaults, 52 s so, its cameras as far
from their GPS). Smaller maps keep COLMAP's defaults."""

LARGE_BASE_SHARE: float = 0.5
"""A kept model of more than :data:`LARGE_MODEL` cameras that takes in at least this share
of the new images it would place at its own rate stands (:func:`_grew_well`)."""

LARGE_BA: dict[str, float | int] = {
    "ba_global_frames_ratio": 1.4, "ba_global_points_ratio": 1.4,
    "ba_global_max_num_iterations": 25, "ba_local_max_num_iterations": 10,
    "ba_local_max_refinements": 1}
"""The incremental pipeline's options for a reconstruction of more than
:data:`LARGE_MODEL` images: a global adjustment after each 40 % of growth instead of 10 %,
fewer iterations, one local refinement; and the global adjustment skips 3-D points that
other points already constrain (``mapper.ba_global_ignore_redundant_points3D``)."""


def settings_key() -> str:
    """What a reconstruction depends on besides its inputs: COLMAP's version and the
    mapper's settings here. A tile kept from an earlier build is reconstructed again when
    they change (:func:`.tiling.tile_key`)."""
    import pycolmap

    return repr((pycolmap.__version__, MIN_POSE_INLIERS, MIN_POSE_INLIER_RATIO, LARGE_MODEL,
                 sorted(LARGE_BA.items()), MAX_FOCAL_CHANGE, GOOD_SHARE, GPS_SIGMA_H,
                 GPS_SIGMA_V, COLMAP_SCALE))


def to_colmap_pixels(keypoints: np.ndarray) -> np.ndarray:
    """Working-resolution pixels (first two columns) -> COLMAP's (n, 2) float64."""
    return (np.asarray(keypoints[:, :2], np.float64) + 0.5) * COLMAP_SCALE


def colmap_camera(focal_px: float | None):
    """The map's camera for COLMAP: SIMPLE_RADIAL at the tie points' resolution, from
    ``focal_px`` (working resolution; None assumes a typical field of view, unknown)."""
    import pycolmap

    width, height = WORK_SIZE
    f = focal_px if focal_px else focal_from_fov(DEFAULT_HFOV_DEG, width)
    camera = pycolmap.Camera.create_from_model_name(
        1, "SIMPLE_RADIAL", f * COLMAP_SCALE, int(width * COLMAP_SCALE),
        int(height * COLMAP_SCALE))
    camera.has_prior_focal_length = focal_px is not None
    return camera


def reconstruct_images(keypoints: Sequence[np.ndarray], pairs: list[PairMatches],
                       gps: np.ndarray, focal_px: float | None, seed: int, *,
                       names: Sequence[str] | None = None, base: Path | None = None,
                       keep: Path | None = None, context: str = "",
                       core: np.ndarray | None = None) -> list[TileModel] | None:
    """COLMAP's models of one set of images (indices of ``keypoints``), aligned to ``gps``
    (:func:`.models.tags`); run again with the intrinsics held where refining them went astray.
    A whole map goes through :func:`.tiling.reconstruct`, which calls this once per tile.

    ``base`` holds the models kept from an earlier build of images among these
    (:mod:`.kept`, its images named by ``names``, one per image here). Where they came
    from the same inputs (images, matches, ``context``), they are only aligned to ``gps``
    again; otherwise the other images are registered into the largest, its cameras and
    intrinsics held (:func:`_extend`). Where that
    places a smaller share of the images new to it than the base placed of its own
    (:func:`_grew_well`; of the new images in ``core``, a mask over the set's images, where
    given), or the base does not fit, the set is reconstructed whole too, and
    the run that places more wins (the extension, where they tie). The largest model found
    are kept in ``keep`` for the next build, with ``context`` (:func:`.kept.save_models`).
    """
    names = [str(k) for k in range(len(gps))] if names is None else list(names)
    inputs = _inputs_key(names, pairs, context)
    extended = None
    if base is not None and read_inputs(base) == inputs:
        loaded = load_models(base, {name: k for k, name in enumerate(names)})
        if loaded is not None:
            order, recs = loaded
            return _kept(_Run(align_models(recs, gps, seed), recs, order), names, keep,
                         context, inputs)
    with tempfile.TemporaryDirectory(prefix="vloc-sfm-") as tmp:
        if base is not None:
            extended = _extend(base, Path(tmp), keypoints, pairs, gps, focal_px, seed, names)
            if extended is not None and _grew_well(extended, core):
                return _kept(extended, names, keep, context, inputs)
        chosen = _reconstruct_whole(Path(tmp), keypoints, pairs, gps, focal_px, seed)
    if extended is not None and _count(extended.models) >= _count(chosen.models):
        chosen = extended
    return _kept(chosen, names, keep, context, inputs)


def _inputs_key(names: list[str], pairs: list[PairMatches], context: str) -> str:
    """The mapper's inputs hashed: the images by name, their verified matches, the
    context (:func:`.kept.read_inputs`)."""
    h = hashlib.sha1(context.encode())
    h.update("\n".join(names).encode())
    for p in sorted(pairs, key=lambda p: (p.a, p.b)):
        h.update(np.array([p.a, p.b, p.config], np.int64).tobytes())
        h.update(np.ascontiguousarray(p.matches, np.int64).tobytes())
    return h.hexdigest()


def _reconstruct_whole(folder: Path, keypoints: Sequence[np.ndarray],
                       pairs: list[PairMatches], gps: np.ndarray, focal_px: float | None,
                       seed: int) -> _Run:
    """The mapper from scratch: intrinsics refined, and held too where refining them went
    astray (:func:`_good`), the run placing more winning."""
    database = folder / "database.db"
    order = _write_database(database, keypoints, pairs, focal_px)
    refined = _run(database, folder, gps, refine=True, seed=seed, order=order)
    if focal_px is None or _good(refined.models, focal_px, len(gps)):
        return refined
    held = _run(database, folder, gps, refine=False, seed=seed, order=order)
    if _focal_strays(refined.models, focal_px):
        # a focal length it does not trust: the held run, unless it places far fewer
        return held if _count(held.models) >= 0.8 * _count(refined.models) else refined
    return held if _count(held.models) > _count(refined.models) else refined


@dataclass
class _Run:
    """One run of the mapper: its models aligned to GPS, COLMAP's own models (by its model
    index) and the database's images in database order (indices); for a run grown from a
    kept model (:func:`_extend`), how many images that model's database held and how many
    it placed."""

    models: list[TileModel] | None
    recs: list
    order: list[int]
    base: tuple[int, int] | None = None


def _kept(run: _Run, names: list[str], keep: Path | None, context: str,
          inputs: str) -> list[TileModel] | None:
    """The run's models, COLMAP's kept in ``keep`` (:func:`.kept.save_models`)."""
    if keep is not None:
        if run.recs and run.models:
            save_models(run.recs, names, run.order, context, inputs, keep)
        else:
            shutil.rmtree(keep, ignore_errors=True)
    return run.models


def _extend(base: Path, folder: Path, keypoints: Sequence[np.ndarray],
            pairs: list[PairMatches], gps: np.ndarray, focal_px: float | None, seed: int,
            names: list[str]) -> _Run | None:
    """The images of ``pairs`` registered into the model kept in ``base``, whose cameras
    and intrinsics stay as they are (COLMAP's ``fix_existing_frames``): the database lists
    the base's images first, as its model numbers them; images of the base not among
    ``names`` (deleted from the map) leave it first. None where fewer than three of its
    cameras are left, or the run places no camera."""
    loaded = load_models(base, {name: k for k, name in enumerate(names)},
                         leave_out_missing=True)
    if loaded is None or not loaded[1]:
        return None
    first, recs = loaded
    largest = max(recs, key=lambda r: r.num_reg_images())
    registered = largest.num_reg_images()
    if registered < 3:
        return None  # too little left to hold the others to (deletions)
    (folder / "base").mkdir()
    largest.write(str(folder / "base"))
    database = folder / "extended.db"
    order = _write_database(database, keypoints, pairs, focal_px, first=first)
    run = _run(database, folder, gps, refine=False, seed=seed, order=order,
               base=folder / "base")
    run.base = (len(first), registered)
    return run if run.models else None


def _grew_well(run: _Run, core: np.ndarray | None = None) -> bool:
    """Whether a run grown from a kept model placed about as large a share of the images
    new to it as that model placed of its own (one image short allowed): a base that
    blocks the way to a better model (lewis-uav's first two thirds, 14 of 18 images placed,
    with the rest added: 6 of 10 placed, 8 of 10 from scratch) is reconstructed anew.

    A base of more than :data:`LARGE_MODEL` cameras is reconstructed anew only where it
    took in fewer than :data:`LARGE_BASE_SHARE` of that share: there a whole run costs
    several times the growth (a tile of 420 cameras and 100 new images of a synthetic
    survey: 144 s of one core whole, 28 s grown), and the new images it leaves out are
    reconstructed apart with the map's other left-out images
    (:func:`.tiling.left_out_models`), aligned to their own GPS.

    Where ``core`` marks the images the set was cut for (a tile's core, by index into the
    set; the rest is its margin, whose images take their poses from the neighbouring tile),
    only the new images of the core are judged: a tile that gains images along its edge
    places fewer of those, which no other run would place better where it counts."""
    held, registered = run.base
    new = np.asarray(run.order[held:], np.int64)
    if core is not None:
        new = new[np.asarray(core, bool)[new]]
    if len(new) == 0:
        return True
    placed = int(np.isin(new, placed_images(run.models)).sum())
    share = registered / max(held, 1) * len(new)
    if registered > LARGE_MODEL:
        return placed >= LARGE_BASE_SHARE * share
    return placed >= share - 1


def _write_database(path: Path, keypoints: Sequence[np.ndarray], pairs: list[PairMatches],
                    focal_px: float | None, first: Sequence[int] = ()) -> list[int]:
    """Write the images of ``pairs`` with their tie points and verified matches into a new
    COLMAP database; returns its images (indices), in database order: ``first`` (images a
    kept model numbers so), then the others ascending."""
    import pycolmap

    listed = set(first)
    order = [*first, *sorted(({p.a for p in pairs} | {p.b for p in pairs}) - listed)]
    db = pycolmap.Database.open(str(path))
    try:
        camera = colmap_camera(focal_px)
        camera.camera_id = db.write_camera(camera)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(camera.sensor_id)
        rig_id = db.write_rig(rig)
        for i in order:
            image_id = db.write_image(pycolmap.Image(name=str(i), camera_id=camera.camera_id))
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(db.read_image(image_id).data_id)
            db.write_frame(frame)
            db.write_keypoints(image_id, to_colmap_pixels(np.asarray(keypoints[i]))
                               .astype(np.float32))
        ids = {i: k + 1 for k, i in enumerate(order)}
        for p in pairs:
            matches = np.ascontiguousarray(p.matches, np.uint32)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration(p.config)
            geometry.inlier_matches = matches
            db.write_matches(ids[p.a], ids[p.b], matches)
            db.write_two_view_geometry(ids[p.a], ids[p.b], geometry)
    finally:
        db.close()
    return order


def _run(database: Path, folder: Path, gps: np.ndarray, *, refine: bool, seed: int,
         order: list[int], base: Path | None = None) -> _Run:
    """COLMAP's incremental mapper over ``database`` (its images ``order``), each model
    aligned to ``gps``; from the model in ``base`` with its cameras held, where given."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1  # the engine's workers run one thread each; and deterministic
    options.random_seed = seed
    options.extract_colors = False
    options.min_model_size = 3
    options.ba_refine_focal_length = refine
    options.ba_refine_extra_params = refine
    options.mapper.abs_pose_refine_focal_length = refine
    options.mapper.abs_pose_refine_extra_params = refine
    # A map's images are a few hundred keypoints apart in scale from COLMAP's usual
    # thousands: register an image from fewer inliers than COLMAP's default 30.
    options.mapper.abs_pose_min_num_inliers = MIN_POSE_INLIERS
    options.mapper.abs_pose_min_inlier_ratio = MIN_POSE_INLIER_RATIO
    if len(gps) > LARGE_MODEL:
        for name, value in LARGE_BA.items():
            setattr(options, name, value)
        options.mapper.ba_global_ignore_redundant_points3D = True
    if base is not None:
        options.fix_existing_frames = True
    out = folder / ("extended" if base is not None else "refined" if refine else "held")
    out.mkdir(exist_ok=True)
    pycolmap.set_random_seed(seed)
    # COLMAP logs every registration to the process's stderr, and a run that finds no
    # model as an error ("Failed to create any sparse model"): an outcome this module
    # handles (the other run, or no geometry, which the build reports), not a fault, so
    # only its fatal messages are let through
    pycolmap.logging.minloglevel = pycolmap.logging.FATAL
    models = pycolmap.incremental_mapping(str(database), str(folder), str(out), options,
                                          input_path="" if base is None else str(base))
    recs = [rec for _, rec in sorted(models.items())]
    return _Run(align_models(recs, gps, seed), recs, order)


def _count(models: list[TileModel] | None) -> int:
    """Distinct images the models place."""
    return len(placed_images(models))


def _good(models: list[TileModel] | None, focal_px: float, n: int) -> bool:
    """Whether a run with refined intrinsics can stand: enough images placed, and the
    largest model's focal length near the EXIF's."""
    return bool(models) and _count(models) >= GOOD_SHARE * n \
        and not _focal_strays(models, focal_px)


def _focal_strays(models: list[TileModel] | None, focal_px: float) -> bool:
    """Whether the largest model's focal length lies further than
    :data:`MAX_FOCAL_CHANGE` from the EXIF's."""
    if not models:
        return False
    largest = max(models, key=lambda m: len(m.images))
    return abs(largest.camera[0] / COLMAP_SCALE / focal_px - 1.0) > MAX_FOCAL_CHANGE


