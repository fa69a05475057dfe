"""The one-command demo: a synthetic world, a real server, a device, a table and a plot.

1. generate a street world seen by a ground robot: a map pass in sunshine and a query
   pass of the same route under another illumination (:func:`clients.world.generate_world`);
2. start ``vloc serve`` as a child process on a free port, with a temporary data folder
   (SQLite and a local worker pool: the embedded defaults), and wait for ``/readyz``;
3. create a map, upload the map pass over HTTP and build it;
4. replay the query pass as a device, once per localiser (hybrid, global, sift);
5. print the table, write ``tracks.png`` and ``results.json``, stop the server.

The server is stopped on every way out (success, error, Ctrl-C): SIGTERM, a grace period
for uvicorn to drain, then SIGKILL.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from vloc.workers.core.modes import FILTER_MODES

DEMO_MODES = FILTER_MODES
STOP_GRACE_S = 20.0


class DemoError(RuntimeError):
    """The demo could not run to the end; the message says where and why."""


@dataclass(frozen=True)
class DemoOptions:
    """Sizes and choices of one demo run (see ``vloc demo --help``)."""

    out: Path = Path("demo-output")
    frames: int = 200
    seed: int = 0
    query_light: str = "cloudy"
    config: str = "weiss2008"
    workers: int | None = None
    port: int | None = None
    """The server's port on 127.0.0.1; a free one when None."""
    keep: bool = False
    quiet: bool = False


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def server_process(data_dir: Path, *, log_path: Path, admin_key: str,
                   workers: int | None = None, port: int | None = None,
                   ready_timeout: float = 180.0) -> Iterator[tuple[str, int]]:
    """Run ``vloc serve`` on the embedded defaults in ``data_dir``; yields its base URL and
    process id.

    Raises
    ------
    DemoError
        The server exited or was not ready in time (the end of its log is in the message).
    """
    from vloc.clients.sdk import Client, WaitTimeout

    port = port or free_port()
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("VLOC_") or k == "VLOC_SHARED_DIR"}
    env.update(VLOC_DATA_DIR=str(data_dir), VLOC_ADMIN_KEY=admin_key, VLOC_LOG_JSON="false",
               VLOC_LOG_LEVEL="WARNING")
    cmd = [sys.executable, "-m", "vloc.clients.cli", "serve", "--host", "127.0.0.1",
           "--port", str(port)]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    url = f"http://127.0.0.1:{port}"
    with open(log_path, "ab") as log:
        # A session of its own: the terminal's Ctrl-C reaches only us, and we stop the
        # server in order (drain, then the workers) below.
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            with Client(url, admin_key=admin_key, retry=0) as probe:
                deadline = time.monotonic() + ready_timeout
                while True:
                    if proc.poll() is not None:
                        raise DemoError(f"the server exited with status {proc.returncode}:\n"
                                        + _tail(log_path))
                    try:
                        probe.wait_ready(timeout=0.5, interval=0.1)
                        break
                    except WaitTimeout as exc:
                        if time.monotonic() > deadline:
                            raise DemoError(f"the server was not ready within "
                                            f"{ready_timeout:g} s:\n" + _tail(log_path)
                                            ) from exc
            yield url, proc.pid
        finally:
            # a second Ctrl-C while the server drains would cut the wait short and leave
            # the server running on its own: it is held off until the server has stopped
            with ctrl_c_held():
                stop_process(proc)


@contextlib.contextmanager
def ctrl_c_held() -> Iterator[None]:
    """SIGINT ignored inside the block, its handler put back after (a no-op outside the main
    thread, where signal handlers cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def stop_process(proc: subprocess.Popen, grace: float = STOP_GRACE_S) -> int:
    """SIGTERM, wait up to ``grace`` seconds, then SIGKILL; returns the exit status."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            proc.wait()
    return proc.returncode


def _tail(path: Path, lines: int = 25) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no server log)"


