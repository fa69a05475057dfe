// Maps: the list, a map's images on the plan with thumbnails, upload and build, its
// revisions restored and dropped (admin).

import { $, api, at, escapeHtml, imageLayer, listAll, plan, say, state } from "./common.js";
import { setOrigin } from "./tiles.js";

const JOB_POLL_MS = 500;

export async function refreshMaps() {
  state.maps = await listAll("/v1/maps");
  const body = $("#maps-table tbody");
  body.replaceChildren(...state.maps.map((m) => {
    const tr = document.createElement("tr");
    tr.dataset.mapId = m.id;
    tr.classList.toggle("selected", m.id === state.mapId);
    for (const v of [m.name, m.status, m.revision, m.image_count, m.pending_images]) {
      const td = document.createElement("td");
      td.textContent = String(v);
      tr.append(td);
    }
    tr.children[1].className = `status-${m.status}`;
    tr.addEventListener("click", () => selectMap(m.id));
    return tr;
  }));
}

$("#create-map").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  try {
    const m = await api("/v1/maps", { method: "POST", json: { name: $("#new-map-name").value } });
    $("#new-map-name").value = "";
    await refreshMaps();
    await selectMap(m.id);
  } catch (err) { say(`could not create the map: ${err.message}`); }
});

export async function selectMap(mapId, { fit = true } = {}) {
  const m = state.maps.find((x) => x.id === mapId) || await api(`/v1/maps/${mapId}`);
  // everything is fetched before anything is shown: the summary never describes a revision
  // whose images are not drawn yet
  const [images, revisions] = await Promise.all([
    listAll(`/v1/maps/${mapId}/images`, { by: "after_id", limit: 10000 }),
    api(`/v1/maps/${mapId}/revisions`)]);
  state.mapId = mapId;
  document.querySelectorAll("#maps-table tbody tr").forEach((tr) =>
    tr.classList.toggle("selected", tr.dataset.mapId === mapId));
  $("#map-detail").hidden = false;
  $("#map-title").textContent = m.name;
  $("#map-summary").textContent = `${m.status}, revision ${m.revision}, ` +
    `${m.image_count} images (${m.pending_images} not built yet)`;
  $("#map-geometry").textContent = geometryLine(m.geometry);
  showRevisions(mapId, revisions);
  state.mapImages = images;
  state.origin = m.origin;
  setOrigin(m.origin);
  drawImages(m, fit);
}

// The map's revisions, newest first: the current one marked, the others restorable, and
// droppable unless sessions use them.
function showRevisions(mapId, revisions) {
  $("#revisions-error").textContent = "";
  $("#revisions-table tbody").replaceChildren(...revisions.map((r) => {
    const tr = document.createElement("tr");
    tr.dataset.revision = String(r.revision);
    tr.classList.toggle("selected", r.current);
    const check = r.geometry && r.geometry.self_check;
    const cells = [
      r.current ? `${r.revision} (current)` : String(r.revision),
      new Date(r.built_at).toISOString().slice(0, 16).replace("T", " "),
      String(r.image_count),
      `+${r.added} -${r.removed} on ${r.base_revision}`,
      check && check.median_m !== null ? `${check.median_m.toFixed(1)} m` : "-",
      r.dropped_at ? "dropped" : r.disk_bytes === null ? "missing"
        : `${(r.disk_bytes / 2 ** 20).toFixed(1)} MiB` + (r.shared_bytes
          ? ` (${(r.shared_bytes / 2 ** 20).toFixed(1)} shared)` : ""),
    ];
    for (const text of cells) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    const actions = document.createElement("td");
    if (!r.current && !r.dropped_at) {
      actions.append(revisionButton(mapId, r, "restore", "POST", `${r.revision}/restore`));
      const drop = revisionButton(mapId, r, "drop", "DELETE", `${r.revision}`);
      if (r.active_sessions) {
        drop.disabled = true;
        drop.title = `${r.active_sessions} active session(s) use this revision`;
      }
      actions.append(drop);
    }
    tr.append(actions);
    return tr;
  }));
}

function revisionButton(mapId, r, label, method, path) {
  const b = document.createElement("button");
  b.type = "button";
  b.textContent = label;
  b.className = `revision-${label}`;
  b.addEventListener("click", async () => {
    try {
      await api(`/v1/maps/${mapId}/revisions/${path}`, { method });
      await refreshMaps();
      await selectMap(mapId, { fit: false });
    } catch (err) {
      $("#revisions-error").textContent = `could not ${label} revision ${r.revision}: ` +
        err.message;
    }
  });
  return b;
}

// What the revision's camera geometry gives frames, in a sentence.
export function geometryLine(g) {
  if (!g) return "";
  const check = g.self_check;
  if (g.status === "accepted" && check && check.median_m !== null) {
    return `Camera geometry: ${g.placed} of ${g.images} images placed; this map localises ` +
      `to about ${check.median_m.toFixed(1)} m (median over ${check.images} of its own ` +
      `images, ${Math.round(100 * check.within_5m)} % within 5 m), where the nearest ` +
      `image alone gives ${check.floor_median_m.toFixed(1)} m` +
      (check.every_image_mean_m == null ? "." : `; over all its images, the ones no pose ` +
        `reaches included, ${check.every_image_mean_m.toFixed(1)} m on average.`);
  }
  if (g.status === "refused" && check) {
    const got = check.median_m === null ? "placed none of its own images"
      : `localised its own images to ${check.median_m.toFixed(1)} m`;
    return `No camera geometry: the reconstruction ${got}, no better than the nearest ` +
      `image (${check.floor_median_m.toFixed(1)} m); positions come from the map's images.`;
  }
  return `No camera geometry${g.reason ? `: ${g.reason}` : ""}; positions come from the ` +
    "map's images.";
}

