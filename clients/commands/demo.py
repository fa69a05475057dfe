"""``vloc demo``: the whole product in one command, on a synthetic world."""

from __future__ import annotations

import signal
from pathlib import Path

import click


@click.command("demo")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("demo-output"), show_default=True,
              help="Folder for the world, tracks.png, results.json and the server log.")
@click.option("--frames", type=click.IntRange(10, 2000), default=200, show_default=True,
              help="Frames per pass, 0.65 m apart: 200 go once round a 130 m block, fewer "
                   "round a smaller one (faster).")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True,
              help="Seeds the world and the sessions.")
@click.option("--query-light", type=click.Choice(["cloudy", "dusk"]), default="cloudy",
              show_default=True, help="Illumination of the replayed pass (the map is sunny).")
@click.option("--config", default="weiss2008", show_default=True,
              help="Filter configuration of the sessions: weiss2008 (the paper's hybrid, "
                   "made for street scenes like the demo's) or default (tuned on real "
                   "UAV imagery: more SIFT steps, slower).")
@click.option("--workers", type=click.IntRange(1), default=None,
              help="Server worker processes [default: one per core].")
@click.option("--port", type=click.IntRange(1, 65535), default=None,
              help="Port of the demo's server on 127.0.0.1 [default: a free one].")
@click.option("--keep", is_flag=True,
              help="Keep the server running after the replay, for the web viewer (its "
                   "address is printed), until Ctrl-C; and keep its data folder "
                   "(database, images, packed map) in --out.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def demo_cmd(out: Path, frames: int, seed: int, query_light: str, config: str, workers,
             port, keep: bool, quiet: bool) -> None:
    """Generate a synthetic street world, start a server on the embedded defaults, build
    the map over HTTP, replay a traversal under other light as a device for the hybrid,
    global and SIFT localisers, print their table, write OUT/tracks.png, stop the server
    (or, with --keep, leave it running for the web viewer at the printed address).

    Needs nothing but this package: no data, no database server, no network.
    """
    from vloc.clients.demo import DemoError, DemoOptions, run_demo
    from vloc.clients.sdk import VlocError

    opts = DemoOptions(out=out, frames=frames, seed=seed, query_light=query_light,
                       config=config, workers=workers, port=port, keep=keep, quiet=quiet)
    try:
        results = run_demo(opts, say=click.echo)
    except (DemoError, VlocError) as exc:
        raise click.ClickException(f"demo failed: {exc}\n(server log: {out / 'server.log'})"
                                   ) from exc
    except KeyboardInterrupt:
        # leaving: another Ctrl-C from here on (or one arriving as the interpreter shuts
        # down, when Python's own handler is gone) must not turn exit 130 into a death by
        # signal
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        click.echo("\ninterrupted; the server was stopped", err=True)
        raise SystemExit(130) from None
    click.echo(f"done in {results['timings_s']['total']:.0f} s; results in {out}")
