"""A map's build, run by the engine's workers (:func:`vloc.app.engine.run_task`).

Extraction is per image and writes its features straight into the database, so that big
arrays never travel through the API process; packing reads every built image's features
back, assembles the map (with the SIFT neighbour reduction, the place descriptors'
vocabularies, trained by a first or full build and kept by updates while they fit the map,
stored with every revision, and the map's camera geometry) and saves it as a
memory-mappable folder. Both open their own database
connection, cached per URL. They run in a worker process, so imports of the core stay inside
the functions that need them.
"""

from __future__ import annotations

import logging
import shutil
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from sqlalchemy import delete, select, update

from vloc.app.jobs.models import BuildJob, BuildStage
from vloc.app.maps.codecs import (
    decode_orb,
    decode_sift,
    decode_vector,
    encode_local,
    encode_vector,
    encode_vocabulary,
)
from vloc.app.maps.models import ImageGlobalFeature, ImageOrb, ImageSift, MapImage, MapVocabulary
from vloc.app.maps.revisions import revision_images, write_image_ids, write_timings
from vloc.app.tasks.database import sessions

if TYPE_CHECKING:
    from vloc.workers.core.geo import GeoOrigin

log = logging.getLogger(__name__)

_BATCH = 500
"""Rows read at a time when a map's stored features are packed."""


def extract_image(database_url: str, image_id: int, path: str, *, max_pixels: int) -> int:
    """Extract one map image's global features, raw SIFT and ORB and store them.

    Returns the number of SIFT keypoints. Raises ImageError for an undecodable file.
    """
    from vloc.workers.core.image import load_frame
    from vloc.workers.core.mapbuild import extract_image_features

    frame = load_frame(Path(path).read_bytes(), max_pixels=max_pixels)
    feats = extract_image_features(frame)
    kps, desc = encode_local(feats.sift)
    orb_kps, orb_desc = encode_local(feats.orb)
    with sessions(database_url)() as db, db.begin():
        db.execute(delete(ImageGlobalFeature).where(ImageGlobalFeature.image_id == image_id))
        db.execute(delete(ImageSift).where(ImageSift.image_id == image_id))
        db.execute(delete(ImageOrb).where(ImageOrb.image_id == image_id))
        for name, vec in sorted(feats.global_features.items()):
            db.add(ImageGlobalFeature(image_id=image_id, name=name, dim=int(vec.shape[0]),
                                      data=encode_vector(vec)))
        db.add(ImageSift(image_id=image_id, n_keypoints=len(feats.sift), keypoints=kps,
                         descriptors=desc))
        db.add(ImageOrb(image_id=image_id, n_keypoints=len(feats.orb), keypoints=orb_kps,
                        descriptors=orb_desc))
    return len(feats.sift)


def _readers(paths: list[str]):
    """A reader per file that still exists (an image may be deleted during a build)."""
    return [Path(p).read_bytes for p in paths if Path(p).is_file()]


def extract_ties(path: str | None, stem: str, donors: list[str] = ()) -> int:
    """Extract one map image file's tie points and write them beside ``stem``
    (:func:`~vloc.workers.core.tiepoints.save_tie_points`), for a build's reconstruction;
    run by the engine's workers, one image per call. Returns the number of tie points, or
    -1 where the file is missing or unreadable (the image's stored SIFT then ties it).

    Tie points already complete beside ``stem`` (a failed build's, kept for its retry: an
    image's file never changes) are kept as they are. ``donors`` are the stems of other
    maps' images of the same file (:class:`~vloc.app.jobs.service.BuildRunner` finds them
    by its hash): the first that holds tie points lends them, hard-linked, and nothing is
    extracted (:func:`~vloc.workers.core.tiepoints.link_tie_points`)."""
    from vloc.workers.core.image import ImageError
    from vloc.workers.core.tiepoints import (
        TiePointFiles,
        extract_tie_points,
        link_tie_points,
        save_tie_points,
    )

    done = TiePointFiles.find(stem)
    if done is not None:
        return len(done)
    for donor in donors:
        linked = link_tie_points(donor, stem)
        if linked >= 0:
            return linked
    if path is None or not Path(path).is_file():
        return -1
    try:
        tie = extract_tie_points(Path(path).read_bytes())
    except (ImageError, OSError):
        log.warning("map image %s unreadable for tie points; its stored SIFT ties it", path)
        return -1
    save_tie_points(tie, stem)
    return len(tie)


