"""The frames a simulated device sends: a data set's query pass, optionally relit.

Relit frames are made exactly as ``vloc eval`` makes them (the working-size colour frame
through :func:`~workers.core.evaluation.photometric.apply_variant` with ``variant_rng(seed, i)``) and
sent as lossless PNG, so the server's decoder sees the same pixels the offline evaluation
does. Unrelit frames are sent as the original files.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from vloc.workers.core.evaluation.datasets import Dataset, DatasetImage, load_dataset, split


@dataclass(frozen=True, slots=True)
class DeviceFrame:
    """One frame of the replayed sequence.

    Attributes
    ----------
    index : int
        Position in the query sequence; sent as the frame's ``seq``.
    data : bytes
        JPEG or PNG file.
    content_type : str
    captured_at : datetime or None
    truth_lat, truth_lon : float
        Ground truth: the CSV's position where the data set has one, else the image's tag.
    metadata : dict or None
        The device's sensor reports sent with the frame (``FrameMetadata.to_dict()``).
    """

    index: int
    name: str
    data: bytes
    content_type: str
    captured_at: datetime | None
    truth_lat: float
    truth_lon: float
    metadata: dict | None = None


@dataclass
class ReplayData:
    dataset: Dataset
    map_images: list[DatasetImage]
    frames: list[DeviceFrame]
    photometric: str


def load_replay_data(folder: str | Path, *, rule: str = "pass", map_pass: int | None = None,
                     query_pass: int | None = None, photometric: str = "none",
                     seed: int = 0, limit: int | None = None,
                     metadata: tuple[str, ...] = (),
                     gps_accuracy: float | None = None) -> ReplayData:
    """Split a data set folder into map images and the device's frames.

    Parameters
    ----------
    folder : path
        A data set folder as ``vloc eval`` reads it.
    rule, map_pass, query_pass
        As :func:`workers.core.evaluation.datasets.split`.
    photometric : str
        One of :data:`workers.core.evaluation.photometric.VARIANTS`.
    seed : int
        Seeds the photometric variant of frame ``i`` (``variant_rng(seed, i)``).
    limit : int, optional
        Replay only the first ``limit`` query frames.
    metadata : tuple of str
        Kinds of device metadata to send with each frame (``heading``, ``gps``,
        ``velocity``, ``altitude``), from the data set's CSV columns; ``gps`` without GPS
        columns is simulated from the truth when ``gps_accuracy`` (metres) is given.

    Raises
    ------
    DatasetError, FileNotFoundError, ValueError
    """
    from vloc.workers.core.evaluation.photometric import VARIANTS

    if photometric not in VARIANTS:
        raise ValueError(f"unknown photometric variant {photometric!r}; "
                         f"valid: {', '.join(VARIANTS)}")
    ds = load_dataset(folder)
    map_images, query_images = split(ds, rule, map_pass=map_pass, query_pass=query_pass)
    if limit is not None:
        query_images = query_images[:limit]
    frames = [_device_frame(i, img, photometric, seed) for i, img in enumerate(query_images)]
    if metadata:
        frames = _with_metadata(frames, query_images, tuple(metadata), gps_accuracy, seed)
    return ReplayData(ds, list(map_images), frames, photometric)


def _with_metadata(frames: list[DeviceFrame], images: list[DatasetImage],
                   kinds: tuple[str, ...], gps_accuracy: float | None,
                   seed: int) -> list[DeviceFrame]:
    """The frames with the named metadata: the data set's own, or a simulated GPS fix
    (the truth plus Gaussian noise of ``gps_accuracy`` metres per axis, seeded)."""
    import dataclasses

    import numpy as np

    from vloc.workers.core.geo import GeoOrigin
    from vloc.workers.core.metadata import METADATA_KINDS, FrameMetadata

    unknown = set(kinds) - set(METADATA_KINDS)
    if unknown:
        raise ValueError(f"unknown metadata kinds {sorted(unknown)}; valid: "
                         f"{', '.join(METADATA_KINDS)}")
    rng = np.random.default_rng(seed)
    out = []
    for frame, img in zip(frames, images, strict=True):
        fields = (img.metadata.only(kinds) if img.metadata is not None else FrameMetadata()
                  ).to_dict()
        if "gps" in kinds and "gps_lat" not in fields:
            if gps_accuracy is None:
                raise ValueError("the data set has no GPS columns: give a GPS accuracy to "
                                 "simulate a fix from the truth")
            here = GeoOrigin(frame.truth_lat, frame.truth_lon)
            lat, lon = here.to_wgs84(*rng.normal(0.0, gps_accuracy, size=2))
            fields.update(gps_lat=float(lat), gps_lon=float(lon), gps_accuracy_m=gps_accuracy)
        if "altitude" in kinds and "altitude_m" not in fields and img.alt is not None:
            fields["altitude_m"] = float(img.alt)
        out.append(dataclasses.replace(frame, metadata=FrameMetadata(**fields).to_dict()
                                       if fields else None))
    marker = {"heading": "heading_deg", "velocity": "velocity_east"}
    missing = [k for k in kinds if k in marker
               and not any(f.metadata and marker[k] in f.metadata for f in out)]
    if missing:
        raise ValueError(f"the data set has no {', '.join(missing)} columns to send")
    return out


def _device_frame(index: int, img: DatasetImage, photometric: str, seed: int) -> DeviceFrame:
    from vloc.clients.sdk._requests import image_content_type

    data = img.path.read_bytes()
    if photometric != "none":
        data = _relit_png(data, photometric, seed, index)
    return DeviceFrame(
        index=index, name=img.name, data=data, content_type=image_content_type(data, img.name),
        captured_at=img.captured_at,
        truth_lat=img.truth_lat if img.truth_lat is not None else img.lat,
        truth_lon=img.truth_lon if img.truth_lon is not None else img.lon)


def _relit_png(data: bytes, variant: str, seed: int, index: int) -> bytes:
    import cv2

    from vloc.workers.core.evaluation.photometric import apply_variant, variant_rng
    from vloc.workers.core.image import load_frame

    colour = apply_variant(load_frame(data).colour, variant, rng=variant_rng(seed, index))
    ok, buf = cv2.imencode(".png", colour)
    if not ok:
        raise ValueError(f"could not encode the relit frame {index} as PNG")
    return buf.tobytes()
