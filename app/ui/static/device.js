// The device page: a phone localises itself. It sends its camera's frames to its session at
// the chosen rate, with its compass heading and location fix as the frames' metadata, and
// draws the poses that come back: position, accuracy circle, track, and its own fix.
//
// The session and its token come in the page's fragment (#session=...&token=..., which no
// request carries), are kept in this tab's sessionStorage and the fragment is cleared at
// once; the token travels only in Authorization headers, never in a URL.

import { $, api, at, plan, say, state } from "./common.js";
import { installTiles, setOrigin } from "./tiles.js";

const STORE_KEY = "vloc.device.credentials";
const FIX_MAX_AGE_MS = 10000;     // an older location fix is not sent
const HEADING_MAX_AGE_MS = 2000;
const COMPASS_ACCURACY_DEG = 30;  // a phone's magnetometer, where it does not say
const FRAME_WIDTH = 640;

const device = {          // what the page did, for the person and for tests
  poses: [], last: null, sent: 0, failed: 0, origin: null, running: false,
};
window.vlocDevice = device;

const layers = {
  track: L.polyline([], { color: "#d62728", weight: 2, className: "vloc-track" }).addTo(plan),
  accuracy: L.circle([0, 0], { radius: 1, color: "#d62728", weight: 1.5, fillOpacity: 0.12,
                               className: "vloc-accuracy" }),
  marker: L.circleMarker([0, 0], { radius: 7, color: "#fff", weight: 2, fillColor: "#d62728",
                                   fillOpacity: 1, className: "vloc-marker" }),
  fix: L.circleMarker([0, 0], { radius: 5, color: "#1f77b4", weight: 2, fillOpacity: 0.3,
                                className: "vloc-phone-fix" }),
};

let fix = null;        // {lat, lon, accuracy, at}
let heading = null;    // {deg, accuracy, at}

// -- credentials ------------------------------------------------------------------------

function takeFragment() {
  const h = new URLSearchParams(location.hash.slice(1));
  if (h.get("session") && h.get("token")) {
    sessionStorage.setItem(STORE_KEY, JSON.stringify({ sessionId: h.get("session"),
                                                       secret: h.get("token") }));
  }
  if (location.hash) history.replaceState(null, "", location.pathname + location.search);
  const saved = sessionStorage.getItem(STORE_KEY);
  return saved ? JSON.parse(saved) : null;
}

async function signIn(creds) {
  state.creds = { kind: "session", ...creds };
  let session;
  try {
    session = await api(`/v1/sessions/${encodeURIComponent(creds.sessionId)}`);
  } catch (err) {
    state.creds = null;
    sessionStorage.removeItem(STORE_KEY);
    $("#login").hidden = false;
    $("#login-error").textContent = `refused: ${err.message}`;
    return;
  }
  sessionStorage.setItem(STORE_KEY, JSON.stringify(creds));
  $("#login").hidden = true;
  $("#controls").hidden = false;
  plan.invalidateSize();  // the panel above it just grew
  $("#who").textContent = `session ${session.id.slice(0, 8)} (${session.mode})`;
  if (session.last_pose) draw(session.last_pose);
  say("ready: Start sends the camera's frames");
  device.ready = true;
}

$("#login").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const creds = { sessionId: $("#login-session").value.trim(),
                  secret: $("#login-token").value.trim() };
  if (creds.sessionId && creds.secret) signIn(creds);
});

// -- sensors ----------------------------------------------------------------------------

function watchLocation() {
  if (!navigator.geolocation) return;
  navigator.geolocation.watchPosition((p) => {
    fix = { lat: p.coords.latitude, lon: p.coords.longitude, accuracy: p.coords.accuracy,
            at: Date.now() };
    showSensors();
  }, (err) => { say(`location: ${err.message}`); }, { enableHighAccuracy: true });
}

function onOrientation(ev) {
  // iOS gives the compass bearing itself; elsewhere an absolute alpha is counter-clockwise
  // from north (the bearing of the phone's top edge is 360 - alpha)
  if (typeof ev.webkitCompassHeading === "number") {
    heading = { deg: ev.webkitCompassHeading % 360,
                accuracy: ev.webkitCompassAccuracy > 0 ? ev.webkitCompassAccuracy
                  : COMPASS_ACCURACY_DEG, at: Date.now() };
  } else if (ev.absolute && typeof ev.alpha === "number") {
    heading = { deg: (360 - ev.alpha) % 360, accuracy: COMPASS_ACCURACY_DEG, at: Date.now() };
  }
}

async function watchHeading() {
  const D = window.DeviceOrientationEvent;
  if (D && typeof D.requestPermission === "function") {
    try { await D.requestPermission(); } catch (err) { /* no compass: frames go without */ }
  }
  window.addEventListener("deviceorientationabsolute", onOrientation);
  window.addEventListener("deviceorientation", onOrientation);
}

function showSensors() {
  const parts = [];
  if (fix) parts.push(`fix ${fix.lat.toFixed(6)}, ${fix.lon.toFixed(6)} ±${fix.accuracy.toFixed(0)} m`);
  if (heading) parts.push(`heading ${heading.deg.toFixed(0)}°`);
  $("#sensor-line").textContent = parts.join("; ") || "no location or compass yet";
  if (fix && device.origin) {
    const p = toPlan(fix.lat, fix.lon);
    layers.fix.setLatLng(at(p.east, p.north)).addTo(plan);
  }
}

