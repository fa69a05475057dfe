"""Viewer benchmark: how the web page keeps up with ten live sessions at 10 Hz.

Runs the browser test ``tests/e2e/test_viewer.py::test_ten_live_sessions_at_10_hz`` (headless
Chromium against the app under uvicorn; ten sessions on one map each stream a pose with a
64-particle sample every 100 ms) for longer than the test suite does, several times, and
writes the median over the runs of what the page measured: messages sent and received,
sequence gaps, poses drawn, animation frame intervals (p50 / p95 / max, frames over 50 ms)
and the time each frame spent drawing. Each run's figures follow.

    python bench/bench_viewer.py [--seconds 30] [--repeats 3] [--out bench/results/viewer.md]
                                 [--report-only]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import RESULTS, ROOT, write_result

TEST = "tests/e2e/test_viewer.py::test_ten_live_sessions_at_10_hz"
FIGURES = (
    ("received", "pose messages received", "{:.0f}"),
    ("gaps", "sequence gaps (lost messages)", "{:.0f}"),
    ("drawn", "poses drawn as the current estimate", "{:.0f}"),
    ("frames", "animation frames", "{:.0f}"),
    ("frame_interval_ms_p50", "frame interval p50, ms", "{:.1f}"),
    ("frame_interval_ms_p95", "frame interval p95, ms", "{:.1f}"),
    ("frame_interval_ms_max", "frame interval max, ms", "{:.1f}"),
    ("long_frames", "frames longer than 50 ms", "{:.0f}"),
    ("draw_ms_p50", "draw time per frame p50, ms", "{:.2f}"),
    ("draw_ms_p95", "draw time per frame p95, ms", "{:.2f}"),
)


def run_once(seconds: float, out: Path) -> dict:
    env = {**os.environ, "VLOC_VIEWER_LOAD_SECONDS": str(seconds),
           "VLOC_VIEWER_BENCH_OUT": str(out), "VLOC_REQUIRE_SERVICES": "1"}
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", TEST],
                   cwd=ROOT, env=env, check=True)
    return json.loads(out.with_suffix(".json").read_text())


def report(runs: list[dict], seconds: float) -> str:
    sent = runs[0]["ticks"] * 10
    lines = [
        "# Viewer: ten live sessions at 10 Hz",
        "",
        f"Headless Chromium, 1280x800, on {platform.machine()} with {os.cpu_count()} cores "
        "shared with the server. Ten sessions on one map each stream a pose with a "
        f"64-particle sample every 100 ms for {seconds:g} s ({sent} messages) over their "
        "WebSockets; the page draws on animation frames. The poses are published on the "
        "sessions' streams inside the server rather than computed from frames: localising "
        "100 frames a second is beyond this machine, and the page cannot tell the "
        f"difference. Median over {len(runs)} runs, then each run.",
        "",
        "    python bench/bench_viewer.py --seconds "
        f"{seconds:g} --repeats {len(runs)}",
        "",
        "| figure | median | " + " | ".join(f"run {i + 1}" for i in range(len(runs))) + " |",
        "|---|---|" + "---|" * len(runs),
    ]
    for key, label, fmt in FIGURES:
        values = [r[key] for r in runs]
        lines.append(f"| {label} | {fmt.format(statistics.median(values))} | "
                     + " | ".join(fmt.format(v) for v in values) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0,
                        help="How long the ten sessions stream in each run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS / "viewer.md")
    parser.add_argument("--report-only", action="store_true",
                        help="Rewrite OUT from the runs already in OUT's .json")
    args = parser.parse_args()
    if args.report_only:
        runs = json.loads(args.out.with_suffix(".json").read_text())
        args.seconds = runs[0]["ticks"] / 10
    else:
        with tempfile.TemporaryDirectory() as tmp:
            runs = [run_once(args.seconds, Path(tmp) / f"run{i}.md")
                    for i in range(args.repeats)]
    write_result(args.out, report(runs, args.seconds))
    args.out.with_suffix(".json").write_text(json.dumps(runs, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
