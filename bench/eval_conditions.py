"""A map of two flights in other light: does a dusk flight added to a sunny map help dusk frames?

For each survey, three maps are built as `vloc eval` builds them: the sunny flight alone,
the sunny flight with a dusk flight over the same ground built at once (a map of several
flights, `vloc eval --map-pass 1,2`), and the sunny map updated with the dusk flight as the
service updates a map (the dusk images registered into the sunny map's COLMAP model, its
place vocabularies kept while they fit: :mod:`workers.core.carryover`). Each localises a
sunny and a dusk query flight with the default `hybrid` filter. A map that holds several
conditions should localise the dusk frames better than the sunny map alone, and the sunny
frames no worse.

The surveys:

- the UAV world (seed 3): passes sunny, dusk (the second map flight), sunny and dusk (the
  query flights), each rendered by the world's lighting (sun, shadows, sky light);
- seneca-uav relit: pass 1 (map), pass 1 relit to dusk as the second map flight (the same
  viewpoints in other light), pass 2 as it is and pass 2 relit to dusk as the queries
  (:func:`workers.core.evaluation.photometric.apply_variant`, ``dusk``).

Writes ``bench/results/conditions.md`` and ``conditions.json``.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/eval_conditions.py [--only uav,seneca]
        [--dusk-alone]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from datetime import datetime, timedelta
from pathlib import Path

from _common import DATASETS, RESULTS, ROOT, machine_and_python, repo_on_path, write_result

repo_on_path()

import cv2  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from vloc.clients.world import generate_world  # noqa: E402
from vloc.workers.core.evaluation.datasets import load_dataset, load_frames, split  # noqa: E402
from vloc.workers.core.evaluation.evaluate import evaluate  # noqa: E402
from vloc.workers.core.evaluation.experiment import (  # noqa: E402
    build_map,
    load_experiment,
    truth_positions,
)
from vloc.workers.core.evaluation.photometric import apply_variant, variant_rng  # noqa: E402
from vloc.workers.core.evaluation.report import results_dict  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402

CACHE = ROOT / "bench" / ".cache" / "conditions"
STARTS, SKIP = 3, 10
MAPS = {"sunny map": (1,), "sunny + dusk map": (1, 2),
        "sunny map updated with dusk": (1, 2)}
UPDATED = "sunny map updated with dusk"
"""Built as an update of the sunny map, not at once."""
DUSK_ALONE = {"dusk map": (2,)}
"""With ``--dusk-alone``: the dusk flight on its own, what it is worth as a map by itself."""
QUERIES = {"sunny": 3, "dusk": 4}


def uav_world() -> Path:
    out = CACHE / "uav"
    if not (out / "world.json").is_file():
        generate_world(out, kind="uav", seed=3, passes=("sunny", "dusk", "sunny", "dusk"),
                       overwrite=True)
    return out


def seneca_relit() -> Path | None:
    """seneca-uav as four passes: 1 as it is, 1 relit (2), 2 as it is (3), 2 relit (4)."""
    source = DATASETS / "seneca-uav"
    if not (source / "images").is_dir():
        return None
    out = CACHE / "seneca-relit"
    table = out / "ground_truth.csv"
    if table.is_file():
        return out
    (out / "images").mkdir(parents=True, exist_ok=True)
    with open(source / "ground_truth.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["pass"] in ("1", "2")]
    written = []
    for k, row in enumerate(rows):
        name, original = row["filename"], source / "images" / row["filename"]
        plain = out / "images" / name
        if not plain.exists():
            plain.symlink_to(original.resolve())
        relit_name = f"dusk-{name}"
        image = cv2.imread(str(original), cv2.IMREAD_COLOR)
        relit = apply_variant(image, "dusk", rng=variant_rng(7, k))
        cv2.imwrite(str(out / "images" / relit_name), relit, [cv2.IMWRITE_JPEG_QUALITY, 92])
        # a later flight: the same ground six hours on
        later = (datetime.fromisoformat(row["captured_at"]) + timedelta(hours=6)).isoformat()
        plain_pass = {"1": "1", "2": "3"}[row["pass"]]
        relit_pass = {"1": "2", "2": "4"}[row["pass"]]
        written.append({**row, "pass": plain_pass})
        written.append({**row, "filename": relit_name, "pass": relit_pass,
                        "captured_at": later})
    with open(table, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(written[0]))
        writer.writeheader()
        writer.writerows(written)
    return out


SURVEYS = {"uav": uav_world, "seneca": seneca_relit}


def queries_of(folder: Path, query_pass: int, map_data) -> tuple[list[QueryFrame], object]:
    """A pass's frames as query frames, and their true positions in the map's frame."""
    images = [im for im in load_dataset(folder).images if im.pass_ == query_pass]
    frames = load_frames(images)
    queries = [QueryFrame(f, None if im.captured_at is None else im.captured_at.timestamp(),
                          key=i) for i, (f, im) in enumerate(zip(frames, images, strict=True))]
    return queries, truth_positions(images, map_data)


def updated_map(folder: Path) -> tuple[object, dict]:
    """The sunny flight's map updated with the dusk flight (both built keeping their COLMAP
    models, the update packed from the sunny map), and its geometry report."""
    ds = load_dataset(folder)
    sunny, _ = split(ds, "pass", map_pass=MAPS["sunny map"], query_pass=QUERIES["sunny"])
    both, _ = split(ds, "pass", map_pass=MAPS[UPDATED], query_pass=QUERIES["sunny"])
    report: dict = {}
    with tempfile.TemporaryDirectory(prefix="vloc-conditions-") as kept:
        first = build_map(sunny, load_frames(sunny), map_id=ds.folder.name, kept=kept,
                          revision=1)
        data = build_map(both, load_frames(both), map_id=ds.folder.name, kept=kept,
                         previous=first, revision=2, report=report)
    return data, report


def run_survey(name: str, folder: Path, maps: dict[str, tuple[int, ...]]) -> list[dict]:
    rows = []
    for map_name, passes in maps.items():
        t0 = time.perf_counter()
        if map_name == UPDATED:
            data, geometry = updated_map(folder)
        else:
            exp = load_experiment(folder, rule="pass", map_pass=passes,
                                  query_pass=QUERIES["sunny"])
            data, geometry = exp.map_data, exp.geometry
        build_s = time.perf_counter() - t0
        trained = sorted({f.revision for f in data.vocabulary_fits.values()})
        for query_name, query_pass in QUERIES.items():
            queries, truth = queries_of(folder, query_pass, data)
            results = evaluate(data, queries, truth, modes=["hybrid"],
                               configs=["default"], starts=STARTS, skip=SKIP)
            hybrid = results_dict(results)["modes"]["hybrid"]
            rows.append({"survey": name, "map": map_name, "query": query_name,
                         "map_images": len(data), "queries": len(queries),
                         "geometry": (geometry or {}).get("status", "none"),
                         "vocabularies_trained_by": trained,
                         "build_s": build_s, "hybrid": hybrid})
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    return rows


def table(rows: list[dict]) -> str:
    out = ["| survey | map | queries | map images | geometry | vocabularies trained by "
           "revision | hybrid mean / median (m) | within 25 m | SIFT steps |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        h = r["hybrid"]
        trained = ", ".join(map(str, r["vocabularies_trained_by"]))
        out.append(f"| {r['survey']} | {r['map']} | {r['query']} | {r['map_images']} | "
                   f"{r['geometry']} | {trained} | "
                   f"{h['mean_error_m']:.1f} / {h['median_error_m']:.1f} | "
                   f"{h['within_25m']:.0%} | {h['sift_step_share']:.0%} |")
    return "\n".join(out)


def verdicts(rows: list[dict]) -> list[str]:
    """Per survey: the dusk frames' gain from the dusk flight, and the sunny frames' change,
    of each map against the sunny map alone."""
    out = []
    sunny_map = next(iter(MAPS))
    for survey in dict.fromkeys(r["survey"] for r in rows):
        err = {(r["map"], r["query"]): r["hybrid"]["mean_error_m"] for r in rows
               if r["survey"] == survey}
        for both_map in dict.fromkeys(m for m, _ in err):
            if both_map == sunny_map:
                continue
            dusk_gain = 1.0 - err[(both_map, "dusk")] / err[(sunny_map, "dusk")]
            sunny_change = err[(both_map, "sunny")] / err[(sunny_map, "sunny")] - 1.0
            out.append(f"- {survey}, {both_map}: dusk frames {dusk_gain:+.0%} better with "
                       f"the dusk flight (target at least +25 %); sunny frames "
                       f"{sunny_change:+.0%} in error (target no worse)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(SURVEYS))
    ap.add_argument("--dusk-alone", action="store_true",
                    help="also build a map of the dusk flight alone")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    maps = {**(DUSK_ALONE if args.dusk_alone else {}), **MAPS}
    rows = []
    with threadpool_limits(limits=1):
        for name in args.only.split(","):
            folder = SURVEYS[name]()
            if folder is None:
                print(f"{name}: data set not found, skipped", file=sys.stderr)
                continue
            rows += run_survey(name, folder, maps)
    args.out.mkdir(parents=True, exist_ok=True)
    text = "\n".join([
        "# A map of two flights in other light", "",
        f"{machine_and_python()}, one BLAS thread. Command: "
        f"`OMP_NUM_THREADS=1 .venv/bin/python bench/eval_conditions.py --only {args.only}"
        f"{' --dusk-alone' if args.dusk_alone else ''}`.",
        f"Default `hybrid`, {STARTS} starts, errors after the first {SKIP} frames of each run.",
        "", table(rows), "", *verdicts(rows), ""])
    write_result(args.out / "conditions.md", text)
    (args.out / "conditions.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
