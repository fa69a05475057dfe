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


def stored_admin_key() -> str | None:
    """The key ``vloc serve`` generated on the embedded defaults, when it is readable here:
    ``$VLOC_DATA_DIR/admin_key`` (``./data/admin_key`` by default)."""
    path = Path(os.environ.get("VLOC_DATA_DIR") or "data") / "admin_key"
    try:
        return path.read_text().strip() or None
    except OSError:
        return None


def server_options(fn: Callable) -> Callable:
    """``--server`` and ``--admin-key``, from the flags or the environment."""
    fn = click.option("--admin-key", envvar="VLOC_ADMIN_KEY", metavar="KEY",
                      help="Admin API key [env VLOC_ADMIN_KEY; else the key the server "
                           "stored in $VLOC_DATA_DIR/admin_key, when readable].")(fn)
    fn = click.option("--server", envvar="VLOC_URL", default=DEFAULT_URL, show_default=True,
                      metavar="URL", help="Server address [env VLOC_URL].")(fn)
    return fn


def make_client(server: str, admin_key: str | None, **kwargs):
    from vloc.clients.sdk import Client

    return Client(server, admin_key=admin_key or stored_admin_key() or "", **kwargs)


def make_async_client(server: str, admin_key: str | None, **kwargs):
    from vloc.clients.sdk import AsyncClient

    return AsyncClient(server, admin_key=admin_key or stored_admin_key() or "", **kwargs)


def reports_errors(fn: Callable) -> Callable:
    """Turn client errors into one clear line on stderr and a non-zero exit status:
    1 for an error answer from the server, 3 when the server cannot be reached."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from vloc.clients.sdk import APIError, TransportError, Unauthorized, VlocError

        try:
            return fn(*args, **kwargs)
        except TransportError as exc:
            server = click.get_current_context().params.get("server", "the server")
            raise CommandError(f"cannot reach {server}: {exc}\n"
                               "Is `vloc serve` running there? Set --server or VLOC_URL.",
                               exit_code=3) from exc
        except Unauthorized as exc:
            raise CommandError(f"{exc}\nGive the admin key with --admin-key or "
                               "VLOC_ADMIN_KEY.") from exc
        except APIError as exc:
            raise CommandError(str(exc)) from exc
        except VlocError as exc:
            raise CommandError(str(exc)) from exc

    return wrapper


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


def build_with_bar(vloc, map_id: str, *, quiet: bool = False, timeout: float = 3600.0):
    """Build a map and wait for it behind a progress bar; returns the finished job."""
    from vloc.clients.sdk import Conflict

    try:
        return _build(vloc, map_id, quiet=quiet, timeout=timeout)
    except Conflict as exc:
        if exc.kind != "map-up-to-date":
            raise
        click.echo(f"map {map_id} is up to date: revision {exc.body.get('revision')} holds "
                   "every image", err=True)
        return None


def _build(vloc, map_id: str, *, quiet: bool, timeout: float):
    from tqdm import tqdm

    from vloc.clients.mapping import build_and_wait

    with tqdm(total=100, unit="%", desc="build", disable=no_bar(quiet),
              bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}") as bar:
        def progress(job) -> None:
            bar.update(round(100 * job.progress) - bar.n)

        job = build_and_wait(vloc, map_id, timeout=timeout, on_progress=progress)
    click.echo(f"map {map_id} built: revision {job.revision}, {job.n_extracted} images "
               "extracted", err=True)
    return job
