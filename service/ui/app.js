// ReRadar operator page: maps, their keyframe trajectories, build progress and the latest localizations,
// polled from the service's own API (GET /maps, /ui/api/maps/{id}/trajectory, /ui/api/maps/{id}/localizations;
// the last two with the API key typed in the header, when one is).
// No framework and no CDN: plain DOM and a 2-D canvas. Map frame: x right, y up, metres; yaw counter-clockwise.
"use strict";

const state = { maps: [], selected: null, trajectory: null, trajectoryKey: null, fixes: [] };
const TRAJ_COLOR = "#1f77b4", OK_COLOR = "#2ca02c";

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = String(text);
  if (cls) e.className = cls;
  return e;
}

// The /ui/api data (where vehicles are) needs a vehicle or operator key when the service has vehicle keys
// (none from loopback without them); the key typed in the header stays in this tab's sessionStorage.
const keyInput = document.getElementById("api-key");
keyInput.value = sessionStorage.getItem("reradar-api-key") || "";
keyInput.addEventListener("change", () => {
  sessionStorage.setItem("reradar-api-key", keyInput.value.trim());
  state.trajectoryKey = null;
  refresh();
});

async function getJSON(url) {
  const headers = { Accept: "application/json" };
  const key = keyInput.value.trim();
  if (key) headers["X-API-Key"] = key;
  const r = await fetch(url, { headers });
  if (r.status === 401 || r.status === 403) throw new Error(`${url}: HTTP ${r.status} - enter a vehicle or operator API key`);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.json();
}

function fmt(v, digits) {
  return v === null || v === undefined ? "-" : Number(v).toFixed(digits);
}

function renderMaps() {
  const body = document.querySelector("#maps tbody");
  body.replaceChildren();
  for (const m of state.maps) {
    const tr = el("tr");
    tr.dataset.mapId = m.id;
    if (m.id === state.selected) tr.classList.add("selected");
    tr.append(el("td", m.id));
    const why = m.error || m.note;
    tr.append(el("td", m.state + (why ? ` (${why})` : ""), `state-${m.state}`));
    const prog = el("td");
    const bar = el("span", null, "bar");
    const fill = el("span");
    fill.style.width = `${Math.round(100 * (m.progress || 0))}%`;
    bar.append(fill);
    prog.append(bar, el("span", ` ${Math.round(100 * (m.progress || 0))}%`, "muted"));
    // with its far-view companion (served, or being built: then both views' scan descriptions are counted)
    const views = m.far_view ? " (map + far view)" : "";
    tr.append(prog, el("td", m.num_keyframes ? `${m.num_keyframes}${views}`
      : (m.scans_total ? `${m.scans_done}/${m.scans_total} scans${views}` : "-")));
    tr.addEventListener("click", () => { state.selected = m.id; state.trajectoryKey = null; refresh(); });
    body.append(tr);
  }
  document.getElementById("maps-note").textContent =
    state.maps.length ? "click a map to show it" : "no maps registered (POST /maps)";
}

function renderFixes() {
  const body = document.querySelector("#fixes tbody");
  body.replaceChildren();
  for (const f of state.fixes.slice(0, 25)) {
    const tr = el("tr");
    tr.append(el("td", (f.utc || "").replace("T", " ").replace("Z", "")),
      el("td", f.status + (f.reason ? ` (${f.reason})` : ""), f.status === "localized" ? "state-ready" : "state-failed"),
      el("td", fmt(f.x_m, 2)), el("td", fmt(f.y_m, 2)), el("td", fmt(f.yaw_deg, 1)),
      el("td", fmt(f.confidence, 2)), el("td", fmt(f.latency_ms, 0)), el("td", f.replica || "-"));
    body.append(tr);
  }
}

