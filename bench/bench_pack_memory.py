"""Benchmark: the memory a map build's packing holds, stage by stage.

Packs a map already ingested by ``bench_large_map.py`` again, in this process, with the same
job function the build worker runs (``app.tasks.build.pack_map``), and reports after each stage
the memory Python and NumPy have allocated (``tracemalloc``: the worker's own heap, without
the pages of memory-mapped files, which the kernel can drop) and its peak during the stage.
A worker's resident size (VmHWM) also counts the pages of the files it maps, such as the tie
points spilled to disk, so it says less about what a large build needs.

Usage::

    .venv/bin/python bench/bench_pack_memory.py [--work bench/.cache/large-map/1000]

Writes ``bench/results/pack_memory.md`` and prints it.
"""

from __future__ import annotations

from _common import RESULTS, ROOT, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import contextlib  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

repo_on_path()

MIB = 2 ** 20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=ROOT / "bench" / ".cache" / "large-map" / "1000",
                        help="a work directory of bench_large_map.py")
    parser.add_argument("--out", type=Path, default=RESULTS / "pack_memory.md")
    args = parser.parse_args()
    tracemalloc.start()
    from sqlalchemy import create_engine, select
    from sqlalchemy.orm import Session

    from vloc.app.maps.models import MapImage
    from vloc.app.tasks import build as tasks
    from vloc.workers.core import mapbuild

    database = args.work / "service" / "vloc.sqlite3"
    if not database.is_file():
        sys.exit(f"no ingested map in {args.work}: run bench/bench_large_map.py first")
    url = f"sqlite:///{database}"
    with Session(create_engine(url)) as db:
        images = list(db.scalars(select(MapImage).order_by(MapImage.id)))
    map_id = str(images[0].map_id)
    folder = args.work / "service" / "maps" / map_id / "images"
    files = {img.id: str(folder / f"{img.file_hash}.jpg") for img in images}

    rows: list[tuple[str, float, float]] = []
    real_stage = mapbuild.stage

    @contextlib.contextmanager
    def stage(timings, name):
        if ": " in name:  # a part of a stage (its peak is the stage's): timed only
            with real_stage(timings, name):
                yield
            return
        tracemalloc.reset_peak()
        with real_stage(timings, name):
            yield
        current, peak = tracemalloc.get_traced_memory()
        rows.append((name, current / MIB, peak / MIB))

    mapbuild.stage = stage
    start = tracemalloc.get_traced_memory()[0] / MIB
    out = Path(tempfile.mkdtemp(prefix="pack-memory-"))
    try:
        tasks.pack_map(url, map_id, 1, str(out / "rev"), image_files=files,
                       lens_files=list(files.values())[:: max(1, len(files) // 25)])
    finally:
        mapbuild.stage = real_stage
        shutil.rmtree(out, ignore_errors=True)
    n = len(images)
    peak = max(p for _, _, p in rows)
    lines = [f"# Memory of packing a {n:,}-image map, by stage", "",
             f"Command: `.venv/bin/python bench/bench_pack_memory.py --work {args.work}`. "
             "MiB allocated by Python and NumPy (`tracemalloc`), the packing job run in one "
             f"process; {start:.0f} MiB were allocated before it began.", "",
             "| stage | held after it (MiB) | peak during it (MiB) |", "|---|---|---|"]
    lines += [f"| {name} | {cur:,.0f} | {p:,.0f} |" for name, cur, p in rows]
    lines += ["", f"Peak {peak:,.0f} MiB: **{(peak - start) * 1024 / n:,.0f} KiB per image** "
              f"above the start ({(peak - start) / 1024 * 50_000 / n:,.1f} GiB at 50,000 "
              "images, if it all grew in proportion; the vocabularies' peak over what they "
              "hold after is their training sample, bounded whatever the map's size)."]
    text = "\n".join(lines) + "\n"
    write_result(args.out, text)


if __name__ == "__main__":
    main()
