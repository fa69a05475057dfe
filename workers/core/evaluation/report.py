"""Tables and plots of evaluation results (Markdown text, PNG via matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .evaluate import ModeSummary, speedups


def results_dict(results: dict[str, dict[str, ModeSummary]]) -> dict:
    """``{"modes": {...first config...}, "configs": {name: {"modes": {...}}}}``.

    Each mode carries ``speedup_vs_sift`` against the ``sift`` run of the same config.
    """
    configs = {}
    for config, modes in results.items():
        rows = {m: s.to_dict() for m, s in modes.items()}
        for m, ratio in speedups(rows).items():
            rows[m]["speedup_vs_sift"] = ratio
        configs[config] = {"modes": rows}
    first = next(iter(configs.values())) if configs else {"modes": {}}
    return {"modes": first["modes"], "configs": configs}


def tracks_dict(map_xy: np.ndarray, results: dict[str, dict[str, ModeSummary]]) -> dict:
    """The first run of every (config, mode) as JSON-ready lists, for the web viewer.

    Parameters
    ----------
    map_xy : (M, 2) float ndarray
        Map image positions, east/north metres in the map's frame.
    results : {config: {mode: ModeSummary}}

    Returns
    -------
    dict
        ``{"map_xy": [[x, y], ...], "tracks": [{"config", "mode", "start", "frames",
        "truth", "estimate", "error_m", "feature", "status"}, ...]}``; positions and errors
        in metres, rounded to centimetres.
    """
    def xy(a: np.ndarray) -> list[list[float]]:
        return np.round(np.asarray(a, dtype=np.float64).reshape(-1, 2), 2).tolist()

    tracks = []
    for config, modes in results.items():
        for mode, summary in modes.items():
            if not summary.runs:
                continue
            run = summary.runs[0]
            tracks.append({"config": config, "mode": mode, "start": int(run.start),
                           "frames": [int(f) for f in run.frames], "truth": xy(run.truth),
                           "estimate": xy(run.estimate),
                           "error_m": np.round(run.errors, 2).tolist(),
                           "feature": list(run.feature), "status": [str(s) for s in run.status]})
    return {"map_xy": xy(map_xy), "tracks": tracks}


def _fmt(v: float, nd: int = 1) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


def markdown_table(data: dict) -> str:
    """One row per (config, mode): the figures of Weiss Tables I and II."""
    head = ("| config | mode | mean err (m) | +- std | median (m) | after conv. (m) | "
            "within 25 m | SIFT steps | ms/frame | ms global | ms SIFT | speed-up vs sift |")
    lines = [head, "|" + "---|" * 12]
    for config, block in data["configs"].items():
        for mode, r in block["modes"].items():
            lines.append(
                f"| {config} | {mode} | {_fmt(r['mean_error_m'])} | {_fmt(r['std_error_m'])} "
                f"| {_fmt(r['median_error_m'])} | {_fmt(r['mean_error_after_convergence_m'])} "
                f"| {100 * r['within_25m']:.0f} % | {100 * r['sift_step_share']:.1f} % "
                f"| {_fmt(r['ms_per_frame'])} | {_fmt(r['ms_per_global_step'])} "
                f"| {_fmt(r['ms_per_sift_step'])} | {_fmt(r.get('speedup_vs_sift'), 2)} |")
    return "\n".join(lines)


def grid_table(grid: dict) -> str:
    """Feature x measure retrieval errors (Flyphone Fig. 7): mean / median in metres."""
    measures = sorted({m for row in grid.values() for m in row})
    lines = ["| feature | " + " | ".join(measures) + " |", "|---|" + "---|" * len(measures)]
    for feat, row in grid.items():
        cells = [f"{row[m]['mean_error_m']:.1f} / {row[m]['median_error_m']:.1f}"
                 if m in row else "-" for m in measures]
        lines.append(f"| {feat} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


PALETTE = ("#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#e377c2",
           "#8c564b", "#bcbd22", "#7f7f7f", "#393b79", "#637939")
"""Track colours, in order: the web viewer's (``app/ui/static/common.js``), so that a mode
has one colour in the PNG and on the Replays page."""


def plot_tracks(path: str | Path, map_xy: np.ndarray,
                results: dict[str, dict[str, ModeSummary]], *, title: str = "") -> Path:
    """PNG of the map images, the true track and each mode's estimates (first run), in the
    viewer's colours; the legend's median error is the table's (after ``skip`` frames)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = next(iter(results))
    modes = results[config]
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    ax.scatter(map_xy[:, 0], map_xy[:, 1], s=8, c="0.75", label="map images")
    truth_drawn = False
    for k, (mode, summary) in enumerate(modes.items()):
        run = summary.runs[0]
        if not truth_drawn:
            ax.plot(run.truth[:, 0], run.truth[:, 1], "k-", lw=2, label="true track")
            truth_drawn = True
        median = summary.to_dict()["median_error_m"]
        ax.plot(run.estimate[:, 0], run.estimate[:, 1], ".-", lw=0.8, ms=3,
                color=PALETTE[k % len(PALETTE)],
                label=f"{mode} ({median:.1f} m median)")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or f"true and estimated tracks ({config})")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
