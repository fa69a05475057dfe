"""A map that grows: rebuilding after images are added, against building it whole.

Starts ``vloc serve`` (SQLite, ``--workers`` engine processes) and builds two maps of a data
set's first pass over HTTP: one of the first images, then the last ``--added`` uploaded and
the map rebuilt (the rebuild takes up the tie points and matched pairs the map keeps from
its first build, and registers the added images into the COLMAP models it kept, their
cameras held), and one of every image built at once. With ``--deleted N``, N of the first
images (spread over them) are then deleted from the grown map and it is rebuilt again (the
kept models lose their cameras, the others held). Then the grown map is rebuilt with
``full`` (its geometry reconstructed whole). Reports each build's wall time by stage (the
job's ``stage``, polled), how far the rebuild moved the first build's cameras (once the
best similarity is taken out: the map's frame moves with its centroid), how far its
cameras lie from the whole build's, and checks that the full rebuild's cameras are the
whole build's, bit for bit.

    python bench/bench_rebuild.py [--dataset PATH] [--added 10] [--deleted 0] [--workers 2]
                                  [--no-whole] [--out bench/results/rebuild.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from _common import DATASETS, RESULTS, repo_on_path, write_result

repo_on_path()

from bench_large_map import build as build_job  # noqa: E402
from bench_service import ADMIN_KEY, start_server  # noqa: E402

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402
from vloc.workers.core.mapdata import MapData  # noqa: E402

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


def upload(http: httpx.Client, map_id: str, images, batch: int = 100) -> None:
    for k in range(0, len(images), batch):
        files = [("files", (im.name, im.path.read_bytes(), "image/jpeg"))
                 for im in images[k:k + batch]]
        http.post(f"/v1/maps/{map_id}/images", files=files, headers=ADMIN).raise_for_status()


def build(http: httpx.Client, map_id: str, *, full: bool = False,
          ) -> tuple[float, dict[str, float]]:
    """Build the map; its wall time and the seconds spent in each of the job's stages."""
    t0 = time.perf_counter()
    job, stages = build_job(http, map_id, headers=ADMIN, full=full)
    if job["status"] != "done":
        raise SystemExit(f"build failed: {job['error']}")
    return time.perf_counter() - t0, stages


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DATASETS / "seneca-uav")
    p.add_argument("--added", type=int, default=10)
    p.add_argument("--deleted", type=int, default=0,
                   help="then delete this many of the first images and rebuild again")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=RESULTS / "rebuild.md")
    p.add_argument("--no-whole", action="store_true",
                   help="build neither the map of every image at once nor the full rebuild "
                        "(a large map: the first build is the full build's measure)")
    args = p.parse_args()
    images, _ = split(load_dataset(args.dataset), "pass", map_pass=1, query_pass=2)
    first, added = images[:-args.added], images[-args.added:]
    tmp = Path(tempfile.mkdtemp(prefix="vloc-bench-"))
    proc, base = start_server(tmp / "data", args.workers)
    try:
        with httpx.Client(base_url=base, timeout=600) as http:
            grown = http.post("/v1/maps", json={"name": "grown"}, headers=ADMIN).json()["id"]
            whole = http.post("/v1/maps", json={"name": "whole"}, headers=ADMIN).json()["id"]
            upload(http, grown, first)
            timed = {"first": build(http, grown)}
            upload(http, grown, added)
            timed["rebuild"] = build(http, grown)
            gone: set[str] = set()
            if args.deleted:
                listed = http.get(f"/v1/maps/{grown}/images", headers=ADMIN).json()
                firsts = listed[:len(first)]
                picks = np.linspace(0, len(firsts) - 1, args.deleted + 2)[1:-1].round()
                for k in sorted({int(k) for k in picks}):
                    http.delete(f"/v1/maps/{grown}/images/{firsts[k]['id']}",
                                headers=ADMIN).raise_for_status()
                    gone.add(firsts[k]["filename"])
                timed["delete"] = build(http, grown)
            if not args.no_whole:
                upload(http, whole, images)
                timed["whole"] = build(http, whole)
                timed["full"] = build(http, grown, full=True)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    maps = tmp / "data" / "maps"
    revisions = {"first": (grown, 1), "rebuild": (grown, 2), "delete": (grown, 3),
                 "whole": (whole, 1), "full": (grown, 4 if "delete" in timed else 3)}
    cameras = {k: centres(maps / m / f"rev-{r:06d}") for k, (m, r) in revisions.items()
               if k in timed}
    # a map that lost images is not the whole build's: its full rebuild is not compared
    same = args.no_whole or bool(gone) or (
        cameras["full"] is not None and cameras["whole"] is not None
        and np.array_equal(cameras["full"], cameras["whole"], equal_nan=True))
    stages = sorted({s for _, st in timed.values() for s in st})
    label = {"first": f"first build, {len(first)} images",
             "rebuild": f"rebuild after {len(added)} added ({len(images)} images)",
             "whole": f"all {len(images)} images built at once",
             "delete": f"rebuild after {len(gone)} of the first deleted "
                       f"({len(images) - len(gone)} images)",
             "full": "the grown map rebuilt with `full`"}
    rows = [f"| {label[k]} | {wall:.1f} | {placed(cameras[k])} | "
            + " | ".join(f"{st.get(s, 0.0):.1f}" for s in stages) + " |"
            for k, (wall, st) in timed.items()]
    moved, apart = compare(cameras, len(first))
    if "delete" in timed:
        moved += " " + compare_deleted(maps / grown, gone)
    if args.no_whole:
        summary = (f"Rebuild / first build: {timed['rebuild'][0] / timed['first'][0]:.3f}. "
                   f"{moved}")
    else:
        deleted = (f"Rebuild after the deletions / whole build: "
                   f"{timed['delete'][0] / timed['whole'][0]:.3f}. " if "delete" in timed
                   else "")
        check = ("The full rebuild's cameras are the whole build's, bit for bit: "
                 f"{'yes' if same else 'NO'}." if not gone else
                 "(The full rebuild, of a map that lost images, is not compared with the "
                 "whole build.)")
        summary = (f"Rebuild / whole build: {timed['rebuild'][0] / timed['whole'][0]:.3f}. "
                   f"{deleted}{moved} {apart} {check}")
    text = "\n".join([
        "# Rebuilding a map that grew", "",
        f"`python bench/bench_rebuild.py --dataset {args.dataset.name} --added {args.added} "
        + (f"--deleted {args.deleted} " if args.deleted else "")
        + f"--workers {args.workers}{' --no-whole' if args.no_whole else ''}`", "",
        f"Machine: {platform.machine()}, {os.cpu_count()} logical CPUs; {args.workers} "
        f"worker process(es); SQLite; {args.dataset.name} pass 1. Wall seconds at the client, "
        "and by the build job's stage (polled every 0.5 s).", "",
        "| build | wall s | cameras placed | " + " | ".join(stages) + " |",
        "|---|---|---|" + "---|" * len(stages), *rows, "",
        summary, "", *packing_table(maps, revisions, label, timed)])
    write_result(args.out, text)
    if not same:
        raise SystemExit("the full rebuild differs from the whole build")


