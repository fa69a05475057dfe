"""A packed map's folder: its ``.npy`` files and ``meta.json``, written and read back.

Every array of :class:`~.mapdata.MapData` is a ``.npy`` file that loads memory-mapped, so
every worker process maps the same pages. The arrays of rows per image (SIFT's and ORB's
keypoints and descriptors, the reduction mask, the geometry's 3-D points, the global
features) are saved in chunks of whole images (:mod:`.rowchunks`) that a later revision of
the map links instead of writing again where its images left them as they were; so is every
other file it would write byte for byte (a kept vocabulary). A revision packed before
chunks, one file per array, loads as it always did.

Chunks keep the ends they had: a revision packed from an earlier one also ends a chunk
after each image that ended one there, so that images appended to a map (an update's usual
case) start chunks of their own rather than joining the earlier last chunk. Each update adds
at most one such end.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from .features.distortion import VocabularyFit
from .features.shortlist import PlaceCodes
from .features.vocabulary import Vocabulary
from .geo import GeoOrigin
from .geometry import MapGeometry
from .mapdata import MapData
from .rowchunks import CHUNK_IMAGES, chunk_bounds, load_chunked, save_chunked, share_identical


def save_map(data: MapData, folder: str | Path, *, share: str | Path | None = None,
             chunk_images: int | None = None) -> Path:
    """Write ``data`` to ``folder``; the write is atomic (temporary folder, rename).

    The per-keypoint arrays, the geometry's points with them, go in chunks of about
    ``chunk_images`` images (:data:`~.rowchunks.CHUNK_IMAGES` by default); where ``share``
    names an earlier revision's folder, every chunk and every other file it holds byte for
    byte is hard-linked from it, not written, and each of its chunk ends is kept."""
    folder = Path(folder)
    share = None if share is None else Path(share)
    tmp = folder.with_name(folder.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)  # left by a save that died: its chunks may be partial
    tmp.mkdir(parents=True)
    np.save(tmp / "positions.npy", data.positions)
    np.save(tmp / "altitudes.npy", data.altitudes)
    np.save(tmp / "sift_offsets.npy", data.sift_offsets)
    np.save(tmp / "captured_at.npy", data.captured_at)
    bounds = chunk_bounds(data.names, every=chunk_images or CHUNK_IMAGES,
                          ends=chunk_ends(share))
    rows = [("sift_keypoints", data.sift_keypoints, data.sift_offsets),
            ("sift_descriptors", data.sift_descriptors, data.sift_offsets),
            ("sift_keep", data.sift_keep, data.sift_offsets)]
    if data.has_orb:
        np.save(tmp / "orb_offsets.npy", data.orb_offsets)
        rows += [("orb_keypoints", data.orb_keypoints, data.orb_offsets),
                 ("orb_descriptors", data.orb_descriptors, data.orb_offsets)]
    each = np.arange(len(data) + 1)  # one row per image
    rows += [(f"global_{name}", mat, each) for name, mat in data.global_features.items()]
    chunks = {stem: save_chunked(tmp, stem, arr, offsets, bounds, share=share)
              for stem, arr, offsets in rows}
    for name, vocab in data.vocabularies.items():
        np.save(tmp / f"vocab_{name}_centroids.npy", vocab.centroids)
        np.save(tmp / f"vocab_{name}_idf.npy", vocab.idf)
        if vocab.projection is not None:
            np.save(tmp / f"vocab_{name}_projection.npy", vocab.projection)
    for name, fit in data.vocabulary_fits.items():
        np.save(tmp / f"vocab_{name}_fit.npy", np.asarray(fit.images, np.float32))
        trained_on = (np.ones(len(fit.images), bool) if fit.trained_on is None
                      else np.asarray(fit.trained_on, bool))
        np.save(tmp / f"vocab_{name}_trained_on.npy", trained_on)
    for name, codes in data.place_codes.items():
        np.save(tmp / f"codes_{name}_basis.npy", codes.basis)
        np.save(tmp / f"codes_{name}.npy", codes.codes)
    meta = {"origin": [data.origin.lat, data.origin.lon, data.origin.alt],
            "names": list(data.names), "features": sorted(data.global_features),
            "map_id": data.map_id, "revision": data.revision, "orb": data.has_orb,
            "codes": sorted(data.place_codes), "chunks": chunks,
            "chunk_images": np.diff(bounds).tolist(),
            "vocabularies": {name: {"branching": v.branching, "depth": v.depth,
                                    "binary": v.binary, "projected": v.projection is not None,
                                    **_fit_meta(data, name)}
                             for name, v in sorted(data.vocabularies.items())}}
    if data.flights is not None:
        meta["flights"] = list(data.flights)
    (tmp / "meta.json").write_text(json.dumps(meta))
    if data.geometry is not None:
        # its points are row-aligned with the keypoints they belong to
        offsets_of = {"sift": data.sift_offsets, "orb": data.orb_offsets}
        data.geometry.save(tmp, save_rows=lambda kind, stem, points: save_chunked(
            tmp, stem, points, offsets_of[kind], bounds, share=share))
    if share is not None:
        share_identical(tmp, share)
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)
    return folder


def chunk_ends(folder: Path | None) -> frozenset[str]:
    """The names of the images that end a chunk in the revision in ``folder``; none where
    there is no such revision or it was packed before chunks."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (TypeError, OSError, ValueError):
        return frozenset()
    names, counts = meta.get("names", []), meta.get("chunk_images", [])
    return frozenset(names[k - 1] for k in np.cumsum(counts).tolist()
                     if 0 < k <= len(names))


