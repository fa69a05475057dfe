"""``vloc map``: create, list, show, delete, import a folder, build, manage revisions."""

from __future__ import annotations

import re
from pathlib import Path

import click

from vloc.clients.commands._common import (
    CommandError,
    build_with_bar,
    make_client,
    model_json,
    no_bar,
    print_json,
    reports_errors,
    server_options,
)


@click.group("map")
def map_group() -> None:
    """Maps: GPS-tagged images the server localises against.

    A map is filled with images (`vloc map import FOLDER`) and then built
    (`vloc map build ID`); sessions open on a built map.
    """


_OBJECT_REPR = re.compile(r"\s*<[\w.]+ object at 0x[0-9a-f]+>")


def readable(reason: str) -> str:
    """A reason without the object reprs a decoder's message may carry."""
    return _OBJECT_REPR.sub("", str(reason)).strip()


def _describe(m) -> str:
    lines = [f"{m.id}  {m.name}",
             f"  status: {m.status}, revision {m.revision}, {m.image_count} images "
             f"({m.pending_images} not yet built)"]
    if m.extent is not None:
        e = m.extent
        lines.append(f"  extent: lat {e.min_lat:.6f}..{e.max_lat:.6f}, "
                     f"lon {e.min_lon:.6f}..{e.max_lon:.6f}")
    if m.local_extent is not None:
        x = m.local_extent
        lines.append(f"  size: {x.max_east - x.min_east:.0f} m east x "
                     f"{x.max_north - x.min_north:.0f} m north")
    if m.last_job_id:
        lines.append(f"  last build job: {m.last_job_id}")
    return "\n".join(lines)


@map_group.command("create")
@click.argument("name")
@click.option("--json", "as_json", is_flag=True, help="Print the map as JSON.")
@server_options
@reports_errors
def create_cmd(name: str, as_json: bool, server: str, admin_key: str | None) -> None:
    """Create an empty map called NAME; prints its id."""
    with make_client(server, admin_key) as vloc:
        m = vloc.create_map(name)
    print_json(model_json(m)) if as_json else click.echo(m.id)


@map_group.command("list")
@click.option("--json", "as_json", is_flag=True)
@server_options
@reports_errors
def list_cmd(as_json: bool, server: str, admin_key: str | None) -> None:
    """List the maps."""
    with make_client(server, admin_key) as vloc:
        maps = vloc.list_maps()
    if as_json:
        print_json(model_json(maps))
        return
    if not maps:
        click.echo("no maps; create one with `vloc map import FOLDER`")
    for m in maps:
        click.echo(f"{m.id}  {m.status:<8} rev {m.revision:<3} {m.image_count:>5} images  "
                   f"{m.name}")


@map_group.command("show")
@click.argument("map_id")
@click.option("--json", "as_json", is_flag=True)
@server_options
@reports_errors
def show_cmd(map_id: str, as_json: bool, server: str, admin_key: str | None) -> None:
    """Show one map: status, revision, images, extent."""
    with make_client(server, admin_key) as vloc:
        m = vloc.get_map(map_id)
    print_json(model_json(m)) if as_json else click.echo(_describe(m))


@map_group.command("delete")
@click.argument("map_id")
@server_options
@reports_errors
def delete_cmd(map_id: str, server: str, admin_key: str | None) -> None:
    """Delete a map with its images (refused while sessions use it)."""
    with make_client(server, admin_key) as vloc:
        vloc.delete_map(map_id)
    click.echo(f"deleted map {map_id}")


@map_group.command("import")
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--map", "map_id", metavar="ID", help="Add to this map [default: a new map].")
@click.option("--name", help="Name of the new map [default: the folder's name].")
@click.option("--pass", "pass_", type=int, help="Only the images of this pass (CSV column).")
@click.option("--flight", metavar="NAME",
              help="Name the flight these images belong to (a map of several flights over "
                   "the same ground reports each one's accuracy).")
@click.option("--flight-per-pass", is_flag=True,
              help="Name each image's flight after its pass in the CSV (\"pass 1\", ...).")