def plan_tie_pairs(database_url: str, map_id: str, tie_dir: str) -> dict:
    """The pairs of the map's images whose tie points its geometry still has to match
    (indices in map order, :func:`vloc.workers.core.tiepairs.plan`) and the image ids they
    index.

    ``tie_dir`` is the map's store of tie points and matched pairs, kept from build to
    build: the pairs matched there before whose images are both still in the map are kept
    at their places now (:func:`vloc.workers.core.tiepairs.keep_valid`) and left out of the
    plan, and the tie points of images no longer in the map are deleted. ``planned`` is
    the number of pairs the map's geometry matches in all."""
    from vloc.workers.core import tiepairs

    images = _read_images(database_url, map_id)
    ids = [img["id"] for img in images]
    kept = tiepairs.keep_valid(tie_dir, ids)
    _forget_tie_points(Path(tie_dir), set(ids))
    pairs = _planned_pairs(images, tie_dir)
    return {"image_ids": ids, "pairs": [p for p in pairs if p not in kept],
            "planned": len(pairs)}


def _planned_pairs(images: list[dict], tie_dir: str | Path) -> list[tuple[int, int]]:
    """The pairs (map indices) whose tie points a build of ``images`` (:func:`_read_images`)
    matches (:func:`vloc.workers.core.tiepairs.plan`), at the reach the map's store in
    ``tie_dir`` keeps (its first build's, decided and kept there by the first to ask)."""
    from vloc.workers.core import tiepairs

    return tiepairs.plan([img["lat"] for img in images], [img["lon"] for img in images],
                         [img["alt"] for img in images],
                         [np.nan if img["captured_at"] is None else img["captured_at"]
                          for img in images], [img["flight"] for img in images],
                         kept=_kept_models(tie_dir, images))


def _kept_models(tie_dir: str | Path, images: list[dict]):
    """The map's store of what its last build reconstructed, in ``tie_dir``
    (:class:`vloc.workers.core.geometry.KeptModels`), its images named by their ids."""
    from vloc.workers.core import tiles
    from vloc.workers.core.geometry import KeptModels

    return KeptModels(Path(tie_dir) / tiles.MODELS, tuple(str(img["id"]) for img in images))


def _forget_tie_points(tie_dir: Path, image_ids: set[int]) -> None:
    """Delete the tie points in ``tie_dir`` (:func:`tie_stem`) of images not in
    ``image_ids``."""
    from vloc.workers.core.tiepoints import TiePointFiles

    for suffix in TiePointFiles.SUFFIXES:
        for path in tie_dir.glob("*" + suffix):
            stem = path.name[:-len(suffix)]
            if stem.isdigit() and int(stem) not in image_ids:
                path.unlink(missing_ok=True)


def match_tie_pairs(tie_dir: str, image_ids: dict[int, int], pairs: list[tuple[int, int]],
                    batch: int) -> int:
    """Match a batch of the planned pairs (:func:`plan_tie_pairs`) from the tie points in
    ``tie_dir`` (``image_ids``: map index -> image id of the images they name); run by the
    engine's workers, the results written to ``tie_dir`` for :func:`pack_map` and later
    builds. Returns how many verified."""
    from vloc.workers.core import tiepairs

    stems = {i: tie_stem(tie_dir, image_id) for i, image_id in image_ids.items()}
    return tiepairs.match_batch(stems, [tuple(p) for p in pairs],
                                tie_pairs_file(tie_dir, batch), image_ids=image_ids)


def tie_pairs_file(tie_dir: str | Path, batch: int) -> Path:
    """Where :func:`match_tie_pairs` writes batch ``batch``'s results."""
    return Path(tie_dir) / f"pairs-{batch:06d}.npz"


