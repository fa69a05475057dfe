"""The web viewer in a real headless Chromium against a real server.

A map is built over HTTP from geotagged JPEGs, a session replays query frames, and the page is
checked for what a person would look at: the map's images on the plan with thumbnails, the
marker following the poses, the particle cloud and the uncertainty ellipse, the last frame.
Wrong credentials are refused; the page never puts a secret in a URL and no request fails.
The last test measures how the page keeps up with ten sessions streaming at 10 Hz.
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.app.conftest import ADMIN, ADMIN_KEY
from tests.conftest import REPO_ROOT
from tests.e2e.browser import N_MAP, PageLog

DOCS = REPO_ROOT / "docs" / "viewer"
N_FRAMES = 6
TIMEOUT_MS = 20_000
VIEWPORT = {"width": 1280, "height": 800}

@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    """Where screenshots go: docs/viewer/ (committed, shown in docs/viewer.md) with
    ``VLOC_UPDATE_SCREENSHOTS=1``; otherwise a temporary folder, so that a test run leaves
    the checkout as it was."""
    if os.environ.get("VLOC_UPDATE_SCREENSHOTS") == "1":
        DOCS.mkdir(parents=True, exist_ok=True)
        return DOCS
    return tmp_path_factory.mktemp("screenshots")


def _session(live, world, **params) -> tuple[str, str]:
    r = httpx.post(f"{live.base_url}/v1/sessions", headers=ADMIN, json={
        "map_id": world["map_id"], "mode": "hybrid", "seed": 3,
        "params": {"n_particles": 200, **params}})
    assert r.status_code == 201, r.text
    return r.json()["id"], r.json()["token"]


def _page(browser, live, log: PageLog):
    page = browser.new_page(viewport=VIEWPORT)
    page.set_default_timeout(TIMEOUT_MS)
    log.watch(page)
    page.goto(f"{live.base_url}/ui/")
    return page


def _sign_in(page, secret: str, session_id: str | None = None) -> None:
    if session_id is not None:
        page.check("input[name=kind][value=session]")
        page.fill("#login-session", session_id)
    page.fill("#login-secret", secret)
    page.click("#login-submit")


def _send(live, sid: str, token: str, jpeg: bytes) -> dict:
    r = httpx.post(f"{live.base_url}/v1/sessions/{sid}/frames?wait=true", content=jpeg,
                   headers={"Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"},
                   timeout=60)
    assert r.status_code == 200, r.text
    return r.json()


def _marker_at(page, sid: str, pose: dict) -> None:
    """Wait until the session's marker stands on the pose's position."""
    page.wait_for_function(
        """([sid, x, y]) => { const p = window.vlocViewer.markerOf(sid);
             return p !== null && Math.abs(p.lng - x) < 1e-6 && Math.abs(p.lat - y) < 1e-6; }""",
        arg=[sid, pose["x"], pose["y"]])


def _wait_live(page, sid: str) -> None:
    """Wait until the session's card says that its stream is open."""
    page.wait_for_function(
        "sid => document.querySelector(`.card[data-session-id='${sid}'] [data-f=status]`)"
        "?.textContent === 'live'", arg=sid)


def _screen_xy(page, selector: str) -> tuple[float, float]:
    box = page.locator(selector).first.bounding_box()
    assert box is not None, selector
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


