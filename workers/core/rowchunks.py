"""A packed map's rows per image stored in chunks that revisions of a map share on disk.

A packed map's rows of images (its SIFT and ORB keypoints, descriptors and reduction mask,
the 3-D points of its keypoints, and each image's global features and place descriptors) are
nearly all of a revision's disk: 126 of the 133 MiB of the 1,000-image benchmark map's. An
update that adds a hundred images leaves the rows of every other image as they were (the
place descriptors too, while it keeps the map's vocabularies), so those arrays are saved in
chunks of whole images, each file named by a digest of its bytes, and a revision packed from
an earlier one hard-links every chunk the earlier one already holds instead of writing it
again. Each revision's folder stays whole on its own (moving or deleting one never touches
another; the file system frees a chunk with its last link). A packed revision's files are
never written again, so a file shared by several revisions never changes under one of them.

Chunks end where the image names say, not at fixed counts: a chunk ends after an image
whose name hashes to a multiple of :data:`CHUNK_IMAGES` (and after four times as many
images at most), so adding or deleting an image changes only the chunk that holds it; and
after every image that ended a chunk in the revision it was packed from
(:mod:`.mapfiles`), so that appended images start chunks of their own.

On load each chunk is memory-mapped on its own and :class:`ChunkedRows` serves an image's
rows as a view of its chunk, as one contiguous file would, gathers rows by index from the
chunks that hold them, and multiplies the rows by a vector chunk by chunk (a frame's place
descriptor against every map image's); anything else reads a gathered copy.
"""

from __future__ import annotations

import filecmp
import hashlib
import os
from collections.abc import Collection, Sequence
from pathlib import Path

import numpy as np

CHUNK_IMAGES: int = 256
"""Images per chunk on average (SIFT descriptors of 256 images: about 10 MB)."""

def chunk_bounds(names: Sequence[str], *, every: int = CHUNK_IMAGES,
                 ends: Collection[str] = ()) -> list[int]:
    """Image indices where chunks start, ``0`` first, and ``len(names)`` last.

    A chunk ends after an image whose name hashes to a multiple of ``every``, after an
    image named in ``ends`` (one that ended a chunk in an earlier revision), or after
    ``4 * every`` images; an empty map has one empty chunk."""
    bounds = [0]
    for i, name in enumerate(names):
        h = int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little")
        if h % every == 0 or name in ends or i + 1 - bounds[-1] >= 4 * every:
            bounds.append(i + 1)
    if bounds[-1] != len(names) or len(bounds) == 1:
        bounds.append(len(names))
    return bounds


def _digest(arr: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=10)
    h.update(f"{arr.dtype.str}{arr.shape}".encode())
    h.update(np.ascontiguousarray(arr).reshape(-1).view(np.uint8))
    return h.hexdigest()


def save_chunked(folder: Path, stem: str, rows: np.ndarray, offsets: np.ndarray,
                 bounds: Sequence[int], *, share: Path | None = None) -> list[list]:
    """Save ``rows`` (one or more per image, image ``i`` owning
    ``rows[offsets[i]:offsets[i + 1]]``) in ``folder`` as chunks of the images between
    consecutive ``bounds``; each is ``{stem}-{digest}.npy``, hard-linked from ``share`` (an
    earlier revision's folder) where that holds the same file. Returns the chunks as
    ``[file name, rows]`` for the revision's ``meta.json``."""
    offsets = np.asarray(offsets)
    out = []
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        part = np.asarray(rows[int(offsets[start]):int(offsets[stop])])
        name = f"{stem}-{_digest(part)}.npy"
        target = folder / name
        if not target.exists() and not (share is not None and _link(share / name, target)):
            np.save(target, part)
        out.append([name, len(part)])
    return out


def _link(source: Path, target: Path) -> bool:
    """Hard-link ``source`` at ``target``; False where it is missing or cannot be linked
    (another file system), and the chunk is written instead."""
    try:
        os.link(source, target)
    except OSError:
        return False
    return True