def packing_table(maps: Path, revisions: dict, label: dict, timed: dict) -> list[str]:
    """The packing's own stages for each build (wall seconds, from the revision's
    ``build_timings.json``), which revision trained its place vocabularies, and its size on
    disk with the part of it in files linked from the revision before it."""
    import json

    stages: dict[str, dict] = {}
    trained: dict[str, str] = {}
    disk: dict[str, str] = {}
    for key, (map_id, revision) in revisions.items():
        folder = maps / map_id / f"rev-{revision:06d}"
        if key not in timed or not (folder / "build_timings.json").is_file():
            continue
        stages[key] = json.loads((folder / "build_timings.json").read_text())
        size, linked = revision_disk(folder, maps / map_id / f"rev-{revision - 1:06d}")
        disk[key] = f"{size / 2**20:.1f} | {linked / 2**20:.1f}"
        vocabularies = json.loads((folder / "meta.json").read_text()).get("vocabularies", {})
        trained[key] = ", ".join(sorted({str(v.get("trained_revision", "-"))
                                         for v in vocabularies.values()})) or "-"
    names = list(dict.fromkeys(name for st in stages.values() for name in st))
    if not names:
        return []
    return ["The packing's stages (wall s, `build_timings.json`), and the revision that "
            "trained the revision's place vocabularies:", "",
            "| build | vocabularies trained by revision | MiB on disk | of which linked from "
            "the revision before | " + " | ".join(names) + " |",
            "|---|---|---|---|" + "---|" * len(names),
            *(f"| {label[k]} | {trained[k]} | {disk[k]} | "
              + " | ".join(f"{st[n]['wall_s']:.2f}" if n in st else "-" for n in names)
              + " |" for k, st in stages.items()), ""]