function metadata() {
  const now = Date.now(), meta = { captured_at: new Date(now).toISOString() };
  if (fix && now - fix.at < FIX_MAX_AGE_MS) {
    meta.gps_lat = fix.lat;
    meta.gps_lon = fix.lon;
    meta.gps_accuracy_m = Math.min(Math.max(fix.accuracy, 0.01), 10000);
  }
  if (heading && now - heading.at < HEADING_MAX_AGE_MS) {
    meta.heading_deg = heading.deg;
    meta.heading_accuracy_deg = Math.min(Math.max(heading.accuracy, 0.01), 180);
  }
  return meta;
}

// -- frames -----------------------------------------------------------------------------

const canvas = document.createElement("canvas");

function grab(video) {
  const scale = Math.min(1, FRAME_WIDTH / video.videoWidth);
  canvas.width = Math.round(video.videoWidth * scale);
  canvas.height = Math.round(video.videoHeight * scale);
  canvas.getContext("2d").drawImage(video, 0, 0, canvas.width, canvas.height);
  return new Promise((ok) => canvas.toBlob(ok, "image/jpeg", 0.85));
}

async function sendFrame(video) {
  const blob = await grab(video);
  if (!blob) return;
  const params = new URLSearchParams({ ...metadata(), wait: "true" });
  const r = await fetch(`/v1/sessions/${encodeURIComponent(state.creds.sessionId)}/frames?${params}`, {
    method: "POST", body: blob, cache: "no-store",
    headers: { Authorization: `Bearer ${state.creds.secret}`, "Content-Type": "image/jpeg" },
  });
  if (!r.ok) {
    device.failed += 1;
    let detail = `${r.status}`;
    try { detail = (await r.json()).detail || detail; } catch (e) { /* not JSON */ }
    say(`frame refused: ${detail}`);
    return;
  }
  device.sent += 1;
  draw(await r.json());
}

async function start() {
  const video = $("#camera");
  try {
    video.srcObject = await navigator.mediaDevices.getUserMedia({
      audio: false, video: { facingMode: "environment", width: { ideal: 1280 } } });
    await video.play();
  } catch (err) {
    say(`camera: ${err.message} (the page needs HTTPS, or http://localhost)`);
    return;
  }
  watchLocation();
  await watchHeading();
  device.running = true;
  $("#start").textContent = "Stop";
  say("sending frames");
  while (device.running) {
    const began = Date.now();
    try { await sendFrame(video); } catch (err) { say(`no answer: ${err.message}`); }
    const period = 1000 / Number($("#rate").value);
    await new Promise((ok) => setTimeout(ok, Math.max(0, period - (Date.now() - began))));
  }
  video.srcObject.getTracks().forEach((t) => t.stop());
  $("#start").textContent = "Start";
  say("stopped");
}

$("#start").addEventListener("click", () => {
  if (device.running) device.running = false; else start();
});

// -- the plan ---------------------------------------------------------------------------

// The map's origin from one pose (its position in both frames): a step back by (x, y)
// metres on the ellipsoid's radii of curvature there.
function originOf(p) {
  const rad = Math.PI / 180, a = 6378137, e2 = 6.69437999014e-3;
  const s2 = Math.sin(p.lat * rad) ** 2;
  const meridian = (a * (1 - e2)) / (1 - e2 * s2) ** 1.5, normal = a / Math.sqrt(1 - e2 * s2);
  const lat = p.lat - p.y / meridian / rad;
  return { lat, lon: p.lon - p.x / (normal * Math.cos(lat * rad)) / rad };
}

function toPlan(lat, lon) {
  const rad = Math.PI / 180, o = device.origin, a = 6378137, e2 = 6.69437999014e-3;
  const s2 = Math.sin(o.lat * rad) ** 2;
  const meridian = (a * (1 - e2)) / (1 - e2 * s2) ** 1.5, normal = a / Math.sqrt(1 - e2 * s2);
  return { east: (lon - o.lon) * rad * normal * Math.cos(o.lat * rad),
           north: (lat - o.lat) * rad * meridian };
}

function draw(p) {
  if (p.type !== "pose") return;
  device.poses.push(p);
  device.last = p;
  if (!device.origin) {
    plan.invalidateSize();
    device.origin = originOf(p);
    setOrigin(device.origin);
    plan.setView(at(p.x, p.y), 1, { animate: false });
  }
  const here = at(p.x, p.y);
  layers.marker.setLatLng(here).addTo(plan);
  layers.accuracy.setLatLng(here).setRadius(p.horizontal_accuracy_m || 1).addTo(plan);
  if (p.status === "tracking") layers.track.addLatLng(here);
  if (!plan.getBounds().pad(-0.2).contains(here)) plan.panTo(here, { animate: false });
  $("#pose-line").textContent = `${p.status}, ${p.lat.toFixed(6)}, ${p.lon.toFixed(6)} ` +
    `±${(p.horizontal_accuracy_m || 0).toFixed(1)} m` +
    (p.heading_deg === null ? "" : `, heading ${p.heading_deg.toFixed(0)}°`) + ` (frame ${p.seq})`;
  showSensors();
}

installTiles();
const creds = takeFragment();
if (creds) signIn(creds); else $("#login").hidden = false;
