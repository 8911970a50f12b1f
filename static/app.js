// Fringescope dashboard: one page for the operating room. No build step, no CDN.
//
// Every REST call goes through api(), which adds "Authorization: Bearer <token>" when a
// token is stored in localStorage "fringescope_token"; WebSockets and the 3-D iframe
// cannot send headers, so they carry ?token= (the server then sets its cookie).
"use strict";

const TOKEN_KEY = "fringescope_token";

// OpenCV's TURBO table (RGB, 256 entries): the same one the server colours depth with
// (app/recon/colormap.py; tests/viewer/test_dashboard_static.py keeps them equal).
const TURBO_HEX =
  "30123b32154333184a341b51351e5836215f37246638276d392a733a2d793b2f803c32863d358b3e38913f3b973f3e9c" +
  "4040a24143a74146ac4249b1424bb5434eba4451bf4454c34456c74559cb455ccf455ed34661d64664da4666dd4669e0" +
  "466be3476ee64771e94773eb4776ee4778f0477bf2467df44680f64682f84685fa4687fb458afc458cfd448ffe4391fe" +
  "4294ff4196ff4099ff3e9bfe3d9efe3ba0fd3aa3fc38a5fb37a8fa35abf833adf731aff52fb2f42eb4f22cb7f02ab9ee" +
  "28bceb27bee925c0e723c3e422c5e220c7df1fc9dd1ecbda1ccdd81bd0d51ad2d21ad4d019d5cd18d7ca18d9c818dbc5" +
  "18ddc218dec018e0bd19e2bb19e3b91ae4b61ce6b41de7b21fe9af20eaac22ebaa25eca727eea42aefa12cf09e2ff19b" +
  "32f29835f39438f4913cf58e3ff68a43f78746f8844af8804ef97d52fa7a55fa7659fb735dfc6f61fc6c65fd6969fd66" +
  "6dfe6271fe5f75fe5c79fe597dff5680ff5384ff5188ff4e8bff4b8fff4992ff4796fe4499fe429cfe409ffd3fa1fd3d" +
  "a4fc3ca7fc3aa9fb39acfb38affa37b1f936b4f836b7f735b9f635bcf534bef434c1f334c3f134c6f034c8ef34cbed34" +
  "cdec34d0ea34d2e935d4e735d7e535d9e436dbe236dde037dfdf37e1dd37e3db38e5d938e7d739e9d539ebd339ecd13a" +
  "eecf3aefcd3af1cb3af2c93af4c73af5c53af6c33af7c13af8be39f9bc39faba39fbb838fbb637fcb336fcb136fdae35" +
  "fdac34fea933fea732fea431fea130fe9e2ffe9b2dfe992cfe962bfe932afe9029fd8d27fd8a26fc8725fc8423fb8122" +
  "fb7e21fa7b1ff9781ef9751df8721cf76f1af66c19f56918f46617f36315f26014f15d13f05b12ef5811ed5510ec530f" +
  "eb500eea4e0de84b0ce7490ce5470be4450ae2430ae14109df3f08dd3d08dc3b07da3907d83706d63506d43305d23105" +
  "d02f05ce2d04cc2b04ca2a04c82803c52603c32503c12302be2102bc2002b91e02b71d02b41b01b21a01af1801ac1701" +
  "a91601a71401a41301a112019e10019b0f01980e01950d01920b018e0a018b09028808028507028106027e05027a0403";
const TURBO = new Uint8Array(768);
for (let i = 0; i < 768; i++) TURBO[i] = parseInt(TURBO_HEX.substr(2 * i, 2), 16);

const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------- requests
function storedToken() {
  try {
    return localStorage.getItem(TOKEN_KEY) || "";
  } catch (_) {
    return "";
  }
}

function withToken(url) {
  const token = storedToken();
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}

class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

/** fetch() with the bearer token, JSON in/out; throws ApiError with the server's detail. */
async function api(path, { method = "GET", json, timeoutMs = 20000, blob = false } = {}) {
  const headers = {};
  const token = storedToken();
  if (token) headers["Authorization"] = "Bearer " + token;
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  }
  const ctrl = new AbortController();
  const timer = setTimeout(() => ctrl.abort(), timeoutMs);
  let resp;
  try {
    resp = await fetch(path, { method, headers, body, signal: ctrl.signal, cache: "no-store" });
  } catch (err) {
    throw new ApiError(0, err.name === "AbortError" ? "timed out" : "server unreachable");
  } finally {
    clearTimeout(timer);
  }
  if (!resp.ok) {
    let detail = resp.statusText || "error " + resp.status;
    try {
      const data = await resp.json();
      detail = typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail);
    } catch (_) { /* not JSON */ }
    throw new ApiError(resp.status, detail);
  }
  if (blob) return resp.blob();
  const type = resp.headers.get("content-type") || "";
  return type.includes("json") ? resp.json() : resp.text();
}

