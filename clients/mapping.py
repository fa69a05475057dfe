"""Filling a map from a data set folder over HTTP, and building it: what ``vloc map import``,
``vloc replay --build-map`` and ``vloc demo`` share.

Images positioned by their own EXIF GPS go up in batches; images positioned only by the
folder's CSV go one at a time with ``lat``/``lon`` form fields. Upload order is capture
order, which is the order of the map the server builds (the same order ``vloc eval`` uses).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from vloc.clients.sdk import APIError, Client, ImageRejection, Job
from vloc.workers.core.evaluation.datasets import DatasetImage

BATCH_FILES = 8
BATCH_BYTES = 16 * 2**20


@dataclass
class ImportSummary:
    """What an import did: counts of accepted files and every rejection."""

    accepted: int = 0
    rejected: list[ImageRejection] = field(default_factory=list)

    @property
    def total(self) -> int:
        return self.accepted + len(self.rejected)


def _batches(images: Sequence[DatasetImage],
             flight_of: Callable[[DatasetImage], str | None] = lambda img: None,
             ) -> list[list[DatasetImage]]:
    """Consecutive runs of one flight: EXIF-positioned images grouped by count and size, the
    others alone."""
    out: list[list[DatasetImage]] = []
    run: list[DatasetImage] = []
    size = 0
    for img in images:
        nbytes = img.path.stat().st_size
        if run and flight_of(img) != flight_of(run[0]):
            out.append(run)
            run, size = [], 0
        if img.source != "exif":
            if run:
                out.append(run)
            out.append([img])
            run, size = [], 0
            continue
        if run and (len(run) >= BATCH_FILES or size + nbytes > BATCH_BYTES):
            out.append(run)
            run, size = [], 0
        run.append(img)
        size += nbytes
    if run:
        out.append(run)
    return out


def import_images(client: Client, map_id: str, images: Sequence[DatasetImage], *,
                  on_progress: Callable[[int, ImportSummary], None] | None = None,
                  flight_of: Callable[[DatasetImage], str | None] | None = None,
                  ) -> ImportSummary:
    """Upload data set images to a map, in the order given.

    Parameters
    ----------
    flight_of : callable, optional
        The flight an image belongs to (its upload's ``flight`` field), None for none.
    on_progress : callable, optional
        ``on_progress(n_files_sent_in_this_batch, summary_so_far)`` after every batch.

    Returns
    -------
    ImportSummary
        A batch the server refuses whole (every file bad, or a duplicate of an image
        already in the map) adds its files to ``rejected``; other errors propagate.
    """
    summary = ImportSummary()
    flight_of = flight_of or (lambda img: None)
    for batch in _batches(images, flight_of):
        files = [(img.name, img.path.read_bytes()) for img in batch]
        single = batch[0] if batch[0].source != "exif" else None
        flight = flight_of(batch[0])
        try:
            if single is not None:
                result = client.upload_images(map_id, files, lat=single.lat, lon=single.lon,
                                              alt=single.alt, captured_at=single.captured_at,
                                              flight=flight)
            else:
                result = client.upload_images(map_id, files, flight=flight)
        except APIError as exc:
            listed = exc.body.get("rejected")
            if exc.kind != "no-image-accepted" or not isinstance(listed, list):
                raise
            summary.rejected += [ImageRejection.model_validate(r) for r in listed]
        else:
            summary.accepted += len(result.accepted)
            summary.rejected += result.rejected
        if on_progress is not None:
            on_progress(len(batch), summary)
    return summary


def build_and_wait(client: Client, map_id: str, *, timeout: float = 1800.0,
                   on_progress: Callable[[Job], None] | None = None,
                   force: bool = False, full: bool = False) -> Job:
    """Start a build of the map and wait for it (raises JobFailed / WaitTimeout)."""
    job = client.build_map(map_id, force=force, full=full)
    return client.wait_for_job(job.id, timeout=timeout, on_progress=on_progress,
                               poll_interval=0.25)
