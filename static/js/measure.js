// Measure in 3-D on the depth image (POST /api/measure): click points, read value ± 1σ.
// The points stay fixed in sensor pixels and are re-measured on every new depth map; the
// finished measurement is kept by the server (PUT /api/measure/tool) so recordings carry it.
// A measurement the server refuses (4xx: e.g. too little of it valid) is shown once and not
// posted again on every new map; a new click, Clear or another kind starts afresh.

import { $, api, fmt } from "./api.js";
import { ui } from "./state.js";
import { onStatus } from "./status.js";

// points each kind needs; profile and area take more until "Done"
const NEED = { length: 2, point_to_line: 3, depth: 4, profile: 2, area: 3 };
const OPEN_ENDED = new Set(["profile", "area"]);
const HINT = {
  length: "click two points",
  point_to_line: "click the point, then two points on the line",
  depth: "click the point, then three points spanning the reference plane",
  profile: "click along the profile, then Done",
  area: "click the polygon's corners, then Done",
};

const m = {
  kind: "", points: [], result: null, done: false, seq: -1, busy: false, error: "",
  refused: false, posts: 0,
};
ui.measure = m; // for tests and the curious

function toSensor(ev) {
  const r = $("roi").getBoundingClientRect();
  const [W, H] = ui.sensor;
  const x = Math.min(Math.max((ev.clientX - r.left) / r.width, 0), 1) * W;
  const y = Math.min(Math.max((ev.clientY - r.top) / r.height, 0), 1) * H;
  return [Math.min(W - 1, Math.round(x - 0.5)), Math.min(H - 1, Math.round(y - 0.5))];
}

function label(r) {
  if (!r) return "";
  const unit = r.kind === "area" ? "mm²" : "mm";
  return `${fmt(r.value_mm, 3)} ± ${fmt(r.sigma_mm, 3)} ${unit}`;
}

/** Draw the clicked points, the lines between them and the value beside them. */
export function drawMeasure() {
  const canvas = $("measure");
  const base = $("roi");
  if (canvas.width !== base.width || canvas.height !== base.height) {
    canvas.width = base.width;
    canvas.height = base.height;
  }
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!ui.sensor || !m.points.length) return;
  const k = canvas.width / ui.sensor[0];
  const used = m.result ? m.result.points.map((p) => p.pixel) : m.points;
  const xy = used.map(([u, v]) => [(u + 0.5) * k, (v + 0.5) * k]);
  const lw = Math.max(2, canvas.width / 400);
  ctx.lineWidth = lw;
  ctx.strokeStyle = "#ffffff";
  ctx.fillStyle = "#ffffff";
  ctx.setLineDash([]);
  const path = (pts, close) => {
    ctx.beginPath();
    pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    if (close) ctx.closePath();
    ctx.stroke();
  };
  const n = m.points.length;
  if (m.kind === "length" || m.kind === "profile") path(xy.slice(0, n), false);
  else if (m.kind === "area") path(xy.slice(0, n), m.done);
  else if (m.kind === "point_to_line" && n >= 3) path(xy.slice(1, 3), false);
  else if (m.kind === "depth" && n >= 4) {
    ctx.setLineDash([6, 4]);
    path(xy.slice(1, 4), true);
    ctx.setLineDash([]);
  }
  xy.forEach(([x, y], i) => {
    ctx.beginPath();
    ctx.arc(x, y, 2.5 * lw, 0, 2 * Math.PI);
    const snapped = m.result && m.result.points[i] && m.result.points[i].snapped;
    ctx.strokeStyle = snapped ? "#ffcc00" : "#ffffff";
    ctx.stroke();
    ctx.strokeStyle = "#ffffff";
  });
  const text = m.error ? m.error : label(m.result);
  if (!text) return;
  const [tx, ty] = xy.reduce((a, p) => [a[0] + p[0] / xy.length, a[1] + p[1] / xy.length], [0, 0]);
  ctx.font = `${Math.max(12, Math.round(canvas.width / 55))}px sans-serif`;
  const w = ctx.measureText(text).width;
  ctx.fillStyle = "rgba(0, 0, 0, 0.65)";
  ctx.fillRect(tx + 8, ty - 22, w + 10, 26);
  ctx.fillStyle = m.error ? "#ff8080" : "#ffffff";
  ctx.fillText(text, tx + 13, ty - 4);
}

