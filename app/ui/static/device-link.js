// A session for a device (admin): opened on the selected map, its token shown once as a QR
// code and a link to the device page. The token rides in the link's fragment, which no
// browser sends to a server, so it is in no request line and no log; the device page
// clears it from its address bar at once.

import { $, api, state } from "./common.js";

export function deviceLink(session) {
  const page = new URL("device", location.href);
  page.hash = new URLSearchParams({ session: session.id, token: session.token }).toString();
  return page.href;
}

function drawQr(svg, text) {
  const qr = qrcode(0, "M");  // the smallest version that holds the link
  qr.addData(text);
  qr.make();
  const n = qr.getModuleCount(), quiet = 4, size = n + 2 * quiet;
  let path = "";
  for (let r = 0; r < n; r++) {
    for (let c = 0; c < n; c++) if (qr.isDark(r, c)) path += `M${c + quiet} ${r + quiet}h1v1h-1z`;
  }
  svg.setAttribute("viewBox", `0 0 ${size} ${size}`);
  svg.innerHTML = `<rect width="${size}" height="${size}" fill="#fff"/>` +
    `<path d="${path}" fill="#000"/>`;
}

$("#device-session").addEventListener("click", async () => {
  if (!state.mapId) return;
  const box = $("#device-box");
  try {
    const s = await api("/v1/sessions", { method: "POST", json: { map_id: state.mapId } });
    const link = deviceLink(s);
    drawQr($("#device-qr"), link);
    $("#device-url").href = link;
    $("#device-id").textContent = s.id;
    box.hidden = false;
  } catch (err) {
    $("#device-error").textContent = `refused: ${err.message}`;
  }
});

$("#device-done").addEventListener("click", () => {
  // shown once: the token goes with the box
  $("#device-qr").innerHTML = "";
  $("#device-url").removeAttribute("href");
  $("#device-box").hidden = true;
});
