"""COLMAP models kept from build to build: images added to a map join the cameras it has.

A map built once keeps, beside its tie points, the COLMAP models of each tile it reconstructed
(:func:`.tiling.reconstruct`), named by the tile's inputs (:func:`.tiling.tile_key`) and
holding, beside COLMAP's binary files, a hash of the mapper's inputs (``inputs.txt``: a tile
whose images and matches are unchanged takes its models up again, aligned to today's GPS,
without running COLMAP), the names of the database's images in database order
(``order.txt``; a name is what the caller calls an image for good: the service's image id)
and what else the reconstruction depended on (``context.txt``: COLMAP's version, the mapper's
settings, the focal length and the seed).
When the map is built again after images were added, a tile whose inputs changed starts from
the largest kept model of the same context whose images all still belong to it
(:meth:`KeptModels.base_for`):
COLMAP registers the new images into it with the kept cameras held (its
``fix_existing_frames``), the bundle adjustments moving only the new cameras and the 3-D
points (:func:`.sfm.reconstruct_images`). A tile of 400 images of a synthetic survey with 40
added took 19 CPU s so against 107 s reconstructed whole, its cameras as close to their GPS.
Images deleted from the map since leave the kept model first (:func:`load_models`): their
cameras and their observations go, the 3-D points the others still see twice or more stay,
and the tile grows from what is left as from any kept model. A build that finds no such
model (a new map, a tile whose kept images moved to another tile, a full rebuild)
reconstructs the tile whole, as before.

A large map's tiles are kept too (``tiles.json``: each tile's core and members, by name), so
that the next build cuts the map where this one did (:func:`.tiling.plan_tiles`): images
added join the tiles around them instead of moving every tile's edges. So is the reach of
its tie pairs (``reach.json``, :meth:`KeptModels.reach`): the first build decides how far
apart two images may be for their tie points to be matched, from the images' spacing, and
later builds match at that reach, so that images added do not move the pairs of the images
the map held (a spacing that moves by a few centimetres adds or drops a pair in every
tile, and every tile's inputs change with it), until images much sparser than the map's
call for a longer one (:func:`~workers.core.geometry.tie_pairs`).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ORDER_FILE = "order.txt"
CONTEXT_FILE = "context.txt"
INPUTS_FILE = "inputs.txt"
TILES_FILE = "tiles.json"
REACH_FILE = "reach.json"
MODEL_DIR = "model-{:02d}"

EXTEND_MIN_SHARE: float = 0.5
"""A kept model is a base for a tile only where its images make at least this share of the
tile's tied images: a tile mostly of new images is reconstructed whole."""


@dataclass(frozen=True)
class KeptModels:
    """The models kept in ``folder`` for a map whose images are called ``names`` (one per map
    index, stable across builds)."""

    folder: Path
    names: tuple[str, ...]

    def base_for(self, inside: np.ndarray, tied: int, context: str) -> Path | None:
        """The kept model a tile of map images ``inside`` (with ``tied`` of them in pairs)
        can grow from: the largest reconstructed in the same ``context`` whose database
        images still in the map all belong to the tile and make at least
        :data:`EXTEND_MIN_SHARE` of ``tied`` (images since deleted from the map leave it
        when it is loaded); None where there is none."""
        member = {self.names[i] for i in np.asarray(inside).tolist()}
        in_map = set(self.names)
        best, size = None, 0
        for order_file in sorted(self.folder.glob("*/" + ORDER_FILE)):
            entry = order_file.parent
            if entry.name.startswith(".") or not (entry / CONTEXT_FILE).is_file() \
                    or (entry / CONTEXT_FILE).read_text() != context:
                continue  # being written, or made otherwise
            order = [name for name in read_order(entry) if name in in_map]
            if len(order) > size and len(order) >= EXTEND_MIN_SHARE * tied \
                    and member.issuperset(order):
                best, size = order_file.parent, len(order)
        return best

    def entry(self, key: str) -> Path:
        """Where the model of a tile of inputs ``key`` is kept."""
        return self.folder / key

    def keep_only(self, keys: Iterable[str]) -> None:
        """Delete the kept models of tiles other than ``keys`` (those of the map as last
        built), and any left half-written."""
        keys = set(keys)
        if not self.folder.is_dir():
            return
        for path in self.folder.iterdir():
            if path.name not in keys and path.name not in (TILES_FILE, REACH_FILE):
                shutil.rmtree(path, ignore_errors=True)

    def reach(self) -> float | None:
        """The reach (m) of the map's tie pairs as its builds decided it (the first, or one
        whose images called for a longer one: :func:`~workers.core.geometry.tie_pairs`);
        None where none was kept."""
        path = self.folder / REACH_FILE
        return float(json.loads(path.read_text())["reach_m"]) if path.is_file() else None

    def save_reach(self, reach: float) -> None:
        """Keep the reach (m) of the map's tie pairs for the builds after this one."""
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / ("." + REACH_FILE)
        tmp.write_text(json.dumps({"reach_m": float(reach)}))
        tmp.replace(self.folder / REACH_FILE)

    def tiles(self) -> list[tuple[np.ndarray, np.ndarray]] | None:
        """The tiles of the map's last build, (core, members) in today's map indices, its
        images since deleted left out; None where none were kept."""
        path = self.folder / TILES_FILE
        if not path.is_file():
            return None
        index = {name: i for i, name in enumerate(self.names)}

        def indices(names: list[str]) -> np.ndarray:
            return np.array(sorted(index[n] for n in names if n in index), np.int64)

        return [(indices(t["core"]), indices(t["members"]))
                for t in json.loads(path.read_text())["tiles"]]

    def save_tiles(self, tiles: Iterable[tuple[np.ndarray, np.ndarray]]) -> None:
        """Keep this build's tiles, (core, members) in map indices, for the next build."""
        self.folder.mkdir(parents=True, exist_ok=True)
        body = {"tiles": [{"core": [self.names[i] for i in core.tolist()],
                           "members": [self.names[i] for i in members.tolist()]}
                          for core, members in tiles]}
        tmp = self.folder / ("." + TILES_FILE)
        tmp.write_text(json.dumps(body))
        tmp.replace(self.folder / TILES_FILE)


