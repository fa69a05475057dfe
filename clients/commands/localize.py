"""``vloc localize MAP_ID IMAGE...``: where was each image taken? One request per image,
answered at once, nothing stored (``POST /v1/maps/{id}/localize``)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from vloc.clients.commands._common import (
    CommandError,
    make_client,
    model_json,
    reports_errors,
    server_options,
)
from vloc.workers.core.modes import FILTER_MODES


def _prior(ctx, param, value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        lat, lon = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter("expected LAT,LON, e.g. 41.0345,-83.3057") from None
    return lat, lon


@click.command("localize")
@click.argument("map_id")
@click.argument("images", nargs=-1, required=True,
                type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--prior", callback=_prior, metavar="LAT,LON",
              help="Where the image is roughly known to be (with --prior-sigma).")
@click.option("--prior-sigma", "prior_sigma_m", type=click.FloatRange(0, min_open=True),
              metavar="M", help="Uncertainty of --prior in metres.")
@click.option("--mode", type=click.Choice(FILTER_MODES), default=None,
              help="How the image is compared with the map [default: the server's, sift].")
@click.option("--json", "as_json", is_flag=True, help="One JSON object per image.")
@server_options
@reports_errors
def localize_cmd(map_id: str, images: tuple[Path, ...], prior, prior_sigma_m, mode,
                 as_json: bool, server: str, admin_key) -> None:
    """Where was each IMAGE (JPEG/PNG) taken, on the built map MAP_ID? Prints one line per
    image: position, 68 % horizontal accuracy, the best matched map image."""
    if (prior is None) != (prior_sigma_m is None):
        raise CommandError("give --prior and --prior-sigma together")
    with make_client(server, admin_key) as vloc:
        for path in images:
            where = vloc.localize(map_id, path, prior=prior, prior_sigma_m=prior_sigma_m,
                                  mode=mode)
            if as_json:
                click.echo(json.dumps({"file": path.name} | model_json(where)))
                continue
            accuracy = (f"+-{where.horizontal_accuracy_m:.1f} m"
                        if where.horizontal_accuracy_m is not None else "accuracy unknown")
            heading = (f", heading {where.heading_deg:.0f} deg"
                       if where.heading_deg is not None else "")
            click.echo(f"{path.name}: {where.lat:.6f}, {where.lon:.6f} {accuracy}{heading}"
                       f" ({where.status}; best match {where.image_filename})")
