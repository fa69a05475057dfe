"""Smoke run of the Weiss Table I/II scripts on a tiny robot world.

One data set, 30 frames per pass on a 30 m round, one start, one pass pair per row: the
scripts must write their Markdown with the paper's rows, and the pooled figures they
report must equal what the evaluation itself reports for the same runs.

The scripts run as the command line runs them, in a child process: they pin BLAS to one
thread before numpy loads, which an in-process call cannot do once pytest has loaded it
(and a multi-threaded BLAS on two busy cores makes SIFT matching ten times slower).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.paper import _common, weiss_table1

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--frames", "30", "--route-length", "30", "--starts", "1", "--pairs", "1",
        "--datasets", "1"]


def run_script(name: str, *args: str) -> None:
    subprocess.run([sys.executable, str(ROOT / "bench" / "paper" / f"{name}.py"), *args],
                   check=True, cwd=ROOT, capture_output=True, timeout=120)


@pytest.fixture(scope="module")
def table1(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    run_script("weiss_table1", *TINY, "--out", str(out), "--cache", str(out / "cache"))
    return out, json.loads((out / "weiss_table1.json").read_text(encoding="utf-8"))


def test_table1_markdown_has_the_paper_rows(table1):
    out, _ = table1
    md = (out / "weiss_table1.md").read_text(encoding="utf-8")
    # ours beside the paper's, for each of dataset 1's four train/test rows
    assert "| 1 | sunny | sunny | 1->3 |" in md and "| 3.15 ± 1.20 |" in md
    assert "| 1 | cloudy | cloudy | 2->4 |" in md and "| 1.59 ± 0.27 |" in md
    assert "| 1 | sunny | cloudy | 1->2 |" in md and "| 3.95 ± 0.54 |" in md
    assert "| 1 | cloudy | sunny | 2->1 |" in md and "| 3.07 ± 0.36 |" in md
    assert "| 2 |" not in md  # dataset 2 was not asked for
    assert (out / "weiss_table1.png").stat().st_size > 0


def test_table1_json_holds_every_run(table1):
    _, stored = table1
    assert len(stored["pairs"]) == 4
    for pair in stored["pairs"]:
        for mode in weiss_table1.MODES:
            (run,) = pair["runs"][mode]
            assert len(run["errors"]) == len(run["ms"]) == len(run["steps"]) == 30
            assert len(run["spread"]) == 30 and min(run["spread"]) >= 0
            assert set(run["steps"]) <= {"S", "G"}
        assert set(pair["runs"]["sift"][0]["steps"]) == {"S"}
        assert set(pair["runs"]["global"][0]["steps"]) == {"G"}
        # Weiss IV-B: the hybrid's first step is always SIFT
        assert pair["runs"]["hybrid"][0]["steps"][0] == "S"


def test_pool_matches_the_evaluation_summary(tmp_path):
    """``_common.pool`` on stored records equals ``ModeSummary.to_dict`` on the same runs."""
    from vloc.workers.core.evaluation.evaluate import evaluate

    folder = _common.world("robot", seed=1, passes=("sunny", "cloudy"), frames=24,
                           route_length=24.0, cache=tmp_path)
    exp = _common.experiment(folder, 1, 2)
    res = evaluate(exp.map_data, exp.queries, exp.truth, modes=["hybrid"],
                   configs=["weiss2008"], starts=2, seed=3, skip=5)
    want = res["weiss2008"]["hybrid"].to_dict()
    got = _common.pool(_common.records(res, "weiss2008")["hybrid"], skip=5)
    for key in ("runs", "frames", "sift_step_share"):
        assert got[key] == want[key]
    for key in ("mean_error_m", "std_error_m", "median_error_m", "ms_per_frame"):
        # records round errors to 1 mm and times to 1 us
        assert got[key] == pytest.approx(want[key], abs=2e-3)


def test_table2_reads_table1_and_judges_the_claim(table1):
    out, data1 = table1
    run_script("weiss_table2", "--out", str(out))
    data = json.loads((out / "weiss_table2.json").read_text(encoding="utf-8"))
    md = (out / "weiss_table2.md").read_text(encoding="utf-8")
    assert "| 1 | constant | 2 | " in md and "/ 2.57 |" in md
    assert "| 1 | changing | 2 | " in md and "/ 6.37 |" in md
    assert "| all | average | 4 | " in md
    assert "## Spread of the particle cloud" in md and "| 1 | changing | SIFT |" in md
    changing = next(r for r in data["rows"] if r["condition"] == "changing")
    hybrid, sift = changing["modes"]["hybrid"], changing["modes"]["sift"]
    assert changing["speedup"] == pytest.approx(sift["ms_per_frame"] / hybrid["ms_per_frame"])
    claim = data["claim"]
    assert claim["holds"] == (claim["error_ratio"] <= 1.10 and claim["sift_share"] < 0.20
                              and claim["speedup"] >= 3.0)
    assert ("The claim holds" in md) == claim["holds"]
    # the changing rows pool exactly the runs of the two changing pass pairs
    runs = [r for p in data1["pairs"] if p["train"] != p["test"] for r in p["runs"]["hybrid"]]
    steps = "".join(r["steps"] for r in runs)
    assert hybrid["sift_step_share"] == pytest.approx(steps.count("S") / len(steps))
    assert np.isfinite(hybrid["mean_error_m"])
