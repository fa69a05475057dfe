// Live sessions: each watched session's pose stream drawn on the plan, and its card.
//
// Poses are drawn on animation frames, not as they arrive: a burst of messages from many
// sessions costs one redraw per frame. `window.vlocViewer.stats()` reports what arrived,
// what was drawn and how long the frames took.

import {
  $, PALETTE, api, at, cloudRenderer, imageLayer, listAll, liveLayer, plan, say, state,
} from "./common.js";
import { imageUrl, refreshMaps, selectMap } from "./maps.js";
import { setOrigin } from "./tiles.js";

const CHI2_95 = 5.991;          // 2 degrees of freedom: the 95 % uncertainty ellipse
const ELLIPSE_POINTS = 48;
const TRACK_LIMIT = 5000;       // points kept per track; older ones are dropped
const THUMB_INTERVAL_MS = 1000; // at most one last-frame fetch per session per second
const STEP_CELLS = 60;          // frames shown in a card's strip of step kinds
const RECONNECT_MS = [500, 1000, 2000, 5000, 10000];  // waits before each new attempt
const FINAL_CLOSE = new Set([4401, 4403, 4404, 4410]);    // refused: trying again will not help

const TABLE_REFRESH_MS = 2000;   // the sessions table's counters, while it is shown

// The sessions table: rows added and removed as sessions come and go, the counters of the
// existing ones updated in place (a tick box being clicked stays where it is).
export async function refreshSessions() {
  const sessions = await listAll("/v1/sessions");
  const body = $("#sessions-table tbody");
  const rows = new Map([...body.children].map((tr) => [tr.dataset.sessionId, tr]));
  body.replaceChildren(...sessions.map((s) => {
    const tr = rows.get(s.id) || sessionRow(s);
    tr.querySelector("[data-f=frames]").textContent = String(s.frames_processed);
    tr.querySelector("input").checked = state.watchers.has(s.id);
    return tr;
  }));
}

function sessionRow(s) {
  const tr = document.createElement("tr");
  tr.dataset.sessionId = s.id;
  const box = document.createElement("input");
  box.type = "checkbox";
  box.addEventListener("change", () => (box.checked ? watch(s) : unwatch(s.id)));
  const cells = [box, s.id.slice(0, 8), s.mode, ""];
  for (const c of cells) {
    const td = document.createElement("td");
    td.append(c);
    tr.append(td);
  }
  tr.lastChild.dataset.f = "frames";
  return tr;
}

// Refresh the table every TABLE_REFRESH_MS while the Live tab shows it.
let tableTimer = null;
export function followSessions(on) {
  clearTimeout(tableTimer);
  tableTimer = null;
  if (!on) return;
  const tick = async () => {
    try { await refreshSessions(); } catch (err) { say(`sessions: ${err.message}`); }
    if (tableTimer !== null) tableTimer = setTimeout(tick, TABLE_REFRESH_MS);
  };
  tableTimer = setTimeout(tick, 0);
}

export async function watch(session) {
  if (state.watchers.has(session.id)) return;
  if (state.creds.kind === "admin" && session.map_id !== state.planFor) {
    // one plan at a time: sessions of another map make way
    for (const id of [...state.watchers.keys()]) unwatch(id);
    state.planFor = session.map_id;  // claimed before waiting: later ticks wait on it
    state.planReady = refreshMaps().then(() => selectMap(session.map_id));
  }
  await state.planReady;
  if (state.watchers.has(session.id)) return;
  const w = new Watcher(session, PALETTE[state.colours++ % PALETTE.length]);
  state.watchers.set(session.id, w);
  w.open();
}

function unwatch(sessionId) {
  const w = state.watchers.get(sessionId);
  if (!w) return;
  w.close();
  state.watchers.delete(sessionId);
  const box = document.querySelector(`#sessions-table tr[data-session-id="${sessionId}"] input`);
  if (box) box.checked = false;
}

