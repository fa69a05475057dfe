"""Build jobs: extract the new images' features in the workers, then pack a new revision.

The job runs as a task on the API's event loop that only awaits the workers and hands the
database writes to threads; the numerics (decoding, features, SIFT reduction) all happen in
the worker processes.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import shutil
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import bindparam, func, or_, select, update
from sqlalchemy.orm import Session, aliased, sessionmaker

from vloc.app.background import BackgroundRunner
from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.engine import Engine, WorkerDied, run_task
from vloc.app.jobs.models import BuildJob, BuildStage, JobStatus
from vloc.app.maps.models import ImageOrb, ImageSift, Map, MapImage, MapRevision, MapStatus
from vloc.app.maps.revisions import revision_images
from vloc.app.maps.service import image_path
from vloc.app.metrics import Metrics
from vloc.app.problems import Problem, ProblemKind
from vloc.app.tasks import build as tasks
from vloc.workers.core.geo import GeoOrigin

log = logging.getLogger(__name__)

EXTRACT_SHARE = 0.5
"""Share of the progress bar that feature extraction fills."""

TIE_SHARE = 0.15
"""Share it fills next while the reconstruction's tie points are extracted, ..."""

PAIR_SHARE = 0.1
"""... next while the engine's workers match them pair by pair, ..."""

TILE_SHARE = 0.15
"""... and next while they reconstruct a large map tile by tile; packing the map (a small
map's reconstruction included) is the rest."""

MATCH_RETRIES = 5
"""Times a batch of pairs that did not run (its worker died of another batch, or was being
replaced) is sent again before the build fails."""

PAIR_BATCH = 256
"""Pairs of map images matched per engine call: a few seconds of work, so that a call's
overhead is small and the progress still moves."""


def _drop_revision_tie_folders(map_dir: Path) -> None:
    """Delete the tie-point folders that builds before the map's store kept beside a
    revision (``rev-NNNNNN.ties``, left by a failed build): nothing reads them now."""
    for old in map_dir.glob("rev-*.ties"):
        shutil.rmtree(old, ignore_errors=True)


def _without_tie_points(tie_dir: Path, image_files: dict[int, str]) -> dict[int, str]:
    """The images of ``image_files`` (image id -> file) whose tie points the map's store in
    ``tie_dir`` does not hold complete (:func:`vloc.app.tasks.build.extract_ties`)."""
    from vloc.workers.core.tiepoints import TiePointFiles

    return {image_id: path for image_id, path in image_files.items()
            if TiePointFiles.find(tasks.tie_stem(tie_dir, image_id)) is None}


def same_files_elsewhere(map_id: uuid.UUID):
    """The query for other maps' images of the same files as map ``map_id``'s: rows of (the
    map's image id, the other image's map id, its id), by the map's image, then the other.

    One join on the file's hash, not a list of the map's hashes (50,000 of them pass
    SQLite's limit on a statement's parameters); the hash's own index
    (``ix_map_images_file_hash``) makes it a lookup per image, where the unique constraint on
    (map_id, file_hash) left SQLite scanning every image for each: 10.4 s on a
    12,000-image database, growing with its square."""
    other = aliased(MapImage)
    return (select(MapImage.id, other.map_id, other.id)
            .join(other, other.file_hash == MapImage.file_hash)
            .where(MapImage.map_id == map_id, other.map_id != map_id)
            .order_by(MapImage.id, other.id))


def forget_reconstruction(tie_dir: Path) -> None:
    """Delete what the map's store keeps of its reconstruction (COLMAP's models, a large
    map's tiles), so that the next build reconstructs the map whole (``full``), and the
    matched pairs that moved in the map's order since they were matched (images deleted
    before them), so that it matches them where they are: the map of a fresh build. The tie
    points and the other pairs, which no earlier build shapes, stay."""
    from vloc.workers.core import tiepairs, tiles

    shutil.rmtree(tie_dir / tiles.MODELS, ignore_errors=True)
    for result in tie_dir.glob(tiles.RESULTS_GLOB):
        result.unlink(missing_ok=True)
    if tie_dir.is_dir():
        tiepairs.forget_moved(tie_dir)


