"""A map image's tie points: many SIFT keypoints at twice the working resolution, for the
map's reconstruction, and their two files on disk.

A map image keeps 300 SIFT keypoints for matching frames; tying overlapping map images
together needs ten times as many (:func:`extract_tie_points`). A build extracts them on the
engine's workers and writes each image's beside its features (:func:`save_tie_points`); the
pair matching (:mod:`workers.core.tiepairs`) and the tiles' reconstruction
(:mod:`workers.core.tiles`) read them back memory-mapped (:func:`load_tie_points`,
:class:`TiePointFiles`), and a map that holds an image of the same bytes as another map's
takes up that map's files as hard links (:func:`link_tie_points`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .image import MAX_PIXELS, WORK_SIZE, load_frame
from .sift import SiftFeatures, extract_sift

TIE_SIZE: tuple[int, int] = (640, 480)
"""Resolution the map's tie points are extracted at: twice the working resolution
(:data:`~workers.core.geometry.models.COLMAP_SCALE`)."""

TIE_KEYPOINTS: int = 3000
"""Most tie points per map image."""


def extract_tie_points(data: bytes, *, max_pixels: int = MAX_PIXELS) -> SiftFeatures:
    """SIFT tie points of one map image file, for reconstructing the map at build time.

    The 300 SIFT keypoints a map image keeps at the working resolution are what frames are
    matched against; tying overlapping map images together needs more. Extracted at
    :data:`TIE_SIZE` (up to :data:`TIE_KEYPOINTS`) and expressed in working-resolution
    pixels, they let COLMAP place 66 of the 70 seneca-uav map images in one model, where
    2,000 at 480x360 left it 40 in three. They are not stored: the build reads the image
    files again.

    Raises ImageError for an undecodable file.
    """
    frame = load_frame(data, size=TIE_SIZE, max_pixels=max_pixels)
    feats = extract_sift(frame.grey, n_features=TIE_KEYPOINTS)
    scale = WORK_SIZE[0] / TIE_SIZE[0]
    keypoints = feats.keypoints.copy()
    # pixel centres: x_work + 0.5 = scale * (x_tie + 0.5)
    keypoints[:, :2] = (keypoints[:, :2] + 0.5) * scale - 0.5
    keypoints[:, 2] *= scale
    return SiftFeatures(keypoints, feats.descriptors)


def save_tie_points(tie: SiftFeatures, stem: str | Path) -> None:
    """Write one map image's tie points beside ``stem`` (``<stem>.kp.npy``, ``.desc.npy``).

    A map image's tie points (up to :data:`TIE_KEYPOINTS` SIFT) take about 430 kB, six times
    its stored features: 21 GB for 50,000 images. A build writes them to disk as they are
    extracted (in parallel, by the engine's workers) and the reconstruction reads them back
    memory-mapped (:func:`load_tie_points`), through the page cache instead of the worker's
    own memory. Each file is written under a temporary name and renamed, the keypoints
    last: their file says the pair is complete.
    """
    kp_path, desc_path = TiePointFiles(stem).paths
    for out, arr in ((desc_path, np.ascontiguousarray(tie.descriptors, np.uint8)),
                     (kp_path, np.ascontiguousarray(tie.keypoints, np.float32))):
        tmp = out.with_name("." + out.name)
        with tmp.open("wb") as f:
            np.save(f, arr)
        tmp.replace(out)


def link_tie_points(source: str | Path, stem: str | Path) -> int:
    """Give ``stem`` the tie points written beside ``source`` as hard links to its files,
    without reading them: tie points depend on an image file's bytes alone, so another map's
    image of the same bytes has the very same ones. Returns their number, or -1 where
    ``source`` has no complete tie points (another map's, deleted meanwhile) or the files
    cannot be linked (another file system); ``stem`` is then left without any.

    Each link is made under a temporary name and renamed, the keypoints last, as
    :func:`save_tie_points` writes them. Tie-point files are never written in place (a
    new version is renamed over the old name), so the maps sharing one never see it change.
    """
    files = TiePointFiles.find(source)
    if files is None:
        return -1
    done = []
    try:
        # the descriptors first, the keypoints (which say the pair is complete) last
        for src, out in zip(reversed(files.paths), reversed(TiePointFiles(stem).paths),
                            strict=True):
            tmp = out.with_name("." + out.name)
            tmp.unlink(missing_ok=True)
            os.link(src, tmp)
            tmp.replace(out)
            done.append(out)
    except OSError:
        for path in done:
            path.unlink(missing_ok=True)
        return -1
    return len(files)


def load_tie_points(stem: str | Path) -> SiftFeatures | None:
    """Tie points written by :func:`save_tie_points`, memory-mapped; None where absent."""
    files = TiePointFiles.find(stem)
    return None if files is None else SiftFeatures(files.keypoints, files.descriptors)


class TiePointFiles:
    """One map image's tie points on disk (:func:`save_tie_points`), mapped when read.

    A memory-mapped array holds a file descriptor for as long as it lives (Python's ``mmap``
    keeps a duplicate of the file's), so every image's tie points mapped at once take two
    descriptors an image: 100,000 for a map of 50,000 images, past the usual limit of a
    process's open files. The packing hands the reconstruction these handles instead: a pair
    it still has to match maps its two images' files only while it matches them.
    """

    SUFFIXES: tuple[str, str] = (".kp.npy", ".desc.npy")
    """The two files' names after the stem's: keypoints, descriptors."""

    def __init__(self, stem: str | Path) -> None:
        stem = Path(stem)
        self._kp, self._desc = (stem.with_name(stem.name + s) for s in self.SUFFIXES)

    @property
    def paths(self) -> tuple[Path, Path]:
        """The keypoints' file and the descriptors' (:data:`SUFFIXES`)."""
        return self._kp, self._desc

    @classmethod
    def find(cls, stem: str | Path) -> TiePointFiles | None:
        """The tie points written beside ``stem``; None where they are not (complete)."""
        files = cls(stem)
        return files if files._kp.is_file() else None

    @property
    def keypoints(self) -> np.ndarray:
        return np.load(self._kp, mmap_mode="r")

    @property
    def descriptors(self) -> np.ndarray:
        return np.load(self._desc, mmap_mode="r")

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])
