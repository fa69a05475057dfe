"""Folders of geotagged images: loading, map/query splits, frames and local positions.

A data set is a folder of JPEG/PNG images, directly or in ``images/``, each positioned by
its EXIF GPS (the exploration phase of Erhard et al., Flyphone section 3) or, failing that,
by an optional CSV beside the images (``filename`` plus any of ``lat, lon, alt_m, captured_at,
pass``). Evaluation splits the images into a map and a query sequence, either by recorded
pass (the rounds of Weiss et al. section V) or by alternating images.
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from vloc.workers.core.exif import GpsError, read_gps
from vloc.workers.core.geo import GeoOrigin, check_lat_lon
from vloc.workers.core.image import WORK_SIZE, Frame, ImageError, load_frame
from vloc.workers.core.metadata import METADATA_FIELDS, FrameMetadata

IMAGE_SUFFIXES: tuple[str, ...] = (".jpg", ".jpeg", ".png")
CSV_NAMES: tuple[str, ...] = ("ground_truth.csv", "positions.csv")
SPLIT_RULES: tuple[str, ...] = ("pass", "alternate")
# CSV header spellings accepted for each field (compared in lower case).
_COLUMNS = {
    "lat": ("lat", "latitude"),
    "lon": ("lon", "lng", "longitude"),
    "alt": ("alt_m", "alt", "altitude"),
    "captured_at": ("captured_at",),
    "pass": ("pass",),
    # optional device metadata per frame (workers.core.metadata.FrameMetadata)
    **{name: (name,) for name in METADATA_FIELDS},
}


class DatasetError(ValueError):
    """The folder or its CSV cannot be used as a data set, or a split is impossible."""


@dataclass(frozen=True, slots=True)
class DatasetImage:
    """One positioned image of a data set.

    Attributes
    ----------
    name : str
        File name (no folder).
    path : Path
    lat, lon : float
        WGS84 degrees used as the image's position.
    alt : float or None
        Metres above sea level.
    captured_at : datetime or None
        From EXIF when present, else from the CSV.
    pass_ : int or None
        Traversal number from the CSV's ``pass`` column.
    source : str
        ``"exif"`` when the position comes from EXIF GPS, ``"csv"`` when from the CSV.
    truth_lat, truth_lon, truth_alt : float or None
        The CSV's position for this image (ground truth for evaluation), None without one.
    metadata : FrameMetadata or None
        What the device reported with the frame, from the CSV's metadata columns
        (``heading_deg``, ``gps_lat``, ``gps_accuracy_m`` ...), None without any.
    """

    name: str
    path: Path
    lat: float
    lon: float
    alt: float | None
    captured_at: datetime | None
    pass_: int | None
    source: str
    truth_lat: float | None = None
    truth_lon: float | None = None
    truth_alt: float | None = None
    metadata: FrameMetadata | None = None


@dataclass(frozen=True, slots=True)
class Dataset:
    """A loaded data set: images in capture order and the files that were left out.

    Attributes
    ----------
    folder : Path
    image_dir : Path
        ``folder`` or ``folder/images``.
    csv_path : Path or None
    images : tuple of DatasetImage
        Sorted by capture time when every image has one, else by file name (natural order).
    skipped : tuple of (name, reason)
        Images that could not be positioned or read.
    """

    folder: Path
    image_dir: Path
    csv_path: Path | None
    images: tuple[DatasetImage, ...]
    skipped: tuple[tuple[str, str], ...]

    def __len__(self) -> int:
        return len(self.images)

    @property
    def passes(self) -> dict[int, int]:
        """Number of images per pass, in pass order (empty without a pass column)."""
        counts = Counter(im.pass_ for im in self.images if im.pass_ is not None)
        return dict(sorted(counts.items()))

    def origin(self) -> GeoOrigin:
        """A local frame at the centroid of the image positions."""
        return GeoOrigin.centroid_of([im.lat for im in self.images],
                                     [im.lon for im in self.images])

    def summary(self) -> str:
        """A few lines of text describing the data set."""
        sources = Counter(im.source for im in self.images)
        lines = [
            f"{self.folder.name}: {len(self)} images ({sources['exif']} positioned by EXIF, "
            f"{sources['csv']} by CSV), {len(self.skipped)} skipped",
            f"  images: {self.image_dir}",
            f"  csv: {self.csv_path.name if self.csv_path else 'none'}",
        ]
        if self.passes:
            lines.append("  passes: " + ", ".join(f"{p} ({n})" for p, n in self.passes.items()))
        times = [im.captured_at for im in self.images if im.captured_at is not None]
        if times:
            lines.append(f"  captured: {min(times, key=_instant)} to {max(times, key=_instant)}")
        if self.images:
            origin = self.origin()
            xy = positions_enu(self.images, origin)
            span = xy.max(axis=0) - xy.min(axis=0)
            lines.append(f"  extent: {span[0]:.0f} m east x {span[1]:.0f} m north, centred on "
                         f"{origin.lat:.6f}, {origin.lon:.6f}")
        lines += [f"  skipped {name}: {reason}" for name, reason in self.skipped[:10]]
        if len(self.skipped) > 10:
            lines.append(f"  ... and {len(self.skipped) - 10} more skipped")
        return "\n".join(lines)


def load_dataset(folder: str | Path, *, csv_path: str | Path | None = None) -> Dataset:
    """Load a folder of geotagged images.

    Parameters
    ----------
    folder : str or Path
        Holds the images directly or in ``images/``; suffixes ``.jpg .jpeg .png`` in any case.
    csv_path : str or Path, optional
        The positions CSV. By default ``ground_truth.csv``, ``positions.csv`` or the only
        ``*.csv`` in the folder or its ``images/``.

    Returns
    -------
    Dataset
        Each image is positioned by EXIF GPS when present, else by the CSV's lat/lon;
        images with neither, unreadable files and bad CSV cells go to ``skipped``.

    Raises
    ------
    FileNotFoundError
        The folder (or the given CSV) does not exist.
    DatasetError
        No images, several candidate CSVs, or a CSV without a ``filename`` column or with
        a file listed twice.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"data set folder {folder} does not exist or is not a folder")
    image_dir = _image_dir(folder)
    files = _image_files(image_dir)
    if not files:
        raise DatasetError(f"no {'/'.join(IMAGE_SUFFIXES)} images in {folder} "
                           f"or {folder / 'images'}")
    csv_file = Path(csv_path) if csv_path is not None else _find_csv(folder, image_dir)
    if csv_file is not None and not csv_file.is_file():
        raise FileNotFoundError(f"CSV file {csv_file} does not exist")
    rows = _read_csv(csv_file) if csv_file is not None else {}
    # Exact names first; case-insensitive as a fallback for "IMG_1.JPG" listed as "img_1.jpg".
    folded = {name.lower(): row for name, row in rows.items()}
    images, skipped = [], []
    for path in files:
        row = rows.get(path.name) or folded.get(path.name.lower())
        try:
            images.append(_position(path, row, csv_file.name if csv_file else ""))
        except _Skip as why:
            skipped.append((path.name, str(why)))
    return Dataset(folder=folder, image_dir=image_dir, csv_path=csv_file,
                   images=tuple(_capture_order(images)), skipped=tuple(skipped))


