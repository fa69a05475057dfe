"""Benchmark: images added to a large built map, the map updated, against its full build.

Runs on the work directory of a finished ``bench_large_map.py`` run: its service data (the
built map), its world and its ``stats.json`` (the full build's times). The next ``--added``
images of the world's map pass, those that follow the map's own in the order the large-map
run fills it (the rest of its last tile, then the next tile's), go through the service as the
map's did: ``add_images``, feature extraction in the worker, then the build job, which
updates the map rather than rebuilding it (tie points of the new images only, pairs that
touch them, the tiles they join registered into the kept COLMAP models, vocabularies kept
while they fit). Reported: the update's wall and CPU seconds by stage beside the full
build's, their ratio, the geometry before and after (cameras placed, self-check), and the
hybrid's error over the large-map run's query frames on the updated revision.

Usage::

    .venv/bin/python bench/bench_large_update.py --work /path/to/large-map/work
        [--added 100] [--workers 2] [--frames 200] [--out bench/results/large_update.md]

The updated map stays in the work directory: a second run adds the next ``--added``.
"""

from __future__ import annotations

from _common import RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from bench_large_map import (  # noqa: E402
    ADMIN,
    Meter,
    add_tile,
    build,
    extract_pending,
    find_or_create_map,
    load_stats,
    query_frames,
    save_stats,
    service_settings,
    time_steps,
    worker_peak_mib,
)
from large_map_world import TILE_FRAMES, map_images, tile_done  # noqa: E402


def next_images(work: Path, have: int, count: int) -> list[Path]:
    """The map-pass image files at places ``have`` to ``have + count`` of the large-map
    run's fill order (tile by tile, each in flight order)."""
    out: list[Path] = []
    tile, skip = divmod(have, TILE_FRAMES)
    while len(out) < count:
        if not tile_done(work, tile):
            raise SystemExit(f"the world has no tile {tile + 1} to take images from: generate "
                             f"it larger (bench_large_map.py --world-images)")
        out += map_images(work, tile)[skip:skip + count - len(out)]
        tile, skip = tile + 1, 0
    return out


def geometry_summary(m: dict) -> dict:
    g = m.get("geometry") or {}
    check = g.get("self_check") or {}
    return {"status": g.get("status"), "placed": g.get("placed"), "images": g.get("images"),
            "models": g.get("models"), "gps_rms_m": g.get("gps_rms_m"),
            "self_check_median_m": check.get("median_m"),
            "self_check_registered": check.get("registered")}


def update(client, map_id: str, files: list[Path]) -> dict:
    """Add ``files`` to the map and build it; wall and CPU seconds of each part."""
    ctx = client.app.state.ctx
    with Meter(ctx) as add:
        accepted = add_tile(client, map_id, files)
    if accepted != len(files):
        raise SystemExit(f"{len(files) - accepted} of the {len(files)} images were refused "
                         "(already in the map?)")
    with Meter(ctx) as ext:
        extracted = extract_pending(ctx, map_id)
    with Meter(ctx) as job_meter:
        job, stages = build(client, map_id)
    if job["status"] != "done":
        raise SystemExit(f"the update failed: {job.get('error')}")
    m = client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    folder = ctx.settings.packed_map_dir(map_id, m["revision"])
    return {"added": accepted, "extracted": extracted, "revision": m["revision"],
            "images": m["image_count"], "folder": str(folder),
            "add": [add.wall, add.api_cpu, add.worker_cpu],
            "extract": [ext.wall, ext.api_cpu, ext.worker_cpu],
            "job": [job_meter.wall, job_meter.api_cpu, job_meter.worker_cpu],
            "job_stages": stages, "worker_peak_mib": worker_peak_mib(ctx),
            "stages": json.loads((folder / "build_timings.json").read_text()),
            "geometry": geometry_summary(m)}


def full_build(stats: dict) -> dict:
    """The large-map run's full build, in :func:`update`'s terms."""
    tiles = stats["tiles"].values()
    b = stats["build"]
    return {"add": [sum(t["add"][k] for t in tiles) for k in range(3)],
            "extract": [sum(t["extract"][k] for t in tiles) for k in range(3)],
            "job": [b["wall"], b["api_cpu"], b["worker_cpu"]],
            "job_stages": b["job_stages"], "stages": b["stages"], "images": b["images"]}


