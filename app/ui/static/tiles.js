// An optional background of map tiles under the plan, off by default (devices may run
// offline): only where the operator configured a tile URL (VLOC_VIEWER_TILE_URL), and only
// for a map whose local frame is anchored to the earth (its origin).
//
// The plan keeps its coordinates (east/north metres from the map's origin). Under tiles it
// switches to a CRS that places those metres in Web Mercator around the origin: there a
// metre on the ground is 1 / cos(latitude) projected metres in every direction (Mercator is
// conformal), so the tiles' pixel grid is EPSG:3857's and standard z/x/y tiles line up.

import { plan } from "./common.js";

const EARTH_RADIUS_M = 6378137;
const SIMPLE = L.CRS.Simple;
const PLAN_ZOOM = { minZoom: -6, maxZoom: 6 };

let config = { tile_url: null, tile_attribution: "" };
let origin = null;     // {lat, lon} of the plan's frame
let tiles = null;      // the tile layer while shown
let box = null;        // the control's checkbox

// Plan metres around `o` in Web Mercator; distances stay plain metres (the scale bar).
function localMercator(o) {
  const centre = L.Projection.SphericalMercator.project(L.latLng(o.lat, o.lon));
  const k = 1 / Math.cos((o.lat * Math.PI) / 180);
  const projection = {
    project: (ll) => L.point(centre.x + k * ll.lng, centre.y + k * ll.lat),
    unproject: (p) => L.latLng((p.y - centre.y) / k, (p.x - centre.x) / k),
    bounds: L.Projection.SphericalMercator.bounds,
  };
  return L.extend({}, L.CRS.EPSG3857, {
    code: "vloc:local-mercator", projection, wrapLng: undefined, wrapLat: undefined,
    distance: SIMPLE.distance });
}

// The zoom under `crs` that keeps the plan's pixels per metre.
function equivalentZoom(fromCrs, toCrs, zoom) {
  const a = fromCrs.latLngToPoint(L.latLng(0, 0), zoom), b = fromCrs.latLngToPoint(L.latLng(0, 1), zoom);
  const pxPerMetre = b.x - a.x;
  const c = toCrs.latLngToPoint(L.latLng(0, 0), 0), d = toCrs.latLngToPoint(L.latLng(0, 1), 0);
  return Math.log2(pxPerMetre / (d.x - c.x));
}

function switchCrs(crs, zoomLimits) {
  const centre = plan.getCenter();
  const zoom = equivalentZoom(plan.options.crs, crs, plan.getZoom());
  plan.options.crs = crs;
  plan.options.minZoom = zoomLimits.minZoom;
  plan.options.maxZoom = zoomLimits.maxZoom;
  plan.setView(centre, zoom, { animate: false, reset: true });
}

function show(on) {
  if (on && origin) {
    const crs = localMercator(origin);
    const shift = equivalentZoom(SIMPLE, crs, 0);
    switchCrs(crs, { minZoom: PLAN_ZOOM.minZoom + shift, maxZoom: PLAN_ZOOM.maxZoom + shift });
    if (!tiles) {
      // a close plan is deeper than tile servers go: their deepest tiles are enlarged
      tiles = L.tileLayer(config.tile_url, { attribution: config.tile_attribution,
                                             maxNativeZoom: 19, maxZoom: 40,
                                             className: "vloc-tiles" });
    }
    tiles.addTo(plan);
    tiles.bringToBack();
  } else {
    if (tiles) tiles.remove();
    if (plan.options.crs !== SIMPLE) switchCrs(SIMPLE, PLAN_ZOOM);
  }
}

const TileControl = L.Control.extend({
  options: { position: "topright" },
  onAdd() {
    const label = L.DomUtil.create("label", "tile-toggle");
    label.title = "map tiles under the plan (needs the tile server on the network)";
    box = L.DomUtil.create("input", "", label);
    box.type = "checkbox";
    box.id = "tiles-toggle";
    box.disabled = true;
    label.append(" tiles");
    L.DomEvent.disableClickPropagation(label);
    box.addEventListener("change", () => show(box.checked));
    return label;
  },
});

// The map on the plan is anchored at `o` ({lat, lon}), or at nothing (null: a plan only).
export function setOrigin(o) {
  const moved = !origin || !o || origin.lat !== o.lat || origin.lon !== o.lon;
  origin = o ? { lat: o.lat, lon: o.lon } : null;
  if (!box) return;
  box.disabled = !origin;
  if (moved && box.checked) {
    if (!origin) box.checked = false;
    show(false);
    show(box.checked);
  }
}

export async function installTiles() {
  try {
    const r = await fetch("config.json", { cache: "no-store" });
    if (r.ok) config = await r.json();
  } catch (err) { /* no configuration: a plan only */ }
  if (!config.tile_url) return;
  plan.attributionControl = L.control.attribution({ prefix: false }).addTo(plan);
  new TileControl().addTo(plan);
  box.disabled = !origin;
}
