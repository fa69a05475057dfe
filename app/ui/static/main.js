// The vloc web viewer: maps drawn on a plan in metres, live sessions from their pose streams,
// replays and evaluations against the truth.
//
// Everything is read from the API with the user's credentials, which stay in this tab's
// sessionStorage and travel only in headers (fetch) or as the WebSocket subprotocol
// `vloc.token.<secret>`: never in a URL, which servers and proxies log.

import { $, api, imageLayer, liveLayer, plan, state } from "./common.js";
import "./device-link.js";
import { followSessions, watch } from "./live.js";
import { refreshMaps } from "./maps.js";
import { replayLayer } from "./replays.js";
import { installTiles, setOrigin } from "./tiles.js";

const STORE_KEY = "vloc.viewer.credentials";

function loginKind() { return document.querySelector("input[name=kind]:checked").value; }

document.querySelectorAll("input[name=kind]").forEach((el) =>
  el.addEventListener("change", () => { $("#session-field").hidden = loginKind() !== "session"; }));

$("#login").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const creds = { kind: loginKind(), secret: $("#login-secret").value.trim(),
                  sessionId: $("#login-session").value.trim() };
  $("#login-error").textContent = "";
  if (!creds.secret || (creds.kind === "session" && !creds.sessionId)) {
    $("#login-error").textContent = creds.secret ? "give the session id" : "give the key or token";
    return;
  }
  await signIn(creds);
});

async function signIn(creds) {
  state.creds = creds;
  try {
    // one request that only these credentials can answer
    if (creds.kind === "admin") await api("/v1/maps?limit=1");
    else await api(`/v1/sessions/${encodeURIComponent(creds.sessionId)}`);
  } catch (err) {
    state.creds = null;
    sessionStorage.removeItem(STORE_KEY);
    $("#login-error").textContent = `refused: ${err.message}`;
    return;
  }
  sessionStorage.setItem(STORE_KEY, JSON.stringify(creds));
  $("#login").hidden = true;
  $("#sign-out").hidden = false;
  $("#who").textContent = creds.kind === "admin" ? "admin" : `session ${creds.sessionId.slice(0, 8)}`;
  $("#tabs").hidden = false;
  // a session token opens no admin view
  $("#tab-maps").hidden = creds.kind !== "admin";
  if (creds.kind === "admin") {
    showTab("maps");  // first: the person may pick another tab while the list loads
    await refreshMaps();
  } else {
    showTab("live");
    $("#live-hint").textContent = "Watching the session this token opens.";
    $("#sessions-table").hidden = true;
    const s = await api(`/v1/sessions/${encodeURIComponent(creds.sessionId)}`);
    watch(s);
  }
}

$("#sign-out").addEventListener("click", () => {
  sessionStorage.removeItem(STORE_KEY);
  location.reload();
});

let shownTab = null;
let viewBeforeReplays = null;  // the plan's view when the Replays tab was opened

function showTab(name) {
  $("#maps-pane").hidden = name !== "maps";
  $("#live-pane").hidden = name !== "live";
  $("#replays-pane").hidden = name !== "replays";
  // a loaded replay has the plan to itself; maps and live sessions come back after it,
  // framed as they were
  for (const layer of [imageLayer, liveLayer]) {
    if (name === "replays") layer.remove(); else layer.addTo(plan);
  }
  if (name === "replays") replayLayer.addTo(plan); else replayLayer.remove();
  if (name === "replays" && shownTab !== "replays") {
    viewBeforeReplays = { center: plan.getCenter(), zoom: plan.getZoom() };
  } else if (name !== "replays" && shownTab === "replays" && viewBeforeReplays) {
    plan.setView(viewBeforeReplays.center, viewBeforeReplays.zoom, { animate: false });
  }
  shownTab = name;
  // a replay's file says nothing of where on earth its frame is
  setOrigin(name === "replays" ? null : state.origin);
  document.querySelectorAll("#tabs button").forEach((b) =>
    b.classList.toggle("active", b.dataset.tab === name));
  followSessions(name === "live" && state.creds.kind === "admin");
}
document.querySelectorAll("#tabs button").forEach((b) =>
  b.addEventListener("click", () => showTab(b.dataset.tab)));

installTiles();
const saved = sessionStorage.getItem(STORE_KEY);
if (saved) signIn(JSON.parse(saved));
