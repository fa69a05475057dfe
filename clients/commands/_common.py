"""What the client commands share: where the server is, the admin key, error reporting."""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

DEFAULT_URL = "http://127.0.0.1:8000"


def admin_key_file() -> Path:
    """Where ``vloc serve`` on the embedded defaults stores the key it generated:
    ``$VLOC_DATA_DIR/admin_key``, ``./data/admin_key`` (of the current folder) by default."""
    return (Path(os.environ.get("VLOC_DATA_DIR") or "data") / "admin_key").absolute()


def stored_admin_key() -> str | None:
    """The key in :func:`admin_key_file`, when it is readable here."""
    try:
        return admin_key_file().read_text().strip() or None
    except OSError:
        return None


def server_options(fn: Callable) -> Callable:
    """``--server`` and ``--admin-key``, from the flags or the environment."""
    fn = click.option("--admin-key", envvar="VLOC_ADMIN_KEY", metavar="KEY",
                      help="Admin API key [env VLOC_ADMIN_KEY; else the key `vloc serve` "
                           "stored in ./data/admin_key of the current folder, or "
                           "$VLOC_DATA_DIR/admin_key].")(fn)
    fn = click.option("--server", envvar="VLOC_URL", default=DEFAULT_URL, show_default=True,
                      metavar="URL", help="Server address [env VLOC_URL].")(fn)
    return fn


def make_client(server: str, admin_key: str | None, **kwargs):
    from vloc.clients.sdk import Client

    return Client(server, admin_key=admin_key or stored_admin_key() or "", **kwargs)


def make_async_client(server: str, admin_key: str | None, **kwargs):
    from vloc.clients.sdk import AsyncClient

    return AsyncClient(server, admin_key=admin_key or stored_admin_key() or "", **kwargs)


CLI_ADVICE = {
    "map-not-built": "build it first: vloc map build {map_id}",
    "map-up-to-date": "`vloc map build --force {map_id}` packs it again",
    "session-expired": "open a new one: vloc session create MAP_ID",
    "revision-current": "restore another first: vloc map restore {map_id} REVISION "
                        "(vloc map revisions {map_id} lists them)",
}
"""What to do about a problem, as commands of this CLI (the server's own advice names the
HTTP routes), by problem kind."""


def reports_errors(fn: Callable) -> Callable:
    """Turn client errors into one clear line on stderr and a non-zero exit status:
    1 for an error answer from the server, 3 when the server cannot be reached."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from vloc.clients.sdk import (
            APIError,
            Forbidden,
            TransportError,
            Unauthorized,
            VlocError,
        )

        params = click.get_current_context().params
        try:
            return fn(*args, **kwargs)
        except TransportError as exc:
            server = params.get("server", "the server")
            raise CommandError(f"cannot reach {server}: {exc}\n"
                               "Is `vloc serve` running there? Set --server or VLOC_URL.",
                               exit_code=3) from exc
        except Unauthorized as exc:
            raise CommandError(f"{exc}\n{_key_hint(params, refused=False)}") from exc
        except Forbidden as exc:
            raise CommandError(f"{exc}\n{_key_hint(params, refused=True)}") from exc
        except APIError as exc:
            raise CommandError(_with_advice(exc, params)) from exc
        except VlocError as exc:
            raise CommandError(str(exc)) from exc

    return wrapper


def _with_advice(exc, params: dict) -> str:
    advice = CLI_ADVICE.get(exc.kind or "")
    if advice is None:
        return str(exc)
    # the server's detail up to its own advice (after "; "), then this CLI's
    detail = exc.detail.split("; ")[0] if "; " in exc.detail else exc.detail
    map_id = params.get("map_id") or "MAP_ID"
    return f"{exc.status} {exc.title}: {detail}\n{advice.format(map_id=map_id)}"


def _key_hint(params: dict, *, refused: bool) -> str:
    """Where the key came from, and where the right one is."""
    path = admin_key_file()
    if params.get("admin_key"):
        source = "--admin-key / VLOC_ADMIN_KEY"
    elif params.get("token"):
        source = "--token / VLOC_SESSION_TOKEN"
    elif stored_admin_key() is not None:
        source = str(path)
    else:
        source = None
    if refused:
        return (f"The server refused the key from {source or 'the command line'}. The "
                "server's admin key is in the admin_key file of its data directory (./data/admin_key where `vloc "
                "serve` runs, or $VLOC_DATA_DIR), or is its VLOC_ADMIN_KEY.")
    return ("No key was sent: give the admin key with --admin-key or VLOC_ADMIN_KEY, or run "
            f"this where `vloc serve` runs (the CLI reads {path}, which is not there).")


class CommandError(click.ClickException):
    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def parse_params(items: tuple[str, ...]) -> dict:
    """``KEY=VALUE`` pairs; values parsed as JSON where they are JSON."""
    params = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint="--param")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def model_json(model) -> Any:
    """A model (or list of models) as plain JSON data."""
    if isinstance(model, list):
        return [m.model_dump(mode="json") for m in model]
    return model.model_dump(mode="json")


def no_bar(quiet: bool) -> bool:
    """Progress bars only on a terminal: piped or logged stderr gets the plain lines."""
    return quiet or not sys.stderr.isatty()


def build_with_bar(vloc, map_id: str, *, quiet: bool = False, timeout: float = 3600.0,
                   force: bool = False, full: bool = False):
    """Build a map and wait for it behind a progress bar; returns the finished job."""
    from vloc.clients.sdk import Conflict

    try:
        return _build(vloc, map_id, quiet=quiet, timeout=timeout, force=force, full=full)
    except Conflict as exc:
        if exc.kind != "map-up-to-date":
            raise
        click.echo(f"map {map_id} is up to date: revision {exc.body.get('revision')} holds "
                   f"every image (`vloc map build --force {map_id}` packs it again)", err=True)
        return None


def _build(vloc, map_id: str, *, quiet: bool, timeout: float, force: bool = False,
           full: bool = False):
    from tqdm import tqdm

    from vloc.clients.mapping import build_and_wait

    with tqdm(total=100, unit="%", desc="build", disable=no_bar(quiet),
              bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}") as bar:
        def progress(job) -> None:
            bar.update(round(100 * job.progress) - bar.n)

        job = build_and_wait(vloc, map_id, timeout=timeout, on_progress=progress, force=force,
                             full=full)
    click.echo(f"map {map_id} built: revision {job.revision}, {job.n_extracted} images "
               "extracted", err=True)
    return job