def split_by_pass(ds: Dataset, map_pass: int | Sequence[int], query_pass: int,
                  ) -> tuple[list[DatasetImage], list[DatasetImage]]:
    """Images of ``map_pass`` and of ``query_pass``, each in capture order.

    ``map_pass`` may name several passes: a map of several flights (over the same ground in
    other light, say), its images pass by pass in the order given."""
    _require_passes(ds)
    map_passes = [map_pass] if isinstance(map_pass, int) else list(map_pass)
    if not map_passes or len(set(map_passes)) < len(map_passes):
        raise DatasetError(f"map passes {map_passes}: name each pass once")
    if query_pass in map_passes:
        raise DatasetError(f"pass {query_pass} is both a map pass and the query pass")
    present = ", ".join(f"{p} ({n} images)" for p, n in ds.passes.items())
    for p in (*map_passes, query_pass):
        if p not in ds.passes:
            raise DatasetError(f"pass {p} has no images; passes present: {present}")
    return ([im for p in map_passes for im in ds.images if im.pass_ == p],
            [im for im in ds.images if im.pass_ == query_pass])


def split_alternate(ds: Dataset) -> tuple[list[DatasetImage], list[DatasetImage]]:
    """Even-indexed images (0, 2, ...) as map, odd-indexed as query, in capture order."""
    if len(ds.images) < 2:
        raise DatasetError(f"the alternate split needs at least 2 images, {ds.folder.name} "
                           f"has {len(ds.images)}")
    return list(ds.images[0::2]), list(ds.images[1::2])


