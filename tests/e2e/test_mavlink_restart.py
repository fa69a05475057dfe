"""``vloc mavlink`` across a restart of the service: ``vloc serve`` on a fixed data folder and
port is stopped (SIGTERM) mid-flight and started again. While it is down the autopilot gets
nothing; nothing it gets afterwards is older than the age limit or comes from a frame taken
before the outage; and the poses resume on the same session once the service is back."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("pymavlink", reason="the mavlink extra (pip install -e '.[dev]')")

from tests.clients.conftest import FAST, make_shots  # noqa: E402
from tests.clients.test_mavlink import check_messages  # noqa: E402
from tests.e2e.conftest import interruptible, start_server  # noqa: E402
from vloc.clients.demo import free_port  # noqa: E402
from vloc.clients.mavlink_sim import SimulatedAutopilot  # noqa: E402
from vloc.clients.sdk import Client  # noqa: E402

MAX_AGE_S = 2.0
LOOPBACK_S = 0.1
"""What the loopback and the simulator's polling may add to a message's age."""


def _log(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


def _until(what: str, check, timeout: float, bridge: subprocess.Popen) -> None:
    """Poll ``check()`` until it holds; fail after ``timeout`` s or if the bridge exits."""
    deadline = time.monotonic() + timeout
    while not check():
        if bridge.poll() is not None:
            pytest.fail(f"vloc mavlink exited with {bridge.returncode} waiting for {what}:\n"
                        + bridge.stderr.read()[-3000:])
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} within {timeout} s")
        time.sleep(0.1)


def _flight_folder(folder: Path, queries) -> Path:
    """The query shots out and back (0..8, 7..1): played in a loop, the flight never jumps."""
    folder.mkdir()
    order = queries + queries[-2:0:-1]
    for i, s in enumerate(order):
        (folder / f"{i:03d}_{s.name}").write_bytes(s.jpeg)
    return folder


def test_vloc_mavlink_across_a_restarted_service(tmp_path):
    maps, queries = make_shots(10)
    servers = [start_server(tmp_path / "data", workers=1, port=free_port())]
    try:
        with SimulatedAutopilot() as autopilot:
            times, records, poses = _fly_through_a_restart(
                servers, autopilot, maps, queries, tmp_path)
            pairs = check_messages(autopilot, records, poses)
    finally:
        for server in servers:
            server.stop()
    got = [m for m, _ in pairs]
    # nothing while the service was down: none was running to answer a frame
    assert not [m for m in got if times["down"] < m.wall < times["restart"]]
    # nothing stale: every message within the age limit of its frame's capture
    for m in got:
        assert m.wall - m.fields["time_usec"] / 1e6 <= MAX_AGE_S + LOOPBACK_S
    # nothing from before the outage after it: a frame read before the service went away
    # was answered then or never
    after = [m for m in got if m.wall > times["down"]]
    assert len(after) >= 3
    assert all(m.fields["time_usec"] / 1e6 > times["restart"] for m in after)
    # the same session went on: its frames' seqs continue across the restart
    sent_seqs = [r["seq"] for r in records if "sent" in r]
    assert sent_seqs == sorted(sent_seqs) and len(set(sent_seqs)) == len(sent_seqs)
    outage = [r for r in records if r.get("why", "").startswith("service")]
    assert len(outage) >= 4 and all("seq" not in r for r in outage)


def _fly_through_a_restart(servers, autopilot, maps, queries, tmp_path):
    """Run the bridge, stop the service once poses reach the autopilot, start it again
    (appended to ``servers``) once the bridge has found it gone, and stop the bridge once
    poses came again. Returns the times, the bridge's log and the session's poses."""
    server = servers[0]
    with Client(server.base_url, admin_key=server.admin_key()) as vloc:
        m = vloc.create_map("restart")
        vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
        vloc.wait_for_job(vloc.build_map(m.id).id, timeout=180)
        session = vloc.create_session(m.id, params=FAST, seed=3)
    folder = _flight_folder(tmp_path / "flight", queries)
    log = tmp_path / "bridge.jsonl"
    times: dict[str, float] = {}
    bridge = interruptible(
        [sys.executable, "-m", "vloc.clients.cli", "mavlink", str(folder), "--loop",
         "--mavlink", autopilot.address, "--server", server.base_url, "--session",
         session.id, "--token", session.token, "--fps", "4", "--max-rate", "10",
         "--max-age", str(MAX_AGE_S), "--frame-interval", "5", "--log", str(log)],
        cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    try:
        _until("3 GPS_INPUT before the restart",
               lambda: len(autopilot.received("GPS_INPUT")) >= 3, 180, bridge)
        times["stop"] = time.time()
        server.stop()
        times["down"] = time.time()
        # the bridge keeps reading frames and finds no service for them
        _until("frames refused while the service is down", lambda: sum(
            1 for r in _log(log) if r.get("why", "").startswith("service")) >= 4, 60, bridge)
        times["restart"] = time.time()
        server = start_server(server.data_dir, workers=1,
                              port=int(server.base_url.rsplit(":", 1)[1]))
        servers.append(server)
        times["ready"] = time.time()
        _until("3 GPS_INPUT after the restart", lambda: sum(
            1 for r in autopilot.received("GPS_INPUT") if r.wall > times["ready"]) >= 3,
            180, bridge)
    finally:
        bridge.send_signal(signal.SIGINT)
        try:
            bridge.wait(30)
        finally:
            if bridge.poll() is None:
                bridge.kill()
    assert bridge.returncode == 130, bridge.stderr.read()[-3000:]
    with Client(server.base_url, admin_key=server.admin_key()) as vloc:
        poses = {p.seq: p for p in vloc.list_poses(session.id) if p.type == "pose"}
    return times, _log(log), poses
