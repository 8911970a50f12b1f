// The depth view: the live colormap (WebSocket, polling as fallback), its colour range and bar.

import { $, api, ApiError, fmt, say, withToken } from "./api.js";
import {
  changeMode, changeRange, drawChangeBar, fetchChange, setChangeRange, setupChange,
} from "./change.js";
import { drawColorbar } from "./colormap.js";
import { drawRoi } from "./analysis.js";
import { ui } from "./state.js";
import { onStatus } from "./status.js";

const sigmaMode = () => $("show-sigma").checked;

/** The colour range of what the image shows: the height, or its 1-σ noise (mm). */
const shownRange = () => (sigmaMode() ? ui.sigmaRange : ui.range);

function paintBar() {
  if (changeMode()) {
    $("bar-title").textContent = "change Δ, mm";
    drawChangeBar($("colorbar"), $("bar-ticks"), changeRange());
    return;
  }
  const range = shownRange();
  $("bar-title").textContent = sigmaMode() ? "σ, mm" : "height, mm";
  if (range) drawColorbar($("colorbar"), $("bar-ticks"), range);
}

function showRangeInputs() {
  const range = changeMode() ? [-changeRange(), changeRange()] : shownRange();
  $("range-min").value = range ? String(range[0]) : "";
  $("range-max").value = range ? String(range[1]) : "";
  for (const id of ["range-min", "range-max"]) $(id).classList.remove("invalid");
}

// σ mode: the bar, its range inputs and the image switch to the σ map at once
function onSigmaToggle() {
  if ($("show-sigma").checked) $("show-change").checked = false;
  showRangeInputs();
  paintBar();
  ui.pendingBlob = null; // an image of the other kind waiting to be drawn
  pollDepth(true);
}

/** The default colour range from /api/limits, unless the user changed it already. */
export function applyLimits(limits) {
  if (ui.range) return; // the user chose one meanwhile
  const [lo, hi] = limits.depth_range_mm;
  ui.range = [lo, hi];
  showRangeInputs();
  paintBar();
  connectStream();
}

let rangeTimer = null;
function onRangeChange() {
  const lo = parseFloat($("range-min").value);
  const hi = parseFloat($("range-max").value);
  const ok = isFinite(lo) && isFinite(hi) && lo < hi;
  $("range-min").classList.toggle("invalid", !ok);
  $("range-max").classList.toggle("invalid", !ok);
  if (!ok) return;
  if (changeMode()) {
    if (setChangeRange(lo, hi)) {
      paintBar();
      pollDepth(true);
    }
    return;
  }
  if (sigmaMode()) {
    ui.sigmaRange = [lo, hi];
    paintBar();
    pollDepth();
    return;
  }
  ui.range = [lo, hi];
  paintBar();
  clearTimeout(rangeTimer);
  rangeTimer = setTimeout(() => connectStream(), 300); // the server colours: ask anew
}

function rangeQuery(range = ui.range) {
  if (!range) return ""; // the server's default range
  return `min_mm=${encodeURIComponent(range[0])}&max_mm=${encodeURIComponent(range[1])}`;
}

async function fetchSensorShape() {
  const meta = await api("/api/result/latest");
  ui.sensor = [meta.shape[1], meta.shape[0]];
}

async function showDepthBlob(blob, kind) {
  // Decode only the newest image; frames arriving meanwhile replace each other.
  if (ui.decoding) {
    ui.pendingBlob = [blob, kind];
    return;
  }
  ui.decoding = true;
  try {
    const bitmap = await createImageBitmap(blob);
    if (!ui.sensor || ui.bitmapSize !== `${bitmap.width}x${bitmap.height}`) {
      await fetchSensorShape();
      ui.bitmapSize = `${bitmap.width}x${bitmap.height}`;
    }
    drawDepth(bitmap);
    bitmap.close();
    ui.framesShown += 1;
    ui.lastFrameAt = performance.now();
    ui.streamKind = kind;
    $("depth-wait").hidden = true;
  } catch (err) {
    const waiting = err instanceof ApiError && (err.status === 409 || err.status === 503);
    if (!waiting) say(`depth image: ${err.message}`, "error");
  } finally {
    ui.decoding = false;
    const next = ui.pendingBlob;
    ui.pendingBlob = null;
    if (next) showDepthBlob(next[0], next[1]);
  }
}