class Watcher {
  constructor(session, colour) {
    this.session = session;
    this.colour = colour;
    this.track = [];
    this.trackSeqs = [];   // the seq of each track point, ascending
    this.pending = null;   // the newest pose not drawn yet
    this.lastSeq = null;
    this.received = 0;     // pose messages
    this.drawn = 0;        // poses that reached the plan as the current estimate
    this.gaps = 0;         // frames missing between consecutive pose messages
    this.errors = 0;       // frame_error messages
    this.lastThumb = 0;
    this.newSteps = [];    // step kinds of poses not yet added to the card's strip
    this.firstLiveSeq = null;
    this.layers = {
      track: L.polyline([], { color: colour, weight: 2, opacity: 0.8, className: "vloc-track" }),
      ellipse: L.polygon([], { color: colour, weight: 1.5, fillOpacity: 0.12, smoothFactor: 0,
                               className: "vloc-ellipse" }),
      cloud: L.layerGroup(),
      heading: L.polyline([], { color: colour, weight: 3, className: "vloc-heading" }),
      marker: L.circleMarker([0, 0], { radius: 7, color: "#fff", weight: 2, fillColor: colour,
                                       fillOpacity: 1, className: "vloc-marker" }),
    };
    this.card = this.makeCard();
  }

  makeCard() {
    const card = document.createElement("div");
    card.className = "card";
    card.dataset.sessionId = this.session.id;
    card.style.setProperty("--colour", this.colour);
    card.innerHTML = `<div class="title"></div><dl>
      <dt>frame</dt><dd data-f="seq">-</dd><dt>status</dt><dd data-f="status">connecting</dd>
      <dt>step</dt><dd data-f="step">-</dd><dt>position</dt><dd data-f="pos">-</dd>
      <dt>&sigma; (m)</dt><dd data-f="sigma">-</dd><dt>latency</dt><dd data-f="latency">-</dd>
      </dl><div class="steps" data-f="steps" title="step kind per frame: global, sift, refined"></div>
      <div class="steps-legend" aria-label="step kinds">
        <span><i class="step-cell step-global"></i>global features</span>
        <span><i class="step-cell step-sift"></i>SIFT</span>
        <span><i class="step-cell step-refined"></i>refined (registered)</span></div>
      <div class="thumbs">
      <figure><img data-f="frame" alt="last frame"><figcaption data-f="frame-cap">last frame</figcaption></figure>
      <figure><img data-f="best" alt="best matched map image"><figcaption data-f="best-cap">best match</figcaption></figure>
      </div>`;
    card.querySelector(".title").textContent =
      `${this.session.id.slice(0, 8)} · ${this.session.mode}`;
    $("#watch-cards").append(card);
    return card;
  }

  field(name) { return this.card.querySelector(`[data-f="${name}"]`); }

  open() {
    for (const layer of Object.values(this.layers)) layer.addTo(liveLayer);
    this.attempts = 0;
    this.connect();
    this.loadHistory();
  }

  connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const url = `${proto}//${location.host}/v1/sessions/${this.session.id}/stream`;
    try {
      this.ws = new WebSocket(url, ["vloc", `vloc.token.${state.creds.secret}`]);
    } catch (err) {
      // a subprotocol is a token: a key with spaces or separators cannot travel as one
      this.field("status").textContent = `cannot open the stream with this key: ${err.message}`;
      return;
    }
    this.ws.onmessage = (ev) => this.onMessage(JSON.parse(ev.data));
    this.ws.onclose = (ev) => this.onClose(ev);
  }

  // A stream that ends for a passing reason (the server restarts, the network drops) is
  // opened again, and the poses answered meanwhile are read from the stored ones.
  onClose(ev) {
    if (this.closing) return;
    const why = `${ev.code}${ev.reason ? ": " + ev.reason : ""}`;
    if (this.deleted || FINAL_CLOSE.has(ev.code)) {
      this.field("status").textContent = `stream closed (${why})`;
      return;
    }
    const wait = RECONNECT_MS[Math.min(this.attempts, RECONNECT_MS.length - 1)];
    this.attempts += 1;
    this.field("status").textContent = `reconnecting (${why})`;
    this.reconnects = (this.reconnects || 0) + 1;
    this.retryTimer = setTimeout(() => this.connect(), wait);
  }

  // Stored poses after `afterSeq` that the stream did not bring, into the track.
  async fillGap(afterSeq) {
    let stored;
    try {
      stored = await api(`/v1/sessions/${this.session.id}/poses?after_seq=${afterSeq}&limit=${TRACK_LIMIT}`);
    } catch (err) { say(`missed poses: ${err.message}`); return; }
    for (const p of stored) {
      if (p.type !== "pose" || this.trackSeqs.includes(p.seq)) continue;
      this.addPoint(p);
      this.filled = (this.filled || 0) + 1;
      if (this.lastSeq === null || p.seq > this.lastSeq) {
        this.lastSeq = p.seq;
        this.pending = p;
      }
    }
  }

  addPoint(p) {
    let i = this.trackSeqs.length;
    while (i > 0 && this.trackSeqs[i - 1] > p.seq) i -= 1;  // poses come in order, mostly
    this.trackSeqs.splice(i, 0, p.seq);
    this.track.splice(i, 0, at(p.x, p.y));
    if (this.track.length > TRACK_LIMIT) {
      this.track.splice(0, this.track.length - TRACK_LIMIT);
      this.trackSeqs.splice(0, this.trackSeqs.length - TRACK_LIMIT);
    }
  }

  // The track so far: the stored poses before the first one the stream brought.
  async loadHistory() {
    const last = this.session.last_seq;
    const after = last === null || last === undefined ? -1 : Math.max(-1, last - TRACK_LIMIT);
    let stored;
    try {
      stored = await api(`/v1/sessions/${this.session.id}/poses?after_seq=${after}&limit=${TRACK_LIMIT}`);
    } catch (err) { say(`track so far: ${err.message}`); return; }
    const past = stored.filter((p) => p.type === "pose" &&
                                      (this.firstLiveSeq === null || p.seq < this.firstLiveSeq));
    if (!past.length) return;
    for (const p of past) this.addPoint(p);
    this.newSteps = past.map(stepKind).concat(this.newSteps);
    this.history = past.length;
    if (this.pending === null && this.lastSeq === null) {
      this.pending = past[past.length - 1];
      this.lastSeq = this.pending.seq;
    }
  }

  close() {
    this.closing = true;
    clearTimeout(this.frameTimer);
    clearTimeout(this.retryTimer);
    if (this.ws) this.ws.close(1000);
    for (const layer of Object.values(this.layers)) layer.remove();
    this.card.remove();
  }

  onMessage(msg) {
    if (msg.type === "hello") {
      this.field("status").textContent = "live";
      if (this.attempts > 0 && this.lastSeq !== null) this.fillGap(this.lastSeq);
      this.attempts = 0;
    } else if (msg.type === "pose") {
      this.received += 1;
      if (this.firstLiveSeq === null) this.firstLiveSeq = msg.seq;
      this.newSteps.push(stepKind(msg));
      if (this.lastSeq !== null && msg.seq > this.lastSeq + 1) this.gaps += msg.seq - this.lastSeq - 1;
      this.lastSeq = msg.seq;
      this.addPoint(msg);
      this.pending = msg;
    } else if (msg.type === "frame_error") {
      this.errors += 1;
      this.lastSeq = msg.seq;
      this.field("status").textContent = `frame ${msg.seq}: ${msg.kind}`;
    } else if (msg.type === "closed") {
      this.deleted = true;
      this.field("status").textContent = msg.kind === "session-expired"
        ? "session expired" : "session deleted";
    }
  }

  draw() {
    const p = this.pending;
    if (!p) return false;
    this.pending = null;
    this.drawn += 1;
    const here = at(p.x, p.y);
    this.layers.marker.setLatLng(here);
    if (state.origin === null && state.creds.kind === "session") {
      // a token reads no map: the frame's origin follows from a pose in both frames
      state.origin = originOf(p);
      setOrigin(state.origin);
    }
    if (!this.centred && imageLayer.getLayers().length === 0) {
      // no map images to frame the view (a session token sees no map): frame the estimate
      plan.setView(here, 1, { animate: false });
      this.centred = true;
    }
    this.layers.track.setLatLngs(this.track);
    this.layers.ellipse.setLatLngs(ellipse(p.x, p.y, p.cov));
    this.drawCloud(p.cloud || []);
    if (typeof p.heading_deg === "number") {
      const r = 3 * Math.max(p.sigma_x, p.sigma_y, 2);
      const a = p.heading_deg * Math.PI / 180;   // clockwise from north
      this.layers.heading.setLatLngs([here, at(p.x + r * Math.sin(a), p.y + r * Math.cos(a))]);
    }
    this.drawSteps();
    this.field("seq").textContent = String(p.seq);
    this.field("status").textContent = p.status;
    const kind = stepKind(p);
    const step = this.field("step");
    step.textContent = `${p.feature}${p.measurement ? " (" + p.measurement + ")" : ""}`;
    step.className = `step-${kind}`;
    this.field("pos").textContent = `${p.x.toFixed(1)} E, ${p.y.toFixed(1)} N`;
    this.field("sigma").textContent = `${p.sigma_x.toFixed(1)} × ${p.sigma_y.toFixed(1)}`;
    this.field("latency").textContent = `${Math.round(p.latency_ms)} ms (step ${Math.round(p.processing_ms)} ms)`;
    this.latest = p;
    this.scheduleFrames();
    return true;
  }

  drawSteps() {
    const strip = this.field("steps");
    for (const kind of this.newSteps.slice(-STEP_CELLS)) {
      const cell = document.createElement("span");
      cell.className = `step-cell step-${kind}`;
      strip.append(cell);
    }
    this.newSteps = [];
    while (strip.childElementCount > STEP_CELLS) strip.firstElementChild.remove();
  }

  drawCloud(points) {
    const cloud = this.layers.cloud;
    const markers = cloud.getLayers();
    // reuse the markers: a sample has the same size from step to step
    for (let i = 0; i < points.length; i += 1) {
      const ll = at(points[i][0], points[i][1]);
      if (i < markers.length) markers[i].setLatLng(ll);
      else {
        cloud.addLayer(L.circleMarker(ll, { renderer: cloudRenderer, radius: 2, stroke: false,
                                            fillColor: this.colour, fillOpacity: 0.55 }));
      }
    }
    for (let i = points.length; i < markers.length; i += 1) cloud.removeLayer(markers[i]);
  }

  // Thumbnails at most once a second, and always for the latest pose in the end.
  scheduleFrames() {
    if (this.frameTimer) return;
    const wait = Math.max(0, this.lastThumb + THUMB_INTERVAL_MS - performance.now());
    this.frameTimer = setTimeout(() => {
      this.frameTimer = null;
      this.lastThumb = performance.now();
      if (!this.closing) this.showFrames(this.latest);
    }, wait);
  }

  async showFrames(p) {
    try {
      const r = await api(`/v1/sessions/${this.session.id}/frames/last`, { blob: true });
      if (r.status === 200) {  // 204: no frame since the server started
        const old = this.field("frame").src;
        this.field("frame").src = URL.createObjectURL(await r.blob());
        if (old.startsWith("blob:")) URL.revokeObjectURL(old);
        const seq = r.headers.get("X-Frame-Seq");
        this.field("frame").title = `frame ${seq}`;
        this.field("frame-cap").textContent = `last frame (${seq})`;
      }
    } catch (err) { say(`last frame: ${err.message}`); }
    if (p.image_id === null || p.image_id === undefined) return;
    this.field("best-cap").textContent = `best match for ${p.seq}: ${p.image_filename}`;
    if (state.creds.kind !== "admin") return;  // a session token reads no map image
    try {
      this.field("best").src = await imageUrl(this.session.map_id, p.image_id);
    } catch (err) { say(`best match: ${err.message}`); }
  }
}

