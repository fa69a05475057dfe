// Replays and evaluations: the tracks of a `vloc replay` / `vloc eval` JSON against the truth.

import { $, PALETTE, at, plan } from "./common.js";

export const replayLayer = L.layerGroup();
const TRUTH_COLOUR = "#111";

$("#replay-file").addEventListener("change", async () => {
  const file = $("#replay-file").files[0];
  if (!file) return;
  $("#replay-error").textContent = "";
  let data;
  try {
    data = JSON.parse(await file.text());
  } catch (err) {
    $("#replay-error").textContent = `${file.name} is not JSON: ${err.message}`;
    return;
  }
  if (!data || !Array.isArray(data.tracks) || !Array.isArray(data.map_xy)) {
    $("#replay-error").textContent = `${file.name} has no tracks: write it with ` +
      "vloc replay --json or vloc eval --json";
    return;
  }
  showReplay(data);
});

function showReplay(data) {
  replayLayer.clearLayers();
  const all = [];
  for (const [x, y] of data.map_xy) {
    replayLayer.addLayer(L.circleMarker(at(x, y), { radius: 3, weight: 1, color: "#78909c",
                                                    fillOpacity: 0.6, className: "vloc-replay-image" }));
    all.push(at(x, y));
  }
  const body = $("#replay-table tbody");
  body.replaceChildren();
  const lines = [];
  data.tracks.forEach((t, k) => {
    const colour = PALETTE[k % PALETTE.length];
    if (k === 0) {  // every track of a file follows the same frames' truth
      const truth = L.polyline(t.truth.map(([x, y]) => at(x, y)),
                               { color: TRUTH_COLOUR, weight: 3, opacity: 0.7, className: "vloc-truth" });
      replayLayer.addLayer(truth.bindTooltip("true track"));
    }
    const line = L.polyline(t.estimate.map(([x, y]) => at(x, y)),
                            { color: colour, weight: 2, className: "vloc-replay-track" });
    line.bindTooltip(`${t.config} / ${t.mode}`);
    replayLayer.addLayer(line);
    t.estimate.forEach(([x, y]) => all.push(at(x, y)));
    lines.push({ track: t, colour, line });
    const tr = document.createElement("tr");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = true;
    box.addEventListener("change", () => {
      if (box.checked) replayLayer.addLayer(line); else replayLayer.removeLayer(line);
      lines[k].hidden = !box.checked;
      drawErrorChart(lines);
    });
    const errs = [...t.error_m].sort((a, b) => a - b);
    const cells = [box, t.config, t.mode, String(t.estimate.length),
                   errs.length ? errs[Math.floor(errs.length / 2)].toFixed(1) : "-",
                   errs.length ? errs[errs.length - 1].toFixed(1) : "-"];
    for (const c of cells) {
      const td = document.createElement("td");
      td.append(c);
      tr.append(td);
    }
    tr.firstChild.style.borderLeft = `6px solid ${colour}`;
    body.append(tr);
  });
  $("#replay-table").hidden = false;
  drawErrorChart(lines);
  if (all.length) plan.fitBounds(L.latLngBounds(all).pad(0.1), { animate: false });
}

// Error against frame number, one polyline per visible track, in an SVG of fixed size.
function drawErrorChart(lines) {
  const svg = $("#error-svg");
  const W = 340, H = 180, left = 36, bottom = 22, top = 8, right = 8;
  const shown = lines.filter((l) => !l.hidden && l.track.error_m.length);
  const frames = shown.flatMap((l) => l.track.frames);
  const errors = shown.flatMap((l) => l.track.error_m);
  const ns = "http://www.w3.org/2000/svg";
  svg.replaceChildren();
  $("#error-chart").hidden = !shown.length;
  if (!shown.length) return;
  const f0 = Math.min(...frames), f1 = Math.max(...frames, f0 + 1);
  const eMax = Math.max(...errors, 1);
  const sx = (f) => left + ((f - f0) / (f1 - f0)) * (W - left - right);
  const sy = (e) => H - bottom - (e / eMax) * (H - bottom - top);
  const el = (name, attrs, text) => {
    const e = document.createElementNS(ns, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
    if (text !== undefined) e.textContent = text;
    svg.append(e);
    return e;
  };
  el("line", { x1: left, y1: H - bottom, x2: W - right, y2: H - bottom, stroke: "#888" });
  el("line", { x1: left, y1: top, x2: left, y2: H - bottom, stroke: "#888" });
  el("text", { x: left - 4, y: top + 8, "text-anchor": "end", "font-size": 10 }, eMax.toFixed(0));
  el("text", { x: left - 4, y: H - bottom, "text-anchor": "end", "font-size": 10 }, "0");
  el("text", { x: left, y: H - 6, "font-size": 10 }, `frame ${f0}`);
  el("text", { x: W - right, y: H - 6, "text-anchor": "end", "font-size": 10 }, String(f1));
  for (const l of shown) {
    const pts = l.track.frames.map((f, i) => `${sx(f).toFixed(1)},${sy(l.track.error_m[i]).toFixed(1)}`);
    el("polyline", { points: pts.join(" "), fill: "none", stroke: l.colour, "stroke-width": 1.5,
                     class: "vloc-error-line" });
  }
}
