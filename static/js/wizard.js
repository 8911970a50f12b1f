// The calibration wizard: a board, poses (pose 0 = reference plane), solve, activate.

import { $, act, api, ApiError, el, fmt, say } from "./api.js";
import { onStatus, pollStatus } from "./status.js";

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

const CELL_PX = 9;
const GAP_PX = 12;

/** The coverage map: per height bin a grid of the image cells (green: board points; teal:
 * the model's sigma within tolerance; red: neither), the shares against the target and the
 * next pose. */
function renderCoverage(cov) {
  const box = $("coverage");
  if (!cov) {
    box.hidden = true;
    return;
  }
  box.hidden = false;
  const [cols, rows] = cov.cells;
  const bins = cov.covered.length;
  const canvas = $("coverage-map");
  canvas.width = bins * (cols * CELL_PX + GAP_PX);
  canvas.height = rows * CELL_PX + 16;
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.font = "10px sans-serif";
  for (let b = 0; b < bins; b += 1) {
    const x0 = b * (cols * CELL_PX + GAP_PX);
    for (let r = 0; r < rows; r += 1) {
      for (let c = 0; c < cols; c += 1) {
        const sigma = cov.sigma_model_um[b][r][c];
        const ok = sigma !== null && sigma <= cov.sigma_tolerance_um;
        ctx.fillStyle = cov.covered[b][r][c] ? "#2e9d4f" : ok ? "#5fb3b3" : "#b04040";
        ctx.fillRect(x0 + c * CELL_PX, r * CELL_PX, CELL_PX - 1, CELL_PX - 1);
      }
    }
    ctx.fillStyle = "#888";
    const lo = cov.height_edges_mm[b];
    const hi = cov.height_edges_mm[b + 1];
    ctx.fillText(`${fmt(lo, 0)}–${fmt(hi, 0)} mm`, x0, rows * CELL_PX + 12);
  }
  const line = $("coverage-line");
  line.textContent = cov.status;
  line.className = cov.reached ? "ok" : "muted";
  $("suggestion-line").textContent = cov.reached
    ? "calibrated volume reached: Solve"
    : `next pose: ${cov.suggestion.text}`;
}

function boardLine(b) {
  const size = b.inner_corners ?? b.grid ?? [];
  const pitch = b.square_mm ?? b.spacing_mm;
  return `${b.type} ${size.join(" × ")}, ${fmt(pitch, 2)} mm`;
}

/** Show the server's session (or none): the wizard's state lives on the server, not in the page. */
function showSession(session) {
  const open = session !== null;
  $("btn-capture").disabled = !open;
  $("btn-suggest").disabled = !open;
  $("btn-cancel-session").disabled = !open;
  $("btn-activate").disabled = !(open && session.solved);
  $("session-line").textContent = open
    ? `session open since ${session.created}: ${boardLine(session.board)}, ` +
      `${session.poses.length} poses` +
      (session.solved ? " · solved" : "")
    : "no session open";
  renderPoses(open ? session.poses : []);
  renderCoverage(open ? session.coverage : null);
  if (!open) {
    $("solve-report").textContent = "";
    $("pose-preview").hidden = true;
  }
}

async function currentSession() {
  try {
    return await api("/api/calibration/session");
  } catch (err) {
    if (err instanceof ApiError && err.status === 409) return null; // none open
    throw err;
  }
}

let shownKey; // the session last shown, as the status describes it

/** Follow the server's session (GET /api/status names it): after a page load, pick up a session
 * opened before (this page or another); when another client closes it, show that. */
async function followSession(st) {
  const s = st.calibration_session;
  const key = s ? `${s.created}|${s.poses}|${s.solved}` : "none";
  if (key === shownKey) return;
  const first = shownKey === undefined;
  shownKey = key;
  if (s === null || s === undefined) {
    showSession(null);
    return;
  }
  const session = await currentSession();
  showSession(session);
  if (first && session !== null) restoreForm(session);
}

function restoreForm(session) {
  const b = session.board;
  $("board-type").value = b.type;
  const size = b.inner_corners ?? b.grid;
  if (size) [$("board-cols").value, $("board-rows").value] = size.map(String);
  $("board-pitch").value = String(b.square_mm ?? b.spacing_mm ?? $("board-pitch").value);
  $("wizard").open = true;
  say(`calibration session restored: ${session.poses.length} poses (Cancel closes it)`);
}

export function setupWizard() {
  onStatus((st) => act(null, "calibration session", () => followSession(st)));
  $("btn-session").addEventListener("click", (ev) => act(ev.target, "new session", async () => {
    const type = $("board-type").value;
    const size = [Number($("board-cols").value), Number($("board-rows").value)];
    const pitch = Number($("board-pitch").value);
    const board = type === "checkerboard"
      ? { type, inner_corners: size, square_mm: pitch }
      : { type, grid: size, spacing_mm: pitch };
    showSession(await api("/api/calibration/session", { method: "POST", json: board }));
    say("calibration session started: capture pose 0 (the reference plane) first");
  }));
  const cancel = $("btn-cancel-session");
  cancel.addEventListener("click", (ev) => act(ev.target, "cancel session", async () => {
    const r = await api("/api/calibration/session", { method: "DELETE" });
    showSession(null);
    say(r.cancelled ? `calibration session cancelled (${r.poses} poses dropped)`
      : "no session was open");
    pollStatus();
  }));
  $("btn-suggest").addEventListener("click", (ev) => act(ev.target, "next pose", async () => {
    const line = $("pose-line");
    line.textContent = "finding the next pose…";
    line.className = "muted";
    const s = await api("/api/calibration/session/suggested-pose",
      { method: "POST", timeoutMs: 60000 });
    line.textContent = s.moved
      ? `${s.hint} — the simulator's board is there (exposure ${fmt(s.exposure_ms, 1)} ms): ` +
        "Capture pose"
      : `${s.hint}, then Capture pose`;
    renderCoverage(s.coverage);
    pollStatus();
  }));
  $("btn-capture").addEventListener("click", (ev) => act(ev.target, "capture pose", async () => {
    const line = $("pose-line");
    line.textContent = "capturing a fringe set and searching for the board…";
    line.className = "muted";
    try {
      const pose = await api("/api/calibration/session/poses",
        { method: "POST", timeoutMs: 60000 });
      line.textContent = pose.found ? `pose ${pose.index}: board found (${pose.corners} points)`
        : `pose ${pose.index}: no board found — bring the whole board into view, ` +
          "or change the exposure";
      line.className = pose.found ? "ok" : "bad";
      renderCoverage(pose.coverage);
      await showPosePreview(pose.preview_url);
    } catch (err) {
      line.textContent = "";
      throw err;
    }
    showSession(await currentSession());
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
    showSession(null); // activation ends the session
    say(`calibration "${r.name}" is active; the session is closed`);
    pollStatus();
  }));
}
