"""A simulated autopilot: a MAVLink endpoint on the loopback that plays a vehicle and
records what it is sent, for the bridge's tests and to try ``vloc mavlink`` without one.

It listens on UDP (``udpin``) as an autopilot's telemetry port does, answers whoever spoke
last, and sends what an ArduPilot or PX4 vehicle streams to a companion computer:
``HEARTBEAT`` once a second, ``ATTITUDE`` and ``GLOBAL_POSITION_INT`` at ``rate_hz``, from
the state the caller sets (heading, altitude, velocity). :meth:`drop_link` and
:meth:`restore_link` close and reopen its socket on the same port, as a radio link that
fades or an autopilot that reboots. :meth:`external_nav` reads the local-frame estimates it
got as an autopilot's EKF takes them: a position from its origin, and a noise.

    python -m vloc.clients.mavlink_sim --port 14550     # prints what it receives
"""

from __future__ import annotations

import argparse
import math
import socket
import threading
import time
from dataclasses import dataclass

from vloc.clients.sdk._mavlink_link import import_mavutil


@dataclass(frozen=True)
class Received:
    """A message the autopilot got: its fields, and when (monotonic and wall clock)."""

    type: str
    fields: dict
    at: float
    wall: float


@dataclass(frozen=True)
class ExternalNav:
    """A ``VISION_POSITION_ESTIMATE`` or ``ODOMETRY`` as the autopilot takes it.

    ``lat``, ``lon``: its north and east metres from the EKF origin (the last
    ``SET_GPS_GLOBAL_ORIGIN`` before it), on the WGS84 ellipsoid. ``cov_ne``: the
    north-east covariance (nn, ne, ee), m^2, as PX4's EKF2 reads it. ``pos_err_m`` and
    ``ang_err_rad``: the two noises ArduPilot reduces the covariance to, the roots of the
    sums of the x, y, z and of the roll, pitch, yaw variances (0 when the covariance is
    flagged unknown by a NaN first element; NaN where any of those is NaN, which ArduPilot
    reports as an internal error).
    """

    type: str
    north: float
    east: float
    lat: float
    lon: float
    cov_ne: tuple[float, float, float]
    pos_err_m: float
    ang_err_rad: float
    reset_counter: int
    usec: int
    wall: float


def _external_nav(r: Received, origin: tuple[float, float]) -> ExternalNav:
    from vloc.workers.core.geo import GeoOrigin

    f = r.fields
    cov = f["covariance"] if r.type == "VISION_POSITION_ESTIMATE" else f["pose_covariance"]
    pos_err = ang_err = 0.0
    if not math.isnan(cov[0]):
        pos_err = math.sqrt(cov[0] + cov[6] + cov[11])
        ang_err = math.sqrt(cov[15] + cov[18] + cov[20])
    lat, lon = GeoOrigin(*origin).to_wgs84(f["y"], f["x"])
    return ExternalNav(r.type, f["x"], f["y"], float(lat), float(lon),
                       (cov[0], cov[1], cov[6]), pos_err, ang_err, f["reset_counter"],
                       f["usec"] if "usec" in f else f["time_usec"], r.wall)