def test_viewer_shows_the_map_and_follows_a_live_session(browser, live, world, shots):
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    row = page.locator(f"#maps-table tr[data-map-id='{world['map_id']}']")
    row.wait_for()
    assert row.locator("td").nth(1).inner_text() == "ready"
    row.click()
    images = page.locator("path.vloc-map-image")
    page.wait_for_function(f"document.querySelectorAll('path.vloc-map-image').length == {N_MAP}")
    # every image stands apart on the plan, north up and east to the right
    xy = [_box_centre(images.nth(i)) for i in range(N_MAP)]
    assert len({(round(x), round(y)) for x, y in xy}) == N_MAP
    api_images = httpx.get(f"{live.base_url}/v1/maps/{world['map_id']}/images",
                           headers=ADMIN).json()
    for a, pa in zip(api_images, xy, strict=True):
        for b, pb in zip(api_images, xy, strict=True):
            if a["north"] > b["north"] + 1:
                assert pa[1] < pb[1]
            if a["east"] > b["east"] + 1:
                assert pa[0] > pb[0]
    # hovering an image shows its thumbnail
    images.nth(0).hover()
    thumb = page.locator(".thumb-tip img")
    thumb.wait_for()
    page.wait_for_function("document.querySelector('.thumb-tip img').naturalWidth > 0")
    assert page.locator(".north-arrow").is_visible()
    assert page.locator(".leaflet-control-scale-line").first.inner_text().endswith("m")
    page.screenshot(path=str(shots / "maps.png"))
    page.mouse.move(5, 5)

    sid, token = _session(live, world)
    page.click("#tab-live")
    box = page.locator(f"#sessions-table tr[data-session-id='{sid}'] input")
    box.check()
    _wait_live(page, sid)
    markers = []
    for q in world["queries"][:N_FRAMES]:
        pose = _send(live, sid, token, q.jpeg)
        _marker_at(page, sid, pose)
        markers.append(_screen_xy(page, "path.vloc-marker"))
    # the marker moved on screen with the poses
    assert len({(round(x), round(y)) for x, y in markers}) > 1
    stats = page.evaluate("window.vlocViewer.stats()")["sessions"][sid]
    assert stats["received"] == N_FRAMES and stats["gaps"] == 0
    assert stats["track"] == N_FRAMES
    assert 0 < stats["cloud"] <= 64
    # the ellipse encloses the marker and has an area on screen
    ellipse = page.locator("path.vloc-ellipse").bounding_box()
    mx, my = markers[-1]
    assert ellipse["width"] > 0 and ellipse["height"] > 0
    assert ellipse["x"] <= mx <= ellipse["x"] + ellipse["width"]
    assert ellipse["y"] <= my <= ellipse["y"] + ellipse["height"]
    assert _cloud_pixels(page) > 0
    card = page.locator(f".card[data-session-id='{sid}']")
    assert card.locator("[data-f=seq]").inner_text() == str(N_FRAMES - 1)
    assert card.locator("[data-f=step]").inner_text().split()[0] in ("sift", "global")
    # the thumbnails catch up with the last pose: its frame beside its best map image
    last = N_FRAMES - 1
    page.wait_for_function(
        "([sid, last]) => { const c = document.querySelector(`.card[data-session-id='${sid}']`);"
        " const f = c.querySelector('img[data-f=frame]'), b = c.querySelector('img[data-f=best]');"
        " return f.title === `frame ${last}` && f.naturalWidth > 0 && b.naturalWidth > 0 &&"
        " c.querySelector('[data-f=best-cap]').textContent.startsWith(`best match for ${last}:`); }",
        arg=[sid, last])
    best = card.locator("[data-f=best-cap]").inner_text().split(": ", 1)[1]
    assert best == pose["image_filename"]
    assert pose["image_id"] in {i["id"] for i in api_images}
    steps = card.locator(".steps .step-cell")  # the strip, not its legend
    assert steps.count() == N_FRAMES
    assert all(c.split()[1] in ("step-global", "step-sift", "step-refined")
               for c in steps.evaluate_all("cells => cells.map(c => c.className)"))
    page.screenshot(path=str(shots / "live.png"))
    assert not log.errors, log.errors
    _no_secret_in_urls(log, ADMIN_KEY, token)
    page.close()

    # watched later, the session shows its track so far from the stored poses
    later = _page(browser, live, log)
    _sign_in(later, ADMIN_KEY)
    later.click("#tab-live")
    later.locator(f"#sessions-table tr[data-session-id='{sid}'] input").check()
    _marker_at(later, sid, pose)
    stats = later.evaluate("window.vlocViewer.stats()")["sessions"][sid]
    assert stats["history"] == stats["track"] == N_FRAMES
    assert not log.errors, log.errors
    later.close()