FRAME_SPACING_M = 0.65
"""Metres between frames, as in Weiss et al.'s robot runs (about 400 images on 260 m): 200
frames go once round a 130 m block; fewer frames go round a smaller block at the same
spacing, so a reduced demo keeps the density of views the localisers see."""

MIN_ROUTE_M = 60.0


def route_length(frames: int) -> float:
    """The loop's length for ``frames`` frames per pass."""
    return max(MIN_ROUTE_M, frames * FRAME_SPACING_M)


def make_world(folder: Path, opts: DemoOptions, say: Callable[[str], None]) -> Path:
    """The synthetic world, reused when ``folder`` already holds one of the same recipe."""
    from tqdm import tqdm

    from vloc.clients.world import generate_world

    recipe = {"kind": "robot", "seed": opts.seed, "passes": ["sunny", opts.query_light],
              "frames": opts.frames, "route_length": route_length(opts.frames)}
    stamp = folder / "demo-recipe.json"
    if stamp.exists() and json.loads(stamp.read_text()) == recipe:
        say(f"world: reusing {folder}")
        return folder
    with tqdm(total=2 * opts.frames, unit="img", desc="world",
              disable=opts.quiet or not sys.stderr.isatty()) as bar:
        info = generate_world(folder, kind="robot", seed=opts.seed,
                              passes=recipe["passes"], frames=opts.frames,
                              route_length=recipe["route_length"], overwrite=True,
                              progress=lambda done, total: bar.update(done - bar.n))
    stamp.write_text(json.dumps(recipe))
    say(f"world: {info.images} images, {info.route_length_m:.0f} m loop, "
        f"{info.frame_spacing_m:.1f} m between frames, passes {', '.join(info.passes)}")
    return folder


