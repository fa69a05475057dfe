"""A map that grows: images added to a built map against the same map built from scratch.

For each survey three maps are built as ``vloc eval`` builds them:

- **first**: the survey's first map images, its COLMAP model kept
  (:mod:`workers.core.geometry.kept`);
- **updated**: the first map's images and the added ones, the added ones registered into the
  kept model with its cameras held, and the first map's place vocabularies, descriptors and
  SIFT masks kept where they still hold (:mod:`workers.core.carryover`): what the service's
  build does once images are added;
- **scratch**: the same images built at once, reconstructed whole (``vloc map build --full``).

The updated and the scratch map localise the same query frames with ``hybrid`` and
``sift``; the mapper's CPU time is COLMAP's (``pycolmap.incremental_mapping``) alone. The
surveys:

- seneca-uav: pass 1, then the first half of pass 2 added; the second half of pass 2 are
  the queries (5 starts, skip 3);
- lewis-uav: the alternate split's map images, the first two thirds by capture time, then
  the rest added; the split's query images are the queries (3 starts, skip 3).

Writes ``bench/results/update.md`` and ``update.json``.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/eval_update.py [--only seneca,lewis]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from _common import DATASETS, RESULTS, repo_on_path, write_result

repo_on_path()

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from vloc.workers.core.evaluation.datasets import (  # noqa: E402
    load_dataset,
    load_frames,
    split,
)
from vloc.workers.core.evaluation.evaluate import evaluate  # noqa: E402
from vloc.workers.core.evaluation.experiment import build_map, truth_positions  # noqa: E402
from vloc.workers.core.evaluation.report import results_dict  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402

MODES = ["hybrid", "sift"]


def _by_time(images):
    return sorted(images, key=lambda im: (im.captured_at is None, im.captured_at, im.name))


def seneca() -> tuple[list, list, list, dict]:
    ds = load_dataset(DATASETS / "seneca-uav")
    first, second = split(ds, map_pass=1, query_pass=2)
    second = _by_time(second)
    half = len(second) // 2
    return first, second[:half], second[half:], {"starts": 5, "skip": 3}


def lewis() -> tuple[list, list, list, dict]:
    ds = load_dataset(DATASETS / "lewis-uav")
    maps, queries = split(ds, "alternate")
    maps = _by_time(maps)
    cut = 2 * len(maps) // 3
    return maps[:cut], maps[cut:], queries, {"starts": 3, "skip": 3}


SURVEYS = {"seneca": seneca, "lewis": lewis}


class MapperClock:
    """CPU seconds spent in COLMAP's mapper while it is installed."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._real = pycolmap.incremental_mapping

    def __enter__(self) -> MapperClock:
        def timed(*args, **kw):
            t0 = time.process_time()
            try:
                return self._real(*args, **kw)
            finally:
                self.seconds += time.process_time() - t0

        pycolmap.incremental_mapping = timed
        return self

    def __exit__(self, *exc) -> None:
        pycolmap.incremental_mapping = self._real


def build(images, kept: Path | None, previous=None,
          revision: int = 1) -> tuple[object, dict, float, float]:
    """The map, its geometry report, the mapper's CPU s and the whole build's CPU s."""
    report: dict = {}
    t0 = time.process_time()
    with MapperClock() as clock:
        data = build_map(images, load_frames(images), map_id="update", report=report,
                         kept=kept, previous=previous, revision=revision)
    return data, report, clock.seconds, time.process_time() - t0


def vocabularies(data) -> str:
    """Which revision trained the map's vocabularies, and how far its images' distortion
    has risen since (the largest over its descriptors)."""
    fits = data.vocabulary_fits.values()
    trained = sorted({f.revision for f in fits})
    rise = max((f.rise() for f in fits), default=0.0)
    return f"revision {', '.join(map(str, trained))}, {100 * rise:+.1f} %"


def localise(data, queries, options: dict) -> dict:
    frames = load_frames(queries)
    stamps = [None if im.captured_at is None else im.captured_at.timestamp() for im in queries]
    qs = [QueryFrame(f, t, key=i) for i, (f, t) in enumerate(zip(frames, stamps, strict=True))]
    results = evaluate(data, qs, truth_positions(queries, data), modes=MODES,
                       configs=["default"], **options)
    return results_dict(results)["modes"]