def test_an_admin_creates_uploads_and_builds_a_map(browser, live, world, tmp_path):
    files = []
    for shot in world["maps"]:
        (tmp_path / shot.name).write_bytes(shot.jpeg)
        files.append(str(tmp_path / shot.name))
    (tmp_path / "notes.jpg").write_bytes(b"not an image at all")
    files.append(str(tmp_path / "notes.jpg"))
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    page.locator("#maps-table tbody tr").first.wait_for()
    page.fill("#new-map-name", "made in the browser")
    page.click("#create-map button")
    page.wait_for_function("document.querySelector('#map-title').textContent"
                           " === 'made in the browser'")
    page.set_input_files("#upload-files", files)
    page.click("#upload button")
    page.wait_for_function("document.querySelector('#upload-result').textContent"
                           ".includes('accepted')")
    result = page.locator("#upload-result").inner_text()
    assert result.startswith(f"{N_MAP} accepted, refused: notes.jpg: "), result
    # before the build the images stand where their GPS puts them, drawn hollow
    page.wait_for_function(
        f"document.querySelectorAll('path.vloc-map-image').length == {N_MAP}")
    assert page.locator("path.vloc-map-image[stroke-dasharray]").count() == N_MAP
    assert "unbuilt" in page.locator("#map-summary").inner_text()
    page.click("#build")
    page.wait_for_function("document.querySelector('#build-status').textContent"
                           ".startsWith('done')", timeout=120_000)
    assert page.locator("#build-status").inner_text() == "done 100 %"
    assert page.locator("#build-progress").evaluate("p => p.value") == 1
    page.wait_for_function("document.querySelector('#map-summary').textContent"
                           ".startsWith('ready, revision 1')")
    assert page.locator("path.vloc-map-image[stroke-dasharray]").count() == 0
    maps = httpx.get(f"{live.base_url}/v1/maps", headers=ADMIN).json()
    made = [m for m in maps if m["name"] == "made in the browser"]
    assert [(m["status"], m["revision"], m["image_count"]) for m in made] == [
        ("ready", 1, N_MAP)]
    # the map says what its camera geometry gives, in the API's own figures
    geometry = made[0]["geometry"]
    line = page.locator("#map-geometry").inner_text()
    if geometry["status"] == "accepted":
        check = geometry["self_check"]
        assert f"localises to about {check['median_m']:.1f} m" in line, line
        assert f"included, {check['every_image_mean_m']:.1f} m on average." in line, line
    else:
        assert line.startswith("No camera geometry"), line
    # a second revision; from the page, the first restored and the second dropped
    map_id = made[0]["id"]
    job = httpx.post(f"{live.base_url}/v1/maps/{map_id}/build", params={"force": "true"},
                     headers=ADMIN).json()["job_id"]
    deadline = time.monotonic() + 120
    while httpx.get(f"{live.base_url}/v1/jobs/{job}", headers=ADMIN).json()["status"] != "done":
        assert time.monotonic() < deadline, "the second build did not finish"
        time.sleep(0.2)
    page.click(f"#maps-table tbody tr[data-map-id='{map_id}']")
    page.wait_for_function("document.querySelectorAll('#revisions-table tbody tr').length == 2")
    page.click("#revisions-box summary")
    rows = page.locator("#revisions-table tbody tr")
    assert rows.nth(0).locator("td").nth(0).inner_text() == "2 (current)"
    assert rows.nth(0).locator("button").count() == 0  # the current one stays
    assert rows.nth(1).locator("td").nth(3).inner_text() == f"+{N_MAP} -0 on 0"
    # built again from the same images: the files that came out the same are shared
    assert re.fullmatch(r"[\d.]+ MiB \([\d.]+ shared\)",
                        rows.nth(0).locator("td").nth(5).inner_text())
    page.click("#revisions-table tr[data-revision='1'] button.revision-restore")
    page.wait_for_function("document.querySelector('#map-summary').textContent"
                           ".startsWith('ready, revision 1')")
    page.click("#revisions-table tr[data-revision='2'] button.revision-drop")
    page.wait_for_function("(document.querySelector(\"#revisions-table tr[data-revision='2']"
                           " td:nth-child(6)\") || {}).textContent === 'dropped'")
    listed = httpx.get(f"{live.base_url}/v1/maps/{map_id}/revisions", headers=ADMIN).json()
    assert [(r["revision"], r["current"], r["dropped_at"] is not None) for r in listed] == [
        (2, False, True), (1, True, False)]
    assert page.locator("#revisions-error").inner_text() == ""
    assert not log.errors, log.errors
    page.close()


PIXELS = 2.5
"""Screen positions agree to this: Leaflet rounds each projection to whole pixels."""