// Built images have east/north in the revision's frame; images waiting for a build are
// placed from their GPS around the map's origin (or their own mean before any build).
function planPositions(m, images) {
  const R = 6378137.0;
  const origin = m.origin || (images.length ? {
    lat: images.reduce((s, i) => s + i.lat, 0) / images.length,
    lon: images.reduce((s, i) => s + i.lon, 0) / images.length } : null);
  return images.map((img) => {
    if (img.east !== null && img.north !== null) return { img, east: img.east, north: img.north, built: true };
    const rad = Math.PI / 180;
    return { img, built: false,
             east: (img.lon - origin.lon) * rad * R * Math.cos(origin.lat * rad),
             north: (img.lat - origin.lat) * rad * R };
  });
}

function drawImages(m, fit) {
  imageLayer.clearLayers();
  const placed = planPositions(m, state.mapImages);
  for (const p of placed) {
    const marker = L.circleMarker(at(p.east, p.north), {
      radius: 4, weight: 1, color: "#37474f", fillColor: p.built ? "#90a4ae" : "#fff",
      fillOpacity: 0.9, dashArray: p.built ? null : "2 2", className: "vloc-map-image" });
    const tip = document.createElement("div");
    tip.className = "thumb-tip";
    tip.innerHTML = `<b>${escapeHtml(p.img.filename)}</b><br>` +
      `${p.east.toFixed(1)} E, ${p.north.toFixed(1)} N m${p.built ? "" : " (not built)"}` +
      `<div class="thumb"></div>`;
    marker.bindTooltip(tip, { direction: "top", offset: [0, -4] });
    marker.on("tooltipopen", (ev) => showThumb(ev.tooltip, tip, m.id, p.img.id));
    marker.addTo(imageLayer);
  }
  if (fit && placed.length) {
    const bounds = L.latLngBounds(placed.map((p) => at(p.east, p.north)));
    plan.fitBounds(bounds.pad(0.15), { maxZoom: 3, animate: false });
  }
}

const thumbUrls = new Map(); // "map/image" -> object URL
export async function imageUrl(mapId, imageId) {
  const key = `${mapId}/${imageId}`;
  if (!thumbUrls.has(key)) {
    const r = await api(`/v1/maps/${mapId}/images/${imageId}/file`, { blob: true });
    thumbUrls.set(key, URL.createObjectURL(await r.blob()));
  }
  return thumbUrls.get(key);
}

async function showThumb(tooltip, tip, mapId, imageId) {
  const holder = tip.querySelector(".thumb");
  if (holder.firstChild) return;
  try {
    const url = await imageUrl(mapId, imageId);
    if (holder.firstChild) return;
    const img = new Image();
    img.alt = "map image";
    img.addEventListener("load", () => tooltip.update());  // re-place it at its new size
    img.src = url;
    holder.append(img);
  } catch (err) { say(`thumbnail: ${err.message}`); }
}

$("#upload").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const files = $("#upload-files").files;
  if (!state.mapId || !files.length) return;
  const form = new FormData();
  for (const f of files) form.append("files", f, f.name);
  $("#upload-result").textContent = `uploading ${files.length} file(s)...`;
  try {
    const res = await api(`/v1/maps/${state.mapId}/images`, { method: "POST", body: form });
    const rejected = res.rejected.map((r) => `${r.filename}: ${r.reason}`).join("; ");
    $("#upload-result").textContent = `${res.accepted.length} accepted` +
      (rejected ? `, refused: ${rejected}` : "");
  } catch (err) {
    $("#upload-result").textContent = `refused: ${err.message}`;
  }
  $("#upload-files").value = "";
  await refreshMaps();
  await selectMap(state.mapId);
});

$("#build").addEventListener("click", async () => {
  if (!state.mapId) return;
  const mapId = state.mapId;
  const bar = $("#build-progress");
  try {
    const job = await api(`/v1/maps/${mapId}/build`, { method: "POST" });
    bar.hidden = false;
    bar.value = 0;
    for (;;) {
      const j = await api(`/v1/jobs/${job.job_id}`);
      bar.value = j.progress;
      $("#build-status").textContent = `${j.status} ${Math.round(100 * j.progress)} %` +
        (j.status === "running" && j.stage ? ` (${j.stage})` : "");
      if (j.status === "done" || j.status === "failed") {
        if (j.error) $("#build-status").textContent += `: ${j.error}`;
        break;
      }
      await new Promise((ok) => setTimeout(ok, JOB_POLL_MS));
    }
  } catch (err) {
    $("#build-status").textContent = `refused: ${err.message}`;
  }
  await refreshMaps();
  if (state.mapId === mapId) await selectMap(mapId);
});