let messageTimer = null;
function say(text, kind = "info") {
  const el = $("message");
  el.textContent = text;
  el.className = "message " + kind;
  clearTimeout(messageTimer);
  messageTimer = setTimeout(() => { el.textContent = ""; }, kind === "error" ? 15000 : 6000);
}

/** Run an action from a button: disable it meanwhile, report errors on the page. */
async function act(button, label, fn) {
  if (button) button.disabled = true;
  try {
    const out = await fn();
    return out;
  } catch (err) {
    say(`${label}: ${err.message}`, "error");
    return undefined;
  } finally {
    if (button) button.disabled = false;
  }
}

const fmt = (x, digits) => (typeof x === "number" && isFinite(x) ? x.toFixed(digits) : "–");

// ---------------------------------------------------------------- state
const ui = {
  status: null,
  sensor: null, // [W, H] of the depth maps, sensor pixels
  range: [0, 35],
  framesShown: 0,
  lastFrameAt: 0,
  streamKind: "none", // "stream" | "poll" | "none"
  ws: null,
  wsRetry: null,
  decoding: false,
  pendingBlob: null,
  crop: null, // {sw, sh}: the depth part of the received image, image pixels
  roi: null, // [x0, y0, x1, y1] sensor pixels
  drag: null,
  exposureTouchedAt: 0,
  textureUrl: null,
};
window.fringescope = ui; // for tests and the curious

// ---------------------------------------------------------------- colour bar
function niceStep(span, maxTicks) {
  const raw = span / Math.max(maxTicks, 1);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 5, 10]) if (m * mag >= raw) return m * mag;
  return 10 * mag;
}

