// The "change" colour mode: Δ against the reference (diverging blue–white–red, mm), the
// changed region's contour (drawn by the server), the largest rise and sink ± σ on hover.

import { $, api, fmt } from "./api.js";

// the server's anchors (app/outputs/change.py): sink blue, no change white, rise red
const ANCHORS = [[33, 102, 172], [247, 247, 247], [178, 24, 43]];

export const changeMode = () => $("show-change").checked;

/** RGB of x in [-1, 1] on the diverging map. */
export function diverging(x) {
  const t = Math.max(-1, Math.min(1, x));
  const [a, b] = t < 0 ? [ANCHORS[0], ANCHORS[1]] : [ANCHORS[1], ANCHORS[2]];
  const f = t < 0 ? t + 1 : t;
  return a.map((v, i) => Math.round(v + f * (b[i] - v)));
}

/** Paint the diverging bar and its ticks for ±r mm. */
export function drawChangeBar(canvas, ticks, r) {
  const ctx = canvas.getContext("2d");
  const img = ctx.createImageData(canvas.width, canvas.height);
  for (let y = 0; y < canvas.height; y++) {
    const [cr, cg, cb] = diverging(1 - (2 * y) / (canvas.height - 1));
    for (let x = 0; x < canvas.width; x++) {
      const o = 4 * (y * canvas.width + x);
      img.data[o] = cr;
      img.data[o + 1] = cg;
      img.data[o + 2] = cb;
      img.data[o + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  ticks.textContent = "";
  for (const f of [1, 0.5, 0, -0.5, -1]) {
    const div = document.createElement("div");
    div.className = "tick";
    div.style.top = `${100 * (1 - (f + 1) / 2)}%`;
    div.textContent = `${f > 0 ? "+" : ""}${+(f * r).toFixed(4)}`;
    ticks.appendChild(div);
  }
}

let halfRange = 1; // mm: the change colours span ±halfRange

/** The half-range (mm) the change colours span (default 1). */
export const changeRange = () => halfRange;

/** A new range from the inputs: ±max(|min|, |max|); false when it is not a number > 0. */
export function setChangeRange(lo, hi) {
  const r = Math.max(Math.abs(lo), Math.abs(hi));
  if (!(isFinite(r) && r > 0)) return false;
  halfRange = r;
  return true;
}

let summary = null;

function tipText() {
  if (!summary) return "no change map yet";
  const part = (label, v, s) => (v === null ? `${label} none`
    : `${label} ${v > 0 ? "+" : ""}${fmt(v, 3)} ± ${fmt(s, 3)} mm`);
  const reg = summary.registration;
  const how = summary.mode === "fixed" ? "fixed scope"
    : summary.mode === "failed" ? `registration failed: ${reg ? reg.note : ""}`
    : `registered, residual ${fmt(reg.residual_mm, 3)} mm`;
  return `largest ${part("rise", summary.rise_mm, summary.rise_sigma_mm)} · `
    + `${part("sink", summary.sink_mm, summary.sink_sigma_mm)} · changed `
    + `${fmt(summary.changed_area_mm2, 2)} mm² · ${how}`;
}

/** The newest change colours (PNG blob) and its figures; null without a reference. */
export async function fetchChange() {
  try {
    summary = await api("/api/change/summary");
  } catch (err) {
    summary = null;
    $("change-tip").textContent = err.message;
    return null;
  }
  $("change-tip").textContent = tipText();
  return api(`/api/change/latest?format=color&range_mm=${encodeURIComponent(changeRange())}`,
    { blob: true });
}

function showTip(ev) {
  if (!changeMode()) return;
  const tip = $("change-tip");
  tip.textContent = tipText();
  tip.hidden = false;
  const box = $("depth").getBoundingClientRect();
  tip.style.left = `${ev.clientX - box.left + 12}px`;
  tip.style.top = `${ev.clientY - box.top + 12}px`;
}

async function takeReference() {
  try {
    await api("/api/reference", { method: "POST", json: {} });
    $("change-tip").textContent = "reference taken";
  } catch (err) {
    $("change-tip").textContent = err.message;
  }
}

export function setupChange(onToggle) {
  $("show-change").addEventListener("change", () => {
    if (changeMode()) $("show-sigma").checked = false;
    $("change-tip").hidden = !changeMode();
    onToggle();
  });
  $("take-reference").addEventListener("click", takeReference);
  for (const id of ["depth", "roi", "measure"]) {
    $(id).addEventListener("mousemove", showTip);
  }
  $("roi").addEventListener("mouseleave", () => { $("change-tip").hidden = true; });
}
