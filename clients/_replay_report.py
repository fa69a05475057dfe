"""Scores of a replay, per mode and device, as JSON-ready dicts and a Markdown table.

The error, SIFT-share and timing figures come from
:meth:`workers.core.evaluation.evaluate.ModeSummary.to_dict` (the numbers ``vloc eval`` prints); the
replay adds what only a device sees: frames lost or refused and the latency from sending a
frame to receiving its pose.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from vloc.clients.replay import DeviceRun, as_eval_run, truth_in_map_frame

_NAN_FIGURES = ("mean_error_m", "std_error_m", "median_error_m", "within_25m",
                "mean_error_after_convergence_m", "sift_step_share", "ms_per_frame",
                "ms_per_global_step", "ms_per_sift_step")


def _figures(runs: list[DeviceRun], truth_xy: np.ndarray, skip: int) -> dict:
    from vloc.workers.core.evaluation.evaluate import ModeSummary

    eval_runs = [as_eval_run(r, truth_xy) for r in runs if r.poses]
    if not eval_runs or sum(max(len(r.frames) - skip, 0) for r in eval_runs) == 0:
        out = dict.fromkeys(_NAN_FIGURES, math.nan)
    else:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            out = ModeSummary(runs[0].mode, "replay", eval_runs, skip).to_dict()
        out.pop("config", None)
        out.pop("runs", None)
    latency = np.array([v for r in runs for v in r.latency_ms.values()], dtype=np.float64)
    out.update(
        frames_sent=sum(r.n_frames for r in runs),
        frames_answered=sum(len(r.poses) for r in runs),
        frames_failed=sum(len(r.failed) for r in runs),
        frames_refused=sum(len(r.refused) for r in runs),
        latency_ms_p50=float(np.percentile(latency, 50)) if len(latency) else math.nan,
        latency_ms_p99=float(np.percentile(latency, 99)) if len(latency) else math.nan,
        wall_s=max(r.wall_s for r in runs))
    return out


def summarise(runs: list[DeviceRun], frames, origin, *, skip: int = 10) -> dict:
    """``{"modes": {mode: figures over all devices}, "runs": [figures per device]}``.

    Parameters
    ----------
    frames : list of DeviceFrame
        The replayed sequence (for the truth).
    origin : workers.core.geo.GeoOrigin
        The map's local frame, as the server reports it.
    skip : int
        Frames at the start of each device's run left out of the errors.
    """
    truth = truth_in_map_frame(frames, origin)
    modes: dict[str, dict] = {}
    devices: list[dict] = []
    for mode in dict.fromkeys(r.mode for r in runs):
        mode_runs = [r for r in runs if r.mode == mode]
        modes[mode] = _figures(mode_runs, truth, skip) | {"devices": len(mode_runs)}
        for r in mode_runs:
            devices.append({"mode": mode, "device": r.device, "seed": r.seed,
                            "session_id": r.session_id} | _figures([r], truth, skip))
    base = modes.get("sift", {}).get("ms_per_frame")
    for row in [*modes.values(), *devices]:
        ms = row.get("ms_per_frame")
        row["speedup_vs_sift"] = (base / ms if base and ms and math.isfinite(base)
                                  and math.isfinite(ms) and ms > 0 else None)
    return {"modes": modes, "runs": devices}


def _fmt(v, nd: int = 1) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{nd}f}"


def replay_table(data: dict) -> str:
    """One row per mode and device (plus an ``all`` row per mode with several devices)."""
    head = ("| mode | device | frames | mean err (m) | median (m) | SIFT steps | ms/frame "
            "| speed-up vs sift | latency p50 (ms) | p99 (ms) |")
    lines = [head, "|" + "---|" * 10]
    for mode, agg in data["modes"].items():
        rows = [r for r in data["runs"] if r["mode"] == mode]
        if len(rows) > 1:
            rows.append(agg | {"device": "all"})
        for r in rows:
            lost = r["frames_sent"] - r["frames_answered"]
            frames = f"{r['frames_answered']}" + (f" ({lost} lost)" if lost else "")
            share = r["sift_step_share"]
            lines.append(
                f"| {mode} | {r['device']} | {frames} | {_fmt(r['mean_error_m'])} "
                f"| {_fmt(r['median_error_m'])} "
                f"| {'-' if not math.isfinite(share) else f'{100 * share:.1f} %'} "
                f"| {_fmt(r['ms_per_frame'])} | {_fmt(r.get('speedup_vs_sift'), 2)} "
                f"| {_fmt(r['latency_ms_p50'], 0)} | {_fmt(r['latency_ms_p99'], 0)} |")
    return "\n".join(lines)


def plot_replay(path, map_xy: np.ndarray, runs: list[DeviceRun], frames, origin, *,
                title: str = "", skip: int = 10, config: str = "default"):
    """PNG of the map images, the true track and device 0's estimated track per mode
    (:func:`workers.core.evaluation.report.plot_tracks`).

    Parameters
    ----------
    map_xy : (M, 2) float64 ndarray
        Map image positions, east/north metres in the map's frame.
    """
    from vloc.workers.core.evaluation.evaluate import ModeSummary
    from vloc.workers.core.evaluation.report import plot_tracks

    truth = truth_in_map_frame(frames, origin)
    modes = {r.mode: ModeSummary(r.mode, config, [as_eval_run(r, truth)], skip)
             for r in runs if r.device == 0 and r.poses}
    if not modes:
        raise ValueError("no estimates to plot")
    return plot_tracks(path, np.asarray(map_xy, dtype=np.float64).reshape(-1, 2),
                       {config: modes}, title=title or "true and estimated tracks")


def replay_tracks(map_xy: np.ndarray, runs: list[DeviceRun], frames, origin, *,
                  config: str = "default") -> dict:
    """Device 0's track per mode against the truth, for the web viewer
    (:func:`workers.core.evaluation.report.tracks_dict`), under the sessions' filter ``config``."""
    from vloc.workers.core.evaluation.evaluate import ModeSummary
    from vloc.workers.core.evaluation.report import tracks_dict

    truth = truth_in_map_frame(frames, origin)
    modes = {r.mode: ModeSummary(r.mode, config, [as_eval_run(r, truth)], 0)
             for r in runs if r.device == 0 and r.poses}
    return tracks_dict(np.asarray(map_xy, dtype=np.float64).reshape(-1, 2),
                       {config: modes})


def mode_table(data: dict) -> str:
    """The per-mode summary: error, SIFT share, ms per frame and speed-up against SIFT."""
    lines = ["| mode | mean err (m) | median (m) | SIFT steps | ms/frame | speed-up vs sift |",
             "|---|---|---|---|---|---|"]
    for mode, r in data["modes"].items():
        share = r["sift_step_share"]
        lines.append(
            f"| {mode} | {_fmt(r['mean_error_m'])} | {_fmt(r['median_error_m'])} "
            f"| {'-' if not math.isfinite(share) else f'{100 * share:.1f} %'} "
            f"| {_fmt(r['ms_per_frame'])} | {_fmt(r.get('speedup_vs_sift'), 2)} |")
    return "\n".join(lines)
