// Analysis of a region of the depth image: drag a box, get plane accuracy/precision or
// a suture's height (POST /api/analysis/plane|feature).

import { $, api, fmt } from "./api.js";
import { ui } from "./state.js";

function toSensor(ev) {
  const r = $("roi").getBoundingClientRect();
  const [W, H] = ui.sensor;
  const x = Math.min(Math.max((ev.clientX - r.left) / r.width, 0), 1) * W;
  const y = Math.min(Math.max((ev.clientY - r.top) / r.height, 0), 1) * H;
  return [x, y];
}

/** Draw the selected (or the dragged) box over the depth image. */
export function drawRoi() {
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

export function setupAnalysis() {
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
