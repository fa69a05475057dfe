// What every part of the viewer shares: the page's state, the plan, the API.

export const PALETTE = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf",
                        "#e377c2", "#8c564b", "#bcbd22", "#7f7f7f", "#393b79", "#637939"];

export const $ = (sel) => document.querySelector(sel);
export const state = {
  creds: null,          // {kind: "admin" | "session", secret, sessionId}
  maps: [],
  mapId: null,          // the map on the plan
  mapImages: [],        // images of that map, with plan positions
  origin: null,         // {lat, lon} of the plan's east/north frame, where known
  planFor: null,        // the map the watched sessions are on
  planReady: Promise.resolve(),
  watchers: new Map(),  // session id -> Watcher
  colours: 0,
};

// -- the plan -------------------------------------------------------------------------

export const plan = L.map("map", { crs: L.CRS.Simple, minZoom: -6, maxZoom: 6, zoomSnap: 0,
                            attributionControl: false });
plan.setView([0, 0], 0);
L.control.scale({ imperial: false, position: "bottomleft", maxWidth: 160 }).addTo(plan);
const NorthArrow = L.Control.extend({
  options: { position: "topright" },
  onAdd() {
    const div = L.DomUtil.create("div", "north-arrow");
    div.title = "north: up (the map's local east-north frame)";
    div.innerHTML = "&#9650;<br>N";
    return div;
  },
});
new NorthArrow().addTo(plan);
export const cloudRenderer = L.canvas({ padding: 0.2 });
export const imageLayer = L.layerGroup().addTo(plan);
export const liveLayer = L.layerGroup().addTo(plan);  // the watched sessions' drawings

// plan coordinates: Leaflet's (lat, lng) are (north, east) in metres under CRS.Simple
export const at = (east, north) => L.latLng(north, east);

// -- API ------------------------------------------------------------------------------

export class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

export async function api(path, { method = "GET", body = null, json = null, blob = false } = {}) {
  const headers = { Authorization: `Bearer ${state.creds.secret}` };
  if (json !== null) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  }
  const r = await fetch(path, { method, headers, body, cache: "no-store" });
  if (!r.ok) {
    let detail = `${r.status} ${r.statusText}`;
    try { detail = (await r.json()).detail || detail; } catch (e) { /* not JSON */ }
    throw new ApiError(r.status, detail);
  }
  if (blob) return r;
  return r.status === 204 ? null : r.json();
}

// Every item of a paged list: pages of `limit` by `offset`, or by the last item's id
// (`after_id`, the map images), until a page comes back short.
export async function listAll(path, { by = "offset", limit = 1000 } = {}) {
  const items = [];
  for (;;) {
    const cursor = by === "offset" ? `offset=${items.length}`
      : `after_id=${items.length ? items[items.length - 1].id : 0}`;
    const page = await api(`${path}?limit=${limit}&${cursor}`);
    items.push(...page);
    if (page.length < limit) return items;
  }
}

export function say(text) { $("#status").textContent = text; }

export function escapeHtml(s) {
  return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;",
                                         '"': "&quot;", "'": "&#39;" }[c]));
}