def test_tiles_are_off_by_default_and_line_up_with_the_plan(browser, live, world):
    import cv2

    tile = cv2.imencode(".png", np.full((256, 256, 3), 200, np.uint8))[1].tobytes()
    requested = []

    def answer(route):
        requested.append(route.request.url)
        route.fulfill(status=200, content_type="image/png", body=tile)

    log = PageLog()
    page = browser.new_page(viewport=VIEWPORT)
    page.set_default_timeout(TIMEOUT_MS)
    log.watch(page)
    page.route("https://tiles.invalid/**", answer)
    page.goto(f"{live.base_url}/ui/")
    _sign_in(page, ADMIN_KEY)
    page.locator(f"#maps-table tr[data-map-id='{world['map_id']}']").click()
    page.wait_for_function(f"document.querySelectorAll('path.vloc-map-image').length == {N_MAP}")
    images = page.locator("path.vloc-map-image")
    before = [_box_centre(images.nth(i)) for i in range(N_MAP)]
    toggle = page.locator("#tiles-toggle")
    assert toggle.is_enabled() and not toggle.is_checked()
    assert requested == []  # off by default: a device may be offline
    toggle.check()
    page.wait_for_function("document.querySelectorAll('img.leaflet-tile-loaded').length > 0")
    # the plan kept its scale and place: the images did not move on screen (Leaflet rounds
    # positions to whole pixels, in each frame)
    after = [_box_centre(images.nth(i)) for i in range(N_MAP)]
    for (x0, y0), (x1, y1) in zip(before, after, strict=True):
        assert abs(x0 - x1) < PIXELS and abs(y0 - y1) < PIXELS, (before, after)
    # the tile under the map's origin is the one the slippy-map formula names, placed so
    # that the origin falls where it should inside it
    origin = httpx.get(f"{live.base_url}/v1/maps/{world['map_id']}", headers=ADMIN).json()[
        "origin"]
    z = int(requested[0].split("/")[-3])
    n = 2 ** z
    lat = math.radians(origin["lat"])
    fx = (origin["lon"] + 180) / 360 * n
    fy = (1 - math.asinh(math.tan(lat)) / math.pi) / 2 * n
    url = f"https://tiles.invalid/{z}/{int(fx)}/{int(fy)}.png"
    assert url in requested, (url, requested)
    box = page.locator(f"img.leaflet-tile[src='{url}']").bounding_box()
    seen = page.evaluate("window.vlocViewer.screenOf(0, 0)")
    assert abs(box["x"] + (fx % 1) * box["width"] - seen["x"]) < PIXELS
    assert abs(box["y"] + (fy % 1) * box["height"] - seen["y"]) < PIXELS
    assert "test tiles" in page.locator(".leaflet-control-attribution").inner_text()
    toggle.uncheck()
    assert page.locator("img.leaflet-tile").count() == 0
    again = [_box_centre(images.nth(i)) for i in range(N_MAP)]
    for (x0, y0), (x1, y1) in zip(before, again, strict=True):
        assert abs(x0 - x1) < PIXELS and abs(y0 - y1) < PIXELS
    assert not log.errors, log.errors
    page.close()


def test_wrong_credentials_are_refused_and_a_token_opens_its_session(browser, live, world):
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, "not-the-admin-key")
    page.wait_for_function("document.querySelector('#login-error').textContent.length > 0")
    assert page.locator("#login-error").inner_text().startswith("refused")
    assert page.locator("#maps-pane").is_hidden() and page.locator("#login").is_visible()
    sid, token = _session(live, world)
    other, other_token = _session(live, world)
    _sign_in(page, other_token, session_id=sid)
    page.wait_for_function("document.querySelector('#login-error').textContent"
                           ".includes('do not open')")
    # the refusals were the page's own requests, and nothing else failed
    assert all("403" in e or "Failed to load resource" in e for e in log.errors), log.errors
    log.errors.clear()

    _sign_in(page, token, session_id=sid)
    page.locator(f".card[data-session-id='{sid}']").wait_for()
    assert page.locator("#tab-maps").is_hidden()  # a token opens no admin view
    _wait_live(page, sid)
    pose = _send(live, sid, token, world["queries"][0].jpeg)
    _marker_at(page, sid, pose)

    # the server ends the stream (as on a restart): the page opens it again, and whatever
    # was answered meanwhile comes from the stored poses, neither lost nor doubled
    from vloc.app.stream.hub import GOING_AWAY

    live.publish(sid, GOING_AWAY)
    page.wait_for_function(
        "sid => document.querySelector(`.card[data-session-id='${sid}'] [data-f=status]`)"
        ".textContent.startsWith('reconnecting (1001')", arg=sid)
    meanwhile = _send(live, sid, token, world["queries"][1].jpeg)
    _marker_at(page, sid, meanwhile)  # live or from the stored poses: connected again
    last = _send(live, sid, token, world["queries"][2].jpeg)
    _marker_at(page, sid, last)
    stats = page.evaluate("window.vlocViewer.stats()")["sessions"][sid]
    assert stats["reconnects"] == 1 and stats["track"] == 3 and stats["last_seq"] == 2
    assert not log.errors, log.errors
    _no_secret_in_urls(log, token, other_token)
    page.close()


