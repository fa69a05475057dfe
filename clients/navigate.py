"""Teach and repeat through the real service: ``vloc navigate``.

1. teach: render one drive round a street block of the robot world (with wheel odometry
   that drifts), upload its frames as a map, build it, and teach the route from the
   odometry CSV (:mod:`clients.world.teach`);
2. repeat: open a session that follows the route; a simulated robot (a unicycle with
   actuation noise) starts near the route's start, renders its camera, sends each frame
   to the service, and drives by the command that comes back with the pose, until the
   session says it has arrived;
3. measure the cross-track error of the true repeated path against the true taught path,
   and plot both.

Everything the robot knows comes from the service: the positions of its frames, the EKF
state and the commands. Only the evaluation reads the world's true poses.
"""

from __future__ import annotations

import contextlib
import math
import secrets
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SUBSTEPS = 10
"""Integration steps of the unicycle per frame interval."""
CONVERGED_M = 0.3
CONVERGED_RAD = math.radians(10.0)


class NavigateError(RuntimeError):
    """Teach or repeat could not run to the end; the message says why."""


@dataclass(frozen=True)
class NavigateOptions:
    """One teach-and-repeat run (see ``vloc navigate --help``)."""

    out: Path = Path("navigate-output")
    route_length: float = 60.0
    seed: int = 0
    mode: str = "hierarchical"
    params: dict = field(default_factory=dict)
    navigation: dict = field(default_factory=dict)
    taught_light: str = "sunny"
    repeat_light: str = "sunny"
    drift: float = 0.05
    offset_m: float = 0.0
    heading_deg: float = 0.0
    starts: int = 0
    start_travel_m: float = 12.0
    noise: tuple[float, float, float] = (0.05, 0.05, 0.01)
    url: str | None = None
    admin_key: str | None = None
    workers: int | None = None
    quiet: bool = False


@dataclass
class Run:
    """One repeat: true robot poses, the service's estimates and EKF states, commands."""

    truth: list[tuple[float, float, float]] = field(default_factory=list)
    estimates: list[tuple[float, float]] = field(default_factory=list)
    ekf: list[tuple[float, float, float]] = field(default_factory=list)
    commands: list[tuple[float, float]] = field(default_factory=list)
    travel: list[float] = field(default_factory=list)
    cross_track: list[float] = field(default_factory=list)
    heading_error: list[float] = field(default_factory=list)
    arrived: bool = False

    def converged_at(self) -> float | None:
        """Metres travelled when the robot came within 0.3 m and 10 degrees of the taught
        path and stayed within 0.3 m for the rest of the run (None if it never did)."""
        d = np.abs(np.asarray(self.cross_track))
        h = np.abs(np.asarray(self.heading_error))
        for k in range(len(d)):
            if d[k] < CONVERGED_M and h[k] < CONVERGED_RAD and (d[k:] < CONVERGED_M).all():
                return float(self.travel[k])
        return None


class Frames:
    """World frame (the robot world's east/north) to the map's frame, and back."""

    def __init__(self, world_origin, map_origin) -> None:
        self.world, self.map = world_origin, map_origin

    def to_map(self, x: float, y: float) -> tuple[float, float]:
        lat, lon = self.world.to_wgs84(x, y)
        e, n = self.map.to_local(lat, lon)
        return float(e), float(n)


def teach_over_http(client, drive, *, say: Callable[[str], None], quiet: bool = False):
    """Map and route from a taught drive: returns the map and the ready route."""
    from vloc.clients.commands._common import build_with_bar
    from vloc.clients.world.teach import odometry_csv

    m = client.create_map("teach and repeat")
    for k in range(0, len(drive.names), 50):
        part = list(zip(drive.names[k:k + 50], drive.jpegs[k:k + 50], strict=True))
        result = client.upload_images(m.id, part)
        if result.rejected:
            raise NavigateError(f"the server refused taught frames: {result.rejected[:3]}")
    build_with_bar(client, m.id, quiet=quiet)
    route = client.create_route(m.id, odometry_csv(drive.names, drive.odometry),
                                name="taught", max_step_m=5.0)
    route = client.wait_for_route(m.id, route.id)
    say(f"route: {route.n_images} frames, {route.n_nodes} nodes, {route.n_loops} loop(s), "
        f"{route.length_m:.1f} m")
    return client.get_map(m.id), route


