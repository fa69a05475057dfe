"""Shared pieces of the paper benchmarks: cached worlds, experiments, pooled figures, output.

Times are per core: BLAS is pinned to one thread through the environment, which only works
before numpy loads (each script sets it first thing, as the other benchmarks do; this
module sets it too for scripts that import it first), and OpenCV through its own call.

Runs are kept in a compact, JSON-friendly record per run (:func:`run_record`): the error
and the milliseconds of every frame and the feature each step used. :func:`pool` turns
records of any number of runs (one pair of passes, or all pairs of a table row) into the
figures of the tables, the way :meth:`workers.core.evaluation.evaluate.ModeSummary.to_dict` does for
the runs of one evaluation.
"""

from __future__ import annotations

from bench._common import RESULTS, ROOT, one_thread

one_thread()

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vloc.clients.world import generate_world  # noqa: E402
from vloc.workers.core.evaluation.evaluate import Run  # noqa: E402
from vloc.workers.core.evaluation.experiment import Experiment, load_experiment  # noqa: E402

cv2.setNumThreads(1)

RESULTS_DIR = RESULTS / "paper"
CACHE_DIR = ROOT / "bench" / ".cache"

ROUTE_M = 260.0
"""Length of the robot's round: Weiss et al.'s dataset 1 ("each round is about 260 m")."""
FRAMES = 433
"""Frames per pass by default: 0.60 m apart on the 260 m round (the paper: about 400 images,
0.65 m apart). The spacing matters: the motion noise is 4 m per frame whatever the spacing,
so frames further apart leave the cloud further behind the robot at every step."""
QUICK = {"frames": 100, "route_length": 60.0, "starts": 2}
"""``--quick``: a 60 m round at the same 0.60 m spacing, two starts."""

_T0 = time.perf_counter()
_NUMBER_LIST = re.compile(r"\[\s*((?:-?[0-9][0-9.eE+-]*,?\s*)+)\]")


def log(message: str) -> None:
    """Print a progress line with the seconds since the script started."""
    print(f"[{time.perf_counter() - _T0:7.1f} s] {message}", flush=True)


# -- command line -------------------------------------------------------------------------

def size_arguments(parser: argparse.ArgumentParser, *, frames: int = FRAMES,
                   route_length: float = ROUTE_M, starts: int | None = 3,
                   quick: dict | None = None) -> None:
    """Add the options every script shares (sizes, seed, output and cache folders).

    ``starts=None`` leaves out ``--starts`` (scripts without a filter). ``quick`` holds the
    sizes ``--quick`` stands for (default :data:`QUICK`).
    """
    quick = QUICK if quick is None else quick
    parser.add_argument("--frames", type=int, default=None,
                        help=f"frames per pass (default {frames}; --quick {quick['frames']})")
    parser.add_argument("--route-length", type=float, default=None,
                        help=f"metres of the route (default {route_length:g})")
    if starts is not None:
        parser.add_argument("--starts", type=int, default=None,
                            help=f"starting frames per experiment (default {starts})")
    parser.add_argument("--quick", action="store_true", help="a small world, fewer starts")
    parser.add_argument("--seed", type=int, default=0, help="seed of the filters' generators")
    parser.add_argument("--skip", type=int, default=10,
                        help="frames at the start of each run left out of the errors")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    parser.add_argument("--cache", type=Path, default=CACHE_DIR, help="cached worlds")
    full = {"frames": frames, "route_length": route_length}
    if starts is not None:
        full["starts"] = starts
    parser.set_defaults(sizes_full=full, sizes_quick=quick)