def plan_tiles(database_url: str, map_id: str, tie_dir: str,
               lens_files: list[str] | None = None, *,
               origin: GeoOrigin | None = None) -> int:
    """Write the tiles of a large map's reconstruction to ``tie_dir`` from the pairs matched
    there (:mod:`vloc.workers.core.tiles`), for :func:`reconstruct_tile` to reconstruct;
    returns how many (0 for a map the packing reconstructs whole). ``origin`` is the local
    frame the build packs in (:func:`pack_map`'s), by default at the images' centroid."""
    from vloc.workers.core import tiepairs, tiles
    from vloc.workers.core.geo import local_frame
    from vloc.workers.core.mapbuild import typical_focal_px

    images = _read_images(database_url, map_id)
    known = tiepairs.load_results(tie_dir, [img["id"] for img in images])
    # the pairs this build planned, as the packing takes them: the store may also hold
    # pairs an earlier build planned that this one does not (a full build decides the
    # pairs' reach again, from the images' spacing)
    planned = _planned_pairs(images, tie_dir)
    _, xy, alt = local_frame([img["lat"] for img in images], [img["lon"] for img in images],
                             [img["alt"] for img in images], origin)
    return tiles.plan(tie_dir, [known[p] for p in planned if known.get(p) is not None], xy,
                      alt, typical_focal_px(_readers(lens_files or [])),
                      [tie_stem(tie_dir, img["id"]) for img in images],
                      times=np.array([np.nan if img["captured_at"] is None
                                      else img["captured_at"] for img in images]))


def reconstruct_tile(tie_dir: str, tile: int) -> int:
    """Reconstruct one planned tile of the map (:func:`plan_tiles`); run by the engine's
    workers, the result written to ``tie_dir`` for :func:`pack_map`."""
    from vloc.workers.core import tiles

    return tiles.reconstruct(tie_dir, tile)


PACKING_PROGRESS: dict[str, float] = {
    BuildStage.PACKING: 0.9, BuildStage.GEOMETRY: 0.92, BuildStage.SAVING: 0.98}
"""Where the progress bar stands as each stage of the packing starts."""


def _set_stage(database_url: str, job_id: str, stage: str) -> None:
    """Record the build job's stage (and its progress, for the packing's stages)."""
    values: dict = {"stage": stage}
    if stage in PACKING_PROGRESS:
        values["progress"] = PACKING_PROGRESS[stage]
    with sessions(database_url)() as db, db.begin():
        db.execute(update(BuildJob).where(BuildJob.id == uuid.UUID(job_id)).values(**values))


def tie_stem(tie_dir: str | Path, image_id: int) -> str:
    """Where a build keeps image ``image_id``'s tie points in ``tie_dir``."""
    return str(Path(tie_dir) / str(image_id))


def _read_images(database_url: str, map_id: str) -> list[dict]:
    """The map's images with extracted features, in map order: the fields a build needs."""
    with sessions(database_url)() as db:
        rows = db.execute(
            select(MapImage.id, MapImage.filename, MapImage.lat, MapImage.lon, MapImage.alt,
                   MapImage.captured_at, MapImage.flight)
            .join(ImageSift, ImageSift.image_id == MapImage.id)
            .where(MapImage.map_id == uuid.UUID(map_id)).order_by(MapImage.id)).all()
    if not rows:
        raise ValueError("the map has no image with extracted features")
    return [{"id": i, "filename": f, "lat": lat, "lon": lon, "alt": alt,
             "captured_at": t.timestamp() if t else None, "flight": flight}
            for i, f, lat, lon, alt, t, flight in rows]


def _previous(folder: str | None, image_ids: list[int]):
    """The packed revision in ``folder`` with where each of ``image_ids`` lies in it
    (:class:`~vloc.workers.core.carryover.Previous`); None without one, or where it
    cannot be read (packed before its image ids were recorded, or damaged)."""
    from vloc.workers.core.carryover import Previous
    from vloc.workers.core.mapdata import MapData

    if folder is None:
        return None
    ids = revision_images(folder).ids
    try:
        data = MapData.load(folder, mmap=True)
    except (OSError, ValueError, KeyError) as exc:
        log.warning("revision %s cannot be packed from, packing afresh: %s", folder, exc)
        return None
    if ids is None or len(ids) != len(data):
        return None
    return Previous.of(data, ids, image_ids)