def revision_disk(folder: Path, before: Path) -> tuple[int, int]:
    """Bytes of a revision's files, and of those that are files of the revision ``before``
    (hard links: :mod:`vloc.workers.core.rowchunks`)."""
    size = linked = 0
    for path in folder.iterdir():
        n = path.stat().st_size
        size += n
        other = before / path.name
        linked += n if other.exists() and os.path.samefile(path, other) else 0
    return size, linked


def centres(folder: Path) -> np.ndarray | None:
    """The camera centres of a packed revision (NaN where not placed); None without
    geometry."""
    data = MapData.load(folder)
    return None if data.geometry is None else np.asarray(data.geometry.centres)


def compare_deleted(folder: Path, gone: set[str]) -> str:
    """How far the rebuild after the deletions moved the other cameras relative to one
    another, as a sentence."""
    from tests.core.geometry.scene import similarity_residuals

    before, after = MapData.load(folder / "rev-000002"), MapData.load(folder / "rev-000003")
    if before.geometry is None or after.geometry is None:
        return "After the deletions: a map without geometry, nothing to compare."
    at = {name: k for k, name in enumerate(before.names)}
    rows = np.array([at[name] for name in after.names])
    a = np.asarray(before.geometry.centres)[rows]
    b = np.asarray(after.geometry.centres)
    both = np.isfinite(a[:, 0]) & np.isfinite(b[:, 0])
    r = similarity_residuals(a[both], b[both])
    return (f"After deleting {len(gone)} images, the {int(both.sum())} cameras placed before "
            f"and after moved by {np.median(r):.3f} m (median; at most {r.max():.3f} m) "
            "relative to one another.")


def placed(c: np.ndarray | None) -> str:
    return "no geometry" if c is None else str(int(np.isfinite(c[:, 0]).sum()))


def compare(cameras: dict, n_first: int) -> tuple[str, str]:
    """How far the rebuild moved the first build's cameras relative to one another, and how
    far its cameras lie from the whole build's, as sentences."""
    from tests.core.geometry.scene import similarity_residuals

    a, b, w = cameras["first"], cameras["rebuild"], cameras.get("whole")
    if a is None or b is None:
        return "A map without geometry: nothing to compare.", ""
    both = np.isfinite(a[:, 0]) & np.isfinite(b[:n_first, 0])
    r = similarity_residuals(a[both], b[:n_first][both])
    moved = (f"The first build's {int(both.sum())} cameras the rebuild also placed moved by "
             f"{np.median(r):.3f} m (median; 90th percentile {np.percentile(r, 90):.3f} m, "
             f"at most {r.max():.3f} m) relative to one another (each tile aligned to its GPS "
             "again; within a tile's COLMAP model they are held).")
    if w is None:
        return moved, ""
    common = np.isfinite(b[:, 0]) & np.isfinite(w[:, 0])
    d = np.linalg.norm(b[common] - w[common], axis=1)
    return moved, (f"Its cameras lie {np.median(d):.2f} m (median; 90th percentile "
                   f"{np.percentile(d, 90):.2f} m) from the whole build's.")

if __name__ == "__main__":
    main()