@dataclass
class VehicleState:
    heading_deg: float = 0.0
    altitude_m: float = 100.0
    velocity_en: tuple[float, float] = (0.0, 0.0)
    lat: float = 0.0
    lon: float = 0.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SimulatedAutopilot:
    """See the module's description. ``address`` is what the bridge connects to."""

    def __init__(self, port: int | None = None, *, rate_hz: float = 10.0,
                 system_id: int = 1) -> None:
        self._mavutil = import_mavutil()
        self.port = port or free_udp_port()
        self.rate_hz = rate_hz
        self.system_id = system_id
        self.state = VehicleState()
        self._lock = threading.Lock()
        self._received: list[Received] = []
        self._conn = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._boot = time.monotonic()

    @property
    def address(self) -> str:
        return f"udpout:127.0.0.1:{self.port}"

    # -- life ---------------------------------------------------------------------------

    def start(self) -> SimulatedAutopilot:
        self._conn = self._mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{self.port}", source_system=self.system_id, source_component=1)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-autopilot", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        if self._conn is not None:
            # what had arrived before the link went was received; only what comes after is lost
            while (msg := self._conn.recv_match(blocking=False)) is not None:
                self._record(msg)
            self._conn.close()
            self._conn = None

    drop_link = close
    """The link goes: nothing is sent, nothing arrives (the port is closed)."""

    def restore_link(self) -> None:
        """The link comes back on the same port, knowing no peer until one speaks."""
        self.start()

    def __enter__(self) -> SimulatedAutopilot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- what it got --------------------------------------------------------------------

    def received(self, kind: str | None = None) -> list[Received]:
        with self._lock:
            return [r for r in self._received if kind is None or r.type == kind]

    def external_nav(self) -> list[ExternalNav]:
        """The local-frame estimates received after an EKF origin, as the EKF takes them
        (see :class:`ExternalNav`); those before any origin have no place and are left
        out."""
        origin, out = None, []
        for r in self.received():
            if r.type == "SET_GPS_GLOBAL_ORIGIN":
                origin = (r.fields["latitude"] / 1e7, r.fields["longitude"] / 1e7)
            elif r.type in ("VISION_POSITION_ESTIMATE", "ODOMETRY") and origin is not None:
                out.append(_external_nav(r, origin))
        return out

    def wait_for(self, kind: str, count: int, timeout: float) -> list[Received]:
        """The first ``count`` messages of ``kind``, once they came; TimeoutError if not
        within ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while len(got := self.received(kind)) < count:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{len(got)} of {count} {kind} in {timeout} s")
            time.sleep(0.05)
        return got[:count]

    # -- the loop -----------------------------------------------------------------------

    def _run(self) -> None:
        period, next_stream, next_beat = 1.0 / self.rate_hz, 0.0, 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                self._send_heartbeat()
                next_beat = now + 1.0
            if now >= next_stream:
                self._send_streams(now)
                next_stream = now + period
            msg = self._conn.recv_match(blocking=True, timeout=min(period, 0.05))
            if msg is not None:
                self._record(msg)

    def _record(self, msg) -> None:
        if msg.get_type() != "BAD_DATA":
            with self._lock:
                self._received.append(Received(msg.get_type(), msg.to_dict(), time.monotonic(),
                                               time.time()))

    def _send_heartbeat(self) -> None:
        m = self._mavutil.mavlink
        self._conn.mav.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                      m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0,
                                      m.MAV_STATE_ACTIVE)

    def _send_streams(self, now: float) -> None:
        s, boot_ms = self.state, int((now - self._boot) * 1000)
        yaw = math.radians((s.heading_deg + 180.0) % 360.0 - 180.0)
        self._conn.mav.attitude_send(boot_ms, 0.0, 0.0, yaw, 0.0, 0.0, 0.0)
        east, north = s.velocity_en
        self._conn.mav.global_position_int_send(
            boot_ms, round(s.lat * 1e7), round(s.lon * 1e7), round(s.altitude_m * 1000),
            round(s.altitude_m * 1000), round(north * 100), round(east * 100), 0,
            round(s.heading_deg * 100) % 36000)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m vloc.clients.mavlink_sim",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--port", type=int, default=14550)
    p.add_argument("--heading", type=float, default=0.0)
    p.add_argument("--altitude", type=float, default=100.0)
    args = p.parse_args(argv)
    sim = SimulatedAutopilot(args.port)
    sim.state.heading_deg, sim.state.altitude_m = args.heading, args.altitude
    seen = 0
    with sim:
        print(f"autopilot on udp 127.0.0.1:{sim.port}: vloc mavlink ... --mavlink {sim.address}")
        try:
            while True:
                time.sleep(0.2)
                got = [r for r in sim.received() if r.type != "HEARTBEAT"]
                for r in got[seen:]:
                    print(r.type, {k: v for k, v in r.fields.items() if k != "mavpackettype"})
                seen = len(got)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