def split(ds: Dataset, rule: str = "pass", map_pass: int | Sequence[int] | None = None,
          query_pass: int | None = None) -> tuple[list[DatasetImage], list[DatasetImage]]:
    """Split into (map images, query images) by a named rule.

    ``rule="pass"``: ``map_pass`` defaults to the lowest pass and ``query_pass`` to the
    lowest other pass. ``rule="alternate"``: see :func:`split_alternate`; takes no passes.
    """
    if rule == "alternate":
        if map_pass is not None or query_pass is not None:
            raise DatasetError("the 'alternate' split takes no map_pass or query_pass")
        return split_alternate(ds)
    if rule != "pass":
        raise DatasetError(f"unknown split rule {rule!r}; valid rules: {', '.join(SPLIT_RULES)}")
    _require_passes(ds)
    passes = list(ds.passes)
    if map_pass is None:
        map_pass = passes[0]
    if query_pass is None:
        used = {map_pass} if isinstance(map_pass, int) else set(map_pass)
        others = [p for p in passes if p not in used]
        if not others:
            raise DatasetError(f"{ds.folder.name} has only pass {map_pass}; "
                               "the query needs another pass")
        query_pass = others[0]
    return split_by_pass(ds, map_pass, query_pass)


def read_image(img: DatasetImage) -> bytes:
    """The image file's bytes."""
    return img.path.read_bytes()


def load_frames(images: list[DatasetImage], size: tuple[int, int] = WORK_SIZE,
                workers: int | None = None) -> list[Frame]:
    """Decode and resize images to the working resolution, in the order given.

    Threads suffice: OpenCV's decoder and resize release the GIL.
    ``workers=None`` uses up to 4 threads, ``workers=1`` runs in the calling thread.
    """
    def one(img: DatasetImage) -> Frame:
        return load_frame(read_image(img), size=size)

    n = min(4, os.cpu_count() or 1) if workers is None else int(workers)
    if n <= 1 or len(images) <= 1:
        return [one(img) for img in images]
    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(one, images))


def positions_enu(images: list[DatasetImage], origin: GeoOrigin) -> np.ndarray:
    """Image positions in the local frame of ``origin``.

    Returns
    -------
    xy : (N, 2) float64 ndarray
        East and north in metres (altitude ignored: the map frame is planar).
    """
    if not images:
        return np.zeros((0, 2), dtype=np.float64)
    east, north = origin.to_local([im.lat for im in images], [im.lon for im in images])
    return np.column_stack([east, north]).astype(np.float64, copy=False)


def _require_passes(ds: Dataset) -> None:
    if not ds.passes:
        raise DatasetError(f"{ds.folder.name} has no pass column: give a CSV with 'pass' "
                           "or use the 'alternate' split")


class _Skip(Exception):
    """An image that cannot join the data set; the message is the reason."""


def _image_dir(folder: Path) -> Path:
    for child in sorted(folder.iterdir()):
        if child.is_dir() and child.name.lower() == "images" and _image_files(child):
            return child
    return folder


def _image_files(folder: Path) -> list[Path]:
    # Dot files are editor and macOS metadata ("._IMG_1.jpg"), not images.
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                  and p.suffix.lower() in IMAGE_SUFFIXES)


def _find_csv(folder: Path, image_dir: Path) -> Path | None:
    dirs = [folder] if image_dir == folder else [folder, image_dir]
    found = [p for d in dirs for p in sorted(d.iterdir())
             if p.is_file() and p.suffix.lower() == ".csv"]
    for name in CSV_NAMES:
        named = [p for p in found if p.name.lower() == name]
        if named:
            return named[0]
    if len(found) > 1:
        raise DatasetError(f"several CSV files ({', '.join(p.name for p in found)}); name one "
                           f"{' or '.join(CSV_NAMES)} or pass csv_path")
    return found[0] if found else None