@click.option("--build/--no-build", default=False, show_default=True,
              help="Build the map after the upload, waiting for it.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@server_options
@reports_errors
def import_cmd(folder: Path, map_id: str | None, name: str | None, pass_: int | None,
               flight: str | None, flight_per_pass: bool, build: bool, quiet: bool,
               server: str, admin_key: str | None) -> None:
    """Upload the geotagged images of FOLDER (EXIF GPS, else the folder's CSV).

    The folder is read as `vloc eval` reads a data set: images directly in it or in
    images/, positions from EXIF or from ground_truth.csv/positions.csv. Images the server
    refuses are listed with the reason; the command fails only when none is accepted.
    Without --flight or --flight-per-pass the server groups the images into flights by
    their capture times.
    """
    if flight is not None and flight_per_pass:
        raise click.UsageError("give --flight or --flight-per-pass, not both")
    from tqdm import tqdm

    from vloc.clients.mapping import import_images
    from vloc.workers.core.evaluation.datasets import DatasetError, load_dataset

    try:
        ds = load_dataset(folder)
    except (DatasetError, FileNotFoundError) as exc:
        raise CommandError(str(exc)) from exc
    for skipped, reason in ds.skipped:
        click.echo(f"  skipped {skipped}: {readable(reason)}", err=True)
    if flight_per_pass and not ds.passes:
        raise CommandError(f"--flight-per-pass: the images of {folder} have no pass (a "
                           "'pass' column in its CSV)")
    images = [im for im in ds.images if pass_ is None or im.pass_ == pass_]
    if not images:
        if ds.images:
            raise CommandError(f"no images of pass {pass_} in {folder}; passes present: "
                               f"{', '.join(map(str, ds.passes))}")
        raise CommandError(f"no usable image in {folder}: "
                           + (f"all {len(ds.skipped)} were skipped (reasons above)"
                              if ds.skipped else "it holds no JPEG or PNG files"))
    with make_client(server, admin_key) as vloc:
        if map_id is None:
            map_id = vloc.create_map(name or folder.resolve().name).id
            click.echo(f"created map {map_id}", err=True)
        with tqdm(total=len(images), unit="img", desc="upload", disable=no_bar(quiet)) as bar:
            summary = import_images(vloc, map_id, images,
                                    on_progress=lambda n, s: bar.update(n),
                                    flight_of=_flight_of(flight, flight_per_pass))
        for r in summary.rejected:
            click.echo(f"  rejected {r.filename}: {r.detail} ({r.reason})", err=True)
        click.echo(f"{summary.accepted} of {summary.total} images added to map {map_id}",
                   err=True)
        if summary.accepted == 0:
            raise CommandError("no image was accepted")
        if build:
            build_with_bar(vloc, map_id, quiet=quiet)
    click.echo(map_id)


def _flight_of(flight: str | None, per_pass: bool):
    """The flight each uploaded image is named as part of (None: the server groups them by
    capture time)."""
    if per_pass:
        return lambda im: None if im.pass_ is None else f"pass {im.pass_}"
    return lambda im: flight


@map_group.command("build")
@click.argument("map_id")
@click.option("--wait/--no-wait", default=True, show_default=True,
              help="Wait for the build, with a progress bar.")
@click.option("--timeout", type=float, default=3600.0, show_default=True,
              help="Seconds to wait.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@click.option("--force", is_flag=True,
              help="Pack a new revision even when no image was added or deleted.")
@click.option("--full", is_flag=True,
              help="Reconstruct the map's camera geometry whole instead of registering the "
                   "images added since the last build into it, and train its place "
                   "vocabularies afresh (implies --force).")
@server_options
@reports_errors
def build_cmd(map_id: str, wait: bool, timeout: float, quiet: bool, force: bool, full: bool,
              server: str, admin_key: str | None) -> None:
    """Extract the features of the new images of MAP_ID and pack a new revision."""
    with make_client(server, admin_key) as vloc:
        if not wait:
            click.echo(vloc.build_map(map_id, force=force, full=full).id)
            return
        build_with_bar(vloc, map_id, quiet=quiet, timeout=timeout, force=force, full=full)


@map_group.command("revisions")
@click.argument("map_id")
@click.option("--json", "as_json", is_flag=True)
@server_options
@reports_errors
def revisions_cmd(map_id: str, as_json: bool, server: str, admin_key: str | None) -> None:
    """List a map's revisions, newest first: what each holds and what changed."""
    with make_client(server, admin_key) as vloc:
        revisions = vloc.list_revisions(map_id)
    if as_json:
        print_json(model_json(revisions))
        return
    if not revisions:
        click.echo(f"map {map_id} has no revision yet; build it: vloc map build {map_id}")
    for r in revisions:
        click.echo(_revision_line(r))


def _revision_line(r) -> str:
    when = r.built_at.strftime("%Y-%m-%d %H:%M") if r.built_at else "?"
    line = (f"{'*' if r.current else ' '} rev {r.revision:<3} {when}  {r.image_count:>5} images"
            f" (+{r.added} -{r.removed} on rev {r.base_revision})")
    check = r.geometry.self_check if r.geometry is not None else None
    if check is not None and check.median_m is not None:
        line += f"  self-check median {check.median_m:.1f} m"
        for f in check.flights or []:
            median = "-" if f.median_m is None else f"{f.median_m:.1f} m"
            line += f"; {f.name or f'flight {f.flight}'} {median}"
    if r.vocabularies_from is not None and r.vocabularies_from != r.revision:
        line += f"  vocabularies of rev {r.vocabularies_from}"
    if r.dropped_at is not None:
        line += "  dropped"
    elif r.disk_bytes is not None:
        line += f"  {r.disk_bytes / 2**20:.1f} MiB"
        if r.shared_bytes:
            line += f" ({r.shared_bytes / 2**20:.1f} shared)"
    else:
        line += "  files missing"
    if r.active_sessions:
        line += f"  {r.active_sessions} active session(s)"
    return line


@map_group.command("restore")
@click.argument("map_id")
@click.argument("revision", type=click.IntRange(min=1))
@server_options
@reports_errors
def restore_cmd(map_id: str, revision: int, server: str, admin_key: str | None) -> None:
    """Make REVISION the map's current revision again (new sessions use it; open sessions
    keep theirs; images it does not hold wait for the next build)."""
    with make_client(server, admin_key) as vloc:
        m = vloc.restore_revision(map_id, revision)
    click.echo(f"map {map_id} is at revision {m.revision} ({m.status}, "
               f"{m.pending_images} image(s) waiting for a build)")


@map_group.command("drop-revision")
@click.argument("map_id")
@click.argument("revision", type=click.IntRange(min=1))
@server_options
@reports_errors
def drop_revision_cmd(map_id: str, revision: int, server: str, admin_key: str | None) -> None:
    """Delete REVISION of a map and its files (not the current one, nor one in use)."""
    with make_client(server, admin_key) as vloc:
        vloc.drop_revision(map_id, revision)
    click.echo(f"dropped revision {revision} of map {map_id}")
