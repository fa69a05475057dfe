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

Every process's own CPU is also sampled from ``/proc`` five times a second while the suite
runs (:class:`ProcessSampler`), so the uncounted part is named too: by kind of process (the
services, Ray, browsers, servers, their worker processes) and by the test file whose test
was running on the worker that started it. A process that lives less than a sample's
interval is missed, and each loses at most its last interval's CPU: a lower bound. The
sampling itself takes about 2.5 % of a core (17 CPU s of a 700 s run), listed with the rest.

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
import threading
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


HZ = os.sysconf("SC_CLK_TCK")


def _boot_time() -> float:
    """When the machine started, in seconds since the epoch, to a hundredth of a second
    (``btime`` in ``/proc/stat`` is whole seconds: too coarse to tell which of two tests
    a second apart started a process)."""
    return time.time() - float(Path("/proc/uptime").read_text().split()[0])


class ProcessSampler(threading.Thread):
    """Every process's parent, command line and own CPU (user + system, its children's not
    included), read from ``/proc`` every ``interval`` seconds until :meth:`stop`.

    ``seen`` maps (pid, start in clock ticks since boot) to a dict with ``ppid``, ``cmd``,
    ``start`` and ``last`` (when it started and was last seen, seconds since the epoch) and
    ``cpu``: the CPU seconds it used while sampled, less what it had used before the first
    sample (the services' past)."""

    def __init__(self, interval: float = 0.2) -> None:
        super().__init__(daemon=True)
        self.interval = interval
        self.seen: dict[tuple[int, int], dict] = {}
        self._before: dict[tuple[int, int], int] = {}
        self._boot = _boot_time()
        self._halt = threading.Event()
        self._sample(first=True)

    def run(self) -> None:
        while not self._halt.wait(self.interval):
            self._sample()

    def stop(self) -> None:
        self._halt.set()
        self.join()
        self._sample()

    def _sample(self, first: bool = False) -> None:
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                stat = Path(entry.path, "stat").read_text()
                cmd = Path(entry.path, "cmdline").read_bytes().replace(b"\0", b" ").strip()
            except OSError:  # it ended between the listing and the read
                continue
            comm = stat[stat.index("(") + 1:stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2:].split()  # from field 3, the state
            ticks, started = int(fields[11]) + int(fields[12]), int(fields[19])
            key = (int(entry.name), started)
            if first:
                self._before[key] = ticks
            record = self.seen.setdefault(key, {"ppid": int(fields[1]),
                                                "start": self._boot + started / HZ})
            # a forked child shows its parent's command line until it execs: keep the last;
            # one that has exited and waits to be reaped (a zombie) shows none: keep the one
            # it had
            if cmd:
                record["cmd"] = cmd.decode(errors="replace")
            else:
                record.setdefault("cmd", f"[{comm}]")
            record["cpu"] = (ticks - self._before.get(key, 0)) / HZ
            record["last"] = time.time()


def process_kind(cmd: str) -> str:
    """A process's kind, from its command line (the first rule that matches; test folders
    are named ``pytest-of-...``, so the pytest rules look for how pytest starts)."""
    rules = [("postgres", "PostgreSQL"), ("redis-server", "Redis"), ("chrom", "Chromium"),
             ("multiprocessing", "worker processes"), ("raylet", "Ray"),
             ("gcs_server", "Ray"), ("ray::", "Ray"), ("/ray/", "Ray"),
             ("ray.scripts", "Ray"), ("vloc.clients.cli serve", "vloc serve"),
             ("exec(eval(sys.stdin", "pytest workers"), ("-m pytest", "pytest workers"),
             ("vloc.clients.cli", "other vloc commands"), ("bin/vloc", "other vloc commands"),
             ("pip", "pip"), ("python", "other Python")]
    for needle, kind in rules:
        if needle in cmd:
            return kind
    return "other"


def attribute(seen: dict[tuple[int, int], dict], rows: list[dict], suite_start: float
              ) -> tuple[dict[str, list[float]], dict[str, float]]:
    """Each sampled process's CPU by kind ([processes, CPU s]), and the CPU of the processes
    that descend from a pytest worker by the test file that was running on that worker when
    the process started (the worker's own CPU is in ``rows`` already). Each process that
    descends from a worker gets that file as its ``file``."""
    by_kind: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    for p in seen.values():
        if p["cpu"] > 0 or p["start"] >= suite_start:
            k = by_kind[process_kind(p["cmd"])]
            k[0] += 1
            k[1] += p["cpu"]
    workers = {r["pid"] for r in rows}
    runs: dict[int, list[dict]] = collections.defaultdict(list)
    for r in rows:
        runs[r["pid"]].append(r)
    parent = {pid: p["ppid"] for (pid, _), p in seen.items()}
    by_file: dict[str, float] = collections.defaultdict(float)
    for (pid, _), p in seen.items():
        if pid in workers or p["start"] < suite_start:
            continue
        ancestor, hops = p["ppid"], 0
        while ancestor not in workers and ancestor in parent and hops < 64:
            ancestor, hops = parent[ancestor], hops + 1
        if ancestor not in workers:
            continue
        test = next((r for r in runs[ancestor] if r["start"] <= p["start"] <= r["end"]),
                    None)
        p["file"] = test["id"].split("::")[0] if test else "(between tests)"
        by_file[p["file"]] += p["cpu"]
    return by_kind, by_file