def read_order(folder: Path) -> list[str]:
    """The names of a kept model's database images, in database order."""
    return (folder / ORDER_FILE).read_text().split()


def save_models(recs: Sequence, names: Sequence[str], order: Sequence[int], context: str,
                inputs: str, folder: Path) -> None:
    """Keep COLMAP models ``recs`` (one run's, their images named by their index into
    ``names``) in ``folder``, their images renamed to ``names``; ``order`` is the database's
    images, in database order (indices into ``names``), ``context`` what else the run
    depended on, ``inputs`` its inputs hashed (:func:`read_inputs`). Written beside and
    moved into place whole."""
    import pycolmap

    tmp = folder.with_name("." + folder.name)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for k, rec in enumerate(recs):
        copy = pycolmap.Reconstruction(rec)
        for image in copy.images.values():
            image.name = names[int(image.name)]
        (tmp / MODEL_DIR.format(k)).mkdir()
        copy.write(str(tmp / MODEL_DIR.format(k)))
    (tmp / ORDER_FILE).write_text("".join(f"{names[i]}\n" for i in order))
    (tmp / CONTEXT_FILE).write_text(context)
    (tmp / INPUTS_FILE).write_text(inputs)
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)


def read_inputs(folder: Path) -> str | None:
    """The hash of the inputs (images, tie points' matches, context) of the run whose models
    ``folder`` keeps; a run of the same inputs gives the same models."""
    path = folder / INPUTS_FILE
    return path.read_text() if path.is_file() else None


def load_models(folder: Path, index: dict[str, int], *,
                leave_out_missing: bool = False) -> tuple[list[int], list] | None:
    """The models kept in ``folder``, their images renamed by ``index`` (name -> index of
    the set being reconstructed), with the database order they need (indices). None where
    one of their images is not in ``index``; or, with ``leave_out_missing``, such images
    (deleted from the map) are left out of the models (:func:`without_images`) and of the
    order, the others numbered by their place in it."""
    import pycolmap

    names = read_order(folder)
    missing = [name for name in names if name not in index]
    if missing and not leave_out_missing:
        return None
    kept = [name for name in names if name in index]
    # the new database lists the kept images in the same order, numbered from 1 again
    place = {name: k + 1 for k, name in enumerate(kept)}
    recs = []
    for path in sorted(folder.glob(MODEL_DIR.replace("{:02d}", "??"))):
        rec = pycolmap.Reconstruction(str(path))
        if missing:
            rec = without_images(rec, {image_id: place[image.name]
                                       for image_id, image in rec.images.items()
                                       if image.name in place})
        for image in rec.images.values():
            image.name = str(index[image.name])
        recs.append(rec)
    return [index[name] for name in kept], recs


def without_images(rec, renumber: dict[int, int]):
    """A copy of COLMAP model ``rec`` (trivial rigs: a frame per image) holding only the
    images ``renumber`` maps (image id -> new image id) and the 3-D points that two or
    more of their placed cameras still see; poses, keypoints and points as they were."""
    import pycolmap

    out = pycolmap.Reconstruction()
    for camera in rec.cameras.values():
        out.add_camera_with_trivial_rig(camera)
    for old, new in sorted(renumber.items(), key=lambda item: item[1]):
        if not rec.exists_image(old):
            continue
        image = rec.images[old]
        xy = np.array([p.xy for p in image.points2D], np.float64).reshape(-1, 2)
        copy = pycolmap.Image(name=image.name, keypoints=xy, camera_id=image.camera_id,
                              image_id=new)
        if image.has_pose:
            out.add_image_with_trivial_frame(copy, image.cam_from_world())
        else:
            out.add_image_with_trivial_frame(copy)
    posed = {old: new for old, new in renumber.items()
             if rec.exists_image(old) and rec.images[old].has_pose}
    for point in rec.points3D.values():
        track = pycolmap.Track()
        for element in point.track.elements:
            if element.image_id in posed:
                track.add_element(posed[element.image_id], element.point2D_idx)
        if track.length() >= 2:
            out.add_point3D(point.xyz, track, point.color)
    return out