// The origin of the map's east/north frame from one pose's (x, y) and (lat, lon), in the
// local tangent approximation the plan uses around it (good to centimetres over a few km).
function originOf(p) {
  const rad = Math.PI / 180, R = 6378137;
  const lat = p.lat - p.y / R / rad;
  return { lat, lon: p.lon - p.x / (R * Math.cos(lat * rad)) / rad };
}

function stepKind(p) {
  if (p.measurement && /registered|interpolated/.test(p.measurement)) return "refined";
  return p.feature === "sift" ? "sift" : "global";
}

// The 95 % ellipse of a 2x2 covariance (row-major [xx, xy, yx, yy]) around (x, y).
function ellipse(x, y, cov) {
  const a = cov[0], b = 0.5 * (cov[1] + cov[2]), d = cov[3];
  const mid = 0.5 * (a + d), rad = Math.sqrt(Math.max(0.25 * (a - d) ** 2 + b * b, 0));
  const l1 = Math.max(mid + rad, 0), l2 = Math.max(mid - rad, 0);
  const theta = 0.5 * Math.atan2(2 * b, a - d);   // major axis from east
  const r1 = Math.sqrt(CHI2_95 * l1), r2 = Math.sqrt(CHI2_95 * l2);
  const c = Math.cos(theta), s = Math.sin(theta);
  const pts = [];
  for (let i = 0; i < ELLIPSE_POINTS; i += 1) {
    const t = (2 * Math.PI * i) / ELLIPSE_POINTS;
    const u = r1 * Math.cos(t), v = r2 * Math.sin(t);
    pts.push(at(x + c * u - s * v, y + s * u + c * v));
  }
  return pts;
}

