"""The device page at /ui/device in headless Chromium: an admin opens a session for a device
from the viewer, which shows its link once as a QR code; the "phone" opens the link with a
fake camera playing a seneca-uav frame and a faked location fix, and its position converges
on the truth. No token in any URL, no console error."""

from __future__ import annotations

import csv
import math
import os
import time
from pathlib import Path

import httpx
import pytest

from tests.app.conftest import ADMIN, ADMIN_KEY
from tests.conftest import REPO_ROOT
from tests.e2e.browser import PageLog, launch_browser

pytestmark = pytest.mark.dataset

QUERY = "IMG_0552.jpg"
"""A pass-2 frame the phone's camera sees; the map is the pass-1 images around it."""
HEADING = 54.0          # the flight line's bearing there
FIX_OFFSET_M = (25.0, -20.0)  # the faked location fix: east, north of the truth
FIX_ACCURACY_M = 40.0
DOCS = REPO_ROOT / "docs" / "devices"


def _truth(seneca_dir: Path) -> dict[str, dict]:
    with open(seneca_dir / "ground_truth.csv", newline="") as fh:
        return {r["filename"]: r for r in csv.DictReader(fh)}


def _write_y4m(jpeg: Path, out: Path, frames: int = 10) -> Path:
    """The frame as a Y4M video Chromium's fake camera plays (in a loop)."""
    import cv2

    image = cv2.resize(cv2.imread(str(jpeg)), (640, 480), interpolation=cv2.INTER_AREA)
    yuv = cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420).tobytes()
    with open(out, "wb") as fh:
        fh.write(b"YUV4MPEG2 W640 H480 F5:1 Ip A1:1 C420jpeg\n")
        for _ in range(frames):
            fh.write(b"FRAME\n" + yuv)
    return out


@pytest.fixture(scope="module")
def camera_file(seneca_dir, tmp_path_factory) -> Path:
    return _write_y4m(seneca_dir / "images" / QUERY, tmp_path_factory.mktemp("cam") / "cam.y4m")


@pytest.fixture(scope="module")
def phone_browser(camera_file):
    yield from launch_browser(("--use-fake-device-for-media-stream",
                               "--use-fake-ui-for-media-stream",
                               f"--use-file-for-fake-video-capture={camera_file}"))


@pytest.fixture(scope="module")
def seneca_map(live, seneca_dir) -> str:
    """A map of the pass-1 images within 60 m of the query frame's truth."""
    from vloc.workers.core.geo import GeoOrigin

    truth = _truth(seneca_dir)
    q = truth[QUERY]
    origin = GeoOrigin(float(q["lat"]), float(q["lon"]), 0.0)
    names = []
    for r in truth.values():
        e, n = origin.to_local([float(r["lat"])], [float(r["lon"])])
        if r["pass"] == "1" and math.hypot(e[0], n[0]) < 60.0:
            names.append(r["filename"])
    with httpx.Client(base_url=live.base_url, headers=ADMIN, timeout=120) as http:
        map_id = http.post("/v1/maps", json={"name": "seneca around the phone"}).json()["id"]
        files = [("files", (n, (seneca_dir / "images" / n).read_bytes(), "image/jpeg"))
                 for n in names]
        assert http.post(f"/v1/maps/{map_id}/images", files=files).status_code == 201
        job_id = http.post(f"/v1/maps/{map_id}/build").json()["job_id"]
        deadline = time.monotonic() + 600
        while (job := http.get(f"/v1/jobs/{job_id}").json())["status"] not in ("done",
                                                                               "failed"):
            assert time.monotonic() < deadline, job
            time.sleep(0.2)
        assert job["status"] == "done", job
    return map_id


def _offset(lat: float, lon: float, east: float, north: float) -> tuple[float, float]:
    from vloc.workers.core.geo import GeoOrigin

    return GeoOrigin(lat, lon, 0.0).to_wgs84([east], [north])