def resolve_sizes(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the sizes left unset from ``--quick`` or the script's defaults."""
    base = args.sizes_quick if args.quick else args.sizes_full
    for name, value in base.items():
        if getattr(args, name, None) is None:
            setattr(args, name, value)
    return args


# -- worlds and experiments ---------------------------------------------------------------

def _generator_digest() -> str:
    """Short hash of the world generator's sources: a changed generator makes new worlds."""
    h = hashlib.sha1()
    for path in sorted((ROOT / "clients" / "world").glob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()[:8]


def world(kind: str, *, seed: int, passes: tuple[str, ...], frames: int,
          route_length: float, cache: Path = CACHE_DIR, **options) -> Path:
    """The folder of a generated world, generating it on first use.

    The cache key holds every argument and a digest of the generator's sources. The world
    is written to a ``.partial`` folder and renamed when complete, so an interrupted run
    leaves no half world behind to be reused.
    """
    extra = "".join(f"-{k}{v:g}" for k, v in sorted(options.items()))
    key = (f"{kind}-s{seed}-f{frames}-r{route_length:g}-{'-'.join(passes)}{extra}"
           f"-g{_generator_digest()}")
    folder = Path(cache) / key
    if (folder / "world.json").is_file():
        return folder
    partial = folder.with_name(key + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.parent.mkdir(parents=True, exist_ok=True)
    log(f"generating world {key} ({frames} frames x {len(passes)} passes)")
    step = max(1, frames * len(passes) // 10)

    def progress(done: int, total: int) -> None:
        if done % step == 0 or done == total:
            log(f"  rendered {done}/{total}")

    generate_world(partial, kind=kind, seed=seed, passes=passes, frames=frames,
                   route_length=route_length, progress=progress, **options)
    partial.rename(folder)
    return folder


def experiment(folder: Path, map_pass: int, query_pass: int, *,
               config: str = "weiss2008") -> Experiment:
    """Map from one pass, queries from another (the map positioned by its EXIF GPS), with
    camera geometry only where the filter configuration ``config`` refines with it."""
    from vloc.workers.core.pf.config import config_from_params

    t = time.perf_counter()
    exp = load_experiment(folder, rule="pass", map_pass=map_pass, query_pass=query_pass,
                          geometry=config_from_params({"config": config}).refine.enabled)
    log(f"  map pass {map_pass} ({len(exp.map_images)} images), query pass {query_pass} "
        f"({len(exp.queries)} frames) loaded in {time.perf_counter() - t:.1f} s")
    return exp


def progress_printer(label: str):
    """A ``progress`` callback for :func:`workers.core.evaluation.evaluate.evaluate`."""
    def progress(config: str, mode: str, k: int, n: int) -> None:
        log(f"  {label} {config}/{mode}: start {k}/{n}")
    return progress


# -- runs and pooled figures --------------------------------------------------------------

def run_record(run: Run) -> dict:
    """One run as plain lists: errors (m), times (ms), step kinds ("S" SIFT, "G" global)
    and the spread of the particle cloud after each step, max(sigma_x, sigma_y) (m), which
    the hybrid compares with its thresholds (Weiss IV-B)."""
    return {"start": int(run.start),
            "errors": [round(float(e), 3) for e in run.errors],
            "ms": [round(float(m), 3) for m in run.ms],
            "steps": "".join("S" if f == "sift" else "G" for f in run.feature),
            "spread": [round(float(v), 2) for v in np.max(run.sigma, axis=1)]}


def records(results: dict, config: str) -> dict[str, list[dict]]:
    """``{mode: [run_record, ...]}`` of one config of an :func:`evaluate` result."""
    return {mode: [run_record(r) for r in summary.runs]
            for mode, summary in results[config].items()}


def pool(runs: list[dict], skip: int) -> dict:
    """Table figures over any set of runs.

    Errors are pooled over the frames after the first ``skip`` of each run; the standard
    deviation is that of the per-run mean errors (Weiss et al. repeat each experiment from
    several starting images); SIFT share and times are over every frame. The same
    definitions as ``ModeSummary.to_dict``.
    """
    errors = np.concatenate([np.asarray(r["errors"])[skip:] for r in runs])
    per_run = np.array([np.mean(r["errors"][skip:]) for r in runs])
    ms = np.concatenate([np.asarray(r["ms"], dtype=float) for r in runs])
    sift = np.array([c == "S" for r in runs for c in r["steps"]], dtype=bool)

    def mean_or_nan(a: np.ndarray) -> float:
        return float(a.mean()) if len(a) else float("nan")

    return {"runs": len(runs), "frames": int(len(errors)),
            "mean_error_m": float(errors.mean()), "std_error_m": float(per_run.std()),
            "median_error_m": float(np.median(errors)),
            "sift_step_share": float(sift.mean()), "ms_per_frame": float(ms.mean()),
            "ms_per_global_step": mean_or_nan(ms[~sift]),
            "ms_per_sift_step": mean_or_nan(ms[sift])}


def error_curve(runs: list[dict]) -> np.ndarray:
    """Mean error over runs against frames since the start, up to the shortest run."""
    n = min(len(r["errors"]) for r in runs)
    return np.mean([r["errors"][:n] for r in runs], axis=0)


# -- output -------------------------------------------------------------------------------

def machine() -> str:
    """One line naming the machine and the library versions."""
    return (f"{platform.machine()}, {os.cpu_count()} cores (shared), Python "
            f"{platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}; "
            "one thread (OMP/OpenBLAS/MKL and OpenCV)")


def pm(mean: float, std: float, nd: int = 2) -> str:
    """``mean ± std``, or ``-`` when not a number."""
    if not (np.isfinite(mean) and np.isfinite(std)):
        return "-"
    return f"{mean:.{nd}f} ± {std:.{nd}f}"


def num(value: float | None, nd: int = 2) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{nd}f}"


def write(out_dir: Path, name: str, markdown: str, data: dict) -> Path:
    """Write ``<name>.md`` and ``<name>.json``; print the Markdown."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md = out_dir / f"{name}.md"
    md.write_text(markdown.rstrip() + "\n", encoding="utf-8")
    text = json.dumps(data, indent=1)
    # lists of numbers (per-frame series) on one line each: a readable, diffable file
    text = _NUMBER_LIST.sub(lambda m: "[" + ", ".join(m.group(1).split()).replace(",,", ",")
                            + "]", text)
    (out_dir / f"{name}.json").write_text(text + "\n", encoding="utf-8")
    print(markdown, flush=True)
    log(f"wrote {md} and {name}.json")
    return md


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def elapsed() -> float:
    """Seconds since the script started."""
    return time.perf_counter() - _T0
