"""``vloc navigate``: teach a route in the robot world, then repeat it through the service."""

from __future__ import annotations

import json
from pathlib import Path

import click

from vloc.clients.commands._common import parse_params


@click.command("navigate")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("navigate-output"), show_default=True,
              help="Folder for navigate.png, results.json and the server log.")
@click.option("--length", "route_length", type=click.FloatRange(24.0, 2000.0), default=60.0,
              show_default=True, help="Metres round the street block.")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True)
@click.option("--mode", default="hierarchical", show_default=True,
              help="Localiser of the repeat session.")
@click.option("--param", "params", multiple=True, metavar="KEY=VALUE",
              help="Localiser parameter (repeatable).")
@click.option("--nav", "nav_params", multiple=True, metavar="KEY=VALUE",
              help="Path-following parameter: alpha, xi, v_max, w_max, gate, ... (repeatable).")
@click.option("--drift", type=click.FloatRange(0.0, 0.5), default=0.05, show_default=True,
              help="Odometry error at the end of the taught drive, share of the distance.")
@click.option("--light", "repeat_light", type=click.Choice(["sunny", "cloudy", "dusk"]),
              default="sunny", show_default=True, help="Illumination of the repeat.")
@click.option("--offset", "offset_m", type=float, default=0.0, show_default=True,
              help="Start this many metres left of the route's start.")
@click.option("--heading", "heading_deg", type=float, default=0.0, show_default=True,
              help="Start turned this many degrees from the route's start.")
@click.option("--starts", type=click.IntRange(0, 1000), default=0, show_default=True,
              help="Also repeat from this many random starts 1 m to the side and 20 degrees "
                   "off (Li et al.'s Fig. 13), each for --start-travel metres.")
@click.option("--start-travel", "start_travel_m", type=click.FloatRange(1.0), default=12.0,
              show_default=True)
@click.option("--url", default=None, help="A running server [default: start one].")
@click.option("--admin-key", envvar="VLOC_ADMIN_KEY", default=None)
@click.option("--workers", type=click.IntRange(1), default=None)
@click.option("--quiet", is_flag=True)
def navigate_cmd(out: Path, route_length: float, seed: int, mode: str, params, nav_params,
                 drift: float, repeat_light: str, offset_m: float, heading_deg: float,
                 starts: int, start_travel_m: float, url, admin_key, workers,
                 quiet: bool) -> None:
    """Teach a route round a street block of the robot world (frames, drifting odometry),
    build the map and the route over HTTP, then let a simulated robot repeat it: each
    rendered frame goes to the service and the robot drives by the command in the pose
    that comes back (Li et al.'s control law and EKF). Prints the cross-track error and
    writes OUT/navigate.png (taught vs repeated path) and OUT/results.json.
    """
    from vloc.clients.navigate import NavigateError, NavigateOptions, run_navigate
    from vloc.clients.sdk import VlocError

    opts = NavigateOptions(out=out, route_length=route_length, seed=seed, mode=mode,
                           params=parse_params(params), navigation=parse_params(nav_params),
                           repeat_light=repeat_light, drift=drift, offset_m=offset_m,
                           heading_deg=heading_deg, starts=starts,
                           start_travel_m=start_travel_m, url=url, admin_key=admin_key,
                           workers=workers, quiet=quiet)
    try:
        results = run_navigate(opts, say=click.echo)
    except (NavigateError, VlocError) as exc:
        raise click.ClickException(f"navigate failed: {exc}") from exc
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    click.echo(f"plot: {results['plot']}; results in {out / 'results.json'}")