ORIENTATION = """
window.addEventListener("load", () => setInterval(() => {
  const ev = new Event("deviceorientationabsolute");
  Object.assign(ev, { absolute: true, alpha: (360 - %f) %% 360, beta: 0, gamma: 0 });
  window.dispatchEvent(ev);
}, 200));
"""


def test_a_phone_localises_itself_from_the_device_page(live, phone_browser, seneca_map,
                                                        seneca_dir):
    from vloc.workers.core.geo import GeoOrigin

    # the admin opens a session for the device from the viewer
    admin = phone_browser.new_context(viewport={"width": 1100, "height": 760})
    viewer = admin.new_page()
    viewer_log = PageLog()
    viewer_log.watch(viewer)
    viewer.goto(live.base_url + "/ui/")
    viewer.check("input[value=admin]")
    viewer.fill("#login-secret", ADMIN_KEY)
    viewer.click("#login-submit")
    viewer.click(f"#maps-table tr[data-map-id='{seneca_map}']")
    viewer.click("#device-session")
    viewer.wait_for_selector("#device-box:not([hidden])")
    link = viewer.get_attribute("#device-url", "href")
    assert "#session=" in link and "&token=" in link
    assert viewer.locator("#device-qr path").count() == 1
    token = link.split("token=")[1]
    if os.environ.get("VLOC_WRITE_SCREENSHOTS") == "1":
        viewer.screenshot(path=str(DOCS / "viewer-device-session.png"))

    # the phone opens the link, with a location fix off by ~32 m and a compass
    truth = _truth(seneca_dir)[QUERY]
    t_lat, t_lon = float(truth["lat"]), float(truth["lon"])
    f_lat, f_lon = _offset(t_lat, t_lon, *FIX_OFFSET_M)
    phone = phone_browser.new_context(
        viewport={"width": 390, "height": 780}, is_mobile=True, has_touch=True,
        geolocation={"latitude": float(f_lat[0]), "longitude": float(f_lon[0]),
                     "accuracy": FIX_ACCURACY_M},
        permissions=["geolocation", "camera"])
    phone.add_init_script(ORIENTATION % HEADING)
    page = phone.new_page()
    log = PageLog()
    log.watch(page)
    page.goto(link)
    page.wait_for_function("window.vlocDevice && window.vlocDevice.ready === true")
    assert page.evaluate("location.href") == live.base_url + "/ui/device"
    page.select_option("#rate", "2")
    page.click("#start")
    # converged: a tracking pose within 10 m of the truth, three in a row
    origin = GeoOrigin(t_lat, t_lon, 0.0)
    errors: list[float] = []
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        poses = page.evaluate("window.vlocDevice.poses.map(p => [p.lat, p.lon, p.status])")
        errors = []
        for lat, lon, _ in poses:
            e, n = origin.to_local([lat], [lon])
            errors.append(math.hypot(e[0], n[0]))
        if len(poses) >= 3 and all(err < 10.0 and s == "tracking"
                                   for err, (_, _, s) in zip(errors[-3:], poses[-3:],
                                                             strict=True)):
            break
        time.sleep(0.5)
    print(f"device page: {len(errors)} poses, error to the truth "
          + ", ".join(f"{e:.1f}" for e in errors) + " m")
    assert len(errors) >= 3 and max(errors[-3:]) < 10.0, errors
    page.wait_for_selector(".vloc-phone-fix")
    if os.environ.get("VLOC_WRITE_SCREENSHOTS") == "1":
        page.screenshot(path=str(DOCS / "phone.png"))
    page.click("#start")  # stop
    page.wait_for_function("window.vlocDevice.running === false")

    # the frames carried the phone's fix and heading; the token went in no URL
    frames = [u for u in log.urls if "/frames?" in u]
    assert frames and all("gps_lat=" in u and "heading_deg=" in u for u in frames[1:])
    assert all(token not in u for u in log.urls + viewer_log.urls)
    assert log.errors == [] and viewer_log.errors == []
    admin.close()
    phone.close()