def _read_features(database_url: str, map_id: str, images: list[dict], ties: list,
                   timings: dict) -> list:
    """The decoded features of ``images`` (from :func:`_read_images`), with their tie points.

    Rows are read a batch at a time and their blobs dropped once decoded, so a large map's
    stored features are never held twice."""
    from vloc.workers.core.mapbuild import ImageFeatures
    from vloc.workers.core.timings import stage

    mid = uuid.UUID(map_id)
    with stage(timings, "reading features"), sessions(database_url)() as db:
        vectors: dict[int, dict[str, np.ndarray]] = {}
        for image_id, name, data in db.execute(
                select(ImageGlobalFeature.image_id, ImageGlobalFeature.name,
                       ImageGlobalFeature.data)
                .join(MapImage, MapImage.id == ImageGlobalFeature.image_id)
                .where(MapImage.map_id == mid)
                .execution_options(yield_per=_BATCH)):
            vectors.setdefault(image_id, {})[name] = decode_vector(data)
        features = []
        for row in db.execute(
                select(MapImage.id, ImageSift.n_keypoints, ImageSift.keypoints,
                       ImageSift.descriptors, ImageOrb.n_keypoints, ImageOrb.keypoints,
                       ImageOrb.descriptors)
                .join(ImageSift, ImageSift.image_id == MapImage.id)
                .outerjoin(ImageOrb, ImageOrb.image_id == MapImage.id)
                .where(MapImage.map_id == mid).order_by(MapImage.id)
                .execution_options(yield_per=_BATCH)):
            k = len(features)
            if k >= len(images) or row[0] != images[k]["id"]:
                raise RuntimeError("the map's images changed while it was being built")
            features.append(ImageFeatures(
                vectors.pop(row[0], {}), decode_sift(row[1], row[2], row[3]),
                None if row[4] is None else decode_orb(row[4], row[5], row[6]), ties[k]))
    if len(features) != len(images):
        raise RuntimeError("the map's images changed while it was being built")
    return features