def report(args, tiles: int, full: dict, before: dict, upd: dict, errors: list[float]) -> str:
    def row(name: str, f: list[float], u: list[float]) -> str:
        return (f"| {name} | {f[0]:.0f} | {f[1] + f[2]:.0f} | {u[0]:.1f} | {u[1] + u[2]:.1f} "
                f"| {u[0] / f[0]:.3f} |")

    whole_f = [sum(full[k][i] for k in ("add", "extract", "job")) for i in range(3)]
    whole_u = [sum(upd[k][i] for k in ("add", "extract", "job")) for i in range(3)]
    stage_names = list(dict.fromkeys([*full["job_stages"], *upd["job_stages"]]))
    lines = [
        f"# {upd['added']:,} images added to a map of {full['images']:,}: the update against "
        "the full build", "",
        f"`.venv/bin/python bench/bench_large_update.py --work {args.work} --added "
        f"{args.added} --workers {args.workers} --frames {args.frames}`", "",
        f"{machine_and_python()}, {os.cpu_count()} CPUs, {args.workers} worker process(es), "
        f"SQLite; load average at the end {os.getloadavg()[0]:.1f}. The map: the first "
        f"{full['images']:,} images of a {tiles}-tile synthetic UAV world "
        "(`bench_large_map.py`, whose run built it in full); the added images: the next "
        f"{upd['added']:,} of its map pass in the same order, revision {upd['revision']} "
        f"({upd['images']:,} images).", "",
        "| part | full build wall s | full build CPU s | update wall s | update CPU s | "
        "update / full (wall) |", "|---|---|---|---|---|---|",
        row("adding images (`add_images`)", full["add"], upd["add"]),
        row("feature extraction (`extract_image`)", full["extract"], upd["extract"]),
        row("build job", full["job"], upd["job"]),
        row("**all**", whole_f, whole_u), "",
        "The build job's stages (wall s, its `stage` polled every half second):", "",
        "| stage | full build | update |", "|---|---|---|"]
    for s in stage_names:
        lines.append(f"| {s} | {full['job_stages'].get(s, 0.0):.1f} | "
                     f"{upd['job_stages'].get(s, 0.0):.1f} |")
    lines += ["", "The packing's own stages (`build_timings.json`, wall s):", "",
              "| packing stage | full build | update |", "|---|---|---|"]
    for s in dict.fromkeys([*full["stages"], *upd["stages"]]):
        lines.append(f"| {s} | {full['stages'].get(s, {}).get('wall_s', 0.0):.2f} | "
                     f"{upd['stages'].get(s, {}).get('wall_s', 0.0):.2f} |")
    lines += ["", f"Peak resident memory of the worker that packed the update: "
        f"{upd['worker_peak_mib']:.0f} MiB.", "",
        "| geometry | status | placed / images | models | GPS RMS m | self-check median m, "
        "registered |", "|---|---|---|---|---|---|"]
    for name, g in (("before", before), ("after the update", upd["geometry"])):
        sc = ("-" if g["self_check_median_m"] is None else
              f"{g['self_check_median_m']:.2f}, {100 * g['self_check_registered']:.0f} %")
        rms = "-" if g["gps_rms_m"] is None else f"{g['gps_rms_m']:.2f}"
        lines.append(f"| {name} | {g['status']} | {g['placed']} / {g['images']} | "
                     f"{g['models']} | {rms} | {sc} |")
    if errors:
        e = np.asarray(errors)
        lines += ["", f"On the updated revision, a hybrid session (`default`, one core) over "
                  f"the large-map run's {len(e)} query frames (tile 0's cloudy pass) from an "
                  f"initial pose (sigma 10 m) at the first frame: median error "
                  f"{np.median(e):.1f} m, mean {e.mean():.1f} m, {100 * np.mean(e <= 5):.0f} % "
                  "within 5 m."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True,
                        help="the work directory of a finished bench_large_map.py run")
    parser.add_argument("--added", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--frames", type=int, default=200,
                        help="query frames to localise on the updated revision (0: none)")
    parser.add_argument("--out", type=Path, default=RESULTS / "large_update.md")
    args = parser.parse_args()
    args.work = args.work.resolve()
    stats = load_stats(args.work)
    if "build" not in stats:
        raise SystemExit(f"{args.work} holds no finished bench_large_map.py build")
    cv2.setNumThreads(1)
    from fastapi.testclient import TestClient

    from vloc.app.main import create_app

    full = full_build(stats)
    with TestClient(create_app(service_settings(args.work / "service", args.workers))) as c:
        map_id = find_or_create_map(c)
        m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
        if m["status"] != "ready" or m["pending_images"]:
            raise SystemExit(f"the map is {m['status']} with {m['pending_images']} images "
                             "pending: finish its build first")
        files = next_images(args.work, m["image_count"], args.added)
        before = geometry_summary(m)
        upd = update(c, map_id, files)
    stats.setdefault("updates", []).append(upd)
    save_stats(args.work, stats)
    errors = (time_steps(upd["folder"], query_frames(args.work, args.frames))["errors"]
              if args.frames else [])
    tiles = sum(1 for _ in (args.work / "world").glob("tile_*/world.json"))
    write_result(args.out, report(args, tiles, full, before, upd, errors), announce=True)


if __name__ == "__main__":
    main()
