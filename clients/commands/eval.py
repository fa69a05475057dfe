"""``vloc eval``: the localisers over a dataset, offline, with the paper-style table."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

import click

from vloc.workers.core.modes import MODES

from ._common import parse_params


def _csv(value: str, allowed: tuple[str, ...], what: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    bad = [v for v in items if v not in allowed]
    if bad or not items:
        raise click.BadParameter(f"unknown {what} {', '.join(bad) or '(none)'}; "
                                 f"valid: {', '.join(allowed)}")
    return items


@click.command("eval")
@click.argument("dataset", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--map-pass", "map_pass_text", metavar="N[,N...]",
              help="Pass number whose images build the map; several (1,3) make a map of "
                   "several flights.")
@click.option("--query-pass", type=int, help="Pass number replayed as the query sequence.")
@click.option("--split", "rule", type=click.Choice(["pass", "alternate"]), default="pass",
              show_default=True, help="Split by pass, or alternate images (even map, odd query).")
@click.option("--modes", default=",".join(MODES), show_default=True,
              help="Comma-separated localisers to run.")
@click.option("--config", "configs", default="default", show_default=True,
              help="Comma-separated filter configurations (default, weiss2008).")
@click.option("--photometric", default="none", show_default=True,
              help="Relight the query images: none, darker, brighter, dusk, warm, shadows.")
@click.option("--starts", type=click.IntRange(1, 1000), default=5, show_default=True,
              help="Repeat from this many starting frames.")
@click.option("--skip", type=click.IntRange(0), default=10, show_default=True,
              help="Frames at the start of each run left out of the errors.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--param", "param_items", multiple=True, metavar="KEY=VALUE",
              help="Override a localiser parameter (JSON value), e.g. n_particles=500.")
@click.option("--retrieval-grid", is_flag=True,
              help="Also the feature x measure retrieval table (Flyphone Fig. 7).")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a PNG of the true and estimated tracks.")
@click.option("--use-metadata", "use_metadata", default="", metavar="KINDS",
              help="Comma-separated device metadata to give the localisers: heading, gps, "
                   "velocity, altitude; from the data set's CSV, else simulated from the "
                   "truth (see --gps-accuracy, --heading-sigma).")
@click.option("--gps-accuracy", type=click.FloatRange(min=0.1), default=None,
              help="Simulated GPS fix accuracy (m, one sigma per axis) where the data set "
                   "has no GPS columns.")
@click.option("--heading-sigma", type=click.FloatRange(min=0.1, max=180.0), default=5.0,
              show_default=True, help="Simulated compass noise (degrees).")
@click.option("--threads", type=click.IntRange(1), default=1, show_default=True,
              help="Threads of OpenCV and the BLAS: one keeps the timings from swinging "
                   "with the machine's load (a small matrix product that waits for a busy "
                   "core costs many times its work), as the service's workers run.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def eval_cmd(dataset: Path, map_pass_text, query_pass, rule, modes, configs, photometric, starts,
             skip, seed, param_items, retrieval_grid, plot, use_metadata, gps_accuracy,
             heading_sigma, threads, as_json) -> None:
    """Run the localisers over DATASET (a folder of geotagged images, optionally with a CSV
    of positions and a `pass` column) and report error and speed per mode."""
    from vloc.workers.core.evaluation.datasets import DatasetError
    from vloc.workers.core.evaluation.evaluate import evaluate
    from vloc.workers.core.evaluation.evaluate import retrieval_grid as run_grid
    from vloc.workers.core.evaluation.experiment import frame_metadata, load_experiment
    from vloc.workers.core.evaluation.photometric import VARIANTS
    from vloc.workers.core.evaluation.report import (
        grid_table,
        markdown_table,
        plot_tracks,
        results_dict,
        tracks_dict,
    )
    from vloc.workers.core.features import FEATURE_NAMES
    from vloc.workers.core.measures import MEASURES
    from vloc.workers.core.metadata import METADATA_KINDS
    from vloc.workers.core.pf.config import CONFIGS

    mode_list = _csv(modes, MODES, "mode")
    config_list = _csv(configs, tuple(CONFIGS), "config")
    if photometric not in VARIANTS:
        raise click.BadParameter(f"valid: {', '.join(VARIANTS)}", param_hint="--photometric")
    params = parse_params(param_items)
    map_pass = _passes(map_pass_text)
    say = (lambda *a, **k: None) if as_json else click.echo
    try:
        exp = load_experiment(dataset, rule=rule, map_pass=map_pass, query_pass=query_pass,
                              photometric=photometric, seed=seed)
    except (DatasetError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    say(f"{exp.dataset.summary()}\nmap: {len(exp.map_data)} images, "
        f"queries: {len(exp.queries)} frames, photometric: {photometric}")
    metadata_summary = None
    if use_metadata:
        kinds = tuple(_csv(use_metadata, METADATA_KINDS, "metadata kind"))
        try:
            metas = frame_metadata(exp, kinds, gps_accuracy=gps_accuracy,
                                   heading_sigma=heading_sigma, seed=seed)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from exc
        for q, m in zip(exp.queries, metas, strict=True):
            q.metadata = m
        metadata_summary = _metadata_summary(exp, metas, kinds, skip)
        say(f"metadata: {metadata_summary['text']}")
    for name, reason in exp.dataset.skipped:
        say(f"  skipped {name}: {reason}", err=True)

    def progress(config, mode, k, n):
        if not as_json:
            click.echo(f"\r  {config}/{mode}: run {k}/{n}", nl=(k == n), err=True)

    wall, cpu = time.perf_counter(), time.process_time()
    try:
        with _threads(threads):
            results = evaluate(exp.map_data, exp.queries, exp.truth, modes=mode_list,
                               configs=config_list, starts=starts, seed=seed, skip=skip,
                               params=params, progress=progress)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from exc
    timing = {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
              "threads": threads}
    data = results_dict(results)
    data["timing"] = timing
    data.update(dataset=str(dataset), photometric=photometric, starts=starts, skip=skip,
                seed=seed, map_images=len(exp.map_data), query_frames=len(exp.queries))
    if metadata_summary is not None:
        data["metadata"] = {k: v for k, v in metadata_summary.items() if k != "text"}
    if retrieval_grid:
        data["retrieval_grid"] = run_grid(exp.map_data, exp.queries, exp.truth,
                                          features=FEATURE_NAMES, measures=MEASURES, skip=skip)
    if plot:
        plot_tracks(plot, exp.map_data.positions, results)
        data["plot"] = str(plot)
    if as_json:
        # the tracks are for the web viewer's replay page; the table does not show them
        data |= tracks_dict(exp.map_data.positions, results)
        json.dump(data, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return
    click.echo(markdown_table(data))
    click.echo(f"\nran in {timing['wall_s']:.1f} s wall clock, {timing['cpu_s']:.1f} s CPU, "
               f"{threads} thread{'s' if threads > 1 else ''} (ms columns: wall clock)")
    if retrieval_grid:
        click.echo("\nretrieval error, mean / median (m), feature x measure:")
        click.echo(grid_table(data["retrieval_grid"]))
    if plot:
        click.echo(f"\ntracks written to {plot}")


@contextlib.contextmanager
def _threads(n: int):
    """OpenCV and the BLAS limited to ``n`` threads for the block."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        cv2.setNumThreads(before)


