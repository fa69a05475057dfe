"""The MAVLink side of the bridge: one connection to the autopilot, read on a thread.

The reader keeps the latest heading, altitude and ground velocity the autopilot reported,
each with the time it came, and the time of its last heartbeat: the link is up while
heartbeats come. The bridge sends its own heartbeat once a second, as a companion computer,
which is also what makes a UDP autopilot learn where to send its streams.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

MISSING_PYMAVLINK = ("vloc mavlink needs pymavlink, an optional extra: pip install "
                     "'vloc[mavlink]' (or, for the light client, 'vloc-client[mavlink]')")

COMPANION_COMPONENT = 197
"""MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: the component the bridge speaks as."""


def import_mavutil():
    """pymavlink's ``mavutil`` on MAVLink 2 (``ODOMETRY`` exists only there), or a clear
    ImportError naming the extra to install."""
    os.environ.setdefault("MAVLINK20", "1")
    try:
        from pymavlink import mavutil
    except ImportError as exc:
        raise ImportError(MISSING_PYMAVLINK) from exc
    return mavutil


@dataclass(frozen=True)
class Telemetry:
    """What the autopilot reported last, each value with the monotonic time it came."""

    heading_deg: tuple[float, float] | None = None
    altitude_m: tuple[float, float] | None = None
    velocity_en: tuple[tuple[float, float], float] | None = None

    def metadata(self, *, now: float, max_age_s: float, heading_offset_deg: float = 0.0,
                 heading_accuracy_deg: float | None = None) -> dict[str, float]:
        """The frame metadata (docs/api.md) of the values younger than ``max_age_s``:
        an old value describes where the vehicle was, not where the frame is taken."""
        out: dict[str, float] = {}
        if self.heading_deg is not None and now - self.heading_deg[1] <= max_age_s:
            out["heading_deg"] = (self.heading_deg[0] + heading_offset_deg) % 360.0
            if heading_accuracy_deg is not None:
                out["heading_accuracy_deg"] = heading_accuracy_deg
        if self.altitude_m is not None and now - self.altitude_m[1] <= max_age_s:
            out["altitude_m"] = self.altitude_m[0]
        if self.velocity_en is not None and now - self.velocity_en[1] <= max_age_s:
            out["velocity_east"], out["velocity_north"] = self.velocity_en[0]
        return out


class Link:
    """A MAVLink connection (any pymavlink address: ``udpout:host:port``, ``udpin:...``,
    ``tcp:...``, a serial device) with a reader thread.

    Parameters
    ----------
    address : str
        Where the autopilot is, as ``mavutil.mavlink_connection`` takes it.
    heartbeat_timeout_s : float
        The link is down when no heartbeat came for this long (MAVLink's usual 3 s).
    clock : callable
        Monotonic seconds; tests may pass their own.
    """

    def __init__(self, address: str, *, system_id: int = 1,
                 component_id: int = COMPANION_COMPONENT, heartbeat_timeout_s: float = 3.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        mavutil = import_mavutil()
        self._mavutil = mavutil
        self.conn = mavutil.mavlink_connection(address, source_system=system_id,
                                               source_component=component_id,
                                               autoreconnect=True)
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self._clock = clock
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._telemetry = Telemetry()
        self._last_heartbeat: float | None = None
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name="mavlink-reader", daemon=True)
        self._beater = threading.Thread(target=self._beat, name="mavlink-heartbeat",
                                        daemon=True)

    def start(self) -> Link:
        self._reader.start()
        self._beater.start()
        return self

    def close(self) -> None:
        self._stop.set()
        for t in (self._reader, self._beater):
            if t.is_alive():
                t.join(2.0)
        self.conn.close()

    def __enter__(self) -> Link:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state --------------------------------------------------------------------------

    def alive(self) -> bool:
        """Whether a heartbeat came within ``heartbeat_timeout_s``."""
        with self._lock:
            last = self._last_heartbeat
        return last is not None and self._clock() - last <= self.heartbeat_timeout_s

    def wait_alive(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the autopilot's heartbeat and first streams."""
        deadline = self._clock() + timeout
        while self._clock() < deadline:
            t = self.telemetry()
            if self.alive() and (t.heading_deg or t.altitude_m):
                return True
            self._stop.wait(0.05)
        return self.alive()

    @property
    def target_system(self) -> int:
        """The autopilot's system id, as its heartbeats gave it."""
        return self.conn.target_system

    def telemetry(self) -> Telemetry:
        with self._lock:
            return self._telemetry

    # -- sending ------------------------------------------------------------------------

    def send(self, name: str, fields: dict[str, Any]) -> None:
        """Send message ``name`` (``"GPS_INPUT"``...) with ``fields`` as its arguments."""
        method = getattr(self.conn.mav, name.lower() + "_send")
        with self._send_lock:
            method(**fields)

    def _beat(self) -> None:
        m = self._mavutil.mavlink
        while not self._stop.is_set():
            try:
                with self._send_lock:
                    self.conn.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER,
                                                 m.MAV_AUTOPILOT_INVALID, 0, 0,
                                                 m.MAV_STATE_ACTIVE)
            except OSError:
                pass  # the link is down: the next beat tries again
            self._stop.wait(1.0)

    # -- receiving ----------------------------------------------------------------------

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.2)
            except OSError:
                msg = None
                self._stop.wait(0.2)
            if msg is not None:
                self._take(msg)

    def _take(self, msg) -> None:
        kind, now = msg.get_type(), self._clock()
        with self._lock:
            t = self._telemetry
            if kind == "HEARTBEAT" and msg.autopilot != self._mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                self._last_heartbeat = now
            elif kind == "ATTITUDE" and math.isfinite(msg.yaw):
                self._telemetry = Telemetry(((math.degrees(msg.yaw)) % 360.0, now),
                                            t.altitude_m, t.velocity_en)
            elif kind == "GLOBAL_POSITION_INT":
                # alt: millimetres above mean sea level; vx, vy: cm/s north, east
                self._telemetry = Telemetry(t.heading_deg, (msg.alt / 1000.0, now),
                                            ((msg.vy / 100.0, msg.vx / 100.0), now))