def run_demo(opts: DemoOptions, say: Callable[[str], None] = print) -> dict:
    """Run the whole demo; returns the results (as written to ``results.json``).

    Raises
    ------
    DemoError
    """
    out = opts.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    world = make_world(out / "world", opts, say)
    t_world = time.perf_counter() - t0
    data_dir = Path(tempfile.mkdtemp(prefix="vloc-demo-", dir=out))
    admin_key = secrets.token_urlsafe(24)
    try:
        say("server: starting `vloc serve` on the embedded defaults (SQLite, local workers)")
        with server_process(data_dir, log_path=out / "server.log", admin_key=admin_key,
                            workers=opts.workers, port=opts.port) as (url, pid):
            say(f"server: ready at {url} (pid {pid})")
            say(f"viewer: {url}/ui/ (sign in with the admin key {admin_key})")
            results = _against_server(url, admin_key, world, opts, say)
            results["timings_s"].update(world=t_world, total=time.perf_counter() - t0)
            (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
            if opts.keep:
                say(f"server: kept running for the viewer at {url}/ui/ (data in "
                    f"{data_dir}); Ctrl-C stops it")
                hold_server(url)
        say("server: stopped")
    finally:
        if not opts.keep:
            shutil.rmtree(data_dir, ignore_errors=True)
    return results


def hold_server(url: str, poll_s: float = 1.0) -> None:
    """Return on Ctrl-C, or once the server at ``url`` stops answering."""
    import httpx

    try:
        while True:
            try:
                httpx.get(url + "/healthz", timeout=5.0)
            except httpx.TransportError:
                return
            time.sleep(poll_s)
    except KeyboardInterrupt:
        return


def _against_server(url: str, admin_key: str, world: Path, opts: DemoOptions,
                    say: Callable[[str], None]) -> dict:
    import asyncio

    import numpy as np
    from tqdm import tqdm

    from vloc.clients._replay_data import load_replay_data
    from vloc.clients._replay_report import mode_table, plot_replay, replay_tracks, summarise
    from vloc.clients.commands._common import build_with_bar
    from vloc.clients.mapping import import_images
    from vloc.clients.replay import replay_async
    from vloc.clients.sdk import AsyncClient, Client
    from vloc.workers.core.geo import GeoOrigin

    data = load_replay_data(world, map_pass=1, query_pass=2)
    with Client(url, admin_key=admin_key) as vloc:
        m = vloc.create_map("demo street")
        with tqdm(total=len(data.map_images), unit="img", desc="upload",
                  disable=opts.quiet or not sys.stderr.isatty()) as bar:
            summary = import_images(vloc, m.id, data.map_images,
                                    on_progress=lambda n, s: bar.update(n))
        if summary.accepted != len(data.map_images):
            raise DemoError(f"the server refused {len(summary.rejected)} map images: "
                            f"{summary.rejected[:3]}")
        t = time.perf_counter()
        build_with_bar(vloc, m.id, quiet=opts.quiet)
        t_build = time.perf_counter() - t
        m = vloc.get_map(m.id)
        map_xy = np.array([(i.east, i.north) for i in vloc.list_images(m.id)])
    origin = GeoOrigin(m.origin.lat, m.origin.lon, m.origin.alt)
    say(f"map: {m.image_count} images built in {t_build:.1f} s; replaying "
        f"{len(data.frames)} frames ({opts.query_light}) per localiser")
    say(config_note(opts.config))

    with tqdm(total=len(data.frames) * len(DEMO_MODES), unit="frame", desc="replay",
              disable=opts.quiet or not sys.stderr.isatty()) as bar:
        async def main():
            async with AsyncClient(url, admin_key=admin_key) as client:
                return await replay_async(
                    client, m.id, data.frames, modes=list(DEMO_MODES), seed=opts.seed,
                    params={"config": opts.config}, rate="max",
                    on_answer=lambda run, msg: (bar.update(1), bar.set_postfix_str(
                        run.mode, refresh=False)))

        t = time.perf_counter()
        runs = asyncio.run(main())
        t_replay = time.perf_counter() - t
    skip = min(10, max(len(data.frames) // 10, 1))
    results = summarise(runs, data.frames, origin, skip=skip)
    plot = plot_replay(opts.out / "tracks.png", map_xy, runs, data.frames, origin,
                       title=f"demo: sunny map, {opts.query_light} query "
                             f"({len(data.frames)} frames, {opts.config})",
                       skip=skip, config=opts.config)
    say("")
    say(mode_table(results))
    say("")
    say(verdict(results))
    say(f"tracks: {plot}")
    results.update(replay_tracks(map_xy, runs, data.frames, origin, config=opts.config))
    results.update(map_id=m.id, frames=len(data.frames), skip=skip,
                   query_light=opts.query_light, config=opts.config, plot=str(plot),
                   timings_s={"build": t_build, "replay": t_replay})
    return results


def config_note(config: str) -> str:
    """Which filter configuration the sessions run, beside the service's own default."""
    if config == "default":
        return "sessions: filter configuration default (the service's default)"
    return (f"sessions: filter configuration {config}; the service's default is `default` "
            "(vloc demo --config default to compare)")


def verdict(results: dict) -> str:
    """One line: hybrid's error relative to SIFT-only, and its share of SIFT's time."""
    hybrid, sift = results["modes"].get("hybrid"), results["modes"].get("sift")
    if not hybrid or not sift or not sift["mean_error_m"] or not hybrid["ms_per_frame"]:
        return "hybrid vs sift: not enough estimates to compare"
    rel = (hybrid["mean_error_m"] - sift["mean_error_m"]) / sift["mean_error_m"]
    return (f"hybrid vs sift-only: mean error {hybrid['mean_error_m']:.1f} m vs "
            f"{sift['mean_error_m']:.1f} m ({100 * rel:+.0f} %), "
            f"{hybrid['ms_per_frame']:.1f} vs {sift['ms_per_frame']:.1f} ms per frame "
            f"({sift['ms_per_frame'] / hybrid['ms_per_frame']:.1f}x faster), "
            f"SIFT on {100 * hybrid['sift_step_share']:.0f} % of hybrid's steps")
