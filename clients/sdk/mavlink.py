"""A MAVLink autopilot fed by vloc: frames from a camera or a folder go to a session with the
autopilot's heading, altitude and velocity as their metadata, and each pose goes back to the
autopilot as ``GPS_INPUT`` or, by option, as a local-frame ``VISION_POSITION_ESTIMATE`` or
``ODOMETRY``.

>>> from vloc_client import Client                                   # doctest: +SKIP
>>> from vloc_client.mavlink import Bridge, Link, folder_frames
>>> with Client(URL) as vloc, Link("udpout:127.0.0.1:14550") as link:
...     Bridge(vloc, SESSION_ID, TOKEN, link).run(folder_frames(Path("flight")))

What it never sends: a position while the pose is not ``tracking`` (initialising or lost),
a pose older than ``max_pose_age_s`` from the frame's capture (a slow answer, a service
that was restarting, a link that was down), or more than ``max_rate_hz`` messages a second.
A link that drops and comes back, or a service that restarts, costs the frames of the gap
and nothing else: they are never queued and sent late. docs/devices/mavlink.md has the
autopilot's side (ArduPilot and PX4 parameters).

Needs the optional extra ``mavlink`` (pymavlink); reading a camera needs OpenCV.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ._exceptions import APIError, ServerError, TooManyRequests, TransportError
from ._frame_sources import Frame, camera_frames, folder_frames
from ._mavlink_link import MISSING_PYMAVLINK, Link, Telemetry
from ._mavlink_messages import (
    RateLimiter,
    gps_input,
    map_origin,
    odometry,
    vision_position_estimate,
)

__all__ = ["Bridge", "BridgeOptions", "Frame", "Link", "Telemetry", "camera_frames",
           "folder_frames", "main"]

Output = Literal["gps", "vision", "odometry"]
MESSAGES: dict[str, str] = {"gps": "GPS_INPUT", "vision": "VISION_POSITION_ESTIMATE",
                            "odometry": "ODOMETRY"}


@dataclass(frozen=True)
class BridgeOptions:
    """How the bridge runs; every field has the command line's default."""

    output: Output = "gps"
    fps: float = 2.0
    """Frames sent a second, at most (a slower service answer slows them)."""
    max_rate_hz: float = 5.0
    """Messages to the autopilot a second, at most."""
    max_pose_age_s: float = 2.0
    """A pose this long after its frame's capture is stale, and is not sent."""
    telemetry_max_age_s: float = 1.0
    """Autopilot values older than this are not given to frames."""
    heading_offset_deg: float = 0.0
    """The bearing of the image's top edge minus the vehicle's yaw (the camera's mount)."""
    heading_accuracy_deg: float | None = None
    gps_id: int = 0


@dataclass
class BridgeStats:
    frames: int = 0
    sent: int = 0
    skipped: dict[str, int] = field(default_factory=dict)