def _metadata_summary(exp, metas, kinds: tuple[str, ...], skip: int) -> dict:
    """What the frames carry, and the error of their GPS fixes alone (frames after skip)."""
    import numpy as np

    have = {k: sum(1 for m in metas if m is not None and k in m.kinds()) for k in kinds}
    out: dict = {"kinds": list(kinds), "frames_with": have}
    text = ", ".join(f"{k} on {n}/{len(metas)} frames" for k, n in have.items())
    fixes = [(i, m) for i, m in enumerate(metas) if i >= skip and m is not None and m.has_gps]
    if fixes:
        east, north = exp.map_data.origin.to_local([m.gps_lat for _, m in fixes],
                                                   [m.gps_lon for _, m in fixes])
        err = np.hypot(np.atleast_1d(east) - exp.truth[[i for i, _ in fixes], 0],
                       np.atleast_1d(north) - exp.truth[[i for i, _ in fixes], 1])
        out["gps_alone_mean_m"] = float(err.mean())
        out["gps_alone_median_m"] = float(np.median(err))
        text += f"; GPS alone: mean {err.mean():.1f} m, median {np.median(err):.1f} m"
    out["text"] = text
    return out


def _passes(text: str | None) -> int | tuple[int, ...] | None:
    """``--map-pass``: one pass number, or several separated by commas."""
    if text is None:
        return None
    try:
        passes = tuple(int(p) for p in text.split(","))
    except ValueError:
        raise click.BadParameter(f"{text!r}: pass numbers separated by commas, e.g. 1,3",
                                 param_hint="--map-pass") from None
    return passes[0] if len(passes) == 1 else passes