function drawColorbar() {
  const canvas = $("colorbar");
  const ctx = canvas.getContext("2d");
  const img = ctx.createImageData(canvas.width, canvas.height);
  for (let y = 0; y < canvas.height; y++) {
    const i = Math.round(255 * (1 - y / (canvas.height - 1)));
    for (let x = 0; x < canvas.width; x++) {
      const o = 4 * (y * canvas.width + x);
      img.data[o] = TURBO[3 * i];
      img.data[o + 1] = TURBO[3 * i + 1];
      img.data[o + 2] = TURBO[3 * i + 2];
      img.data[o + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  const [lo, hi] = ui.range;
  const ticks = $("bar-ticks");
  ticks.textContent = "";
  const step = niceStep(hi - lo, 6);
  for (let t = Math.ceil(lo / step) * step; t <= hi + 1e-9 * (hi - lo); t += step) {
    const div = document.createElement("div");
    div.className = "tick";
    div.style.top = `${100 * (1 - (t - lo) / (hi - lo))}%`;
    div.textContent = `${+t.toFixed(6)}`;
    ticks.appendChild(div);
  }
}

let rangeTimer = null;
function onRangeChange() {
  const lo = parseFloat($("range-min").value);
  const hi = parseFloat($("range-max").value);
  const ok = isFinite(lo) && isFinite(hi) && lo < hi;
  $("range-min").classList.toggle("invalid", !ok);
  $("range-max").classList.toggle("invalid", !ok);
  if (!ok) return;
  ui.range = [lo, hi];
  drawColorbar();
  clearTimeout(rangeTimer);
  rangeTimer = setTimeout(() => connectStream(), 300); // the server colours: ask anew
}

// ---------------------------------------------------------------- depth image
function rangeQuery() {
  return `min_mm=${encodeURIComponent(ui.range[0])}&max_mm=${encodeURIComponent(ui.range[1])}`;
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
    if (!(err instanceof ApiError && err.status === 503)) say(`depth image: ${err.message}`, "error");
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

function connectStream() {
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
  ws.onmessage = (ev) => { if (ui.ws === ws && !$("show-sigma").checked) showDepthBlob(ev.data, "stream"); };
  ws.onclose = () => {
    if (ui.ws !== ws) return; // replaced on purpose
    ui.ws = null;
    $("stream-kind").textContent = "polling";
    ui.wsRetry = setTimeout(connectStream, 5000);
  };
}

// Fallback while the stream is down: poll the latest colormap.
async function pollDepth() {
  const st = ui.status;
  const sigma = $("show-sigma").checked; // the σ map is polled, the stream carries depth
  if (!sigma && ui.ws && ui.ws.readyState === WebSocket.OPEN) return;
  if (!st || !st.results_published) return; // nothing to fetch yet (avoid 503 noise)
  try {
    const query = sigma ? "field=sigma" : rangeQuery();
    const blob = await api(`/api/depth/latest?format=color&${query}`, { blob: true });
    await showDepthBlob(blob, "poll");
  } catch (_) { /* shown by the status bar */ }
}

// ---------------------------------------------------------------- ROI analysis
function toSensor(ev) {
  const r = $("roi").getBoundingClientRect();
  const [W, H] = ui.sensor;
  const x = Math.min(Math.max((ev.clientX - r.left) / r.width, 0), 1) * W;
  const y = Math.min(Math.max((ev.clientY - r.top) / r.height, 0), 1) * H;
  return [x, y];
}

function drawRoi() {
  const canvas = $("roi");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const box = ui.drag ? ui.drag.box : ui.roi;
  if (!box || !ui.sensor) return;
  const k = canvas.width / ui.sensor[0];
  ctx.lineWidth = Math.max(2, canvas.width / 300);
  ctx.strokeStyle = "#ffffff";
  ctx.setLineDash([8, 5]);
  ctx.strokeRect(box[0] * k, box[1] * k, (box[2] - box[0]) * k, (box[3] - box[1]) * k);
}

function roiBox(a, b) {
  const [W, H] = ui.sensor;
  const x0 = Math.max(0, Math.floor(Math.min(a[0], b[0])));
  const y0 = Math.max(0, Math.floor(Math.min(a[1], b[1])));
  const x1 = Math.min(W, Math.ceil(Math.max(a[0], b[0])));
  const y1 = Math.min(H, Math.ceil(Math.max(a[1], b[1])));
  return [x0, y0, x1, y1];
}

function setupRoi() {
  const canvas = $("roi");
  canvas.addEventListener("pointerdown", (ev) => {
    if (!ui.sensor || ev.button !== 0) return;
    canvas.setPointerCapture(ev.pointerId);
    const p = toSensor(ev);
    ui.drag = { start: p, box: roiBox(p, p) };
  });
  canvas.addEventListener("pointermove", (ev) => {
    if (!ui.drag) return;
    ui.drag.box = roiBox(ui.drag.start, toSensor(ev));
    drawRoi();
  });
  const finish = (ev) => {
    if (!ui.drag) return;
    const box = roiBox(ui.drag.start, toSensor(ev));
    ui.drag = null;
    if (box[2] - box[0] >= 4 && box[3] - box[1] >= 4) {
      ui.roi = box;
      analyse();
    }
    drawRoi();
  };
  canvas.addEventListener("pointerup", finish);
  canvas.addEventListener("pointercancel", () => { ui.drag = null; drawRoi(); });
  $("roi-clear").addEventListener("click", () => {
    ui.roi = null;
    drawRoi();
    $("roi-result").textContent = "no region selected";
  });
  for (const input of [...document.querySelectorAll('input[name="roi-kind"]'), $("roi-polarity")]) {
    input.addEventListener("change", () => { if (ui.roi) analyse(); });
  }
}

async function analyse() {
  const kind = document.querySelector('input[name="roi-kind"]:checked').value;
  const out = $("roi-result");
  const roi = ui.roi;
  out.textContent = `measuring [${roi.join(", ")}]…`;
  out.className = "roi-result muted";
  try {
    const body = kind === "feature" ? { roi, polarity: $("roi-polarity").value } : { roi };
    const r = await api(`/api/analysis/${kind}`, { method: "POST", json: body });
    out.className = "roi-result";
    if (kind === "plane") {
      out.innerHTML =
        `<b>accuracy</b> ${fmt(r.accuracy_mm, 3)} mm · <b>precision</b> ${fmt(r.precision_mm, 3)} mm · ` +
        `flatness ${fmt(r.flatness_mm, 3)} mm · ${r.points.toLocaleString()} points`;
    } else {
      out.innerHTML =
        `<b>suture height</b> ${fmt(r.height_mm, 3)} ± ${fmt(r.height_std_mm, 3)} mm · ` +
        `${r.count} sample${r.count === 1 ? "" : "s"}`;
    }
    out.title = `ROI [${roi.join(", ")}] sensor pixels`;
  } catch (err) {
    out.className = "roi-result error";
    out.textContent = `measurement failed: ${err.message}`;
  }
}

// ---------------------------------------------------------------- texture
async function pollTexture() {
  const st = ui.status;
  if (!st || !st.results_published) return;
  try {
    const blob = await api("/api/texture/latest.png", { blob: true });
    const url = URL.createObjectURL(blob);
    const img = $("texture");
    const old = ui.textureUrl;
    ui.textureUrl = url;
    img.onload = () => {
      if (old) URL.revokeObjectURL(old);
      img.hidden = false;
      $("texture-wait").hidden = true;
    };
    img.src = url;
  } catch (_) { /* next time */ }
}

// ---------------------------------------------------------------- status bar
function showStatus(st) {
  ui.status = st;
  const state = $("state");
  state.textContent = st.state;
  state.className = `pill state-${st.state}`;
  $("m-camera").textContent = fmt(st.camera_fps, 1);
  $("m-depth").textContent = fmt(st.depth_fps, 2);
  $("m-latency").textContent = fmt(st.latency_ms, 0);
  $("m-dropped").textContent = String(st.dropped_sets ?? "–");
  $("m-incomplete").textContent = String(st.incomplete_sets ?? "–");
  $("m-mode").textContent = st.mode;
  const sch = st.schedule;
  $("m-sensor").textContent = (st.bit_depth ? `${st.bit_depth}-bit` : "–") + (sch
    ? ` · ${sch.unwrap || "hierarchical"} [${sch.frequencies.map((k) => +k.toFixed(2)).join(", ")}]×${sch.steps}` +
      (sch.orientation === "horizontal" ? " horizontal" : "")
    : "");

  const devices = $("devices");
  devices.textContent = "";
  for (const d of st.devices || []) {
    const chip = document.createElement("span");
    chip.className = `chip dev-${d.state}`;
    chip.textContent = `${d.kind}: ${d.state}`;
    chip.title = `${d.name}${d.error ? " — " + d.error : ""}`;
    devices.appendChild(chip);
  }

  const fault = $("fault");
  fault.hidden = st.state !== "fault";
  if (st.state === "fault") {
    const bad = (st.devices || []).filter((d) => d.state === "fault" || d.error);
    $("fault-text").textContent =
      (st.last_error || "device fault") + (bad.length ? ` (${bad.map((d) => d.name).join(", ")})` : "");
  }
  const warnings = $("warnings");
  const list = st.warnings || [];
  warnings.hidden = list.length === 0;
  warnings.textContent = list.map((w) => "⚠ " + w).join("   ");

  $("acq-state").textContent = st.acquiring ? "acquiring" : "stopped";
  $("btn-start").disabled = st.acquiring;
  $("btn-stop").disabled = !st.acquiring;
  if (performance.now() - ui.exposureTouchedAt > 3000) {
    $("exposure").value = String(st.exposure_ms);
    $("exposure-value").textContent = fmt(st.exposure_ms, 0);
  }
  if (document.activeElement !== $("led")) $("led").value = st.led;
  $("rolling").checked = st.mode === "rolling";

  const rec = $("btn-record");
  if (ui.recording !== (st.recording ?? null)) {
    ui.recording = st.recording ?? null;
    refreshRecordings();
  }
  rec.textContent = ui.recording ? `Stop recording (${ui.recording})` : "Record";
  rec.classList.toggle("recording", Boolean(ui.recording));

  const cal = st.calibration;
  $("calib-line").textContent = cal
    ? `calibration: ${cal.name ?? "?"} · ${cal.poses} poses · ` +
      `${fmt(cal.height_range_mm[0], 1)}–${fmt(cal.height_range_mm[1], 1)} mm · model ${cal.model ?? "eq5"}` +
      (cal.held_out?.[cal.model]?.rms_mm != null ? ` (held-out RMS ${fmt(cal.held_out[cal.model].rms_mm, 4)} mm)` : "")
    : st.state === "calibrating" ? "calibration: being created…" : "calibration: none active";

  const waiting = $("depth-wait");
  if (!ui.framesShown) {
    waiting.textContent = st.state === "calibrating" ? "creating the calibration…"
      : !st.acquiring ? "acquisition stopped" : "waiting for depth…";
  }
  const age = ui.lastFrameAt ? (performance.now() - ui.lastFrameAt) / 1000 : null;
  $("depth-info").textContent = ui.framesShown
    ? `${ui.framesShown} images · last ${fmt(age, 1)} s ago` : "no depth yet";
}

async function pollStatus() {
  try {
    showStatus(await api("/api/status", { timeoutMs: 5000 }));
  } catch (err) {
    const state = $("state");
    state.textContent = "offline";
    state.className = "pill state-fault";
    say(`status: ${err.message}`, "error");
  }
}

// ---------------------------------------------------------------- controls
function setupControls() {
  const slider = $("exposure");
  let sendTimer = null;
  const send = () => act(null, "exposure", async () => {
    const r = await api("/api/exposure", { method: "PUT", json: { exposure_ms: Number(slider.value) } });
    say(`exposure ${fmt(r.exposure_ms, 0)} ms (${r.applies})`);
  });
  slider.addEventListener("input", () => {
    ui.exposureTouchedAt = performance.now();
    $("exposure-value").textContent = slider.value;
    clearTimeout(sendTimer);
    sendTimer = setTimeout(send, 250);
  });
  slider.addEventListener("change", () => {
    ui.exposureTouchedAt = performance.now();
    clearTimeout(sendTimer);
    send();
  });
  $("led").addEventListener("change", (ev) => act(null, "LED", async () => {
    const r = await api("/api/led", { method: "PUT", json: { led: ev.target.value } });
    say(`LED ${r.led} (${r.applies})`);
  }));
  $("rolling").addEventListener("change", (ev) => act(null, "mode", async () => {
    const r = await api("/api/mode", { method: "PUT", json: { rolling: ev.target.checked } });
    say(`mode: ${r.mode}`);
  }));
  $("btn-start").addEventListener("click", (ev) => act(ev.target, "start", async () => {
    await api("/api/acquisition/start", { method: "POST" });
    say("acquisition started");
    pollStatus();
  }));
  $("btn-stop").addEventListener("click", (ev) => act(ev.target, "stop", async () => {
    await api("/api/acquisition/stop", { method: "POST" });
    say("acquisition stopped");
    pollStatus();
  }));
  $("btn-auto").addEventListener("click", (ev) => act(ev.target, "auto exposure", async () => {
    say("auto exposure: measuring a few sets…");
    const r = await api("/api/exposure/auto", { method: "POST", json: {}, timeoutMs: 120000 });
    say(`auto exposure: ${fmt(r.exposure_ms, 1)} ms, ${fmt(100 * r.saturated_fraction, 2)} % saturated` +
      (r.warning ? ` — ${r.warning}` : ""));
    pollStatus();
  }));
  for (const id of ["range-min", "range-max"]) $(id).addEventListener("change", onRangeChange);
  $("btn-record").addEventListener("click", (ev) => act(ev.target, "recording", async () => {
    if (ui.recording) {
      await api("/api/recording/stop", { method: "POST" });
      say(`recording ${ui.recording} stopped`);
    } else {
      const name = $("record-name").value.trim();
      await api("/api/recording/start", { method: "POST", json: name ? { name } : {} });
      say("recording started");
    }
    pollStatus();
  }));
}

// ---------------------------------------------------------------- recordings
async function refreshRecordings() {
  try {
    const data = await api("/api/recordings");
    const list = $("recordings");
    list.replaceChildren();
    const items = Array.isArray(data) ? data : [];
    for (const r of items.slice(0, 8)) {
      const li = el("li");
      const a = el("a", `${r.name} (${r.n_sets ?? "?"} sets)`);
      a.href = `/api/recordings/${encodeURIComponent(r.name)}.zip`;
      a.download = `${r.name}.zip`;
      li.append(a);
      list.append(li);
    }
  } catch (err) {
    say(`recordings: ${err.message}`);
  }
}

// ---------------------------------------------------------------- calibration wizard
function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

async function showPosePreview(url) {
  try {
    const blob = await api(url, { blob: true });
    const img = $("pose-preview");
    if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
    img.src = URL.createObjectURL(blob);
    img.hidden = false;
  } catch (err) {
    say(`pose preview: ${err.message}`, "error");
  }
}

function renderPoses(poses) {
  const body = $("pose-table").querySelector("tbody");
  body.textContent = "";
  for (const p of poses) {
    const tr = el("tr");
    tr.appendChild(el("td", String(p.index)));
    tr.appendChild(el("td", p.found ? "✓ found" : "✗ not found", p.found ? "ok" : "bad"));
    tr.appendChild(el("td", String(p.corners)));
    tr.appendChild(el("td", `${fmt(p.exposure_ms, 0)} ms`));
    const td = el("td");
    const view = el("button", "view", "small-btn");
    view.addEventListener("click", () => showPosePreview(p.preview_url));
    const del = el("button", "delete", "small-btn danger");
    del.addEventListener("click", (ev) => act(ev.target, "delete pose", async () => {
      renderPoses(await api(`/api/calibration/session/poses/${p.index}`, { method: "DELETE" }));
    }));
    td.append(view, del);
    tr.appendChild(td);
    body.appendChild(tr);
  }
  $("btn-solve").disabled = poses.filter((p) => p.found).length < 2;
}

function renderReport(r) {
  const box = $("solve-report");
  box.textContent = "";
  box.appendChild(el("p",
    `RMS ${fmt(r.rms_mm, 4)} mm · reprojection ${fmt(r.reprojection_px, 3)} px · ` +
    `heights ${fmt(r.height_range_mm[0], 1)}–${fmt(r.height_range_mm[1], 1)} mm`));
  box.appendChild(el("p", `model: ${r.model ?? "eq5"} · held-out poses: ` +
    (Object.entries(r.held_out ?? {}).map(([m, h]) =>
      `${m} RMS ${fmt(h.rms_mm, 4)} / max ${fmt(h.max_mm, 4)} mm`).join(" · ") || "–")));
  const table = el("table");
  const head = el("tr");
  for (const h of ["pose", "name", "points", "reproj. px", "RMS mm", "height mm", "used"]) head.appendChild(el("th", h));
  table.appendChild(head);
  for (const p of r.poses) {
    const tr = el("tr");
    const heights = p.height_mm.filter((h) => h !== null);
    const hr = heights.length ? `${fmt(Math.min(...heights), 1)}–${fmt(Math.max(...heights), 1)}` : "–";
    for (const v of [String(p.pose), p.name, String(p.points), fmt(p.reprojection_px, 3), fmt(p.rms_mm, 4), hr,
      p.dropped ? "dropped" : "yes"]) tr.appendChild(el("td", v));
    if (p.dropped) tr.className = "bad";
    table.appendChild(tr);
  }
  box.appendChild(table);
}

function setupWizard() {
  $("btn-session").addEventListener("click", (ev) => act(ev.target, "new session", async () => {
    const type = $("board-type").value;
    const board = { type, inner_corners: [Number($("board-cols").value), Number($("board-rows").value)] };
    board[type === "checkerboard" ? "square_mm" : "spacing_mm"] = Number($("board-pitch").value);
    await api("/api/calibration/session", { method: "POST", json: board });
    renderPoses([]);
    $("solve-report").textContent = "";
    $("pose-preview").hidden = true;
    $("btn-capture").disabled = false;
    $("btn-activate").disabled = true;
    say("calibration session started: capture pose 0 (the reference plane) first");
  }));
  $("btn-capture").addEventListener("click", (ev) => act(ev.target, "capture pose", async () => {
    say("capturing a fringe set…");
    const pose = await api("/api/calibration/session/poses", { method: "POST", timeoutMs: 60000 });
    say(pose.found ? `pose ${pose.index}: board found (${pose.corners} points)`
      : `pose ${pose.index}: board NOT found — move it or change exposure`, pose.found ? "info" : "error");
    await showPosePreview(pose.preview_url);
    renderPoses(await api("/api/calibration/session/poses"));
  }));
  $("btn-solve").addEventListener("click", (ev) => act(ev.target, "solve", async () => {
    say("solving…");
    const report = await api("/api/calibration/session/solve", { method: "POST", json: {}, timeoutMs: 300000 });
    renderReport(report);
    $("btn-activate").disabled = false;
    say(`solved: RMS ${fmt(report.rms_mm, 4)} mm`);
  }));
  $("btn-activate").addEventListener("click", (ev) => act(ev.target, "activate", async () => {
    const r = await api("/api/calibration/session/activate", { method: "POST", json: { name: $("calib-name").value } });
    say(`calibration "${r.name}" is active`);
    pollStatus();
  }));
}

// ---------------------------------------------------------------- start
function start() {
  drawColorbar();
  setupControls();
  setupRoi();
  setupWizard();
  $("viewer3d").src = withToken("/viser/");
  $("open3d").href = withToken("/viser/");
  pollStatus();
  setInterval(pollStatus, 1000);
  setInterval(pollDepth, 700);
  setInterval(pollTexture, 1000);
  connectStream();
}

document.addEventListener("DOMContentLoaded", start);