def test_replay_file_draws_tracks_against_the_truth(browser, live, tmp_path, shots):
    from vloc.workers.core.evaluation.evaluate import ModeSummary, Run
    from vloc.workers.core.evaluation.report import tracks_dict

    n = 40
    t = np.arange(n, dtype=float)
    # an L-shaped route; hybrid's error grows and settles, sift's is always 3 m worse
    truth = np.where((t < 20)[:, None], np.c_[2 * t, 0 * t], np.c_[0 * t + 38, 2 * (t - 19)])
    spread = 1.0 + 3.0 * np.exp(-t / 6) + 0.5 * np.sin(t / 2)
    error = {"hybrid": spread, "sift": spread + 3.0}
    angle = t / 5

    def run(mode):
        offset = error[mode][:, None] * np.c_[np.cos(angle), np.sin(angle)]
        return Run(mode=mode, config="default", start=0, frames=np.arange(n), truth=truth,
                   estimate=truth + offset, sigma=np.ones((n, 2)),
                   feature=["sift"] * n, status=["tracking"] * n, ms=np.ones(n))

    results = {"default": {m: ModeSummary(m, "default", [run(m)]) for m in error}}
    data = tracks_dict(truth[::4] + (0, 6), results)
    path = tmp_path / "eval.json"
    path.write_text(json.dumps({"modes": {}} | data))
    bad = tmp_path / "table-only.json"
    bad.write_text(json.dumps({"modes": {}}))

    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    page.click("#tab-replays")
    page.set_input_files("#replay-file", str(bad))
    page.wait_for_function("document.querySelector('#replay-error').textContent.length > 0")
    assert "has no tracks" in page.locator("#replay-error").inner_text()
    page.set_input_files("#replay-file", str(path))
    page.wait_for_function("!document.querySelector('#replay-table').hidden || document.querySelector('#replay-error').textContent")
    assert page.locator("#replay-error").inner_text() == "", log.errors
    rows = page.locator("#replay-table tbody tr")
    want = []
    for track in data["tracks"]:
        errs = sorted(track["error_m"])
        want.append(["default", track["mode"], str(n), f"{errs[n // 2]:.1f}", f"{errs[-1]:.1f}"])
    assert [rows.nth(i).locator("td").all_inner_texts()[1:] for i in range(2)] == want
    assert page.locator("path.vloc-replay-track").count() == 2
    assert page.locator("path.vloc-truth").count() == 1
    assert page.locator("path.vloc-replay-image").count() == len(data["map_xy"])
    lines = page.locator("#error-svg polyline.vloc-error-line")
    assert lines.count() == 2
    points = [[tuple(map(float, p.split(","))) for p in lines.nth(i).get_attribute("points")
               .split()] for i in range(2)]
    assert len(points[0]) == len(points[1]) == n
    # one point per frame, left to right; sift's larger error is drawn higher at every frame
    assert all(a[0] < b[0] for a, b in zip(points[0], points[0][1:], strict=False))
    assert all(s[1] < h[1] for h, s in zip(points[0], points[1], strict=True))
    page.screenshot(path=str(shots / "replay.png"))
    rows.nth(1).locator("input").uncheck()
    assert lines.count() == 1 and page.locator("path.vloc-replay-track").count() == 1
    assert not log.errors, log.errors
    page.close()


SESSIONS, HZ = 10, 10.0
LOAD_SECONDS = float(os.environ.get("VLOC_VIEWER_LOAD_SECONDS", "5"))


