"""The Markdown report of ``bench_large_map.py``, from the statistics it saved.

:func:`report` reads ``stats.json``'s contents (the per-tile meters, the build job and its
``build_timings.json``, the step timings, the worker's memory and the database sizes) and
writes the tables of ``bench/results/large_map.md``.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

import cv2
import numpy as np
from large_map_world import ALTITUDE_M, SPACING_M, tile_done

from vloc.workers.core.timings import top_level  # the repository is on the path now


def world_seconds(work: Path, layout) -> float:
    """Generation seconds per tile, from the generator's log."""
    times = []
    log = work / "world.log"
    if log.is_file():
        for line in log.read_text().splitlines():
            if line.startswith("tile ") and " generated in " in line:
                times.append(float(line.rsplit(" in ", 1)[1].split()[0]))
    return float(np.median(times)) if times else float("nan")


def _median_ms(values) -> str:
    return f"{1e3 * float(np.median(values)):.1f}" if len(values) else "-"


def _p90_ms(values) -> str:
    return f"{1e3 * float(np.percentile(values, 90)):.1f}" if len(values) else "-"


def _generated(work: Path, layout) -> int:
    return sum(tile_done(work, t) for t in range(layout.tiles))


def _scaled_rows(stats: dict) -> list[str]:
    if "scaled" not in stats:
        return []
    sc, t = stats["scaled"], stats["timing"]
    dims = ", ".join(f"{k} {v}-d" for k, v in sc["dims"].items())
    rows = [f"| every image scored exactly, scaled to {sc['rows']:,} images ({dims}, the map's "
            f"rows repeated, memory-mapped) + top {sc['top']} | {len(sc['seconds'])} | "
            f"{_median_ms(sc['seconds'])} | {_p90_ms(sc['seconds'])} | |"]
    if "shortlist_seconds" in sc:
        code_dims = ", ".join(f"{v}-d" for v in sc["code_dims"].values())
        rows.append(f"| SIFT shortlist at {sc['rows']:,} images: the scan over the shortlist "
                    f"codes ({code_dims}), the shortlist scored exactly, top {sc['top']} | "
                    f"{len(sc['shortlist_seconds'])} | {_median_ms(sc['shortlist_seconds'])} | "
                    f"{_p90_ms(sc['shortlist_seconds'])} | < 20 |")
        steps = [s for used, s in t["steps"] if used == "global"]
        if steps:
            # the global step less its own all-image scoring on the built map, plus the
            # scaled map's scan through the codes
            est = (np.median(steps) - np.median(t["shortlist_s"])
                   + np.median(sc["shortlist_seconds"]))
            rows.append(f"| global step at {sc['rows']:,} images (the global step above, less "
                        f"its all-image scoring, plus the row above) | - | {1e3 * est:.1f} "
                        "| | < 20 |")
    return rows


