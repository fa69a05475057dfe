"""Benchmark: a map of tens of thousands of images, built by the service and localised on.

A synthetic UAV survey of ``--images`` frames (tiles of 1,000 frames, 40 m up, 6 m apart,
laid side by side over a few square kilometres: :mod:`large_map_world`) goes through the
service's own build path, driven in-process on SQLite with ``--workers`` worker processes (one
by default): images enter
through ``app.maps.service.add_images`` (screening, full decode in the worker, files and
rows), each image's features are extracted by ``app.tasks.build.extract_image`` in the worker
as soon as its tile is generated (the world is generated alongside, in a second process),
and a build job started over the API packs the revision (SIFT reduction, vocabularies,
geometry; stage times from its ``build_timings.json``). Then, on the packed revision:

* one core, CPU time (``time.thread_time``), every thread pool pinned to one thread: the
  steps of a hybrid :class:`~workers.core.localisers.filtering.FilterLocaliser` (default
  configuration) over the query pass of tile 0 (the same ground, flown again under cloud),
  started from an initial pose at the first frame; a global step is the global measurement
  plus the filter step (``_filter_step`` with global features), a SIFT step its SIFT
  counterpart; and the SIFT shortlist on its own, the global scoring of every map image
  (``_global_scores`` plus the ``argsort`` for ``sift.candidates``), features extracted
  beforehand;
* memory: a session opened over the API on the worker process, stepped through the same
  frames; the worker's RSS, and PSS and private memory from ``/proc/<pid>/smaps_rollup``
  (the memory-mapped map shows as shared, file-backed pages);
* the SQLite database's size per 1,000 images.

Everything is kept in the work directory: finished tiles, ingested tiles (the images of a
map are deduplicated by content, so a rerun adds nothing twice), extracted features and
the packed revision, so an interrupted run resumes where it stopped.

Usage::

    .venv/bin/python bench/bench_large_map.py [--images 50000]
        [--work bench/.cache/large-map/50000] [--frames 200] [--world-images N]
        [--no-generate] [--scale-to 50000] [--postgres 1000]
        [--out bench/results/large_map.md]

The report is written by :mod:`large_map_report`; ``make bench-large`` runs the default.
"""

from __future__ import annotations

from _common import RESULTS, ROOT, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import csv  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from large_map_report import report  # noqa: E402
from large_map_world import (  # noqa: E402
    layout_for,
    map_images,
    tile_dir,
    tile_done,
)
from sqlalchemy import func, select  # noqa: E402

ADMIN_KEY = "large-map-bench-admin-key-0123456789"
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
MAP_NAME = "large map"
CLK_TCK = os.sysconf("SC_CLK_TCK")


# -- the service ---------------------------------------------------------------------------

def service_settings(data_dir: Path, workers: int = 1):
    """SQLite in the work directory, ``workers`` worker processes, uploads of synthetic
    JPEGs."""
    from vloc.app.config import Settings

    return Settings(data_dir=data_dir, workers=workers, admin_key=ADMIN_KEY, log_json=False,
                    max_pixels=2_000_000, session_ttl_s=24 * 3600)


def worker_cpu(ctx) -> float:
    """CPU seconds (user + system) the engine's worker processes have used so far."""
    total = 0.0
    for pid in ctx.engine.worker_pids():
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / CLK_TCK
    return total


def worker_peak_mib(ctx) -> float:
    """The largest peak resident memory (VmHWM) of the engine's worker processes (MiB)."""
    peaks = [0.0]
    for pid in ctx.engine.worker_pids():
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                peaks.append(int(line.split()[1]) / 1024)
    return max(peaks)


class Meter:
    """Wall and CPU seconds of a block, this process and the worker separately."""

    def __init__(self, ctx) -> None:
        self.ctx = ctx

    def __enter__(self) -> Meter:
        self.t = (time.perf_counter(), time.process_time(), worker_cpu(self.ctx))
        return self

    def __exit__(self, *exc) -> None:
        wall, api, worker = self.t
        self.wall = time.perf_counter() - wall
        self.api_cpu = time.process_time() - api
        self.worker_cpu = worker_cpu(self.ctx) - worker


