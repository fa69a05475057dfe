"""``vloc demo`` as a newcomer runs it: a child process, nothing prepared, a reduced size.

The demo starts its own ``vloc serve`` (another process) on the embedded defaults, so this
test covers the whole product path: world generation, server start-up and readiness, map
upload and build over HTTP, device replay over HTTP and WebSocket, the table, the plot,
and the server's shutdown.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from tests.e2e.conftest import interruptible

FRAMES = 60
"""Frames per pass: the smallest (60 m) block, small enough for CI."""

ERROR_MARGIN_M = 1.0
"""Absolute slack on "hybrid within 10 % of SIFT-only": a few frames decide a small run."""

INTERRUPTED = (130, -signal.SIGINT)
"""How an interrupted demo may end: exit 130 from its handler, or a death by SIGINT, which a
shell also reports as 130 (CI once saw the latter after the handler had run and said so)."""

ROW = re.compile(r"^\| (hybrid|global|sift) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) % \| "
                 r"([\d.]+) \| ([\d.]+) \|$", re.M)


def demo_command(out) -> list[str]:
    return [sys.executable, "-m", "vloc.clients.cli", "demo", "--frames", str(FRAMES), "--out",
            str(out), "--quiet"]


def clean_env() -> dict:
    """The environment of a newcomer: no VLOC_* settings."""
    return {k: v for k, v in os.environ.items() if not k.startswith("VLOC_")}


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = subprocess.run(demo_command(out), cwd=out, env=clean_env(), capture_output=True,
                          text=True, timeout=900)
    return proc, out


def test_demo_exits_0_and_prints_the_table(demo):
    proc, out = demo
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rows = {m.group(1): m.groups()[1:] for m in ROW.finditer(proc.stdout)}
    assert set(rows) == {"hybrid", "global", "sift"}, proc.stdout
    results = json.loads((out / "results.json").read_text())
    # The printed table is the results' figures.
    for mode, (mean, median, share, ms, _) in rows.items():
        r = results["modes"][mode]
        assert float(mean) == pytest.approx(r["mean_error_m"], abs=0.051)
        assert float(median) == pytest.approx(r["median_error_m"], abs=0.051)
        assert float(share) == pytest.approx(100 * r["sift_step_share"], abs=0.051)
        assert float(ms) == pytest.approx(r["ms_per_frame"], abs=0.051)
    assert float(rows["sift"][2]) == 100.0 and float(rows["global"][2]) == 0.0
    assert results["frames"] == FRAMES
    assert "hybrid vs sift-only" in proc.stdout and "server: stopped" in proc.stdout
    assert re.search(r"^viewer: http://127\.0\.0\.1:\d+/ui/ ", proc.stdout, re.M), proc.stdout
    # the sessions' configuration is said, beside the service's default, and the Replays
    # page names it for each track
    assert "sessions: filter configuration weiss2008; the service's default is `default`" \
        in proc.stdout
    assert {t["config"] for t in results["tracks"]} == {"weiss2008"}


def test_hybrid_error_close_to_sift_with_fewer_sift_steps(demo):
    proc, out = demo
    assert proc.returncode == 0
    modes = json.loads((out / "results.json").read_text())["modes"]
    hybrid, sift = modes["hybrid"], modes["sift"]
    assert hybrid["mean_error_m"] <= 1.1 * sift["mean_error_m"] + ERROR_MARGIN_M, modes
    # "At a fraction of the time": the time hybrid saves is the SIFT steps it skips.
    assert hybrid["sift_step_share"] < 0.5
    assert hybrid["frames_answered"] == sift["frames_answered"] == FRAMES


def test_demo_writes_the_plot_and_cleans_up(demo):
    proc, out = demo
    assert proc.returncode == 0
    png = (out / "tracks.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    # The server's temporary data folder is gone; the world is kept for the next run.
    assert not list(out.glob("vloc-demo-*"))
    assert (out / "world" / "ground_truth.csv").is_file()
    assert (out / "server.log").is_file()


@pytest.mark.parametrize("pauses", [(), (0.3, 0.3)], ids=["once", "thrice"])
def test_ctrl_c_stops_the_server(demo, pauses):
    """Interrupted once its server is up (the world is reused from the first run), the demo
    exits 130 and leaves no server process behind; Ctrl-C pressed again while the server
    drains, and a third time as the demo exits, changes neither."""
    _, out = demo
    proc = interruptible(demo_command(out), cwd=out, env=clean_env(),
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        pid = None
        for line in proc.stdout:
            ready = re.search(r"server: ready at \S+ \(pid (\d+)\)", line)
            if ready:
                pid = int(ready.group(1))
                break
        assert pid is not None and _alive(pid)
        proc.send_signal(signal.SIGINT)
        for pause in pauses:  # the server takes seconds to drain
            time.sleep(pause)
            proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode in INTERRUPTED, rest
    assert rest.count("interrupted; the server was stopped") == 1, rest
    assert not _alive(pid)


def test_keep_leaves_the_server_up_for_the_viewer(tmp_path):
    """``--keep``: after the replay the server stays up with the viewer at the printed
    address and the demo's map in it, until Ctrl-C."""
    import httpx

    cmd = [sys.executable, "-m", "vloc.clients.cli", "demo", "--frames", "10", "--out",
           str(tmp_path), "--quiet", "--keep"]
    proc = interruptible(cmd, cwd=tmp_path, env=clean_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    try:
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("server: kept running"):
                break
        text = "".join(seen)
        viewer = re.search(r"^viewer: (http://\S+/ui/) \(sign in with the admin key (\S+)\)",
                           text, re.M)
        pid = re.search(r"server: ready at \S+ \(pid (\d+)\)", text)
        assert viewer and pid and "kept running" in text, text
        page = httpx.get(viewer.group(1), timeout=10)
        assert page.status_code == 200 and "vendor/leaflet/leaflet.js" in page.text
        base = viewer.group(1).removesuffix("/ui/")
        maps = httpx.get(f"{base}/v1/maps", timeout=10,
                         headers={"Authorization": f"Bearer {viewer.group(2)}"}).json()
        assert [(m["name"], m["status"]) for m in maps] == [("demo street", "ready")]
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, rest
    assert "server: stopped" in rest
    assert not _alive(int(pid.group(1)))
    # kept: the server's data folder, with its database
    assert list(tmp_path.glob("vloc-demo-*/vloc.sqlite3"))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
