"""Benchmark: the hybrid against SIFT alone on seneca-uav, CPU time per frame on one core.

Both localisers run the ``default`` configuration over pass 2 against the map of pass 1,
from the same starting frames, alternately (sift, hybrid, sift, hybrid ...), so that both see
the same machine. Each step is timed by the thread's CPU time (``time.thread_time``) with
every thread pool pinned to one thread: on a shared machine a wall clock also counts the time
the process waits for a CPU. Reported per mode: mean and median error after the tenth frame,
the share of SIFT steps (an escalated global step counts as SIFT, its failed attempt
included in its time), the mean CPU ms per frame and per step kind, and the speed-up of the
hybrid as the ratio of mean CPU ms per frame.

Usage::

    .venv/bin/python bench/bench_hybrid.py [--starts 5] [--photometric none]

Writes ``bench/results/hybrid.md`` (or ``hybrid_<photometric>.md``) and prints it.
"""

from __future__ import annotations

from _common import DATASETS, RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.evaluation.evaluate import choose_starts  # noqa: E402
from vloc.workers.core.evaluation.experiment import load_experiment  # noqa: E402
from vloc.workers.core.localisers import make_localiser  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402

SENECA = DATASETS / "seneca-uav"
SKIP = 10


def run(exp, mode: str, start: int, seed: int) -> dict:
    loc = make_localiser(mode, exp.map_data, {"config": "default"}, seed=seed)
    err, cpu, kinds = [], [], []
    for k, i in enumerate(range(start, len(exp.queries))):
        q = exp.queries[i]
        fresh = QueryFrame(q.frame, q.captured_at, key=q.key)  # no features cached
        t0 = time.thread_time()
        e = loc.step(fresh)
        dt = (time.thread_time() - t0) * 1e3
        if k >= SKIP:
            err.append(float(np.hypot(e.x - exp.truth[i, 0], e.y - exp.truth[i, 1])))
            cpu.append(dt)
            kinds.append(e.feature)
    return {"err": err, "cpu": cpu, "kinds": kinds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--photometric", default="none")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None,
                        help="where to write the table [bench/results/hybrid*.md]")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    exp = load_experiment(SENECA, map_pass=1, query_pass=2, photometric=args.photometric,
                          seed=args.seed)
    starts = choose_starts(len(exp.queries), args.starts, SKIP)
    out = {m: {"err": [], "cpu": [], "kinds": []} for m in ("sift", "hybrid")}
    for k, s in enumerate(starts):
        for mode in ("sift", "hybrid"):
            # seeded per start as `vloc eval` seeds it: its runs are the evaluation's runs
            r = run(exp, mode, int(s), args.seed + k)
            for key in r:
                out[mode][key] += r[key]
            print(f"start {s}: {mode} done", flush=True)
    base = float(np.mean(out["sift"]["cpu"]))
    lines = [f"# Hybrid against SIFT on seneca-uav, CPU time on one core"
             f"{'' if args.photometric == 'none' else f' ({args.photometric} queries)'}", "",
             f"{machine_and_python()}, OpenCV "
             f"{cv2.__version__}; one thread; {len(starts)} starts {list(map(int, starts))}; "
             f"errors and times over the frames after the {SKIP}th of each run; load average "
             f"at the end {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs.",
             f"Command: `.venv/bin/python bench/bench_hybrid.py --starts {args.starts} "
             f"--photometric {args.photometric}`.", "",
             "| mode | mean err (m) | median (m) | SIFT steps | CPU ms/frame | ms global step "
             "| ms SIFT step | speed-up vs sift |", "|---|---|---|---|---|---|---|---|"]
    for mode, r in out.items():
        err, cpu, kinds = np.array(r["err"]), np.array(r["cpu"]), np.array(r["kinds"])
        sift = kinds == "sift"
        g = f"{np.mean(cpu[~sift]):.1f}" if (~sift).any() else "-"
        lines.append(f"| {mode} | {err.mean():.1f} | {np.median(err):.1f} | "
                     f"{100 * sift.mean():.1f} % | {cpu.mean():.1f} | {g} | "
                     f"{np.mean(cpu[sift]):.1f} | {base / cpu.mean():.2f} |")
    text = "\n".join(lines) + "\n"
    suffix = "" if args.photometric == "none" else f"_{args.photometric}"
    path = args.out or RESULTS / f"hybrid{suffix}.md"
    write_result(path, text)


if __name__ == "__main__":
    main()