def find_or_create_map(client) -> str:
    for m in client.get("/v1/maps", params={"limit": 1000}, headers=ADMIN).json():
        if m["name"] == MAP_NAME:
            return m["id"]
    r = client.post("/v1/maps", json={"name": MAP_NAME}, headers=ADMIN)
    r.raise_for_status()
    return r.json()["id"]


def add_tile(client, map_id: str, files: list[Path]) -> int:
    """Add a tile's images through the maps service in uploads of the largest allowed
    size; returns how many were accepted (duplicates of an earlier run are rejected)."""
    from vloc.app.maps.dependencies import get_verifier
    from vloc.app.maps.service import Upload, add_images
    from vloc.app.problems import Problem

    ctx = client.app.state.ctx
    verify = client.portal.call(get_verifier, ctx)
    size = ctx.settings.max_files_per_upload
    accepted = 0
    for start in range(0, len(files), size):
        uploads = [Upload(f.name, f.read_bytes()) for f in files[start:start + size]]
        try:
            result = client.portal.call(functools.partial(
                add_images, db_sessions=ctx.db_sessions, map_id=_uuid(map_id),
                uploads=uploads, position=None, settings=ctx.settings, verify=verify))
        except Problem as p:
            if p.kind != "no-image-accepted":  # all already there from an earlier run
                raise
            continue
        accepted += len(result.accepted)
    return accepted


def extract_pending(ctx, map_id: str) -> int:
    """Extract the features of the map's images that have none yet, in the worker, with
    the build job's own task; returns how many."""
    from vloc.app.maps.models import ImageOrb, ImageSift, MapImage
    from vloc.app.maps.service import image_path
    from vloc.app.tasks import build as tasks

    with ctx.db_sessions() as db:
        todo = [(img.id, str(image_path(ctx.settings, img))) for img in db.scalars(
            select(MapImage).outerjoin(ImageSift, ImageSift.image_id == MapImage.id)
            .outerjoin(ImageOrb, ImageOrb.image_id == MapImage.id)
            .where(MapImage.map_id == _uuid(map_id),
                   (ImageSift.image_id.is_(None)) | (ImageOrb.image_id.is_(None)))
            .order_by(MapImage.id))]
    url = ctx.settings.resolved_database_url
    futures = [ctx.engine.call(tasks.extract_image, url, image_id, path,
                               max_pixels=ctx.settings.max_pixels) for image_id, path in todo]
    for fut in futures:
        fut.result()
    return len(todo)


def build(client, map_id: str, headers: dict[str, str] = ADMIN, *, full: bool = False,
          ) -> tuple[dict, dict[str, float]]:
    """Start a build job over the API (``client``: a test client or an ``httpx.Client``)
    and wait for it; the job's record and the wall seconds spent in each of its stages
    (polled every half second). ``full`` reconstructs the map's geometry whole."""
    # forced: a map built before (a rerun measuring the build again) is up to date
    r = client.post(f"/v1/maps/{map_id}/build",
                    params={"force": "true"} | ({"full": "true"} if full else {}),
                    headers=headers)
    r.raise_for_status()
    job_id = r.json()["job_id"]
    stages: dict[str, float] = {}
    current, since = None, time.perf_counter()
    while True:
        job = client.get(f"/v1/jobs/{job_id}", headers=headers).json()
        now = time.perf_counter()
        if job.get("stage") != current:
            if current is not None:
                stages[current] = stages.get(current, 0.0) + now - since
            current, since = job.get("stage"), now
        if job["status"] in ("done", "failed"):
            return job, stages
        time.sleep(0.5)


def _uuid(value: str):
    import uuid

    return uuid.UUID(value)


# -- the stages ------------------------------------------------------------------------------