class Bridge:
    """Frames in, poses out to the autopilot; see the module's description.

    Parameters
    ----------
    client : Client
        The vloc client (its retries are not used: a frame sent again is a stale frame).
    session_id, token : str
        The session the frames go to, and its token (None: the client's admin key).
    link : Link
        The started MAVLink connection.
    log : callable, optional
        Called with one dictionary per frame: its ``seq``, the pose's ``status``, what was
        ``sent`` (the message's name and fields) or ``why`` nothing was.
    """

    def __init__(self, client, session_id: str, token: str | None, link: Link,
                 options: BridgeOptions = BridgeOptions(), *,
                 log: Callable[[dict[str, Any]], None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.client, self.session_id, self.token = client, session_id, token
        self.link, self.options = link, options
        self._log = log or (lambda record: None)
        self._clock, self._sleep = clock, sleep
        self._limiter = RateLimiter(options.max_rate_hz, clock)
        self._origin_sent_for_link = False
        self._was_alive = False
        self._tracked = False
        self._lost_since_tracked = False
        self._reset_counter = 0
        self.stats = BridgeStats()

    def run(self, frames: Iterable[Frame], *, limit: int | None = None) -> BridgeStats:
        """Send ``frames`` at ``options.fps`` (at most ``limit`` of them)."""
        period = 1.0 / self.options.fps
        due = self._clock()
        for i, frame in enumerate(frames):
            if limit is not None and i >= limit:
                break
            self.step(frame)
            due = max(due + period, self._clock() - period)  # a slow step is not caught up
            if (wait := due - self._clock()) > 0:
                self._sleep(wait)
        return self.stats

    def step(self, frame: Frame) -> dict[str, Any]:
        """One frame: sent to the session, its pose to the autopilot where it may go."""
        self.stats.frames += 1
        o = self.options
        meta = self.link.telemetry().metadata(
            now=self._clock(), max_age_s=o.telemetry_max_age_s,
            heading_offset_deg=o.heading_offset_deg, heading_accuracy_deg=o.heading_accuracy_deg)
        record: dict[str, Any] = {"frame": frame.name, "metadata": meta}
        try:
            pose = self.client.send_frame(self.session_id, (frame.name, frame.data), wait=True,
                                          captured_at=frame.captured_at or frame.taken_at,
                                          metadata=meta, token=self.token)
        except (TransportError, ServerError, TooManyRequests) as exc:
            return self._skip(record, f"service: {exc}")
        except APIError as exc:
            if not (exc.kind or "").startswith("frame-"):
                raise  # the session is gone or refuses us: nothing later will do better
            return self._skip(record, f"frame refused: {exc.kind}")
        record |= {"seq": pose.seq, "status": pose.status}
        self._note_status(pose.status)
        age = self._clock() - frame.read_at
        record["age_s"] = round(age, 3)
        if age > o.max_pose_age_s:
            return self._skip(record, "stale")
        fields = self._message(pose, frame)
        if fields is None:
            return self._skip(record, f"no fix: {pose.status}")
        if not self._link_up(pose):
            return self._skip(record, "link down")
        if not self._limiter.allow():
            return self._skip(record, "rate")
        self.link.send(MESSAGES[o.output], fields)
        self.stats.sent += 1
        record["sent"] = {"message": MESSAGES[o.output], **_plain(fields)}
        self._log(record)
        return record

    # -- pieces ---------------------------------------------------------------------------

    def _skip(self, record: dict[str, Any], why: str) -> dict[str, Any]:
        key = why.split(":")[0]
        self.stats.skipped[key] = self.stats.skipped.get(key, 0) + 1
        record["why"] = why
        self._log(record)
        return record

    def _note_status(self, status: str) -> None:
        # a jump in the local frame (lost, then found elsewhere) is a reset for the autopilot
        if status == "tracking":
            if self._lost_since_tracked:
                self._reset_counter = (self._reset_counter + 1) % 256
            self._tracked, self._lost_since_tracked = True, False
        elif self._tracked:
            self._lost_since_tracked = True

    def _message(self, pose, frame: Frame) -> dict[str, Any] | None:
        if self.options.output == "gps":
            return gps_input(pose, at=frame.taken_at, gps_id=self.options.gps_id)
        usec = int(frame.taken_at.timestamp() * 1e6)
        build = vision_position_estimate if self.options.output == "vision" else odometry
        return build(pose, usec=usec, reset_counter=self._reset_counter)

    def _link_up(self, pose) -> bool:
        alive = self.link.alive()
        if alive and not self._was_alive:
            self._origin_sent_for_link = False  # a restarted autopilot forgot its origin
        self._was_alive = alive
        if alive and self.options.output != "gps" and not self._origin_sent_for_link:
            lat, lon = map_origin(pose)
            self.link.send("SET_GPS_GLOBAL_ORIGIN", {
                "target_system": self.link.target_system, "latitude": round(lat * 1e7),
                "longitude": round(lon * 1e7),
                "altitude": round((pose.altitude_m or 0.0) * 1000), "time_usec": 0})
            self._origin_sent_for_link = True
        return alive


def _plain(fields: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in fields.items() if k not in ("covariance", "pose_covariance",
                                                           "velocity_covariance")}


# -- the command line ---------------------------------------------------------------------

def parser(prog: str = "vloc-mavlink") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description="Localise a MAVLink vehicle: frames from SOURCE go to a vloc "
        "session with the autopilot's heading, altitude and velocity; each tracking pose "
        "goes to the autopilot (GPS_INPUT, or a local-frame estimate).")
    p.add_argument("source", help="a folder of JPEG/PNG images; or, with OpenCV, a camera "
                                  "index (0), a device path (/dev/video0), a stream URL "
                                  "(rtsp://...) or a video file (played at its frame rate)")
    p.add_argument("--mavlink", required=True, metavar="ADDRESS",
                   help="the autopilot: udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or "
                        "a serial device (/dev/ttyAMA0,921600)")
    p.add_argument("--server", default=os.environ.get("VLOC_URL", "http://127.0.0.1:8000"),
                   help="vloc server [env VLOC_URL; default %(default)s]")
    p.add_argument("--session", metavar="ID", help="the session to send frames to")
    p.add_argument("--token", default=os.environ.get("VLOC_SESSION_TOKEN"),
                   help="its token [env VLOC_SESSION_TOKEN]")
    p.add_argument("--map", metavar="MAP_ID",
                   help="open a new session on this map instead (needs the admin key)")
    p.add_argument("--admin-key", default=os.environ.get("VLOC_ADMIN_KEY"),
                   help="[env VLOC_ADMIN_KEY]")
    p.add_argument("--output", choices=sorted(MESSAGES), default="gps",
                   help="gps: GPS_INPUT (default); vision: VISION_POSITION_ESTIMATE; "
                        "odometry: ODOMETRY (both in the map's frame, north-east-down)")
    p.add_argument("--fps", type=float, default=2.0, help="frames a second (default 2)")
    p.add_argument("--max-rate", type=float, default=5.0,
                   help="messages to the autopilot a second, at most (default 5)")
    p.add_argument("--max-age", type=float, default=2.0,
                   help="seconds from a frame's capture after which its pose is not sent "
                        "(default 2)")
    p.add_argument("--frame-interval", type=float, metavar="SECONDS",
                   help="folder: the seconds between the images' captures, when they are "
                        "played at another rate than they were taken")
    p.add_argument("--heading-offset", type=float, default=0.0, metavar="DEG",
                   help="the image top edge's bearing minus the vehicle's yaw")
    p.add_argument("--heading-accuracy", type=float, metavar="DEG",
                   help="the compass's standard deviation to report with the heading")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("--loop", action="store_true", help="folder: play it over and over")
    p.add_argument("--log", metavar="FILE", help="one JSON line per frame ('-': stdout)")
    return p


SECRET_OPTIONS = ("--token", "--admin-key")


def _attached(argv: list[str]) -> list[str]:
    """``--token VALUE`` as ``--token=VALUE``: a token is URL-safe base64, which starts
    with ``-`` one time in 64, and argparse takes such a value only attached."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in SECRET_OPTIONS:
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv: list[str] | None = None, *, prog: str = "vloc-mavlink",
         admin_key: str | None = None) -> int:
    args = parser(prog).parse_args(_attached(sys.argv[1:] if argv is None else argv))
    if (args.session is None) == (args.map is None):
        print(f"{prog}: give --session ID (with --token) or --map MAP_ID", file=sys.stderr)
        return 2
    try:
        link = Link(args.mavlink)
    except ImportError:
        print(f"{prog}: {MISSING_PYMAVLINK}", file=sys.stderr)
        return 2
    from ._client import Client

    source = Path(args.source)
    frames = folder_frames(source, loop=args.loop, interval_s=args.frame_interval) \
        if source.is_dir() else camera_frames(args.source)
    options = BridgeOptions(output=args.output, fps=args.fps, max_rate_hz=args.max_rate,
                            max_pose_age_s=args.max_age, heading_offset_deg=args.heading_offset,
                            heading_accuracy_deg=args.heading_accuracy)
    out = sys.stdout if args.log == "-" else \
        open(args.log, "a") if args.log else None  # noqa: SIM115 (closed below)

    def log(record: dict[str, Any]) -> None:
        if out is not None:
            out.write(json.dumps(record) + "\n")
            out.flush()

    with Client(args.server, admin_key=args.admin_key or admin_key or "", retry=0) as vloc, \
            link:
        if not link.wait_alive(10.0):
            print(f"{prog}: no heartbeat from {args.mavlink} yet; frames go without the "
                  "autopilot's values, poses wait for the link", file=sys.stderr)
        session_id, token = args.session, args.token
        if args.map is not None:
            s = vloc.create_session(args.map)
            session_id, token = s.id, s.token
            print(f"session {s.id} {s.token}", file=sys.stderr)
        try:
            stats = Bridge(vloc, session_id, token, link, options, log=log).run(
                frames, limit=args.frames)
        except KeyboardInterrupt:
            return 130
        except APIError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 1
        finally:
            if out not in (None, sys.stdout):
                out.close()
    print(f"{stats.frames} frames, {stats.sent} poses sent"
          + "".join(f", {n} {why}" for why, n in sorted(stats.skipped.items())),
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