def test_ten_live_sessions_at_10_hz(browser, live, world, shots):
    """Ten sessions on one map, each publishing a pose (with its 64-particle sample) ten
    times a second on its real stream; the page must draw them all without losing a message.
    Frame intervals and draw times are reported (``VLOC_VIEWER_BENCH_OUT`` names a file for
    them; ``bench/bench_viewer.py`` writes ``bench/results/viewer.md``).

    The poses are published on the streams directly: localising 100 frames a second is
    beyond this machine, and the page cannot tell the difference."""
    sessions = [_session(live, world)[0] for _ in range(SESSIONS)]
    template = _send(live, *_session(live, world), world["queries"][0].jpeg)
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    page.click("#tab-live")
    for sid in sessions:
        page.locator(f"#sessions-table tr[data-session-id='{sid}'] input").check()
    page.wait_for_function(
        f"document.querySelectorAll('.card [data-f=status]').length == {SESSIONS} && "
        "[...document.querySelectorAll('.card [data-f=status]')]"
        ".every(e => e.textContent == 'live')")
    page.evaluate("window.vlocViewer.resetStats()")
    ticks = int(LOAD_SECONDS * HZ)
    t0 = time.monotonic()
    for tick in range(ticks):
        for k, sid in enumerate(sessions):
            live.publish(sid, _moving_pose(template, sid, k, tick))
        time.sleep(max(0.0, t0 + (tick + 1) / HZ - time.monotonic()))
    page.wait_for_function(f"window.vlocViewer.stats().received == {ticks * SESSIONS}")
    stats = page.evaluate("window.vlocViewer.stats()")
    assert stats["gaps"] == 0
    for sid in sessions:
        s = stats["sessions"][sid]
        assert s["received"] == ticks and s["last_seq"] == ticks - 1
        assert s["cloud"] == 64 and s["track"] == ticks
    assert stats["drawn"] > 0
    page.screenshot(path=str(shots / "ten-sessions.png"))
    assert not log.errors, log.errors
    _report_load(stats, ticks)
    page.close()


def _moving_pose(template: dict, sid: str, k: int, tick: int) -> dict:
    """Session ``k`` circling its own point of the map, a tight cloud around it."""
    angle = 2 * math.pi * (tick / 50 + k / SESSIONS)
    cx, cy = template["x"] + 15 * math.cos(2 * math.pi * k / SESSIONS), template["y"]
    x, y = cx + 10 * math.cos(angle), cy + 10 * math.sin(angle)
    cloud = [[round(x + 2 * math.cos(i), 2), round(y + 2 * math.sin(1.7 * i), 2)]
             for i in range(64)]
    return template | {"session_id": sid, "seq": tick, "x": x, "y": y, "cloud": cloud,
                       "cov": [4.0, 0.5, 0.5, 2.0], "sigma_x": 2.0, "sigma_y": 1.41}


def _report_load(stats: dict, ticks: int) -> None:
    lines = [
        "# Viewer: ten live sessions at 10 Hz",
        "",
        f"Headless Chromium ({platform.machine()}, {os.cpu_count()} cores shared with the "
        "server), 1280x800; 10 sessions on one map, each streaming a pose with a 64-particle "
        f"sample every 100 ms for {ticks / HZ:g} s over its WebSocket; the page draws on "
        "animation frames.",
        "",
        "| figure | value |",
        "|---|---|",
        f"| pose messages sent / received | {ticks * SESSIONS} / {stats['received']} |",
        f"| sequence gaps (lost messages) | {stats['gaps']} |",
        f"| poses drawn as the current estimate | {stats['drawn']} "
        f"({stats['received'] - stats['drawn']} superseded within one frame) |",
        f"| animation frames | {stats['frames']} |",
        f"| frame interval p50 / p95 / max, ms | {stats['frame_interval_ms_p50']:.1f} / "
        f"{stats['frame_interval_ms_p95']:.1f} / {stats['frame_interval_ms_max']:.1f} |",
        f"| frames longer than 50 ms | {stats['long_frames']} of {stats['intervals']} |",
        f"| draw time per frame p50 / p95, ms | {stats['draw_ms_p50']:.2f} / "
        f"{stats['draw_ms_p95']:.2f} |",
        "",
    ]
    out = os.environ.get("VLOC_VIEWER_BENCH_OUT")
    text = "\n".join(lines)
    print(text)
    if out:
        Path(out).write_text(text)
        Path(out).with_suffix(".json").write_text(json.dumps(stats | {"ticks": ticks},
                                                             indent=1, sort_keys=True))


def _box_centre(locator) -> tuple[float, float]:
    box = locator.bounding_box()
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


def _cloud_pixels(page) -> int:
    """Coloured pixels on the canvas the particle cloud is drawn on."""
    return page.evaluate("""() => {
        let n = 0;
        for (const c of document.querySelectorAll('canvas.leaflet-zoom-animated')) {
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n += 1;
        }
        return n; }""")


def _no_secret_in_urls(log: PageLog, *secrets: str) -> None:
    assert log.urls
    for url in log.urls:
        for secret in secrets:
            assert secret not in url, url



