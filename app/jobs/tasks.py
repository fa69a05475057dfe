"""Map-building tasks the service hands to the worker processes (``engine.call``).

Extraction is per image and writes its features straight into the database, so that big
arrays never travel through the API process; packing reads every built image's features
back, assembles the map (with the SIFT neighbour reduction, the place descriptors'
vocabularies, trained anew for every revision and stored with it, and the map's camera
geometry) and saves it as a memory-mappable folder. Both open their own database
connection, cached per URL. They run in a worker process, so imports of the core stay inside
the functions that need them.
"""

from __future__ import annotations

import json
import logging
import uuid
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from sqlalchemy import delete, select

from vloc.app.db import make_engine, make_session_factory
from vloc.app.engine import (
    decode_orb,
    decode_sift,
    decode_vector,
    encode_local,
    encode_vector,
    encode_vocabulary,
)
from vloc.app.maps.models import ImageGlobalFeature, ImageOrb, ImageSift, MapImage, MapVocabulary
from vloc.app.sessions.pose import write_image_ids

log = logging.getLogger(__name__)

TIMINGS_FILE = "build_timings.json"
"""Seconds each stage of packing a revision took, beside the revision."""


@lru_cache(maxsize=8)
def _sessions(database_url: str):
    return make_session_factory(make_engine(database_url))


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
    with _sessions(database_url)() as db, db.begin():
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


def _tie_points(path: str | None):
    """Tie points of one map image file, or None where it cannot be read."""
    from vloc.workers.core.image import ImageError
    from vloc.workers.core.mapbuild import extract_tie_points

    if path is None or not Path(path).is_file():
        return None
    try:
        return extract_tie_points(Path(path).read_bytes())
    except (ImageError, OSError):
        log.warning("map image %s unreadable for tie points; its stored SIFT ties it", path)
        return None


def pack_map(database_url: str, map_id: str, revision: int, folder: str, *,
             lens_files: list[str] | None = None,
             image_files: dict[int, str] | None = None) -> dict:
    """Assemble every extracted image of a map into a MapData folder.

    ``lens_files`` are some of the map's image files, read for the camera's focal length
    (EXIF) that the map's camera geometry starts from. ``image_files`` (image id -> file)
    are read again for the tie points of the reconstruction
    (:func:`~vloc.workers.core.mapbuild.extract_tie_points`); an image whose file is
    missing or unreadable is tied by its stored SIFT.

    The place descriptors' vocabularies are trained here on the map's images and stored in
    ``map_vocabularies`` under ``revision`` (replacing rows a failed earlier attempt at the
    same revision left); the descriptors over ORB need every image's ORB features.

    The (wall, CPU) seconds of each stage, reading the features included, are written
    beside the revision as ``build_timings.json``.

    Returns
    -------
    dict
        ``origin`` (lat, lon, alt), ``image_ids`` (in map order) and their ``east`` and
        ``north`` in the new local frame.
    """
    from vloc.workers.core.mapbuild import ImageFeatures, assemble_map, stage, typical_focal_px

    timings: dict[str, tuple[float, float]] = {}
    with stage(timings, "reading features"), _sessions(database_url)() as db:
        rows = db.execute(
            select(MapImage, ImageSift, ImageOrb)
            .join(ImageSift, ImageSift.image_id == MapImage.id)
            .outerjoin(ImageOrb, ImageOrb.image_id == MapImage.id)
            .where(MapImage.map_id == uuid.UUID(map_id)).order_by(MapImage.id)).all()
        ids = [img.id for img, _, _ in rows]
        vectors: dict[int, dict[str, np.ndarray]] = {i: {} for i in ids}
        for feat in db.scalars(select(ImageGlobalFeature)
                               .where(ImageGlobalFeature.image_id.in_(ids))):
            vectors[feat.image_id][feat.name] = decode_vector(feat.data)
        if not rows:
            raise ValueError("the map has no image with extracted features")
        features = [ImageFeatures(vectors[img.id],
                                  decode_sift(s.n_keypoints, s.keypoints, s.descriptors),
                                  None if o is None
                                  else decode_orb(o.n_keypoints, o.keypoints, o.descriptors))
                    for img, s, o in rows]
        images = [img for img, _, _ in rows]
    with stage(timings, "tie points"):
        ties = [_tie_points((image_files or {}).get(i)) for i in ids]
    features = [replace(f, tie=t) for f, t in zip(features, ties, strict=True)]
    times = [img.captured_at.timestamp() if img.captured_at else None for img in images]
    data = assemble_map(names=[img.filename for img in images],
                        lats=[img.lat for img in images], lons=[img.lon for img in images],
                        alts=[img.alt for img in images], features=features,
                        captured_at=times, map_id=map_id, revision=revision,
                        focal_px=typical_focal_px(_readers(lens_files or [])),
                        timings=timings)
    with stage(timings, "storing vocabularies"), _sessions(database_url)() as db, db.begin():
        db.execute(delete(MapVocabulary).where(MapVocabulary.map_id == uuid.UUID(map_id),
                                               MapVocabulary.revision == revision))
        for name, vocab in sorted(data.vocabularies.items()):
            centroids, idf, projection = encode_vocabulary(vocab)
            db.add(MapVocabulary(map_id=uuid.UUID(map_id), revision=revision, name=name,
                                 branching=vocab.branching, depth=vocab.depth,
                                 binary=vocab.binary, dim=vocab.dim, centroids=centroids,
                                 idf=idf, projection=projection))
    with stage(timings, "saving"):
        data.save(folder)
        write_image_ids(folder, ids)
    (Path(folder) / TIMINGS_FILE).write_text(json.dumps(
        {name: {"wall_s": wall, "cpu_s": cpu} for name, (wall, cpu) in timings.items()},
        indent=1))
    o = data.origin
    return {"origin": (o.lat, o.lon, o.alt), "image_ids": ids,
            "east": np.asarray(data.positions)[:, 0].tolist(),
            "north": np.asarray(data.positions)[:, 1].tolist()}