def repeat(client, map_id: str, route_id: str, camera, taught: np.ndarray, start: np.ndarray,
           *, opts: NavigateOptions, rng: np.random.Generator, frames: Frames,
           max_frames: int, max_travel: float | None = None) -> Run:
    """Drive a simulated robot from ``start`` (world frame) by the session's commands.

    ``taught`` is the true taught path ((N, 3) world frame) the cross-track error is
    measured against.
    """
    import cv2

    from vloc.workers.core.navigation import ActuationNoise, Path, unicycle_step

    path = Path(taught[:, :2], smoothing=0.3)
    session = client.create_session(map_id, mode=opts.mode, params=opts.params,
                                    seed=opts.seed, navigation={"route_id": route_id,
                                                                "params": opts.navigation})
    noise = ActuationNoise(*opts.noise)
    pose = np.asarray(start, np.float64).copy()
    run, travel, s_hint = Run(), 0.0, None
    try:
        for k in range(max_frames):
            # a plain JPEG: the robot has no GPS, only its camera
            ok, jpeg = cv2.imencode(".jpg", camera.frame(*pose), [cv2.IMWRITE_JPEG_QUALITY, 90])
            if not ok:
                raise NavigateError("could not encode a frame")
            msg = client.send_frame(session, ("frame.jpg", jpeg.tobytes()), seq=k,
                                    captured_at=1.0e9 + k, wait=True)
            proj = path.project(pose[:2], s_hint=s_hint)
            s_hint = proj.s
            run.truth.append(tuple(float(v) for v in pose))
            run.travel.append(travel)
            run.cross_track.append(proj.d)
            run.heading_error.append(math.remainder(pose[2] - proj.theta, 2 * math.pi))
            run.estimates.append((msg.x, msg.y))
            nav = msg.navigation
            if nav is None:
                raise NavigateError(f"frame {k} came back without navigation")
            st = nav["state"]
            run.ekf.append((st["x"], st["y"], st["theta"]))
            cmd = (nav["command"]["v"], nav["command"]["omega"])
            run.commands.append(cmd)
            if nav["arrived"] or (max_travel is not None and travel >= max_travel):
                run.arrived = bool(nav["arrived"])
                break
            v, w = noise.apply(*cmd, rng)
            for _ in range(SUBSTEPS):
                pose = unicycle_step(pose, v, w, 1.0 / SUBSTEPS)
            travel += abs(v)
    finally:
        with contextlib.suppress(Exception):
            client.delete_session(session)
    return run


def offset_start(taught: np.ndarray, lateral: float, heading: float, *,
                 at: int = 0) -> np.ndarray:
    """The taught pose ``at`` moved ``lateral`` metres to the left and turned ``heading``
    radians."""
    x, y, th = taught[at]
    return np.array([x - lateral * math.sin(th), y + lateral * math.cos(th), th + heading])


def summarise(run: Run) -> dict:
    d = np.abs(np.asarray(run.cross_track))
    return {"frames": len(run.truth), "travel_m": float(run.travel[-1]) if run.travel else 0.0,
            "arrived": run.arrived, "mean_cross_track_m": float(d.mean()),
            "median_cross_track_m": float(np.median(d)), "max_cross_track_m": float(d.max()),
            "converged_at_m": run.converged_at()}