def start_build(db: Session, *, map_: Map, force: bool = False, full: bool = False,
                ) -> BuildJob:
    """Queue a build of a map; 409 while one runs, when the map has no image, or (unless
    ``force`` or ``full``) when its current revision already holds every image with all
    its features: the build would pack the same revision again. ``full`` builds it whole
    (the caller forgets the reconstruction: :func:`forget_reconstruction`)."""
    force = force or full
    if db.scalar(select(func.count(BuildJob.id)).where(
            BuildJob.map_id == map_.id, BuildJob.status.in_(JobStatus.ACTIVE))):
        raise Problem(409, "a build of this map is already running", kind=ProblemKind.MAP_BUSY)
    if not db.scalar(select(func.count(MapImage.id)).where(MapImage.map_id == map_.id)):
        raise Problem(409, "the map has no images to build from", kind=ProblemKind.MAP_EMPTY)
    if not force and map_.status == MapStatus.READY and map_.revision > 0 \
            and not db.scalar(select(func.count(MapImage.id))
                              .outerjoin(ImageSift, ImageSift.image_id == MapImage.id)
                              .outerjoin(ImageOrb, ImageOrb.image_id == MapImage.id)
                              .where(MapImage.map_id == map_.id,
                                     or_(ImageSift.image_id.is_(None),
                                         ImageOrb.image_id.is_(None)))):
        raise Problem(409, f"revision {map_.revision} already holds every image of the map; "
                      "add or delete images first, or pass force=true to pack it again",
                      kind=ProblemKind.MAP_UP_TO_DATE,
                      revision=map_.revision)
    job = BuildJob(map_id=map_.id, status=JobStatus.QUEUED, progress=0.0, full=full)
    db.add(job)
    map_.status = MapStatus.BUILDING
    db.commit()
    return job


def fail_interrupted(db: Session) -> int:
    """Jobs left queued/running by a stopped server can never finish: mark them failed."""
    jobs = list(db.scalars(select(BuildJob).where(BuildJob.status.in_(JobStatus.ACTIVE))))
    for job in jobs:
        job.status, job.error, job.finished_at = (JobStatus.FAILED,
                                                  "interrupted by a server restart", utcnow())
        m = db.get(Map, job.map_id)
        if m is not None and m.status == MapStatus.BUILDING:
            m.status = MapStatus.FAILED
    db.commit()
    return len(jobs)


