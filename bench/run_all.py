"""Run every benchmark and paper reproduction in turn (``make bench``).

Stage timings first (``bench_features.py``, ``bench_core.py``, ``bench_world.py``, and
``bench_service.py``, ``bench_place.py``, ``eval_place.py``, ``eval_seneca_place.py`` and
``bench_hybrid.py`` where the seneca-uav data set they read is present), then the paper
experiments under ``bench/paper/`` (Weiss Table I, Table II from Table I's runs, Fig. 4 e/f,
Flyphone Fig. 7/9) and Li et al.'s route relaxation and path following (``bench/nav/``).
Each runs in its own process, one after the other, so that timings do not compete with each
other; results go to ``bench/results/`` and ``bench/results/paper/``.
The full run takes about half an hour on two cores; ``--quick`` runs small versions of
everything in a few minutes and writes them under ``bench/.cache/quick-results/`` instead.

Usage::

    .venv/bin/python bench/run_all.py [--quick] [--only NAME,...] [--skip NAME,...]
                                      [--keep-going]

NAME is a script's file name without ``.py`` (e.g. ``weiss_table1``, ``bench_core``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from _common import DATASETS, ROOT

SENECA = DATASETS / "seneca-uav"

QUICK_OUT = ROOT / "bench" / ".cache" / "quick-results"
"""Where ``--quick`` writes, so that small runs never replace the committed results."""

STAGES: tuple[tuple[str, list[str]], ...] = (
    # (script, extra arguments for --quick)
    ("bench/bench_features.py", ["--repeats", "30", "--out", f"{QUICK_OUT}/features.md"]),
    ("bench/bench_core.py", ["--repeats", "5", "--out", f"{QUICK_OUT}/core.md"]),
    ("bench/bench_world.py", ["--frames", "30", "--repeats", "1",
                              "--out", f"{QUICK_OUT}/world.md"]),
    ("bench/bench_service.py", ["--sessions", "1,10", "--frames", "20,5",
                                "--out", f"{QUICK_OUT}/service.md"]),
    ("bench/bench_viewer.py", ["--seconds", "5", "--repeats", "1",
                               "--out", f"{QUICK_OUT}/viewer.md"]),
    ("bench/bench_place.py", ["--map-images", "200", "--queries", "10", "--repeats", "1",
                              "--out", f"{QUICK_OUT}/place_timing.md"]),
    ("bench/eval_place.py", ["--variants", "none", "--seeds", "1", "--no-sift",
                             "--out", str(QUICK_OUT)]),
    ("bench/eval_seneca_place.py", ["--variants", "none", "--starts", "1",
                                    "--out", str(QUICK_OUT)]),
    ("bench/paper/weiss_table1.py", ["--quick", "--pairs", "1", "--out", f"{QUICK_OUT}/paper"]),
    ("bench/paper/weiss_table2.py", ["--quick", "--out", f"{QUICK_OUT}/paper"]),
    ("bench/paper/weiss_fig4.py", ["--quick", "--out", f"{QUICK_OUT}/paper"]),
    ("bench/paper/flyphone_fig7.py", ["--quick", "--out", f"{QUICK_OUT}/paper"]),
    ("bench/bench_hybrid.py", ["--starts", "1", "--out", f"{QUICK_OUT}/hybrid.md"]),
    ("bench/nav/relaxation.py", ["--length", "80", "--seeds", "0", "--extra", "10",
                                 "--out", f"{QUICK_OUT}/nav_relaxation"]),
    ("bench/nav/convergence.py", ["--starts", "5", "--length", "80",
                                  "--out", f"{QUICK_OUT}/nav_convergence"]),
)


def _name(script: str) -> str:
    return Path(script).stem


def _missing_input(script: str) -> str | None:
    """Why a stage cannot run here, or None."""
    if not (ROOT / script).is_file():
        return "script not present"
    seneca_stages = ("bench_service", "bench_place", "eval_place", "eval_seneca_place",
                     "bench_hybrid")
    if _name(script) in seneca_stages and not (SENECA / "images").is_dir():
        return f"data set {SENECA} not present"
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small versions of every stage")
    parser.add_argument("--only", default="", help="comma-separated stage names to run")
    parser.add_argument("--skip", default="", help="comma-separated stage names to leave out")
    parser.add_argument("--keep-going", action="store_true",
                        help="run the remaining stages after one fails")
    args = parser.parse_args(argv)
    only = {s for s in args.only.split(",") if s}
    skip = {s for s in args.skip.split(",") if s}
    known = {_name(s) for s, _ in STAGES}
    unknown = (only | skip) - known
    if unknown:
        parser.error(f"unknown stage(s) {', '.join(sorted(unknown))}; "
                     f"stages: {', '.join(_name(s) for s, _ in STAGES)}")
    summary, failed = [], False
    t_all = time.perf_counter()
    for script, quick in STAGES:
        name = _name(script)
        if (only and name not in only) or name in skip:
            continue
        why = _missing_input(script)
        if why:
            print(f"== {name}: skipped ({why})", flush=True)
            summary.append((name, "skipped", 0.0))
            continue
        if failed and not args.keep_going:
            summary.append((name, "not run", 0.0))
            continue
        cmd = [sys.executable, script, *(quick if args.quick else [])]
        print(f"== {name}: {' '.join(cmd[1:])}", flush=True)
        t = time.perf_counter()
        rc = subprocess.run(cmd, cwd=ROOT).returncode
        seconds = time.perf_counter() - t
        summary.append((name, "ok" if rc == 0 else f"failed (exit {rc})", seconds))
        failed = failed or rc != 0
        print(f"== {name}: {summary[-1][1]} in {seconds / 60:.1f} min", flush=True)
    print(f"\n{'stage':<16} {'result':<18} minutes")
    for name, result, seconds in summary:
        print(f"{name:<16} {result:<18} {seconds / 60:7.1f}")
    print(f"{'total':<16} {'':<18} {(time.perf_counter() - t_all) / 60:7.1f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