def run_survey(name: str) -> dict:
    first, added, queries, options = SURVEYS[name]()
    out = {"survey": name, "first_images": len(first), "added_images": len(added),
           "queries": len(queries), "options": options, "maps": {}}
    with tempfile.TemporaryDirectory(prefix="vloc-update-") as tmp:
        kept = Path(tmp)
        before, report, mapper_s, build_s = build(first, kept)
        out["maps"]["first"] = {"geometry": report, "mapper_cpu_s": mapper_s,
                                "build_cpu_s": build_s}
        print(f"{name} first: mapper {mapper_s:.1f} s, placed {report.get('placed')}",
              flush=True)
        for label, store, previous in (("updated", kept, before), ("scratch", None, None)):
            data, report, mapper_s, build_s = build(first + added, store, previous, 2)
            modes = localise(data, queries, options)
            out["maps"][label] = {"geometry": report, "mapper_cpu_s": mapper_s,
                                  "build_cpu_s": build_s, "modes": modes,
                                  "vocabularies": vocabularies(data)}
            print(f"{name} {label}: mapper {mapper_s:.1f} s, placed {report.get('placed')}, "
                  f"hybrid {modes['hybrid']['mean_error_m']:.2f} m", flush=True)
    return out


def table(rows: list[dict]) -> str:
    lines = ["| survey | map | images | placed | GPS RMS h / v m | mapper CPU s | "
             "vocabularies trained by, distortion since | "
             "hybrid mean / median m | SIFT steps | sift mean / median m |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for label, m in row["maps"].items():
            g = m["geometry"]
            n = row["first_images"] + (0 if label == "first" else row["added_images"])
            cells = [row["survey"], label, str(n), str(g.get("placed", "-")),
                     f"{g.get('gps_rms_m') or float('nan'):.1f} / "
                     f"{g.get('gps_rms_vertical_m') or float('nan'):.1f}",
                     f"{m['mapper_cpu_s']:.1f}", m.get("vocabularies", "-")]
            if "modes" in m:
                h, s = m["modes"]["hybrid"], m["modes"]["sift"]
                cells += [f"{h['mean_error_m']:.2f} / {h['median_error_m']:.2f}",
                          f"{100 * h['sift_step_share']:.1f} %",
                          f"{s['mean_error_m']:.2f} / {s['median_error_m']:.2f}"]
            else:
                cells += ["-", "-", "-"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default=",".join(SURVEYS))
    p.add_argument("--out", type=Path, default=RESULTS / "update.md")
    args = p.parse_args()
    rows = []
    with threadpool_limits(limits=1):
        for name in args.only.split(","):
            rows.append(run_survey(name))
    for row in rows:
        for m in row["maps"].values():
            m["geometry"] = {k: v for k, v in m["geometry"].items()
                             if isinstance(v, (int, float, str, type(None)))}
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1, default=float))
    text = ["# A map that grows: images added to a built map, against the map built from scratch",
            "", f"`OMP_NUM_THREADS=1 .venv/bin/python bench/eval_update.py --only {args.only}` "
            f"({platform.python_version()}, {platform.machine()}, one BLAS thread).", "",
            __doc__.split("\n\n", 1)[1].split("Writes")[0].strip(), "", table(rows), ""]
    for row in rows:
        maps = row["maps"]
        ratio = (maps["updated"]["modes"]["hybrid"]["mean_error_m"]
                 / maps["scratch"]["modes"]["hybrid"]["mean_error_m"])
        text.append(f"- {row['survey']}: the updated map's hybrid mean error is {ratio:.2f} of "
                    f"the scratch map's; its mapper took "
                    f"{maps['updated']['mapper_cpu_s']:.1f} CPU s against "
                    f"{maps['scratch']['mapper_cpu_s']:.1f} (the first map's: "
                    f"{maps['first']['mapper_cpu_s']:.1f}).")
    write_result(args.out, "\n".join(text) + "\n")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
