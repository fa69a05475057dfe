"""The tracks PNG says what the table says: its legend's median error is the table's (after
the skipped frames), and each mode has the colour the web viewer gives it."""

from __future__ import annotations

import re

import numpy as np

from tests.conftest import REPO_ROOT
from vloc.workers.core.evaluation.evaluate import ModeSummary, Run
from vloc.workers.core.evaluation.report import PALETTE, plot_tracks


def _run(mode: str, early: float, late: float, n: int = 30) -> Run:
    truth = np.c_[np.arange(n, dtype=float), np.zeros(n)]
    errors = np.where(np.arange(n) < 10, early, late)
    return Run(mode=mode, config="default", start=0, frames=np.arange(n), truth=truth,
               estimate=truth + np.c_[np.zeros(n), errors], sigma=np.ones((n, 2)),
               feature=["sift"] * n, status=["tracking"] * n, ms=np.ones(n))


def test_the_legend_gives_the_tables_median_in_the_viewers_colours(tmp_path, monkeypatch):
    import matplotlib.figure

    drawn = {}

    def savefig(fig, path, *args, **kwargs):
        ax = fig.axes[0]
        drawn["labels"] = [t.get_text() for t in ax.get_legend().get_texts()]
        drawn["colours"] = [line.get_color() for line in ax.get_lines()[1:]]

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    # 10 bad frames before the table's window, then 1 m (hybrid) and 2 m (sift)
    modes = {m: ModeSummary(m, "default", [_run(m, 50.0, late)], skip=10)
             for m, late in (("hybrid", 1.0), ("sift", 2.0))}
    plot_tracks(tmp_path / "t.png", np.zeros((3, 2)), {"default": modes})
    assert drawn["labels"][-2:] == ["hybrid (1.0 m median)", "sift (2.0 m median)"]
    assert [modes[m].to_dict()["median_error_m"] for m in modes] == [1.0, 2.0]
    assert drawn["colours"] == list(PALETTE[:2])


def test_the_palette_is_the_viewers():
    common = (REPO_ROOT / "app" / "ui" / "static" / "common.js").read_text()
    block = re.search(r"PALETTE = \[(.*?)\]", common, re.S).group(1)
    assert tuple(re.findall(r'"(#[0-9a-f]{6})"', block)) == PALETTE