def run_suite(workers: int, records: Path, extra: list[str]
              ) -> tuple[float, int, int, str, ProcessSampler, float]:
    env = dict(os.environ, VLOC_REQUIRE_SERVICES="1", SUITE_CPU_RECORDS=str(records),
               PYTHONPATH=os.pathsep.join(filter(None, [str(HERE),
                                                       os.environ.get("PYTHONPATH")])))
    env.setdefault("VLOC_TEST_POSTGRES_URL",
                   "postgresql+psycopg://postgres@127.0.0.1:5432/test")
    env.setdefault("VLOC_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", str(workers), "--dist", "loadgroup",
           "-p", "_suite_cpu", "-p", "no:cacheprovider", *extra]
    sampler = ProcessSampler()
    sampler.start()
    busy0, idle0 = cpu_ticks()
    t0, started = time.perf_counter(), time.time()
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    busy1, idle1 = cpu_ticks()
    sampler.stop()
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
    if done.returncode:
        sys.stderr.write(done.stdout[-5000:] + done.stderr[-2000:])
        summary = f"FAILED: {summary}"
    return wall, busy1 - busy0, idle1 - idle0, summary, sampler, started


def report(rows: list[dict], wall: float, busy: int, idle: int, summary: str, workers: int,
           top: int, by_kind: dict[str, list[float]], by_file: dict[str, float],
           processes: list[dict]) -> str:
    hz = HZ
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
        "## Every process's CPU, by kind (sampled from /proc)",
        "",
        "| kind | processes | CPU s |",
        "|---|---|---|",
        *(f"| {kind} | {n} | {cpu:.0f} |"
          for kind, (n, cpu) in sorted(by_kind.items(), key=lambda kv: -kv[1][1])),
        f"| all | {sum(n for n, _ in by_kind.values())} | "
        f"{sum(c for _, c in by_kind.values()):.0f} |",
        "",
        f"## The {top} files with the most CPU in all: their tests' own (the pytest worker's) "
        "and every process started while they ran (sampled)",
        "",
        "| file | tests | CPU s | in their own worker | in other processes |",
        "|---|---|---|---|---|",
        *_whole_cpu_rows(rows, by_file, top),
        "",
        f"## The {top} processes with the most CPU (sampled; lived: from its start to its "
        "last sample)",
        "",
        "| CPU s | lived s | kind | started during | command |",
        "|---|---|---|---|---|",
        *(f"| {p['cpu']:.1f} | {p['last'] - p['start']:.0f} | {process_kind(p['cmd'])} | "
          f"`{p.get('file', '-')}` | `{p['cmd'][:110].replace('|', '/')}` |"
          for p in sorted(processes, key=lambda p: -p["cpu"])[:top]),
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


def _whole_cpu_rows(rows: list[dict], by_file: dict[str, float], top: int) -> list[str]:
    own: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    for r in rows:
        f = own[r["id"].split("::")[0]]
        f[0] += 1
        f[1] += r["cpu_self"]
    names = set(own) | set(by_file)
    total = {n: own[n][1] + by_file.get(n, 0.0) for n in names}
    return [f"| `{n}` | {own[n][0]} | {total[n]:.1f} | {own[n][1]:.1f} | "
            f"{by_file.get(n, 0.0):.1f} |"
            for n in sorted(names, key=lambda n: -total[n])[:top]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "test_suite.md")
    ap.add_argument("pytest_args", nargs="*", help="after --: passed on to pytest")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="suite-cpu-") as tmp:
        records = Path(tmp)
        wall, busy, idle, summary, sampler, started = run_suite(args.workers, records,
                                                                args.pytest_args)
        rows = [json.loads(line) for f in sorted(records.glob("*.jsonl"))
                for line in f.read_text().splitlines() if line]
    by_kind, by_file = attribute(sampler.seen, rows, started)
    text = report(rows, wall, busy, idle, summary, args.workers, args.top, by_kind, by_file,
                  list(sampler.seen.values()))
    if summary.startswith("FAILED"):
        # a failing run's figures are not a result: printed to look into, not written
        print(text)
        raise SystemExit(f"the suite failed ({summary}): {args.out} left as it was")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