def pack_map(database_url: str, map_id: str, revision: int, folder: str, *,
             lens_files: list[str] | None = None,
             image_files: dict[int, str] | None = None, tie_dir: str | None = None,
             job_id: str | None = None, previous: str | None = None,
             share: str | None = None, chunk_images: int | None = None,
             origin: GeoOrigin | None = None) -> dict:
    """Assemble every extracted image of a map into a MapData folder, in the local frame at
    ``origin`` (by default at the images' centroid).

    ``lens_files`` are some of the map's image files, read for the camera's focal length
    (EXIF) that the map's camera geometry starts from. The tie points of the
    reconstruction are read from ``tie_dir``, where :func:`extract_ties` wrote them (the
    build runs it over the images in parallel); an image without them there has them
    extracted here from its file in ``image_files`` (image id -> file), and one whose file
    is missing or unreadable is tied by its stored SIFT. Without ``tie_dir`` they go to a
    folder beside ``folder``, removed afterwards. Pairs of them matched in ``tie_dir``
    beforehand (:func:`match_tie_pairs`) are not matched again, nor tiles of the
    reconstruction reconstructed there (:func:`reconstruct_tile`) reconstructed again; COLMAP's
    models kept there from the map's last build take in the images added since
    (:mod:`vloc.workers.core.geometry.kept`).

    The place descriptors' vocabularies are trained here on the map's images and stored in
    ``map_vocabularies`` under ``revision`` (replacing rows a failed earlier attempt at the
    same revision left); the descriptors over ORB need every image's ORB features. With
    ``previous`` (the folder of the revision the map has now), its vocabularies are kept
    while they still fit the map, with its images' descriptors and SIFT reduction masks
    (:mod:`vloc.workers.core.carryover`); a revision that cannot be read is not packed
    from. Every file of the revision in ``share`` (the map's current one, on a full build
    too) that the new one would write byte for byte is hard-linked instead, its rows per
    image saved in files of about ``chunk_images`` images each
    (:mod:`vloc.workers.core.rowchunks`).

    The (wall, CPU) seconds of each stage, reading the features included, are written
    beside the revision as ``build_timings.json``. With ``job_id``, the build job's stage and
    progress follow the packing (:data:`PACKING_PROGRESS`).

    Returns
    -------
    dict
        ``origin`` (lat, lon, alt), ``image_ids`` (in map order) and their ``east`` and
        ``north`` in the new local frame, and ``geometry``: what became of the map's camera
        geometry (:func:`vloc.workers.core.mapbuild.geometry_report`).
    """
    from vloc.workers.core import tiepairs, tiles
    from vloc.workers.core.mapbuild import assemble_map, typical_focal_px
    from vloc.workers.core.tiepoints import TiePointFiles
    from vloc.workers.core.timings import stage

    timings: dict[str, tuple[float, float]] = {}
    report: dict = {}

    def on_stage(name: str) -> None:
        if job_id is not None:
            _set_stage(database_url, job_id, name)

    on_stage(BuildStage.PACKING)
    images = _read_images(database_url, map_id)
    own = tie_dir is None
    ties_at = Path(folder).with_name(Path(folder).name + ".ties") if own else Path(tie_dir)
    ties_at.mkdir(parents=True, exist_ok=True)
    try:
        with stage(timings, "tie points"):
            ties = []
            for img in images:
                stem = tie_stem(ties_at, img["id"])
                tie = TiePointFiles.find(stem)
                if tie is None and extract_ties((image_files or {}).get(img["id"]), stem) >= 0:
                    tie = TiePointFiles.find(stem)
                ties.append(tie)
        with stage(timings, "reading tie pairs and tiles"):
            known = tiepairs.load_results(ties_at, [img["id"] for img in images])
            reconstructed = tiles.load_results(ties_at)
        # The features go straight into the map: holding no list of them here lets the
        # build drop each image's decoded copy once the map has packed them.
        data = assemble_map(names=[img["filename"] for img in images],
                            lats=[img["lat"] for img in images],
                            lons=[img["lon"] for img in images],
                            alts=[img["alt"] for img in images],
                            features=_read_features(database_url, map_id, images, ties,
                                                    timings),
                            captured_at=[img["captured_at"] for img in images],
                            flights=[img["flight"] for img in images],
                            map_id=map_id, revision=revision,
                            origin=origin, known_pairs=known,
                            known_tiles=reconstructed,
                            kept=None if own else _kept_models(ties_at, images),
                            previous=_previous(previous, [img["id"] for img in images]),
                            focal_px=typical_focal_px(_readers(lens_files or [])),
                            timings=timings, report=report,
                            on_stage=lambda name: on_stage(
                                BuildStage.GEOMETRY if name == "geometry" else name))
    finally:
        if own:
            shutil.rmtree(ties_at, ignore_errors=True)
    with stage(timings, "storing vocabularies"), sessions(database_url)() as db, db.begin():
        db.execute(delete(MapVocabulary).where(MapVocabulary.map_id == uuid.UUID(map_id),
                                               MapVocabulary.revision == revision))
        for name, vocab in sorted(data.vocabularies.items()):
            centroids, idf, projection = encode_vocabulary(vocab)
            db.add(MapVocabulary(map_id=uuid.UUID(map_id), revision=revision, name=name,
                                 branching=vocab.branching, depth=vocab.depth,
                                 binary=vocab.binary, dim=vocab.dim, centroids=centroids,
                                 idf=idf, projection=projection))
    on_stage(BuildStage.SAVING)
    with stage(timings, "saving"):
        data.save(folder, share=share, chunk_images=chunk_images)
        write_image_ids(folder, [img["id"] for img in images])
    write_timings(folder, timings)
    o = data.origin
    return {"origin": (o.lat, o.lon, o.alt), "image_ids": [img["id"] for img in images],
            "geometry": report or None,
            "east": np.asarray(data.positions)[:, 0].tolist(),
            "north": np.asarray(data.positions)[:, 1].tolist()}
