// Fringe pattern schedule: a selector over GET /api/schedules, each with its predicted depth σ
// and fringe-order error rate at the rig's noise; PUT /api/schedule switches between two sets.

import { $, act, api, el, fmt, say } from "./api.js";
import { onStatus } from "./status.js";

let rows = [];
let loadedFor = null; // schedule name the table was last loaded for
let loadedAt = 0;

const rate = (p) => (typeof p !== "number" ? "–" : p === 0 ? "0" : p.toExponential(1));

function label(r) {
  const sigma = r.predicted_sigma_mm == null ? "σ –" : `σ ${fmt(1000 * r.predicted_sigma_mm, 0)} µm`;
  return `${r.name} · ${r.frames_per_depth} frames · ${sigma} · order err ${rate(r.predicted_order_error_rate)}` +
    (r.calibration_applies === false ? " · calibration does not apply" : "");
}

function render() {
  const select = $("schedule");
  if (document.activeElement === select) return;
  select.replaceChildren(...rows.map((r) => {
    const opt = el("option", label(r));
    opt.value = r.name;
    return opt;
  }));
  const active = rows.find((r) => r.active);
  if (active) select.value = active.name;
  $("schedule-line").textContent = active
    ? `[${active.frequencies.join(", ")}] × ${active.steps} (${active.unwrap}): predicted σ ` +
      `${active.predicted_sigma_mm == null ? "– (no depth map yet)" : `${fmt(active.predicted_sigma_mm, 4)} mm`}, ` +
      `order-error rate ${rate(active.predicted_order_error_rate)} (${active.prediction_source})`
    : "schedule: not a registered one";
}

async function load() {
  try {
    rows = await api("/api/schedules");
    loadedAt = performance.now();
    render();
  } catch (err) {
    say(`schedules: ${err.message}`, "error");
  }
}

export function setupSchedule() {
  $("schedule").addEventListener("change", (ev) => act(null, "schedule", async () => {
    const r = await api("/api/schedule", { method: "PUT", json: { name: ev.target.value } });
    say(`schedule ${r.name}: ${r.frames_per_depth} frames a depth map (${r.applies})`);
    ev.target.blur();
    await load();
  }));
  onStatus((st) => {
    const name = st.schedule?.name ?? null;
    // reload on a switch (from any client) and every 10 s: the predictions follow the live rig
    if (name !== loadedFor || performance.now() - loadedAt > 10000) {
      loadedFor = name;
      load();
    }
  });
}
