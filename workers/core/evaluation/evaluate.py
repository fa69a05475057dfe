"""Offline evaluation: run localisers over a query sequence and measure them.

The protocol follows Weiss et al. 2008, section V: each experiment is repeated from several
starting frames and the errors are averaged; the table reports the mean and median error,
the error after convergence, the share of SIFT steps, the time per frame by step type and
the speed-up against SIFT alone (Tables I and II).

Errors are taken over the frames after the first ``skip`` of each run (the filter starts
from a uniform cloud, and every localiser deserves a few frames to find itself).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..estimate import Status
from ..localisers import make_localiser
from ..mapdata import MapData
from ..query import QueryFrame


@dataclass
class Run:
    """One pass of one localiser over the query frames from ``start`` to the end."""

    mode: str
    config: str
    start: int
    frames: np.ndarray  # (n,) query indexes
    truth: np.ndarray  # (n, 2)
    estimate: np.ndarray  # (n, 2)
    sigma: np.ndarray  # (n, 2)
    feature: list[str]
    status: list[str]
    ms: np.ndarray  # (n,)

    @property
    def errors(self) -> np.ndarray:
        return np.linalg.norm(self.estimate - self.truth, axis=1)


@dataclass
class ModeSummary:
    """The numbers of one row of the table, over all runs of a mode."""

    mode: str
    config: str
    runs: list[Run] = field(repr=False)
    skip: int = 10

    def _pooled(self, what) -> np.ndarray:
        return np.concatenate([what(r)[self.skip:] for r in self.runs])

    def to_dict(self) -> dict:
        errors = self._pooled(lambda r: r.errors)
        per_run = np.array([r.errors[self.skip:].mean() for r in self.runs])
        after = []
        for r in self.runs:
            tracked = [i for i, s in enumerate(r.status) if s == Status.TRACKING]
            if tracked:
                after.append(r.errors[tracked[0]:])
        after_conv = float(np.concatenate(after).mean()) if after else None
        feats = np.array(sum((r.feature for r in self.runs), []))
        ms = np.concatenate([r.ms for r in self.runs])
        is_sift = feats == "sift"

        def mean_or_none(a: np.ndarray) -> float | None:
            # None (JSON null) where a mode took no step of that kind
            return float(a.mean()) if len(a) else None

        return {
            "config": self.config,
            "runs": len(self.runs),
            "frames": int(len(errors)),
            "mean_error_m": float(errors.mean()),
            "std_error_m": float(per_run.std()),
            "median_error_m": float(np.median(errors)),
            "within_25m": float((errors <= 25.0).mean()),
            "mean_error_after_convergence_m": after_conv,
            "sift_step_share": float(is_sift.mean()),
            "ms_per_frame": float(ms.mean()),
            "ms_per_global_step": mean_or_none(ms[~is_sift]),
            "ms_per_sift_step": mean_or_none(ms[is_sift]),
        }


def choose_starts(n_frames: int, n_starts: int, skip: int) -> list[int]:
    """Evenly spaced starting frames in the first half of the sequence.

    Every run goes to the end, so each keeps at least half the sequence (and more than
    ``skip`` frames) to be measured on.
    """
    last = max(0, min(n_frames // 2, n_frames - skip - 1))
    if n_starts <= 1 or last == 0:
        return [0]
    return sorted({int(round(s)) for s in np.linspace(0, last, n_starts)})


def run_sequence(map_data: MapData, queries: list[QueryFrame], truth: np.ndarray, *,
                 mode: str, params: dict, seed: int, start: int, config: str) -> Run:
    """Localise ``queries[start:]`` in order with a fresh localiser."""
    loc = make_localiser(mode, map_data, params, seed=seed)
    idx = np.arange(start, len(queries))
    est = np.zeros((len(idx), 2))
    sig = np.zeros((len(idx), 2))
    ms = np.zeros(len(idx))
    feats, status = [], []
    for j, i in enumerate(idx):
        e = loc.step(queries[i])
        est[j] = e.x, e.y
        sig[j] = e.sigma_x, e.sigma_y
        ms[j] = e.processing_ms
        feats.append(e.feature if e.feature == "sift" else "global")
        status.append(str(e.status))
    return Run(mode, config, start, idx, np.asarray(truth)[idx], est, sig, feats, status, ms)


def evaluate(map_data: MapData, queries: list[QueryFrame], truth: np.ndarray, *,
             modes: list[str], configs: list[str], starts: int = 5, seed: int = 0,
             skip: int = 10, params: dict | None = None,
             progress=None) -> dict[str, dict[str, ModeSummary]]:
    """Every mode under every config, repeated from several starting frames.

    Configs apply to the filter modes; ``retrieval`` and ``hierarchical`` run once, under
    the first config's name. Each starting frame runs every mode in turn before the next
    starts (each run a fresh localiser, so the order changes no estimate): the modes'
    times per frame, and so their speed-ups, are measured under the same load.

    Returns
    -------
    dict config -> dict mode -> ModeSummary
    """
    from ..localisers import FILTER_MODES

    first = choose_starts(len(queries), starts, skip)
    out: dict[str, dict[str, ModeSummary]] = {}
    for ci, config in enumerate(configs):
        todo = [m for m in modes if m in FILTER_MODES or ci == 0]
        runs: dict[str, list[Run]] = {m: [] for m in todo}
        # start by start, every mode in turn: a speed-up compares runs made under the same
        # load, where a shared machine's speed drifts over an evaluation's minutes
        for k, s in enumerate(first):
            for mode in todo:
                p = dict(params or {})
                if mode in FILTER_MODES:
                    p["config"] = config
                runs[mode].append(run_sequence(map_data, queries, truth, mode=mode, params=p,
                                               seed=seed + k, start=s, config=config))
                if progress:
                    progress(config, mode, k + 1, len(first))
        out[config] = {m: ModeSummary(m, config, runs[m], skip) for m in todo}
    return out


def speedups(summaries: dict[str, dict]) -> dict[str, float]:
    """ms per frame of ``sift`` divided by each mode's (same config)."""
    base = summaries.get("sift", {}).get("ms_per_frame")
    if not base:
        return {}
    return {m: base / d["ms_per_frame"] for m, d in summaries.items() if d["ms_per_frame"] > 0}


def retrieval_grid(map_data: MapData, queries: list[QueryFrame], truth: np.ndarray, *,
                   features: tuple[str, ...], measures: tuple[str, ...],
                   skip: int = 0) -> dict[str, dict[str, dict[str, float]]]:
    """Single-frame retrieval error for every feature under every measure (Flyphone Fig. 7).

    Returns
    -------
    dict feature -> measure -> {"mean_error_m", "median_error_m"}
    """
    from ..measures import similarities

    xy = np.asarray(map_data.positions)
    truth = np.asarray(truth)[skip:]
    grid: dict[str, dict[str, dict[str, float]]] = {}
    for feat in features:
        if feat not in map_data.global_features:
            continue
        mat = map_data.global_features[feat]
        q = np.stack([qf.global_features((feat,))[0][feat] for qf in queries[skip:]])
        grid[feat] = {}
        for measure in measures:
            best = np.array([int(np.argmax(similarities(measure, v, mat))) for v in q])
            err = np.linalg.norm(xy[best] - truth, axis=1)
            grid[feat][measure] = {"mean_error_m": float(err.mean()),
                                   "median_error_m": float(np.median(err))}
    return grid