function drawProfile() {
  const canvas = $("measure-plot");
  const p = m.result && m.result.profile;
  canvas.hidden = !p;
  if (!p) return;
  const ctx = canvas.getContext("2d");
  const { width: W, height: H } = canvas;
  ctx.clearRect(0, 0, W, H);
  const idx = p.height_mm.map((h, i) => i).filter((i) => p.height_mm[i] !== null && p.distance_mm[i] !== null);
  if (idx.length < 2) return;
  const xs = idx.map((i) => p.distance_mm[i]);
  const lo = Math.min(...idx.map((i) => p.height_mm[i] - (p.sigma_mm[i] || 0)));
  const hi = Math.max(...idx.map((i) => p.height_mm[i] + (p.sigma_mm[i] || 0)));
  const x0 = Math.min(...xs), x1 = Math.max(...xs);
  const pad = 24;
  const X = (d) => pad + ((d - x0) / Math.max(x1 - x0, 1e-9)) * (W - 2 * pad);
  const Y = (h) => H - pad - ((h - lo) / Math.max(hi - lo, 1e-9)) * (H - 2 * pad);
  ctx.fillStyle = "rgba(120, 170, 255, 0.3)"; // ±1σ band
  ctx.beginPath();
  idx.forEach((i, j) => (j ? ctx.lineTo : ctx.moveTo).call(ctx, X(p.distance_mm[i]), Y(p.height_mm[i] + (p.sigma_mm[i] || 0))));
  [...idx].reverse().forEach((i) => ctx.lineTo(X(p.distance_mm[i]), Y(p.height_mm[i] - (p.sigma_mm[i] || 0))));
  ctx.fill();
  ctx.strokeStyle = "#ffffff";
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  idx.forEach((i, j) => (j ? ctx.lineTo : ctx.moveTo).call(ctx, X(p.distance_mm[i]), Y(p.height_mm[i])));
  ctx.stroke();
  ctx.fillStyle = "#cccccc";
  ctx.font = "11px sans-serif";
  ctx.fillText(`${fmt(hi, 2)} mm`, 2, pad - 6);
  ctx.fillText(`${fmt(lo, 2)} mm`, 2, H - 6);
  ctx.fillText(`${fmt(x1 - x0, 1)} mm`, W - pad - 40, H - 6);
}

function spec() {
  return { kind: m.kind, points: m.points };
}

async function remeasure() {
  if (!m.done || m.busy || m.refused) return;
  m.busy = true;
  m.posts += 1;
  const out = $("measure-result");
  try {
    const r = await api("/api/measure", { method: "POST", json: spec() });
    m.result = r;
    m.error = "";
    out.className = "roi-result";
    const snapped = r.points.filter((p) => p.snapped).length;
    const filled = r.points.filter((p) => p.filled).length;
    const partial = r.coverage !== undefined && r.coverage < 1;
    const cover = partial ? ` · ${fmt(100 * r.coverage, 0)} % valid` : "";
    out.innerHTML = `<b>${r.kind.replace(/_/g, " ")}</b> <span id="measure-value">${label(r)}</span> (1σ)` +
      cover +
      (snapped ? ` · ${snapped} point${snapped > 1 ? "s" : ""} snapped to a valid pixel` : "") +
      (filled ? ` · ${filled} point${filled > 1 ? "s" : ""} filled across a hole` : "") +
      ` · depth map #${r.source.seq}`;
    out.dataset.value = String(r.value_mm);
    out.dataset.sigma = String(r.sigma_mm);
    out.dataset.coverage = String(r.coverage);
  } catch (err) {
    m.result = null;
    m.error = err.message;
    // refused for what was clicked (4xx but 409, which is "no depth map yet"): said once, not
    // re-posted on every map; a network fault or a busy server is tried again on the next map
    m.refused = err.status >= 400 && err.status < 500 && err.status !== 409;
    out.className = "roi-result error";
    out.textContent = `measurement failed: ${err.message}` +
      (m.refused ? " (not measured again: click new points, or Clear)" : "");
  } finally {
    m.busy = false;
    drawMeasure();
    drawProfile();
  }
}

async function keep() {
  // the server keeps the finished measurement: every recorded set's metadata carries it
  try {
    await api("/api/measure/tool", { method: "PUT", json: { measurements: m.done ? [spec()] : [] } });
  } catch (_) { /* shown by the status bar */ }
}

function finish() {
  if (m.points.length < NEED[m.kind]) return;
  m.done = true;
  $("measure-done").disabled = true;
  keep();
  remeasure();
}

function reset(kind) {
  const had = m.done;
  Object.assign(m, { kind, points: [], result: null, done: false, error: "", refused: false });
  $("measure-done").disabled = true;
  $("measure-done").hidden = !OPEN_ENDED.has(kind);
  $("measure-result").className = "roi-result muted";
  $("measure-result").textContent = kind ? HINT[kind] : "measure tool off (drag to select a region)";
  $("measure-result").removeAttribute("data-value");
  $("roi").classList.toggle("measuring", Boolean(kind));
  drawMeasure();
  drawProfile();
  if (had) keep();
}

export function setupMeasure() {
  const canvas = $("roi");
  // capture phase: while a measure kind is chosen, clicks are points, not a region drag
  canvas.addEventListener("pointerdown", (ev) => {
    if (!m.kind || !ui.sensor || ev.button !== 0) return;
    ev.stopImmediatePropagation();
    if (m.done) reset(m.kind); // a new click starts a new measurement of the same kind
    m.points.push(toSensor(ev));
    $("measure-done").disabled = m.points.length < NEED[m.kind];
    drawMeasure();
    if (!OPEN_ENDED.has(m.kind) && m.points.length === NEED[m.kind]) finish();
    else $("measure-result").textContent = `${HINT[m.kind]} (${m.points.length} so far)`;
  }, true);
  $("measure-kind").addEventListener("change", (ev) => reset(ev.target.value));
  $("measure-done").addEventListener("click", finish);
  $("measure-clear").addEventListener("click", () => reset(m.kind));
  onStatus((st) => { // a new depth map: measure the same pixels again
    if (m.done && st.results_published !== m.seq) {
      m.seq = st.results_published;
      remeasure();
    }
  });
  new ResizeObserver(drawMeasure).observe(canvas);
  reset("");
}