@dataclass(eq=False)
class BuildRunner(BackgroundRunner):
    """Runs build jobs on the event loop, with the engine doing the work."""

    settings: Settings
    db_sessions: sessionmaker[Session]
    engine: Engine
    metrics: Metrics
    on_revised: Callable[[str, int], None] | None = None
    """Told the map and its new revision once a build is done (the sessions that follow
    the map move to it)."""
    loop: asyncio.AbstractEventLoop | None = None

    task_name = "build"

    async def run(self, job_id: uuid.UUID) -> None:
        try:
            await self._run(job_id)
        except asyncio.CancelledError:
            await asyncio.to_thread(self._finish_failed, job_id, "cancelled by shutdown")
            raise
        except Exception as exc:  # noqa: BLE001 - the job records the failure
            log.exception("build job %s failed", job_id)
            await asyncio.to_thread(self._finish_failed, job_id, f"{type(exc).__name__}: {exc}")

    async def _run(self, job_id: uuid.UUID) -> None:
        map_id, todo = await asyncio.to_thread(self._begin, job_id)
        url = self.settings.resolved_database_url
        futures = [run_task(self.engine, tasks.extract_image, url, image_id, path,
                            max_pixels=self.settings.max_pixels) for image_id, path in todo]
        for done, fut in enumerate(asyncio.as_completed(futures), start=1):
            await fut
            await asyncio.to_thread(self._progress, job_id, done, len(todo))
        revision = await asyncio.to_thread(self._next_revision, map_id)
        folder = self.settings.packed_map_dir(str(map_id), revision)
        lens_files, image_files = await asyncio.to_thread(self._files, map_id)
        # The reconstruction's tie points, extracted over the images in parallel by the
        # engine's workers into the map's store, their pairs matched and a large map's tiles
        # reconstructed there. The store outlives the build: a rebuild extracts the tie
        # points of new images only and matches only the pairs that changed, and a build
        # that fails leaves its work for the retry (hours for a map of 50,000 images).
        tie_dir = self.settings.tie_store_dir(str(map_id))
        await asyncio.to_thread(tie_dir.mkdir, parents=True, exist_ok=True)
        await asyncio.to_thread(_drop_revision_tie_folders, folder.parent)
        await asyncio.to_thread(self._set_progress, job_id, EXTRACT_SHARE,
                                BuildStage.TIE_POINTS)
        donors = await asyncio.to_thread(self._tie_donors, map_id)
        # only the images the store holds no tie points of, an update's new ones: a call a
        # worker answers at once still costs a round trip through the engine, per image
        missing = await asyncio.to_thread(_without_tie_points, tie_dir, image_files)
        await self._fan_out(job_id, [run_task(
            self.engine, tasks.extract_ties, path, tasks.tie_stem(tie_dir, image_id),
            donors.get(image_id, []))
            for image_id, path in missing.items()], EXTRACT_SHARE, TIE_SHARE)
        await self._match_pairs(job_id, url, map_id, tie_dir)
        origin = await asyncio.to_thread(self._frame_origin, job_id, map_id)
        await self._reconstruct_tiles(job_id, url, map_id, tie_dir, lens_files, origin)
        current = await asyncio.to_thread(self._current_folder, map_id)
        previous = await asyncio.to_thread(self._previous_folder, job_id, current)
        packed = await run_task(
            self.engine, tasks.pack_map, url, str(map_id), revision, str(folder),
            lens_files=lens_files, image_files=image_files, tie_dir=str(tie_dir),
            job_id=str(job_id), previous=previous, share=current,
            chunk_images=self.settings.map_chunk_images, origin=origin)
        await asyncio.to_thread(self._finish_done, job_id, map_id, revision, packed)
        if self.on_revised is not None:
            self.on_revised(str(map_id), revision)

    async def _match_pairs(self, job_id: uuid.UUID, url: str, map_id: uuid.UUID,
                           tie_dir: Path) -> None:
        """The reconstruction's pairs of neighbouring images that ``tie_dir`` does not hold
        yet, matched from their tie points in batches by the engine's workers
        (:mod:`vloc.workers.core.tiepairs`); the packing reads the results from there."""
        await asyncio.to_thread(self._set_progress, job_id, EXTRACT_SHARE + TIE_SHARE,
                                BuildStage.MATCHING)
        plan = await run_task(self.engine, tasks.plan_tie_pairs, url, str(map_id),
                              str(tie_dir))
        ids, pairs = plan["image_ids"], plan["pairs"]
        batches = [pairs[k:k + PAIR_BATCH] for k in range(0, len(pairs), PAIR_BATCH)]
        numbers = itertools.count(len(batches))  # files for the pairs a crash leaves out
        await self._fan_out(job_id, [self._match_batch(tie_dir, ids, batch, k, numbers)
                                     for k, batch in enumerate(batches)],
                            EXTRACT_SHARE + TIE_SHARE, PAIR_SHARE)

    async def _match_batch(self, tie_dir: Path, ids: list[int], batch: list, number: int,
                           numbers: Iterator[int]) -> None:
        """One batch of planned pairs matched by the engine's workers, whatever COLMAP does.

        COLMAP can bring a worker down on a pair's matches (a segmentation fault in its
        two-view solvers, seen on a pair of a synthetic survey whose ratio matches hit
        fifty keypoints of one image twice over), and it would again on every retry: such
        a pair (the batch's record of the pair it was matching says which,
        :func:`~vloc.workers.core.tiepairs.crashed_pair`) is stored as matched without
        verifying, so that no build matches it again, and the rest of the batch is matched
        again. A batch that did not run (queued on the worker that died, or sent while it
        was replaced) is sent again after a pause, :data:`MATCH_RETRIES` times at most."""
        from vloc.workers.core import tiepairs

        out = tasks.tie_pairs_file(tie_dir, number)
        retries = 0
        while True:
            names = {i: ids[i] for pair in batch for i in pair}
            try:
                await run_task(self.engine, tasks.match_tie_pairs, str(tie_dir), names,
                               batch, number)
                return
            except WorkerDied:
                crashed = await asyncio.to_thread(tiepairs.crashed_pair, out)
                if crashed is None:
                    retries += 1
                    if retries > MATCH_RETRIES:
                        raise
                    await asyncio.sleep(min(0.5 * 2 ** retries, 10.0))
                    continue
            where = {image_id: k for k, image_id in enumerate(ids)}
            pair = (where[crashed[0]], where[crashed[1]])
            log.warning("COLMAP ended a worker on the tie points of images %d and %d; the "
                        "map is built without that pair", *crashed)
            await asyncio.to_thread(tiepairs.save_results, [(*pair, None)],
                                    tasks.tie_pairs_file(tie_dir, next(numbers)),
                                    image_ids={pair[0]: crashed[0], pair[1]: crashed[1]})
            batch = [p for p in batch if tuple(p) != pair]
            if not batch:
                return

    async def _reconstruct_tiles(self, job_id: uuid.UUID, url: str, map_id: uuid.UUID,
                                 tie_dir: Path, lens_files: list[str],
                                 origin: GeoOrigin | None) -> None:
        """A large map's reconstruction, tile by tile on the engine's workers
        (:mod:`vloc.workers.core.tiles`), in the frame the packing packs in (``origin``);
        the packing reads the results from ``tie_dir``."""
        n = await run_task(self.engine, tasks.plan_tiles, url, str(map_id), str(tie_dir),
                           lens_files, origin=origin)
        if n:
            await asyncio.to_thread(self._set_progress, job_id,
                                    EXTRACT_SHARE + TIE_SHARE + PAIR_SHARE, BuildStage.TILES)
        await self._fan_out(job_id, [run_task(
            self.engine, tasks.reconstruct_tile, str(tie_dir), k) for k in range(n)],
            EXTRACT_SHARE + TIE_SHARE + PAIR_SHARE, TILE_SHARE)

    async def _fan_out(self, job_id: uuid.UUID, futures: list, start: float,
                       share: float) -> None:
        """Await the engine's calls as they finish, the job's progress moving from ``start``
        by ``share`` (a hundred updates of the bar at most)."""
        every = max(1, len(futures) // 100)
        for done, fut in enumerate(asyncio.as_completed(futures), start=1):
            await fut
            if done % every == 0 or done == len(futures):
                await asyncio.to_thread(self._set_progress, job_id,
                                        start + share * done / len(futures))

    # -- database steps (threads) -----------------------------------------------------------

    def _begin(self, job_id: uuid.UUID) -> tuple[uuid.UUID, list[tuple[int, str]]]:
        with self.db_sessions() as db:
            job = db.get(BuildJob, job_id)
            # new images, and images extracted before ORB features were stored
            images = list(db.scalars(
                select(MapImage).outerjoin(ImageSift, ImageSift.image_id == MapImage.id)
                .outerjoin(ImageOrb, ImageOrb.image_id == MapImage.id)
                .where(MapImage.map_id == job.map_id,
                       or_(ImageSift.image_id.is_(None), ImageOrb.image_id.is_(None)))
                .order_by(MapImage.id)))
            job.status, job.started_at = JobStatus.RUNNING, utcnow()
            job.stage = BuildStage.FEATURES
            job.n_images = len(images)
            db.commit()
            return job.map_id, [(img.id, str(image_path(self.settings, img))) for img in images]

    def _frame_origin(self, job_id: uuid.UUID, map_id: uuid.UUID) -> GeoOrigin | None:
        """Where the build's local frame lies: for an update, where the
        current revision's does, so that the images it holds keep their east and north, and
        a large map's tiles that no added or deleted image reached keep the keys of their
        reconstructions and are taken up as they are (a frame moved to the new centroid
        moves every image's GPS position in it, so every tile's key changed and each tile's
        kept model was aligned to its GPS again). None for a first or a ``full`` build: the
        frame is centred on the images, as a fresh build of them centres it."""
        with self.db_sessions() as db:
            m = db.get(Map, map_id)
            if db.get(BuildJob, job_id).full or m.origin_lat is None:
                return None
            return GeoOrigin(m.origin_lat, m.origin_lon, m.origin_alt or 0.0)

    def _previous_folder(self, job_id: uuid.UUID, current: str | None) -> str | None:
        """The packed revision the build packs from: ``current``, the map's current one
        (:meth:`_current_folder`), whose place vocabularies and SIFT masks its images keep
        where they still hold; None for a first or a ``full`` build, or where that revision
        is gone or has no image ids."""
        if current is None or not revision_images(current).ids:
            return None
        with self.db_sessions() as db:
            return None if db.get(BuildJob, job_id).full else current

    def _current_folder(self, map_id: uuid.UUID) -> str | None:
        """The folder of the map's current revision, whose files the new one shares where
        they are the same (a full build's too); None for a map not built yet, or where
        that revision's files are gone."""
        with self.db_sessions() as db:
            revision = db.get(Map, map_id).revision
        if revision == 0:
            return None
        folder = self.settings.packed_map_dir(str(map_id), revision)
        return str(folder) if folder.is_dir() else None

    def _files(self, map_id: uuid.UUID, lens_sample: int = 25,
               ) -> tuple[list[str], dict[int, str]]:
        """Files of up to ``lens_sample`` of the map's images, spread over the map, whose
        EXIF gives the camera's focal length for the map's geometry; and every image's file
        by image id, for the reconstruction's tie points."""
        with self.db_sessions() as db:
            images = list(db.scalars(select(MapImage).where(MapImage.map_id == map_id)
                                     .order_by(MapImage.id)))
        step = max(1, len(images) // lens_sample)
        lens = [str(image_path(self.settings, img)) for img in images[::step]][:lens_sample]
        return lens, {img.id: str(image_path(self.settings, img)) for img in images}

    def _tie_donors(self, map_id: uuid.UUID, most: int = 3) -> dict[int, list[str]]:
        """For each of the map's images, where up to ``most`` other maps' images of the same
        file (by its hash) keep their tie points: a second map of the same survey links
        them instead of extracting them again (:func:`vloc.app.tasks.build.extract_ties`)."""
        with self.db_sessions() as db:
            rows = db.execute(same_files_elsewhere(map_id)).all()
        donors: dict[int, list[str]] = {}
        for image_id, other_map, other_id in rows:
            stems = donors.setdefault(image_id, [])
            if len(stems) < most:
                stems.append(tasks.tie_stem(self.settings.tie_store_dir(str(other_map)),
                                            other_id))
        return donors

    def _progress(self, job_id: uuid.UUID, done: int, total: int) -> None:
        with self.db_sessions() as db:
            db.execute(update(BuildJob).where(BuildJob.id == job_id).values(
                n_extracted=done, progress=EXTRACT_SHARE * done / max(total, 1),
                stage=BuildStage.FEATURES))
            db.commit()

    def _set_progress(self, job_id: uuid.UUID, progress: float,
                      stage: str | None = None) -> None:
        values: dict = {"progress": progress}
        if stage is not None:
            values["stage"] = stage
        with self.db_sessions() as db:
            db.execute(update(BuildJob).where(BuildJob.id == job_id).values(**values))
            db.commit()

    def _next_revision(self, map_id: uuid.UUID) -> int:
        """One past every revision the map has had: after a restore the current revision
        is not the latest, and a later one's folder must not be packed over."""
        with self.db_sessions() as db:
            latest = db.scalar(select(func.max(MapRevision.revision))
                               .where(MapRevision.map_id == map_id))
            return max(db.get(Map, map_id).revision, latest or 0) + 1

    def _finish_done(self, job_id: uuid.UUID, map_id: uuid.UUID, revision: int,
                     packed: dict) -> None:
        with self.db_sessions() as db:
            m = db.get(Map, map_id)
            lat, lon, alt = packed["origin"]
            base = m.revision
            before = set(self._revision_image_ids(map_id, base))
            now = set(packed["image_ids"])
            db.add(MapRevision(
                map_id=map_id, revision=revision, built_at=utcnow(), job_id=job_id,
                base_revision=base, image_count=len(now), added=len(now - before),
                removed=len(before - now), origin_lat=lat, origin_lon=lon, origin_alt=alt,
                geometry=packed.get("geometry")))
            m.revision, m.origin_lat, m.origin_lon, m.origin_alt = revision, lat, lon, alt
            m.built_at, m.geometry = utcnow(), packed.get("geometry")
            # one statement executed for every image (executemany), not one round trip each
            table = MapImage.__table__
            db.execute(update(table).where(table.c.id == bindparam("image_id")).values(
                east=bindparam("image_east"), north=bindparam("image_north"),
                built_revision=func.coalesce(table.c.built_revision, revision)),
                [{"image_id": i, "image_east": e, "image_north": n}
                 for i, e, n in zip(packed["image_ids"], packed["east"], packed["north"],
                                    strict=True)])
            # Images uploaded while the job ran are not in this revision yet.
            waiting = db.scalar(select(func.count(MapImage.id)).where(
                MapImage.map_id == map_id, MapImage.built_revision.is_(None)))
            m.status = MapStatus.UNBUILT if waiting else MapStatus.READY
            job = db.get(BuildJob, job_id)
            job.status, job.progress, job.revision = JobStatus.DONE, 1.0, revision
            job.stage = BuildStage.DONE
            job.finished_at = utcnow()
            db.commit()
        self.metrics.build_jobs.labels(JobStatus.DONE).inc()
        log.info("map %s built: revision %d, %d images", map_id, revision,
                 len(packed["image_ids"]))

    def _revision_image_ids(self, map_id: uuid.UUID, revision: int) -> tuple[int, ...]:
        """The image ids a packed revision holds (none for revision 0 or a revision packed
        before its ids were recorded beside it)."""
        if revision == 0:
            return ()
        ids = revision_images(str(self.settings.packed_map_dir(str(map_id), revision))).ids
        return ids or ()

    def _finish_failed(self, job_id: uuid.UUID, error: str) -> None:
        with self.db_sessions() as db:
            job = db.get(BuildJob, job_id)
            if job is None:
                return  # the map (and its jobs) was deleted meanwhile
            job.status, job.error, job.finished_at = JobStatus.FAILED, error[:2000], utcnow()
            m = db.get(Map, job.map_id)
            if m is not None:
                m.status = MapStatus.FAILED
            db.commit()
        self.metrics.build_jobs.labels(JobStatus.FAILED).inc()