def ingest(client, map_id: str, work: Path, layout, images: int, stats: dict,
           generator) -> None:
    """Add and extract the first ``images`` images of the world, each tile as soon as it
    is generated."""
    ctx = client.app.state.ctx
    done = stats.setdefault("tiles", {})
    for tile in range(-(-images // layout.tile_frames)):
        if str(tile) in done:
            continue
        while not tile_done(work, tile):
            if generator is not None and generator.poll() not in (None, 0):
                raise RuntimeError(f"world generation failed ({generator.returncode})")
            time.sleep(2.0)
        files = map_images(work, tile)
        files = files[:max(0, images - tile * layout.tile_frames)]
        with Meter(ctx) as add:
            accepted = add_tile(client, map_id, files)
        with Meter(ctx) as ext:
            extracted = extract_pending(ctx, map_id)
        done[str(tile)] = {"images": len(files), "accepted": accepted,
                           "extracted": extracted,
                           "add": [add.wall, add.api_cpu, add.worker_cpu],
                           "extract": [ext.wall, ext.api_cpu, ext.worker_cpu]}
        save_stats(work, stats)
        print(f"tile {tile + 1}/{layout.tiles}: {accepted} added in {add.wall:.0f} s, "
              f"{extracted} extracted in {ext.wall:.0f} s", flush=True)


def pack(client, map_id: str, stats: dict, work: Path) -> dict:
    """Run the build job unless the map is already built from every image."""
    m = client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    if not (m["status"] == "ready" and m["pending_images"] == 0 and "build" in stats):
        ctx = client.app.state.ctx
        with Meter(ctx) as meter:
            job, job_stages = build(client, map_id)
        if job["status"] != "done":
            raise RuntimeError(f"the build failed: {job.get('error')}")
        m = client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
        folder = ctx.settings.packed_map_dir(map_id, m["revision"])
        stats["build"] = {"wall": meter.wall, "api_cpu": meter.api_cpu,
                          "worker_cpu": meter.worker_cpu, "revision": m["revision"],
                          "worker_peak_mib": worker_peak_mib(ctx),
                          "folder": str(folder), "images": m["image_count"],
                          "job_stages": job_stages,
                          "stages": json.loads((folder / "build_timings.json").read_text())}
        save_stats(work, stats)
    return stats["build"]


def query_frames(work: Path, count: int):
    """Tile 0's query pass: (QueryFrame factory, true lat/lon) per frame."""
    from vloc.workers.core.image import load_frame

    folder = tile_dir(work, 0)
    with (folder / "ground_truth.csv").open(newline="", encoding="utf-8") as f:
        rows = [r for r in csv.DictReader(f) if r["pass"] == "2"][:count]
    out = []
    for r in rows:
        data = (folder / "images" / r["filename"]).read_bytes()
        out.append((data, load_frame(data, max_pixels=2_000_000),
                    _epoch(r["captured_at"]), float(r["lat"]), float(r["lon"])))
    return out


def _epoch(iso: str) -> float:
    return datetime.fromisoformat(iso).replace(tzinfo=UTC).timestamp()


def time_steps(folder: str, frames, params: dict | None = None) -> dict:
    """CPU ms of each step of a hybrid session (the ``default`` configuration, changed by
    ``params``), and of the SIFT shortlist on its own."""
    from vloc.workers.core.localisers import make_localiser
    from vloc.workers.core.mapdata import MapData
    from vloc.workers.core.query import QueryFrame

    t0 = time.perf_counter()
    data = MapData.load(folder, mmap=True)
    loc = make_localiser("hybrid", data, {"config": "default", **(params or {})}, seed=0)
    setup_s = time.perf_counter() - t0
    x, y = data.origin.to_local(frames[0][3], frames[0][4])
    loc.set_initial_pose(float(x), float(y), 10.0)
    steps: list[tuple[str, float]] = []
    measurements: list[tuple[str, float]] = []
    step_fn, measurement_fn = loc._filter_step, loc._measurement

    def timed_step(query, used, dt, sensors):
        t = time.thread_time()
        out = step_fn(query, used, dt, sensors)
        steps.append((used, time.thread_time() - t))
        return out

    def timed_measurement(query, kind):
        t = time.thread_time()
        out = measurement_fn(query, kind)
        measurements.append((kind, time.thread_time() - t))
        return out

    loc._filter_step, loc._measurement = timed_step, timed_measurement
    frame_ms, errors = [], []
    truth = [data.origin.to_local(lat, lon) for _, _, _, lat, lon in frames]
    for (_, frame, t, _, _), (tx, ty) in zip(frames, truth, strict=True):
        q = QueryFrame(frame, t)
        t = time.thread_time()
        est = loc.step(q)
        frame_ms.append((est.feature, 1e3 * (time.thread_time() - t)))
        errors.append(float(np.hypot(est.x - tx, est.y - ty)))
    cfg = loc.config
    shortlist, extraction = [], []
    for _, frame, t, _, _ in frames:
        q = QueryFrame(frame, t)
        c = time.thread_time()
        q.global_features(cfg.measurement.global_features, data.vocabularies)
        extraction.append(time.thread_time() - c)
        c = time.thread_time()
        g, _ = loc._global_scores(q)
        np.argsort(-g, kind="stable")[: cfg.sift.candidates]
        shortlist.append(time.thread_time() - c)
    return {"steps": steps, "measurements": measurements, "frame_ms": frame_ms,
            "errors": errors, "shortlist_s": shortlist, "global_extraction_s": extraction,
            "setup_s": setup_s, "candidates": cfg.sift.candidates,
            "global_features": list(cfg.measurement.global_features),
            "map_images": len(data)}


def scaled_scoring(data, config, frames, rows: int, work: Path) -> dict:
    """CPU seconds of scoring every map image, as ``_global_scores`` does, on matrices of
    ``rows`` rows made by repeating the built map's own rows, memory-mapped from files:
    exactly (one matrix-vector product per feature over every row, what a map of at most
    ``CODES_FROM`` images does) and through the shortlist codes a larger map is packed with
    (the scan over the codes, the exact scores of the shortlist, written into a vector of
    every image).

    Only the size differs from the real map: this answers how the shortlist and the global
    step's all-image scoring grow with the map, for maps larger than the one built. It is
    not a map build.
    """
    from types import SimpleNamespace

    from vloc.workers.core.features.shortlist import PlaceCodes
    from vloc.workers.core.localisers.scoring import global_similarity
    from vloc.workers.core.query import QueryFrame

    m = config.measurement
    matrices, codes = {}, {}
    for name in m.global_features:
        path = work / f"scaled_{rows}_{name}.npy"
        if not path.is_file():
            real = np.asarray(data.global_features[name])
            np.save(path, np.resize(real, (rows, real.shape[1])))
        matrices[name] = np.load(path, mmap_mode="r")
        basis, coded = (work / f"scaled_{rows}_{name}_{s}.npy" for s in ("basis", "codes"))
        if not coded.is_file():
            fitted = PlaceCodes.fit(matrices[name])
            np.save(basis, fitted.basis)
            np.save(coded, fitted.codes)
        codes[name] = PlaceCodes(np.load(basis), np.load(coded, mmap_mode="r"))
    big = SimpleNamespace(global_features=matrices)
    k = config.sift.candidates or 20
    exact, short = [], []
    for _, frame, t, _, _ in frames:
        q, _ = QueryFrame(frame, t).global_features(m.global_features, data.vocabularies)
        c = time.thread_time()
        g = global_similarity(q, big, np.arange(rows), features=m.global_features,
                              measure=m.global_measure)
        np.argsort(-g, kind="stable")[:k]
        exact.append(time.thread_time() - c)
        c = time.thread_time()
        idx = codes[m.global_features[0]].shortlist(q[m.global_features[0]])
        g = np.zeros(rows)
        g[idx] = global_similarity(q, big, idx, features=m.global_features,
                                   measure=m.global_measure)
        np.argsort(-g, kind="stable")[:k]
        short.append(time.thread_time() - c)
    return {"rows": rows, "seconds": exact, "shortlist_seconds": short, "top": k,
            "dims": {name: int(v.shape[1]) for name, v in matrices.items()},
            "code_dims": {name: int(v.basis.shape[1]) for name, v in codes.items()}}


def session_memory(client, map_id: str, frames) -> dict:
    """A session over the API on the worker, stepped through ``frames``: the worker's
    memory before the session and after the steps."""
    ctx = client.app.state.ctx
    pid = ctx.engine.worker_pids()[0]
    before = memory(pid)
    r = client.post("/v1/sessions", json={"map_id": map_id, "mode": "hybrid", "seed": 0},
                    headers=ADMIN)
    r.raise_for_status()
    session_id, token = r.json()["id"], r.json()["token"]
    auth = {"Authorization": f"Bearer {token}"}
    r = client.post(f"/v1/sessions/{session_id}/initial-pose",
                    json={"lat": frames[0][3], "lon": frames[0][4], "sigma": 10.0}, headers=auth)
    r.raise_for_status()
    opened = memory(pid)
    kinds = []
    for seq, (data, _, _, _, _) in enumerate(frames):
        r = client.post(f"/v1/sessions/{session_id}/frames", params={"seq": seq, "wait": True},
                        content=data, headers={**auth, "Content-Type": "image/jpeg"})
        r.raise_for_status()
        kinds.append(r.json().get("feature"))
    stepped = memory(pid)
    client.delete(f"/v1/sessions/{session_id}", headers=ADMIN)
    return {"before": before, "opened": opened, "stepped": stepped, "frames": len(frames),
            "sift_share": float(np.mean([k == "sift" for k in kinds]))}


def memory(pid: int) -> dict:
    """VmRSS, VmHWM and the smaps_rollup totals of a process, in MiB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        key, _, value = line.partition(":")
        if key in ("Rss", "Pss", "Pss_Anon", "Pss_File", "Shared_Clean", "Private_Clean",
                   "Private_Dirty", "Anonymous"):
            out[key] = int(value.split()[0]) / 1024
    return out


def database_size(ctx, map_id: str) -> dict:
    """SQLite file bytes (WAL checkpointed) and the map's rows."""
    from vloc.app.maps.models import MapImage

    with ctx.db_engine.connect() as conn:
        conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
    with ctx.db_sessions() as db:
        images = db.scalar(select(func.count(MapImage.id))
                           .where(MapImage.map_id == _uuid(map_id)))
    path = Path(ctx.settings.resolved_database_url.removeprefix("sqlite:///"))
    return {"bytes": path.stat().st_size, "images": images}


POSTGRES_URL = os.environ.get("VLOC_TEST_POSTGRES_URL",
                              "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def postgres_size(ctx, map_id: str, sample: int) -> dict | None:
    """Bytes per image in PostgreSQL: ``sample`` of the map's images with their feature
    rows copied from SQLite into a schema of their own (migrated as the service migrates
    its database), measured with ``pg_total_relation_size`` (tables, indexes, TOAST), then
    dropped. None when PostgreSQL cannot be reached."""
    import uuid

    import psycopg
    from sqlalchemy.engine import make_url

    from vloc.app import migrate
    from vloc.app.db import make_engine
    from vloc.app.maps.models import ImageGlobalFeature, ImageOrb, ImageSift, Map, MapImage

    url = make_url(POSTGRES_URL)
    plain = url.set(drivername="postgresql").render_as_string(hide_password=False)
    schema = f"vloc_bench_{uuid.uuid4().hex[:12]}"
    try:
        admin = psycopg.connect(plain, autocommit=True, connect_timeout=3)
    except psycopg.OperationalError:
        return None
    with admin:
        admin.execute(f'CREATE SCHEMA "{schema}"')
        try:
            pg = make_engine(url.update_query_dict({"options": f"-csearch_path={schema}"})
                             .render_as_string(hide_password=False))
            migrate.upgrade(pg)
            with ctx.db_engine.connect() as src, pg.begin() as dst:
                ids = src.execute(select(MapImage.id).where(MapImage.map_id == _uuid(map_id))
                                  .order_by(MapImage.id).limit(sample)).scalars().all()
                _copy(src, dst, Map.__table__, Map.__table__.c.id == _uuid(map_id))
                _copy(src, dst, MapImage.__table__, MapImage.__table__.c.id.in_(ids))
                for model in (ImageGlobalFeature, ImageSift, ImageOrb):
                    _copy(src, dst, model.__table__, model.__table__.c.image_id.in_(ids))
                dst.exec_driver_sql("ANALYZE")
            with pg.connect() as conn:
                size = conn.exec_driver_sql(
                    "SELECT sum(pg_total_relation_size(c.oid)) FROM pg_class c JOIN "
                    "pg_namespace n ON n.oid = c.relnamespace WHERE n.nspname = %(s)s AND "
                    "c.relname IN ('map_images', 'image_global_features', 'image_sift', "
                    "'image_orb')", {"s": schema}).scalar()
            pg.dispose()
        finally:
            admin.execute(f'DROP SCHEMA "{schema}" CASCADE')
    return {"bytes": int(size), "images": len(ids)}


def _copy(src, dst, table, where) -> None:
    rows = [dict(r._mapping) for r in src.execute(select(table).where(where))]
    for start in range(0, len(rows), 500):
        dst.execute(table.insert(), rows[start:start + 500])


# -- bookkeeping ----------------------------------------------------------------------------

def load_stats(work: Path) -> dict:
    path = work / "stats.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def save_stats(work: Path, stats: dict) -> None:
    tmp = work / "stats.json.part"
    tmp.write_text(json.dumps(stats, indent=1))
    tmp.replace(work / "stats.json")


def start_generator(work: Path, images: int, layout) -> subprocess.Popen | None:
    """World generation in its own process, unless every tile is there already."""
    if all(tile_done(work, t) for t in range(layout.tiles)):
        return None
    log = (work / "world.log").open("a")
    return subprocess.Popen([sys.executable, str(ROOT / "bench" / "large_map_world.py"),
                             str(work), "--images", str(images)], stdout=log, stderr=log)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=50_000)
    parser.add_argument("--work", type=Path, default=None,
                        help="work directory (default bench/.cache/large-map/IMAGES)")
    parser.add_argument("--frames", type=int, default=200, help="query frames to step")
    parser.add_argument("--workers", type=int, default=1,
                        help="the engine's worker processes (the build's parallel stages)")
    parser.add_argument("--postgres", type=int, default=1000, metavar="IMAGES",
                        help="images to copy into PostgreSQL for its size (0: skip)")
    parser.add_argument("--scale-to", type=int, default=50_000,
                        help="also time the all-image scoring on matrices of this many rows "
                             "when the map built is smaller")
    parser.add_argument("--world-images", type=int, default=None,
                        help="size of the world to generate, when larger than the map "
                             "(default: --images)")
    parser.add_argument("--no-generate", action="store_true",
                        help="wait for tiles another process generates")
    parser.add_argument("--out", type=Path, default=RESULTS / "large_map.md")
    args = parser.parse_args()
    args.work = (args.work or ROOT / "bench" / ".cache" / "large-map" / str(args.images)).resolve()
    args.work.mkdir(parents=True, exist_ok=True)
    cv2.setNumThreads(1)
    from fastapi.testclient import TestClient

    from vloc.app.main import create_app

    layout = layout_for(args.world_images or args.images)
    stats = load_stats(args.work)
    generator = None if args.no_generate else start_generator(args.work, layout.images,
                                                              layout)
    settings = service_settings(args.work / "service", args.workers)
    with TestClient(create_app(settings)) as client:
        map_id = find_or_create_map(client)
        ingest(client, map_id, args.work, layout, args.images, stats, generator)
        build_stats = pack(client, map_id, stats, args.work)
        print(f"built: {build_stats}", flush=True)
    # A fresh service for the measurements: the worker that packed the map keeps the
    # build's heap, which is not what a worker holding a session needs.
    with TestClient(create_app(settings)) as client:
        frames = query_frames(args.work, args.frames)
        stats["timing"] = time_steps(build_stats["folder"], frames)
        if args.scale_to > stats["build"]["images"]:
            from vloc.workers.core.mapdata import MapData
            from vloc.workers.core.pf.config import config_from_params

            stats["scaled"] = scaled_scoring(
                MapData.load(build_stats["folder"], mmap=True),
                config_from_params({"config": "default"}), frames, args.scale_to, args.work)
        stats["memory"] = session_memory(client, map_id, frames)
        stats["database"] = database_size(client.app.state.ctx, map_id)
        if args.postgres and "postgres" not in stats:
            pg = postgres_size(client.app.state.ctx, map_id, args.postgres)
            if pg is not None:
                stats["postgres"] = pg
        stats["packed_bytes"] = sum(p.stat().st_size for p in
                                    Path(build_stats["folder"]).rglob("*") if p.is_file())
        save_stats(args.work, stats)
    if generator is not None:
        generator.wait()
    text = report(args, layout, stats, os.getloadavg()[0])
    write_result(args.out, text, announce=True)


if __name__ == "__main__":
    main()