def report(args, layout, stats: dict, load: float) -> str:
    b, t, mem, db = stats["build"], stats["timing"], stats["memory"], stats["database"]
    tiles = stats["tiles"].values()
    n = b["images"]
    add = np.sum([v["add"] for v in tiles], axis=0)
    ext = np.sum([v["extract"] for v in tiles], axis=0)
    gen_tile = world_seconds(args.work, layout)
    steps = {k: [s for used, s in t["steps"] if used == k] for k in ("global", "sift")}
    meas = {k: [s for used, s in t["measurements"] if used == k] for k in ("global", "sift")}
    cmd = " ".join([".venv/bin/python", "bench/bench_large_map.py"] + sys.argv[1:])
    # per-tile meters: a run stopped in the middle of a tile loses that tile's meter, so
    # each stage is divided by the images its meters saw
    added = sum(v["accepted"] for v in tiles)
    extracted = sum(v["extracted"] for v in tiles)
    rows = [("adding images (`add_images`: screening, EXIF, hash; decode in the worker)",
             added, add[0], add[1] + add[2], f"API {add[1]:.0f} + worker {add[2]:.0f}"),
            ("feature extraction (`extract_image`: decode, 6 global features, SIFT, ORB, "
             "rows)", extracted, ext[0], ext[1] + ext[2],
             f"API {ext[1]:.0f} + worker {ext[2]:.0f}")]
    for name, v in b["stages"].items():
        rows.append((f"packing: {name}", n, v["wall_s"], v["cpu_s"], "worker"))
    # a stage's parts ("geometry: self-check") are timed inside it: not added again
    whole = top_level(b["stages"])
    packing = (sum(v["wall_s"] for v in whole.values()),
               sum(v["cpu_s"] for v in whole.values()))
    job_cpu = b["api_cpu"] + b["worker_cpu"]
    rows.append(("outside the packing, on the engine's workers: the tie points "
                 "(`extract_ties`, one call per image), their pairs (`match_tie_pairs`, "
                 "batches of pairs), the reconstruction's tiles (`reconstruct_tile`, one "
                 "call per tile) and bookkeeping", n, b["wall"] - packing[0],
                 job_cpu - packing[1], "API + workers"))
    rows.append(("build job in all", n, b["wall"], job_cpu,
                 f"API {b['api_cpu']:.0f} + worker {b['worker_cpu']:.0f}"))
    per_image = ((add[1] + add[2]) / max(added, 1) + (ext[1] + ext[2]) / max(extracted, 1)
                 + job_cpu / n)
    lines = [
        f"# A map of {n:,} images: build, step times and memory",
        "",
        f"`{cmd}`",
        "",
        f"World: a synthetic UAV survey laid out as {layout.tiles} tiles of "
        f"{layout.tile_frames:,} frames (a {layout.columns} x {layout.rows} grid, "
        f"{layout.extent_m[0] / 1e3:.1f} x {layout.extent_m[1] / 1e3:.1f} km), nadir camera "
        f"{ALTITUDE_M:g} m up, {SPACING_M:g} m between frames on average (30 % gusts), "
        f"lawnmower lanes {0.6 * 2 * ALTITUDE_M * np.tan(np.radians(30)):.1f} m apart; map "
        "pass sunny, with 2 m GPS noise in its EXIF; tile 0's cloudy pass is the query pass. "
        f"{_generated(args.work, layout)} tiles generated"
        + (f", in a second process alongside the build, {gen_tile:.0f} s per tile (median "
           "wall)" if np.isfinite(gen_tile) else " beforehand")
        + f"; the map holds the first {n:,} "
        f"images (tiles 1 to {-(-n // layout.tile_frames)}, filled row by row).",
        "",
        "## Per frame, one core (320x240, 300 particles, default hybrid configuration)",
        "",
        f"CPU time (`time.thread_time`), OpenCV, BLAS and OpenMP limited to one thread; "
        f"{len(t['frame_ms'])} frames of the query pass through one hybrid session started "
        f"from an initial pose (sigma 10 m) at the first frame; median error "
        f"{np.median(t['errors']):.1f} m. Map loaded memory-mapped in {t['setup_s']:.1f} s "
        "(with its KD-tree).",
        "",
        "| what | frames | median ms | p90 ms | target |",
        "|---|---|---|---|---|",
        f"| global step (`_measurement(query, GLOBAL)` + filter step, extraction "
        f"included) | {len(steps['global'])} | {_median_ms(steps['global'])} | "
        f"{_p90_ms(steps['global'])} | < 20 |",
        f"| of which the global measurement (`_measurement`, mostly extraction) | "
        f"{len(meas['global'])} | {_median_ms(meas['global'])} | {_p90_ms(meas['global'])} | |",
        f"| SIFT shortlist: `_global_scores` over all {t['map_images']:,} images + top "
        f"{t['candidates']} (features extracted) | {len(t['shortlist_s'])} | "
        f"{_median_ms(t['shortlist_s'])} | {_p90_ms(t['shortlist_s'])} | < 20 |",
        f"| the frame's global features ({', '.join(t['global_features'])}) | "
        f"{len(t['global_extraction_s'])} | {_median_ms(t['global_extraction_s'])} | "
        f"{_p90_ms(t['global_extraction_s'])} | |",
        *_scaled_rows(stats),
        f"| SIFT step (`_filter_step` with SIFT, shortlist included) | {len(steps['sift'])} | "
        f"{_median_ms(steps['sift'])} | {_p90_ms(steps['sift'])} | |",
        f"| whole frame (`localise`), all steps | {len(t['frame_ms'])} | "
        f"{np.median([ms for _, ms in t['frame_ms']]):.1f} | "
        f"{np.percentile([ms for _, ms in t['frame_ms']], 90):.1f} | |",
        "",
        "## Memory of the worker process (session open and stepping)",
        "",
        "One worker of the local engine, started after the build; a hybrid session "
        "opened over the API, "
        f"{mem['frames']} frames posted (share of SIFT steps {mem['sift_share']:.0%}). MiB, "
        "from `/proc/<pid>/status` and `/proc/<pid>/smaps_rollup`. The packed map is "
        "memory-mapped: its pages show as file-backed (`Pss_File`) and are shared with "
        "every other process that maps the revision (and the page cache).",
        "",
        "| when | RSS | peak RSS | PSS | PSS anon | PSS file | private dirty |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, key in (("worker started, no session", "before"),
                       ("session opened (map loaded)", "opened"),
                       (f"after {mem['frames']} frames", "stepped")):
        m = mem[key]
        lines.append(f"| {label} | {m['VmRSS']:.0f} | {m['VmHWM']:.0f} | {m['Pss']:.0f} | "
                     f"{m.get('Pss_Anon', float('nan')):.0f} | "
                     f"{m.get('Pss_File', float('nan')):.0f} | {m['Private_Dirty']:.0f} |")
    lines += [
        "",
        f"Packed revision on disk: {stats['packed_bytes'] / 2**20:,.0f} MiB.",
        "",
        "## Build throughput",
        "",
        f"Driven in-process through the service layer on SQLite, {args.workers} worker "
        "process(es); CPU seconds are the API process's plus the workers', so images/s per "
        "core = images / CPU seconds.",
        "",
        "| stage | images | wall s | CPU s | CPU ms per image | images/s per core | where |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, count, wall, cpu, where in rows:
        lines.append(f"| {name} | {count:,} | {wall:,.0f} | {cpu:,.0f} | "
                     f"{1e3 * cpu / max(count, 1):.1f} | {count / max(cpu, 1e-9):,.0f} | "
                     f"{where} |")
    lines += [
        f"| **all stages** (adding + extraction + build job) | | | | {1e3 * per_image:.1f} | "
        f"{1 / per_image:,.1f} | |",
        "",
        *([("The build job's stages by wall time (its `stage`, polled every half second): "
            + ", ".join(f"{name} {wall:,.0f} s" for name, wall in b["job_stages"].items())
            + "."), ""] if b.get("job_stages") else []),
        *([f"Peak resident memory of the worker that packed the map (VmHWM, extraction "
           f"before it included): {b['worker_peak_mib']:,.0f} MiB, "
           f"{b['worker_peak_mib'] * 1024 / n:,.0f} KiB per image.", ""]
          if "worker_peak_mib" in b else []),
        "## Database",
        "",
        f"SQLite (WAL checkpointed): {db['bytes'] / 2**20:,.0f} MiB for {db['images']:,} "
        f"images, **{db['bytes'] / db['images'] * 1000 / 2**20:,.1f} MiB per 1,000 images** "
        "(image rows, global features, SIFT and ORB keypoints and descriptors, vocabularies).",
        "",
    ]
    if "postgres" in stats:
        pg = stats["postgres"]
        lines += [f"PostgreSQL: {pg['bytes'] / 2**20:,.1f} MiB for {pg['images']:,} of these "
                  "images with their feature rows, copied into a schema of its own "
                  "(tables, indexes and TOAST), "
                  f"**{pg['bytes'] / pg['images'] * 1000 / 2**20:,.1f} MiB per 1,000 images**.",
                  ""]
    lines += [
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs "
        f"shared with other jobs (1-minute load average {load:.1f} at the end of the run, "
        "with the world generated on the other core during ingestion); "
        f"Python {platform.python_version()}, NumPy {np.__version__}, OpenCV {cv2.__version__}.",
        "",
    ]
    return "\n".join(lines)
