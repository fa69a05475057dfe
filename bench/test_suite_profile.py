"""Where the test suite's time goes: ``make test``'s run, with each test's CPU time beside its
wall time, summed per file.

The suite runs as ``make test`` runs it (``pytest -n WORKERS --dist loadgroup``, the CI
services required), with a small pytest plugin (:mod:`_suite_cpu` beside this file) that
records, per test, the wall time of its setup, call and teardown together, and the CPU time
of the worker process and of the child processes it has waited for in that time (a server a
test starts and stops is counted; a process it does not wait for, such as the Ray cluster's,
PostgreSQL's or the browser's, is not). The machine's own busy and idle time over the run
come from ``/proc/stat``: the difference between them and the tests' CPU is what the
uncounted processes did, and the idle share says whether more workers could help.

Usage::

    .venv/bin/python bench/test_suite_profile.py [--workers 2] [--top 40]
        [--out bench/results/test_suite.md] [-- PYTEST ARGS...]

It takes as long as the suite (ten minutes or so on two cores).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent


def cpu_ticks() -> tuple[int, int]:
    """The machine's (busy, idle) time so far, in clock ticks (user + nice + system; idle +
    I/O wait)."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    user, nice, system, idle, iowait = (int(v) for v in fields[:5])
    return user + nice + system, idle + iowait


def run_suite(workers: int, records: Path, extra: list[str]) -> tuple[float, int, int, str]:
    env = dict(os.environ, VLOC_REQUIRE_SERVICES="1", SUITE_CPU_RECORDS=str(records),
               PYTHONPATH=os.pathsep.join(filter(None, [str(HERE),
                                                       os.environ.get("PYTHONPATH")])))
    env.setdefault("VLOC_TEST_POSTGRES_URL",
                   "postgresql+psycopg://postgres@127.0.0.1:5432/test")
    env.setdefault("VLOC_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", str(workers), "--dist", "loadgroup",
           "-p", "_suite_cpu", "-p", "no:cacheprovider", *extra]
    busy0, idle0 = cpu_ticks()
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    busy1, idle1 = cpu_ticks()
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
    if done.returncode:
        sys.stderr.write(done.stdout[-5000:] + done.stderr[-2000:])
        raise SystemExit(f"the suite failed ({summary}): figures from a failing run are "
                         "not written")
    return wall, busy1 - busy0, idle1 - idle0, summary


def report(rows: list[dict], wall: float, busy: int, idle: int, summary: str, workers: int,
           top: int) -> str:
    hz = os.sysconf("SC_CLK_TCK")
    tests_cpu = sum(r["cpu"] for r in rows)
    tests_wall = sum(r["wall"] for r in rows)
    per_file: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for r in rows:
        f = per_file[r["id"].split("::")[0]]
        f[0] += r["cpu"]
        f[1] += r["wall"]
        f[2] += 1
    lines = [
        "# The test suite's time",
        "",
        f"`.venv/bin/python bench/test_suite_profile.py --workers {workers}` "
        f"({platform.python_version()}, {os.cpu_count()} cores).",
        "",
        f"- `{summary}`",
        f"- wall {wall:.0f} s on {workers} workers; the machine busy {busy / hz:.0f} CPU s, "
        f"idle {idle / hz:.0f} CPU s ({idle / max(busy + idle, 1):.0%} of its time)",
        f"- the tests' own CPU (worker processes and the children they waited for) "
        f"{tests_cpu:.0f} s; the rest of the busy time ({busy / hz - tests_cpu:.0f} s) is "
        "what those records leave out: start-up and collection, and the processes the "
        "tests did not wait for (Ray, PostgreSQL, Redis, browsers, servers still up at the "
        "end of a test)",
        f"- the tests' wall times add up to {tests_wall:.0f} s: {tests_wall / workers:.0f} s "
        f"per worker",
        "",
        f"## The {top} files with the most CPU",
        "",
        "| file | tests | CPU s | wall s |",
        "|---|---|---|---|",
    ]
    for name, (cpu, w, n) in sorted(per_file.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"| `{name}` | {n} | {cpu:.1f} | {w:.1f} |")
    lines += ["", f"## The {top} tests with the most CPU (a module's shared fixtures count "
              "against its first test)", "", "| test | CPU s | wall s |", "|---|---|---|"]
    for r in sorted(rows, key=lambda r: -r["cpu"])[:top]:
        name = r["id"].split("@")[0]
        lines.append(f"| `{name[:140]}` | {r['cpu']:.1f} | {r['wall']:.1f} |")
    lines += ["", f"## The {top} tests with the longest wall time", "",
              "| test | wall s | CPU s |", "|---|---|---|"]
    for r in sorted(rows, key=lambda r: -r["wall"])[:top]:
        name = r["id"].split("@")[0]
        lines.append(f"| `{name[:140]}` | {r['wall']:.1f} | {r['cpu']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "test_suite.md")
    ap.add_argument("pytest_args", nargs="*", help="after --: passed on to pytest")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="suite-cpu-") as tmp:
        records = Path(tmp)
        wall, busy, idle, summary = run_suite(args.workers, records, args.pytest_args)
        rows = [json.loads(line) for f in sorted(records.glob("*.jsonl"))
                for line in f.read_text().splitlines() if line]
    text = report(rows, wall, busy, idle, summary, args.workers, args.top)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
