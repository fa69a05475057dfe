"""``vloc session``: open, inspect and close localisation sessions; send frames; watch poses."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import click

from vloc.clients.commands._common import (
    CommandError,
    make_client,
    model_json,
    parse_params,
    print_json,
    reports_errors,
    server_options,
)
from vloc.workers.core.modes import MODES

token_option = click.option("--token", envvar="VLOC_SESSION_TOKEN", metavar="TOKEN",
                            help="The session's token [env VLOC_SESSION_TOKEN; else the "
                                 "admin key].")


@click.group("session")
def session_group() -> None:
    """Localisation sessions: a device's filter on one map.

    `vloc session create MAP_ID` prints the session id and its token (shown once); frames
    and the pose stream take either that token or the admin key.
    """


def _describe(s) -> str:
    st = s.stats
    follows = {True: ", follows the map", False: ", stays on it"}.get(s.follows_map, "")
    lines = [f"{s.id}  mode {s.mode} on map {s.map_id} (revision {s.map_revision}"
             f"{follows}), seed {s.seed}",
             f"  frames: {s.frames_processed} processed, {s.frames_failed} failed, "
             f"{s.frames_pending} pending; last seq {s.last_seq}"]
    if st.sift_share is not None:
        lines.append(f"  SIFT steps {100 * st.sift_share:.1f} %, processing "
                     f"{st.processing_ms_mean:.1f} ms/frame, latency p50 "
                     f"{st.latency_ms_p50:.0f} ms, p99 {st.latency_ms_p99:.0f} ms")
    if s.last_pose is not None:
        p = s.last_pose
        lines.append(f"  last pose: seq {p.seq} at {p.lat:.6f}, {p.lon:.6f} "
                     f"(x {p.x:.1f} m, y {p.y:.1f} m, sigma {p.sigma_x:.1f}/{p.sigma_y:.1f} m,"
                     f" {p.feature}, {p.status})")
    return "\n".join(lines)


@session_group.command("create")
@click.argument("map_id")
@click.option("--mode", type=click.Choice(MODES), default="hybrid", show_default=True)
@click.option("--param", "param_items", multiple=True, metavar="KEY=VALUE",
              help="A localiser parameter (JSON value), e.g. n_particles=500.")
@click.option("--seed", type=click.IntRange(0), help="Random seed [default: random].")
@click.option("--ttl", "ttl_s", type=click.IntRange(10), metavar="SECONDS",
              help="Seconds without a frame or keep-alive after which the session expires "
                   "[default: the server's, VLOC_SESSION_TTL_S].")
@click.option("--revision", "map_revision", type=click.IntRange(1), metavar="N",
              help="Localise against this revision of the map and stay on it [default: the "
                   "current one, followed as the map is rebuilt or restored].")
@click.option("--no-follow", "no_follow", is_flag=True,
              help="Stay on the revision the session starts on when the map is rebuilt or "
                   "restored.")
@click.option("--json", "as_json", is_flag=True)
@server_options
@reports_errors
def create_cmd(map_id: str, mode: str, param_items, seed, ttl_s, map_revision, no_follow,
               as_json: bool, server: str, admin_key: str | None) -> None:
    """Open a session on a built map. Prints `ID TOKEN`.

    The session follows the map: when the map is rebuilt or restored, it moves to the new
    revision between two frames, keeping what its filter has learnt."""
    with make_client(server, admin_key) as vloc:
        s = vloc.create_session(map_id, mode=mode, params=parse_params(param_items), seed=seed,
                                ttl_s=ttl_s, map_revision=map_revision,
                                follow_map=False if no_follow else None)
    print_json(model_json(s)) if as_json else click.echo(f"{s.id} {s.token}")


@session_group.command("list")
@click.option("--json", "as_json", is_flag=True)
@server_options
@reports_errors
def list_cmd(as_json: bool, server: str, admin_key: str | None) -> None:
    """List the sessions."""
    with make_client(server, admin_key) as vloc:
        sessions = vloc.list_sessions()
    if as_json:
        print_json(model_json(sessions))
        return
    if not sessions:
        click.echo("no sessions")
    for s in sessions:
        click.echo(f"{s.id}  {s.mode:<12} map {s.map_id}  {s.frames_processed} frames")


@session_group.command("show")
@click.argument("session_id")
@click.option("--json", "as_json", is_flag=True)
@token_option
@server_options
@reports_errors
def show_cmd(session_id: str, as_json: bool, token, server: str, admin_key) -> None:
    """Show a session: counters, statistics, last pose."""
    with make_client(server, admin_key) as vloc:
        s = vloc.get_session(session_id, token=token)
    print_json(model_json(s)) if as_json else click.echo(_describe(s))


@session_group.command("delete")
@click.argument("session_id")
@token_option
@server_options
@reports_errors
def delete_cmd(session_id: str, token, server: str, admin_key) -> None:
    """Close a session (its streams end)."""
    with make_client(server, admin_key) as vloc:
        vloc.delete_session(session_id, token=token)
    click.echo(f"deleted session {session_id}")


@session_group.command("reset")
@click.argument("session_id")
@token_option
@server_options
@reports_errors
def reset_cmd(session_id: str, token, server: str, admin_key) -> None:
    """Global re-initialisation: particles spread over the whole map again."""
    with make_client(server, admin_key) as vloc:
        vloc.reset_session(session_id, token=token)
    click.echo(f"reset session {session_id}")


@session_group.command("initial-pose")
@click.argument("session_id")
@click.option("--lat", type=float)
@click.option("--lon", type=float)
@click.option("--x", type=float, help="East, metres in the map's frame.")
@click.option("--y", type=float, help="North, metres in the map's frame.")
@click.option("--sigma", type=float, default=5.0, show_default=True, help="Metres.")
@token_option
@server_options
@reports_errors
def initial_pose_cmd(session_id: str, lat, lon, x, y, sigma: float, token, server: str,
                     admin_key) -> None:
    """Restart the filter around a known position (--lat/--lon or --x/--y)."""
    geo, local = (lat, lon) != (None, None), (x, y) != (None, None)
    if geo == local or None in ((lat, lon) if geo else (x, y)):
        raise click.UsageError("give --lat and --lon, or --x and --y")
    with make_client(server, admin_key) as vloc:
        vloc.set_initial_pose(session_id, lat=lat, lon=lon, x=x, y=y, sigma=sigma,
                              token=token)
    click.echo(f"initial pose set on session {session_id}")


@session_group.command("send")
@click.argument("session_id")
@click.argument("images", nargs=-1, required=True,
                type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--seq", type=click.IntRange(0), help="Sequence number of the first image.")
@click.option("--captured-at", "captured_at", multiple=True, metavar="TIME",
              help="Capture time: ISO 8601 or seconds since the epoch, once per image in "
                   "order, or once with --interval; 'exif' reads each image's EXIF time. "
                   "The motion model needs it to know how far the device may have moved.")
@click.option("--interval", type=click.FloatRange(0, min_open=True), metavar="SECONDS",
              help="With one --captured-at: the time between consecutive images.")
@click.option("--wait/--no-wait", default=True, show_default=True,
              help="Print each frame's estimate (else only its sequence number).")
@token_option
@server_options
@reports_errors
def send_cmd(session_id: str, images, seq, captured_at, interval, wait: bool, token,
             server: str, admin_key) -> None:
    """Send IMAGES (JPEG/PNG) as frames, in order; prints one JSON line per frame."""
    times = capture_times(images, captured_at, interval)
    with make_client(server, admin_key) as vloc:
        for i, path in enumerate(images):
            got = vloc.send_frame(session_id, path, seq=None if seq is None else seq + i,
                                  captured_at=times[i], wait=wait, token=token)
            click.echo(json.dumps(got.model_dump(mode="json") | {"file": path.name}))


def capture_times(images, given: tuple[str, ...], interval: float | None) -> list:
    """One capture time (or None) per image from ``--captured-at`` and ``--interval``."""
    if not given:
        if interval is not None:
            raise click.UsageError("--interval needs a --captured-at for the first image")
        return [None] * len(images)
    if given == ("exif",):
        from vloc.workers.core.exif import GpsError, read_gps

        times = []
        for path in images:
            try:
                tag = read_gps(path.read_bytes())
            except (GpsError, ValueError):
                tag = None
            if tag is None or tag.captured_at is None:
                raise click.UsageError(f"{path.name} has no EXIF capture time")
            times.append(tag.captured_at)
        return times
    parsed = [_parse_time(t) for t in given]
    if len(parsed) == len(images) and interval is None:
        return parsed
    if len(parsed) == 1 and interval is not None:
        return [parsed[0] + timedelta(seconds=i * interval) for i in range(len(images))]
    raise click.UsageError(f"{len(parsed)} --captured-at for {len(images)} images: give one "
                           "per image, or one with --interval")


def _parse_time(text: str) -> datetime:
    try:
        return datetime.fromtimestamp(float(text), UTC)
    except ValueError:
        pass
    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        raise click.BadParameter(f"{text!r} is neither ISO 8601 nor seconds since the epoch",
                                 param_hint="--captured-at") from None
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


@session_group.command("watch")
@click.argument("session_id")
@click.option("--count", type=click.IntRange(1), help="Stop after this many messages.")
@click.option("--timeout", type=click.FloatRange(0, min_open=True), metavar="SECONDS",
              help="Give up when no message comes for this long [default: wait for ever; "
                   "60 s with --count].")
@token_option
@server_options
@reports_errors
def watch_cmd(session_id: str, count, timeout, token, server: str, admin_key) -> None:
    """Print the session's pose stream, one JSON line per message, until it ends (or
    --count messages came, or none came for --timeout seconds)."""
    from vloc.clients.sdk import (
        FrameRejected,
        ServerShutdown,
        SessionDeleted,
        SessionExpired,
        WaitTimeout,
    )

    if timeout is None and count is not None:
        timeout = 60.0
    n = 0
    try:
        with make_client(server, admin_key) as vloc, \
                vloc.stream(session_id, token=token, timeout=timeout) as poses:
            for msg in poses:
                n += 1
                data = ({"type": "error", "problem": msg.error.body}
                        if isinstance(msg, FrameRejected) else msg.model_dump(mode="json"))
                click.echo(json.dumps(data), nl=True)
                if count is not None and n >= count:
                    return
    except WaitTimeout:
        raise CommandError(f"no message for {timeout:g} s after {n}"
                           + (f" of {count}" if count else "") + " messages") from None
    except (SessionDeleted, SessionExpired, ServerShutdown) as exc:
        why = {SessionDeleted: "the session was deleted", SessionExpired:
               "the session expired (create a new one: vloc session create MAP_ID)",
               ServerShutdown: "the server is stopping"}[type(exc)]
        click.echo(f"stream ended: {why}" + (f" after {n} of {count} messages" if count
                                             else ""), err=True)
        if count is not None or not isinstance(exc, SessionDeleted):
            raise SystemExit(1) from None
        return
    click.echo("stream ended" + (f" after {n} of {count} messages" if count else ""),
               err=True)
    if count is not None:
        raise SystemExit(1)