function drawDepth(bitmap) {
  // The server's image is the depth colormap at the top left, its colour bar to the
  // right; keep only the depth part (same scale for both), so display pixels map to
  // sensor pixels by one factor.
  const [W, H] = ui.sensor;
  const s = Math.min(bitmap.width / W, bitmap.height / H);
  const sw = Math.max(1, Math.round(W * s));
  const sh = Math.max(1, Math.round(H * s));
  const canvas = $("depth");
  if (canvas.width !== sw || canvas.height !== sh) {
    canvas.width = sw;
    canvas.height = sh;
    $("roi").width = sw;
    $("roi").height = sh;
  }
  ui.crop = { sw, sh };
  canvas.getContext("2d").drawImage(bitmap, 0, 0, W * s, H * s, 0, 0, sw, sh);
  drawRoi();
}

export function connectStream() {
  clearTimeout(ui.wsRetry);
  if (ui.ws) {
    const old = ui.ws;
    ui.ws = null;
    old.close();
  }
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(withToken(`${proto}//${location.host}/api/stream/depth?${rangeQuery()}`));
  ws.binaryType = "blob";
  ui.ws = ws;
  ws.onopen = () => { $("stream-kind").textContent = "live"; };
  ws.onmessage = (ev) => {
    if (ui.ws === ws && !$("show-sigma").checked && !changeMode()) showDepthBlob(ev.data, "stream");
  };
  ws.onclose = () => {
    if (ui.ws !== ws) return; // replaced on purpose
    ui.ws = null;
    $("stream-kind").textContent = "polling";
    ui.wsRetry = setTimeout(connectStream, 5000);
  };
}

// Fallback while the stream is down: poll the latest colormap (and once on a mode change,
// so the image matches the bar even when no new map arrives).
async function pollDepth(force = false) {
  const st = ui.status;
  const sigma = $("show-sigma").checked; // the σ map is polled, the stream carries depth
  const change = changeMode(); // so is the change map
  if (!force && !sigma && !change && ui.ws && ui.ws.readyState === WebSocket.OPEN) return;
  if (!st || !st.results_published) return; // nothing to fetch yet
  if (change) {
    try {
      const blob = await fetchChange();
      if (blob && changeMode()) await showDepthBlob(blob, "change");
    } catch (_) { /* shown in the change line */ }
    return;
  }
  try {
    const query = sigma ? `field=sigma&${rangeQuery(ui.sigmaRange)}` : rangeQuery();
    const blob = await api(`/api/depth/latest?format=color&${query}`, { blob: true });
    await showDepthBlob(blob, "poll");
  } catch (_) { /* shown by the status bar */ }
}

function showWaiting(st) {
  if (!ui.framesShown) {
    $("depth-wait").textContent = st.state === "calibrating" ? "creating the calibration…"
      : !st.acquiring ? "acquisition stopped" : "waiting for depth…";
  }
  const age = ui.lastFrameAt ? (performance.now() - ui.lastFrameAt) / 1000 : null;
  $("depth-info").textContent = ui.framesShown
    ? `${ui.framesShown} images · last ${fmt(age, 1)} s ago` : "no depth yet";
}

export function setupDepth() {
  paintBar();
  for (const id of ["range-min", "range-max"]) $(id).addEventListener("change", onRangeChange);
  $("show-sigma").addEventListener("change", onSigmaToggle);
  setupChange(onSigmaToggle);
  onStatus(showWaiting);
  setInterval(() => pollDepth(), 700);
  connectStream();
}