def plot(path: Path, taught: np.ndarray, runs: list[Run], frames: Frames | None,
         title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5.5),
                                  gridspec_kw={"width_ratios": [1.3, 1]})
    ax.plot(taught[:, 0], taught[:, 1], "k-", lw=2, label="taught (true)")
    for i, run in enumerate(runs):
        t = np.asarray(run.truth)
        ax.plot(t[:, 0], t[:, 1], "-", lw=1, color=f"C{i % 10}",
                label="repeated (true)" if i == 0 else None)
        ax2.plot(run.travel, run.cross_track, "-", lw=1, color=f"C{i % 10}")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    ax2.axhline(0.3, color="grey", lw=0.5, ls="--")
    ax2.axhline(-0.3, color="grey", lw=0.5, ls="--")
    ax2.set_xlabel("travelled (m)")
    ax2.set_ylabel("cross-track error (m, left +)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@contextlib.contextmanager
def service(opts: NavigateOptions, say: Callable[[str], None]) -> Iterator[tuple[str, str]]:
    """The server to talk to: ``opts.url``, or ``vloc serve`` started for the run."""
    from vloc.clients.demo import server_process

    if opts.url is not None:
        yield opts.url, opts.admin_key
        return
    data_dir = Path(tempfile.mkdtemp(prefix="vloc-navigate-", dir=opts.out))
    key = secrets.token_urlsafe(24)
    try:
        with server_process(data_dir, log_path=opts.out / "server.log", admin_key=key,
                            workers=opts.workers) as (url, pid):
            say(f"server: ready at {url} (pid {pid})")
            yield url, key
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def run_navigate(opts: NavigateOptions, say: Callable[[str], None] = print) -> dict:
    """Teach, repeat from the route's start (and from ``opts.starts`` random offset starts),
    measure and plot; returns the results."""
    from vloc.clients.sdk import Client
    from vloc.clients.world.teach import TeachWorld
    from vloc.workers.core.geo import GeoOrigin

    opts.out.mkdir(parents=True, exist_ok=True)
    world = TeachWorld(opts.seed, opts.route_length)
    drive = world.teach(light=opts.taught_light, drift=opts.drift)
    say(f"teach: {len(drive.names)} frames round a {world.route.length:.0f} m block")
    rng = np.random.default_rng(opts.seed + 1)
    results: dict = {"options": {k: (str(v) if isinstance(v, Path) else v)
                                 for k, v in opts.__dict__.items() if k != "admin_key"}}
    with service(opts, say) as (url, key), Client(url, admin_key=key) as client:
        m, route = teach_over_http(client, drive, say=say, quiet=opts.quiet)
        frames = Frames(world.origin, GeoOrigin(m.origin.lat, m.origin.lon, m.origin.alt))
        camera = world.camera(opts.repeat_light)
        taught = drive.poses
        start = offset_start(taught, opts.offset_m, math.radians(opts.heading_deg))
        main = repeat(client, m.id, route.id, camera, taught, start, opts=opts, rng=rng,
                      frames=frames, max_frames=int(1.5 * len(taught)) + 30)
        results["repeat"] = summarise(main)
        say(f"repeat: {results['repeat']['frames']} frames, arrived "
            f"{results['repeat']['arrived']}, cross-track mean "
            f"{results['repeat']['mean_cross_track_m']:.2f} m, max "
            f"{results['repeat']['max_cross_track_m']:.2f} m")
        runs = [main]
        starts = []
        # the starts are drawn apart from the actuation noise, so that they are the same
        # starts whatever the runs before them did
        where = np.random.default_rng(opts.seed + 2)
        for i in range(opts.starts):
            side = where.choice([-1.0, 1.0])
            turn = where.choice([-1.0, 1.0])
            at = int(where.integers(5, max(6, len(taught) - 40)))
            st = offset_start(taught, side * 1.0, turn * math.radians(20.0), at=at)
            run = repeat(client, m.id, route.id, camera, taught, st, opts=opts, rng=rng,
                         frames=frames, max_frames=int(opts.start_travel_m / 0.3) + 10,
                         max_travel=opts.start_travel_m)
            conv = run.converged_at()
            starts.append({"start_image": at, "lateral_m": side, "heading_deg": turn * 20.0,
                           "converged_at_m": conv, **summarise(run)})
            say(f"start {i + 1}/{opts.starts}: image {at}, {side:+.0f} m, {turn * 20:+.0f} deg: "
                + (f"converged after {conv:.1f} m" if conv is not None else "did not converge"))
            runs.append(run)
        if starts:
            ok = [s for s in starts if s["converged_at_m"] is not None
                  and s["converged_at_m"] <= 5.0]
            results["starts"] = {"runs": starts, "n": len(starts),
                                 "success_rate": len(ok) / len(starts),
                                 "median_converged_at_m": float(np.median(
                                     [s["converged_at_m"] for s in starts
                                      if s["converged_at_m"] is not None] or [float("nan")]))}
            say(f"starts: {len(ok)}/{len(starts)} converged within 5 m")
    results["plot"] = str(plot(opts.out / "navigate.png", drive.poses, runs, frames,
                               f"{opts.mode}: taught vs repeated, {world.route.length:.0f} m"))
    return results