def load_chunked(folder: Path, chunks: Sequence[Sequence], *, mmap: bool = True,
                 ) -> ChunkedRows:
    """The rows :func:`save_chunked` saved, from its ``[file name, rows]`` list."""
    mode = "r" if mmap else None
    parts = [np.load(folder / name, mmap_mode=mode) for name, _ in chunks]
    for part, (name, n) in zip(parts, chunks, strict=True):
        if len(part) != int(n):
            raise ValueError(f"chunk {name} holds {len(part)} rows, not {n}")
    return ChunkedRows(parts)


class ChunkedRows:
    """Rows held in consecutive chunks, read like one array.

    A slice within one chunk (an image's rows never straddle two) is a view of it, of a
    memory-mapped chunk a view of the file's pages; anything else (a slice across chunks,
    ``np.asarray``) gathers a copy.
    """

    def __init__(self, parts: Sequence[np.ndarray]) -> None:
        if not parts:
            raise ValueError("chunked rows need at least one chunk")
        tails = {(p.dtype, p.shape[1:]) for p in parts}
        if len(tails) != 1:
            raise ValueError(f"chunks disagree on their rows: {sorted(map(str, tails))}")
        self.parts = list(parts)
        self.starts = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
        self.dtype = parts[0].dtype
        self.shape = (int(self.starts[-1]), *parts[0].shape[1:])
        self.ndim = len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        if isinstance(key, slice) and key.step in (None, 1):
            start, stop, _ = key.indices(len(self))
            if start >= stop:
                return self.parts[0][:0]
            k = int(np.searchsorted(self.starts, start, side="right")) - 1
            if stop <= self.starts[k + 1]:
                return self.parts[k][start - self.starts[k]:stop - self.starts[k]]
        elif not isinstance(key, tuple | slice):
            rows = np.asarray(key)
            if rows.dtype.kind in "iu" and rows.ndim == 1:
                return self._take(rows)
            if rows.dtype.kind in "iu" and rows.ndim == 0:
                return self._take(rows[None])[0]
        return np.asarray(self)[key]

    def _take(self, rows: np.ndarray) -> np.ndarray:
        """Rows by index (one image's keypoints, a frame's matches), gathered from the
        chunks that hold them."""
        n = len(self)
        if len(rows) and (rows.min() < -n or rows.max() >= n):
            raise IndexError(f"row index out of range for {n} rows")
        rows = np.where(rows < 0, rows + n, rows)
        which = np.searchsorted(self.starts, rows, side="right") - 1
        if len(rows) == 0 or which.min() == which.max():
            k = int(which[0]) if len(rows) else 0
            return np.asarray(self.parts[k][rows - self.starts[k]])
        out = np.empty((len(rows), *self.shape[1:]), self.dtype)
        for k in np.unique(which).tolist():
            sel = which == k
            out[sel] = self.parts[k][rows[sel] - self.starts[k]]
        return out

    def __matmul__(self, other):
        """The rows times ``other`` (a vector or a matrix), chunk by chunk: a map's place
        descriptors scored against a frame's without gathering them first."""
        other = np.asarray(other)
        if len(self.parts) == 1:
            return self.parts[0] @ other
        return np.concatenate([part @ other for part in self.parts])

    def __array__(self, dtype=None, copy=None):
        whole = np.concatenate(self.parts) if len(self.parts) > 1 else np.array(self.parts[0])
        return whole if dtype is None else whole.astype(dtype)


def share_identical(folder: Path, share: Path) -> int:
    """Replace each file of ``folder`` that ``share`` holds byte for byte under the same
    name by a hard link to it (a kept vocabulary, a chunk written before the earlier
    revision was found); the number of files now shared."""
    shared = 0
    for path in sorted(folder.iterdir()):
        other = share / path.name
        if not path.is_file() or not other.is_file() or os.path.samefile(path, other):
            continue
        if other.stat().st_size != path.stat().st_size or not filecmp.cmp(path, other,
                                                                          shallow=False):
            continue
        spare = path.with_name(path.name + ".link")
        if _link(other, spare):
            os.replace(spare, path)
            shared += 1
    return shared
