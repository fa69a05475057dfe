"""``vloc replay``: simulated devices play a data set into a running server."""

from __future__ import annotations

import math
from pathlib import Path

import click

from vloc.clients.commands._common import (
    CommandError,
    build_with_bar,
    make_async_client,
    make_client,
    no_bar,
    parse_params,
    print_json,
    reports_errors,
    server_options,
)
from vloc.workers.core.modes import MODES


def _modes(value: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    bad = [v for v in items if v not in MODES]
    if bad or not items:
        raise click.BadParameter(f"unknown mode {', '.join(bad) or '(none)'}; "
                                 f"valid: {', '.join(MODES)}", param_hint="--mode")
    return list(dict.fromkeys(items))


@click.command("replay")
@click.argument("dataset", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--map-id", metavar="ID", help="Localise against this built map.")
@click.option("--build-map", is_flag=True,
              help="Create a map from the map pass's images, upload and build it first.")
@click.option("--map-pass", type=int, help="Pass whose images make the map [default: lowest].")
@click.option("--query-pass", type=int,
              help="Pass the devices replay [default: the lowest other pass].")
@click.option("--split", "rule", type=click.Choice(["pass", "alternate"]), default="pass",
              show_default=True, help="Split by pass, or alternate images (even map, odd query).")
@click.option("--mode", "modes_text", default="hybrid", show_default=True,
              help="Comma-separated localisers, replayed one after the other.")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True,
              help="Session seed of device 0 (device d gets seed+d); also seeds --photometric.")
@click.option("--param", "param_items", multiple=True, metavar="KEY=VALUE",
              help="A localiser parameter for every session (JSON value).")
@click.option("--rate", type=click.Choice(["recorded", "max"]), default="max",
              show_default=True, help="Keep the capture times' spacing, or send as fast as "
                                      "the server answers.")
@click.option("--speed", type=click.FloatRange(min=0.001), default=1.0, show_default=True,
              help="With --rate recorded: play this many times faster than recorded.")
@click.option("--transport", type=click.Choice(["http", "ws"]), default="http",
              show_default=True, help="POST each frame, or send it on the pose stream's socket.")
@click.option("--devices", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Simulated devices at once (load).")
@click.option("--window", type=click.IntRange(1, 64), default=8, show_default=True,
              help="Frames a device has in flight, at most.")
@click.option("--photometric", default="none", show_default=True,
              help="Relight the frames: none, darker, brighter, dusk, warm, shadows.")
@click.option("--skip", type=click.IntRange(0), default=10, show_default=True,
              help="Frames at the start of each run left out of the errors (as vloc eval).")
@click.option("--limit", type=click.IntRange(1), help="Replay only the first N frames.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path),
              help="Write a PNG of the true and estimated tracks.")
@click.option("--use-metadata", "use_metadata", default="", metavar="KINDS",
              help="Comma-separated device metadata sent with each frame: heading, gps, "
                   "velocity, altitude (from the data set's CSV; gps simulated with "
                   "--gps-accuracy where it has none).")
@click.option("--gps-accuracy", type=click.FloatRange(min=0.1), default=None,
              help="Simulated GPS fix accuracy (m, one sigma per axis).")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
@server_options
@reports_errors
def replay_cmd(dataset: Path, map_id, build_map: bool, map_pass, query_pass, rule, modes_text,
               seed, param_items, rate, speed, transport, devices, window, photometric, skip,
               limit, plot, use_metadata, gps_accuracy, as_json, quiet, server,
               admin_key) -> None:
    """Play the query pass of DATASET into a running server as one or more devices, read
    the pose streams, and print the error table (comparable with `vloc eval`).

    \b
    Example, against `vloc serve` on this machine:
      vloc replay ../shared/datasets/seneca-uav --build-map --map-pass 1 --query-pass 2 \\
          --mode hybrid,global,sift --rate max
    """
    from vloc.clients._replay_data import load_replay_data
    from vloc.workers.core.evaluation.datasets import DatasetError

    modes = _modes(modes_text)
    params = parse_params(param_items)
    if (map_id is None) == (not build_map):
        raise click.UsageError("give --map-id ID (a built map) or --build-map")
    try:
        kinds = tuple(k.strip() for k in use_metadata.split(",") if k.strip())
        data = load_replay_data(dataset, rule=rule, map_pass=map_pass, query_pass=query_pass,
                                photometric=photometric, seed=seed, limit=limit,
                                metadata=kinds, gps_accuracy=gps_accuracy)
    except (DatasetError, FileNotFoundError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    if not data.frames:
        raise CommandError("the query pass has no frames")
    quiet = quiet or as_json
    say = (lambda *a, **k: None) if as_json else click.echo
    say(f"{data.dataset.summary()}\nreplaying {len(data.frames)} frames x {devices} "
        f"device(s) x {', '.join(modes)}, rate {rate}, over {transport}", err=True)
    map_id, origin, map_xy = _prepare_map(server, admin_key, map_id, data, quiet=quiet)
    runs = _run(server, admin_key, map_id, data.frames, origin, modes=modes, devices=devices,
                seed=seed, params=params, rate=rate, speed=speed, transport=transport,
                window=window, quiet=quiet)
    _report(runs, data, origin, map_xy, skip=skip, plot=plot, as_json=as_json,
            config=str(params.get("config", "default")),
            extra={"dataset": str(dataset), "map_id": map_id, "photometric": photometric,
                   "rate": rate, "transport": transport, "devices": devices, "seed": seed,
                   "skip": skip, "query_frames": len(data.frames),
                   "map_images": len(data.map_images)})


def _prepare_map(server, admin_key, map_id, data, *, quiet: bool):
    """The map to localise on (built here with --build-map), its origin and image positions."""
    import numpy as np

    from vloc.clients.mapping import import_images
    from vloc.workers.core.geo import GeoOrigin

    with make_client(server, admin_key) as vloc:
        if map_id is None:
            passes = sorted({im.pass_ for im in data.map_images if im.pass_ is not None})
            name = f"{data.dataset.folder.resolve().name}" + (
                f" pass {passes[0]}" if len(passes) == 1 else "")
            map_id = _existing_map(vloc, name, len(data.map_images))
        if map_id is None:
            from tqdm import tqdm

            map_id = vloc.create_map(name).id
            click.echo(f"created map {map_id} ({name})", err=True)
            with tqdm(total=len(data.map_images), unit="img", desc="upload",
                      disable=no_bar(quiet)) as bar:
                summary = import_images(vloc, map_id, data.map_images,
                                        on_progress=lambda n, s: bar.update(n))
            if summary.accepted == 0:
                raise CommandError("the server accepted none of the map images")
            build_with_bar(vloc, map_id, quiet=quiet)
        m = vloc.get_map(map_id)
        if m.status != "ready" or m.origin is None:
            raise CommandError(f"map {map_id} is {m.status}, not built; "
                               f"run `vloc map build {map_id}`")
        images = [im for im in vloc.list_images(map_id) if im.east is not None]
    map_xy = np.array([(im.east, im.north) for im in images], dtype=np.float64)
    return map_id, GeoOrigin(m.origin.lat, m.origin.lon, m.origin.alt), map_xy


def _existing_map(vloc, name: str, n_images: int) -> str | None:
    """A built map an earlier ``--build-map`` made of the same images: same name, ready,
    as many images. Reused rather than built again."""
    for m in vloc.list_maps():
        if m.name == name and m.status == "ready" and m.image_count == n_images:
            click.echo(f"using map {m.id} ({name}), built from the same images", err=True)
            return m.id
    return None


def _run(server, admin_key, map_id, frames, origin, *, modes, devices, quiet, **options):
    import asyncio

    from tqdm import tqdm

    from vloc.clients.replay import replay_async, truth_in_map_frame
    from vloc.clients.sdk import Pose

    truth = truth_in_map_frame(frames, origin)
    total = len(frames) * devices * len(modes)
    with tqdm(total=total, unit="frame", desc="replay", disable=no_bar(quiet)) as bar:
        def on_answer(run, msg) -> None:
            bar.update(1)
            if isinstance(msg, Pose):
                err = math.hypot(msg.x - truth[msg.seq, 0], msg.y - truth[msg.seq, 1])
                bar.set_postfix_str(f"{run.mode} dev {run.device}: seq {msg.seq} "
                                    f"{msg.feature} err {err:.1f} m", refresh=False)

        async def main():
            async with make_async_client(server, admin_key) as client:
                return await replay_async(client, map_id, frames, modes=modes,
                                          devices=devices, on_answer=on_answer, **options)

        return asyncio.run(main())


def _report(runs, data, origin, map_xy, *, skip, plot, as_json, extra,
            config: str = "default") -> None:
    from vloc.clients._replay_report import plot_replay, replay_table, replay_tracks, summarise

    results = summarise(runs, data.frames, origin, skip=skip) | extra
    if plot is not None:
        plot_replay(plot, map_xy, runs, data.frames, origin, skip=skip, config=config)
        results["plot"] = str(plot)
    if as_json:
        print_json(results | replay_tracks(map_xy, runs, data.frames, origin, config=config))
        return
    click.echo(replay_table(results))
    if plot is not None:
        click.echo(f"\ntracks written to {plot}")
    lost = sum(r["frames_sent"] - r["frames_answered"] for r in results["runs"])
    if lost:
        click.echo(f"{lost} frame(s) got no estimate (failed or refused)", err=True)