function draw() {
  const canvas = document.getElementById("trajectory");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const t = state.trajectory;
  canvas.dataset.points = "0";
  canvas.dataset.fixes = "0";
  if (!t || t.x_m.length === 0) {
    ctx.fillStyle = "#7a8494";
    ctx.font = "16px system-ui";
    ctx.fillText(state.selected ? "no keyframes yet" : "select a map", 20, 30);
    return;
  }
  const located = state.fixes.filter((f) => f.status === "localized" && f.x_m !== null);
  const xs = t.x_m.concat(located.map((f) => f.x_m)), ys = t.y_m.concat(located.map((f) => f.y_m));
  let x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const pad = 30, span = Math.max(x1 - x0, y1 - y0, 1);
  const scale = Math.min((canvas.width - 2 * pad) / Math.max(x1 - x0, span * 0.05),
    (canvas.height - 2 * pad) / Math.max(y1 - y0, span * 0.05));
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const px = (x) => canvas.width / 2 + (x - cx) * scale;
  const py = (y) => canvas.height / 2 - (y - cy) * scale; // map y up, canvas y down
  document.getElementById("map-extent").textContent =
    `${t.x_m.length} keyframes, ${(x1 - x0).toFixed(0)} m x ${(y1 - y0).toFixed(0)} m`;

  ctx.strokeStyle = TRAJ_COLOR;
  ctx.lineWidth = 4;
  ctx.lineJoin = "round";
  ctx.beginPath();
  t.x_m.forEach((x, i) => (i ? ctx.lineTo(px(x), py(t.y_m[i])) : ctx.moveTo(px(x), py(t.y_m[i]))));
  ctx.stroke();
  ctx.fillStyle = TRAJ_COLOR;
  for (let i = 0; i < t.x_m.length; i++) {
    ctx.beginPath();
    ctx.arc(px(t.x_m[i]), py(t.y_m[i]), 3, 0, 2 * Math.PI);
    ctx.fill();
  }
  canvas.dataset.points = String(t.x_m.length);

  for (const f of located) {
    const a = (f.yaw_deg * Math.PI) / 180;
    ctx.strokeStyle = OK_COLOR;
    ctx.fillStyle = OK_COLOR;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc(px(f.x_m), py(f.y_m), 6, 0, 2 * Math.PI);
    ctx.fill();
    ctx.beginPath();
    ctx.moveTo(px(f.x_m), py(f.y_m));
    ctx.lineTo(px(f.x_m) + 16 * Math.cos(a), py(f.y_m) - 16 * Math.sin(a));
    ctx.stroke();
  }
  canvas.dataset.fixes = String(located.length);
}

async function refresh() {
  const status = document.getElementById("service-status");
  try {
    const list = await getJSON("/maps");
    state.maps = list.data;
    if (!state.selected || !state.maps.some((m) => m.id === state.selected)) {
      const ready = state.maps.find((m) => m.state === "ready");
      state.selected = ready ? ready.id : (state.maps[0] ? state.maps[0].id : null);
      state.trajectoryKey = null;
    }
    renderMaps();
    document.getElementById("selected-map").textContent = state.selected || "-";
    const sel = state.maps.find((m) => m.id === state.selected);
    if (sel && sel.state === "ready") {
      const key = `${sel.id}:${sel.num_keyframes}:${sel.registered_utc}`;
      if (state.trajectoryKey !== key) {
        state.trajectory = await getJSON(`/ui/api/maps/${encodeURIComponent(sel.id)}/trajectory`);
        state.trajectoryKey = key;
      }
      state.fixes = (await getJSON(`/ui/api/maps/${encodeURIComponent(sel.id)}/localizations?limit=50`)).data;
    } else {
      state.trajectory = null;
      state.fixes = [];
    }
    renderFixes();
    draw();
    status.textContent = `live · ${new Date().toISOString().slice(11, 19)} UTC`;
  } catch (err) {
    status.textContent = /HTTP 40[13]/.test(err.message) ? err.message : `API unreachable: ${err.message}`;
  }
}

refresh();
setInterval(refresh, 1000);
