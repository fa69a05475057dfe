"""``vloc mavlink``: a MAVLink autopilot localised by vloc (the light client's
``vloc-mavlink``, with the admin key ``vloc serve`` stored as the default)."""

from __future__ import annotations

import click

from vloc.clients.commands._common import stored_admin_key


@click.command("mavlink", add_help_option=False,
               context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def mavlink_cmd(args: tuple[str, ...]) -> None:
    """Frames from a camera or folder to a session, its poses to the autopilot as GPS_INPUT
    (or a local-frame estimate). `vloc mavlink --help` lists the options."""
    from vloc.clients.sdk.mavlink import main

    raise SystemExit(main(list(args), prog="vloc mavlink", admin_key=stored_admin_key()))