def _fit_meta(data: MapData, name: str) -> dict:
    fit = data.vocabulary_fits.get(name)
    return {} if fit is None else {"trained_distortion": fit.trained,
                                   "trained_revision": fit.revision}


def load_map(folder: str | Path, *, mmap: bool = True) -> MapData:
    """The map :func:`save_map` wrote to ``folder``, its arrays memory-mapped (read-only)
    where ``mmap``."""
    folder = Path(folder)
    meta = json.loads((folder / "meta.json").read_text())
    mode = "r" if mmap else None
    orb = bool(meta.get("orb", False))

    def ld(name: str) -> np.ndarray:
        return np.load(folder / name, mmap_mode=mode)

    def rows(stem: str):
        if stem in meta.get("chunks", {}):
            return load_chunked(folder, meta["chunks"][stem], mmap=mmap)
        return ld(f"{stem}.npy")  # packed before chunks

    vocabularies = {
        name: Vocabulary(ld(f"vocab_{name}_centroids.npy"), int(shape["branching"]),
                         int(shape["depth"]), bool(shape["binary"]),
                         ld(f"vocab_{name}_idf.npy"),
                         ld(f"vocab_{name}_projection.npy") if shape["projected"] else None)
        for name, shape in meta.get("vocabularies", {}).items()}
    fits = {name: VocabularyFit(float(shape["trained_distortion"]),
                                ld(f"vocab_{name}_fit.npy"), int(shape["trained_revision"]),
                                ld(f"vocab_{name}_trained_on.npy"))
            for name, shape in meta.get("vocabularies", {}).items()
            if "trained_distortion" in shape}
    return MapData(origin=GeoOrigin(*meta["origin"]), names=tuple(meta["names"]),
                   positions=ld("positions.npy"), altitudes=ld("altitudes.npy"),
                   global_features={n: rows(f"global_{n}") for n in meta["features"]},
                   sift_offsets=ld("sift_offsets.npy"), sift_keypoints=rows("sift_keypoints"),
                   sift_descriptors=rows("sift_descriptors"), map_id=meta["map_id"],
                   revision=int(meta["revision"]), captured_at=ld("captured_at.npy"),
                   flights=meta.get("flights"), sift_keep=rows("sift_keep"),
                   vocabularies=vocabularies, vocabulary_fits=fits,
                   geometry=MapGeometry.load(folder, mmap=mmap),
                   orb_offsets=ld("orb_offsets.npy") if orb else None,
                   orb_keypoints=rows("orb_keypoints") if orb else None,
                   orb_descriptors=rows("orb_descriptors") if orb else None,
                   place_codes={name: PlaceCodes(ld(f"codes_{name}_basis.npy"),
                                                 ld(f"codes_{name}.npy"))
                                for name in meta.get("codes", [])})