// One loop on the display's frame clock draws what arrived since the last frame; while
// sessions are watched, the intervals between its frames measure how smooth the page is.
const perf = { frames: 0, intervals: [], lastFrame: null, drawMs: [] };
function frameLoop(ts) {
  if (state.watchers.size) {
    const t0 = performance.now();
    let drew = false;
    for (const w of state.watchers.values()) drew = w.draw() || drew;
    if (drew) perf.drawMs.push(performance.now() - t0);
    if (perf.lastFrame !== null) perf.intervals.push(ts - perf.lastFrame);
    perf.lastFrame = ts;
    perf.frames += 1;
  } else {
    perf.lastFrame = null;
  }
  requestAnimationFrame(frameLoop);
}
requestAnimationFrame(frameLoop);

function quantile(values, q) {
  if (!values.length) return null;
  const s = [...values].sort((a, b) => a - b);
  return s[Math.min(s.length - 1, Math.floor(q * s.length))];
}

window.vlocViewer = {
  stats() {
    const sessions = {};
    let received = 0, drawn = 0, gaps = 0;
    for (const [id, w] of state.watchers) {
      sessions[id] = { received: w.received, drawn: w.drawn, gaps: w.gaps, errors: w.errors,
                       last_seq: w.lastSeq, track: w.track.length, history: w.history || 0,
                       reconnects: w.reconnects || 0, filled: w.filled || 0,
                       cloud: w.layers.cloud.getLayers().length };
      received += w.received; drawn += w.drawn; gaps += w.gaps;
    }
    return {
      sessions, received, drawn, gaps, frames: perf.frames,
      frame_interval_ms_p50: quantile(perf.intervals, 0.5),
      frame_interval_ms_p95: quantile(perf.intervals, 0.95),
      frame_interval_ms_max: perf.intervals.length ? Math.max(...perf.intervals) : null,
      long_frames: perf.intervals.filter((v) => v > 50).length,
      intervals: perf.intervals.length,
      draw_ms_p50: quantile(perf.drawMs, 0.5),
      draw_ms_p95: quantile(perf.drawMs, 0.95),
    };
  },
  resetStats() {
    perf.intervals = []; perf.drawMs = []; perf.frames = 0; perf.lastFrame = null;
    for (const w of state.watchers.values()) { w.received = 0; w.drawn = 0; w.gaps = 0; }
  },
  screenOf(east, north) {  // a plan position in the page's CSS pixels
    const p = plan.latLngToContainerPoint(at(east, north));
    const box = plan.getContainer().getBoundingClientRect();
    return { x: box.left + p.x, y: box.top + p.y };
  },
  view() {  // the plan's centre (metres) and zoom
    const c = plan.getCenter();
    return { north: c.lat, east: c.lng, zoom: plan.getZoom() };
  },
  markerOf(sessionId) {
    const w = state.watchers.get(sessionId);
    return w ? w.layers.marker.getLatLng() : null;
  },
  watch: (session) => watch(session),
};
