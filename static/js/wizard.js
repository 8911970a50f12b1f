// The calibration wizard: a board, poses (pose 0 = reference plane), solve, activate.

import { $, act, api, el, fmt, say } from "./api.js";
import { pollStatus } from "./status.js";

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

export function setupWizard() {
  $("btn-session").addEventListener("click", (ev) => act(ev.target, "new session", async () => {
    const type = $("board-type").value;
    const size = [Number($("board-cols").value), Number($("board-rows").value)];
    const pitch = Number($("board-pitch").value);
    const board = type === "checkerboard"
      ? { type, inner_corners: size, square_mm: pitch }
      : { type, grid: size, spacing_mm: pitch };
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