def _read_csv(path: Path) -> dict[str, dict[str, str]]:
    """Rows keyed by file name, cells keyed by the canonical names of ``_COLUMNS``."""
    with open(path, newline="", encoding="utf-8-sig") as fh:
        reader = csv.DictReader(fh)
        header = {(h or "").strip().lower(): h for h in reader.fieldnames or []}
        if "filename" not in header:
            raise DatasetError(f"{path.name} has no 'filename' column "
                               f"(columns: {', '.join(header) or 'none'})")
        fields = {key: next((header[a] for a in aliases if a in header), None)
                  for key, aliases in _COLUMNS.items()}
        rows: dict[str, dict[str, str]] = {}
        for row in reader:
            name = Path((row[header["filename"]] or "").strip()).name
            if not name:
                continue
            if name in rows:
                raise DatasetError(f"{path.name} lists {name} more than once")
            rows[name] = {k: (row[c] or "").strip() for k, c in fields.items() if c is not None}
    return rows


def _parse_row(row: dict[str, str]) -> dict:
    """CSV cells -> typed values; ValueError names the bad cell."""
    out: dict = {}
    lat, lon = row.get("lat", ""), row.get("lon", "")
    if bool(lat) != bool(lon):
        raise ValueError("has lat without lon or lon without lat")
    if lat:
        try:
            out["lat"], out["lon"] = float(lat), float(lon)
        except ValueError:
            raise ValueError(f"lat/lon not numeric: {lat!r}, {lon!r}") from None
        check_lat_lon(out["lat"], out["lon"])
    if row.get("alt"):
        out["alt"] = float(row["alt"])
        if not math.isfinite(out["alt"]):
            raise ValueError(f"alt must be finite, got {row['alt']!r}")
    if row.get("captured_at"):
        out["captured_at"] = datetime.fromisoformat(row["captured_at"])
    if row.get("pass"):
        out["pass"] = int(row["pass"])
    cells = {name: row[name] for name in METADATA_FIELDS if row.get(name)}
    if cells:
        try:
            out["metadata"] = FrameMetadata(**{k: float(v) for k, v in cells.items()})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"bad metadata: {exc}") from None
    return out


def _position(path: Path, row: dict[str, str] | None, csv_name: str) -> DatasetImage:
    try:
        given = _parse_row(row) if row else {}
    except ValueError as exc:
        raise _Skip(f"bad {csv_name} row: {exc}") from None
    gps_problem = ""
    try:
        tag = read_gps(path.read_bytes())
    except GpsError as exc:
        tag, gps_problem = None, f"malformed EXIF GPS ({exc}); "
    except (ImageError, OSError) as exc:
        raise _Skip(f"unreadable image: {exc}") from None
    if tag is not None:
        lat, lon, alt, source = tag.lat, tag.lon, tag.alt, "exif"
    elif "lat" in given:
        lat, lon, alt, source = given["lat"], given["lon"], given.get("alt"), "csv"
    else:
        raise _Skip(f"{gps_problem or 'no EXIF GPS; '}no position in "
                    f"{csv_name or 'a CSV (none found)'}")
    captured = tag.captured_at if tag is not None and tag.captured_at else None
    return DatasetImage(
        name=path.name, path=path, lat=lat, lon=lon, alt=alt,
        captured_at=captured or given.get("captured_at"), pass_=given.get("pass"),
        source=source, truth_lat=given.get("lat"), truth_lon=given.get("lon"),
        truth_alt=given.get("alt"), metadata=given.get("metadata"))


def _instant(when: datetime) -> datetime:
    """Comparable key for naive and aware times (naive ones are taken as UTC)."""
    return when.astimezone(UTC).replace(tzinfo=None) if when.tzinfo is not None else when


def _natural_key(name: str) -> tuple:
    # "IMG_2" before "IMG_10", as a person would number them.
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name.lower()))


def _capture_order(images: list[DatasetImage]) -> list[DatasetImage]:
    if images and all(im.captured_at is not None for im in images):
        return sorted(images, key=lambda im: (_instant(im.captured_at), _natural_key(im.name)))
    return sorted(images, key=lambda im: _natural_key(im.name))
