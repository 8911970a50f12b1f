// The status bar: state, rates, devices, faults and warnings from GET /api/status.
// Other panels subscribe with onStatus(fn) and get every new status after the bar.

import { $, api, el, fmt, say } from "./api.js";
import { ui } from "./state.js";

const listeners = [];

/** Call fn(status) with every status polled from now on. */
export function onStatus(fn) {
  listeners.push(fn);
}

function showStatus(st) {
  ui.status = st;
  const state = $("state");
  state.textContent = st.state;
  state.className = `pill state-${st.state}`;
  state.title = st.state_reason ? `${st.state}: ${st.state_reason}` : "instrument state";
  $("m-camera").textContent = fmt(st.camera_fps, 1);
  $("m-depth").textContent = fmt(st.depth_fps, 2);
  $("m-latency").textContent = fmt(st.latency_ms, 0);
  // losses since the first depth map; the start-up's own (camera before engine) in the tooltip
  const live = st.since_warmup && Object.keys(st.since_warmup).length ? st.since_warmup : st;
  const warm = st.warmup || {};
  $("m-dropped").textContent = String(live.dropped_sets ?? "–");
  $("m-incomplete").textContent = String(live.incomplete_sets ?? "–");
  for (const [id, key] of [["m-dropped", "dropped_sets"], ["m-incomplete", "incomplete_sets"]]) {
    $(id).parentElement.title = key in warm
      ? `since the first depth map; ${warm[key]} during start-up, ${st[key]} in all`
      : "since start-up";
  }
  // exposure bracketing: as wide as "rolling" (the bar must not move); its note below
  $("m-mode").textContent = st.bracket ? "bracket" : st.mode;
  $("m-mode").title = st.bracket ? st.bracket.note : "";
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
  const list = (st.warnings || []).map((w) => "⚠ " + w);
  if (st.phase) {
    const pct = typeof st.progress === "number" ? ` (${Math.round(100 * st.progress)} %)` : "";
    // "calibrating: calibrating pose 2 of 8" says it twice: the phase alone when it names the state
    const what = st.phase.startsWith(st.state) ? st.phase : `${st.state}: ${st.phase}`;
    list.unshift(`⏳ ${what}${pct}`);
  } else if (st.state_reason && st.state !== "fault" && st.state !== "running") {
    list.unshift(`⚠ ${st.state}: ${st.state_reason}`);
  }
  if (st.bracket) list.push(`ⓘ ${st.bracket.note}`); // why the depth rate halved
  if (st.last_error && st.last_error_resolved === false && st.state !== "fault") {
    const at = st.last_error_at ? new Date(st.last_error_at).toLocaleTimeString() : "";
    list.push(`⚠ last error ${at}: ${st.last_error}`);
  }
  warnings.hidden = list.length === 0;
  warnings.textContent = list.join("   ");
  showAlarms(st.alarms || []);
  for (const fn of listeners) fn(st);
}

let shownAlarms = "";

// The unacknowledged alarms, each with its Acknowledge button; redrawn only when the list
// changes, so a button is never replaced under the cursor.
function showAlarms(alarms) {
  const key = alarms.map((a) => a.id).join(",");
  if (key === shownAlarms) return;
  shownAlarms = key;
  const box = $("alarms");
  box.textContent = "";
  for (const a of alarms) {
    const row = el("div", undefined, "alarm");
    row.dataset.alarmId = String(a.id);
    row.appendChild(el("span", new Date(a.raised_at).toLocaleTimeString(), "alarm-time"));
    row.appendChild(el("span", `ALARM (${a.source}): ${a.message}`, "alarm-text"));
    const ack = el("button", "Acknowledge", "alarm-ack");
    ack.addEventListener("click", () => acknowledge(a.id, ack));
    row.appendChild(ack);
    box.appendChild(row);
  }
  box.hidden = alarms.length === 0;
}

async function acknowledge(id, button) {
  button.disabled = true;
  try {
    await api(`/api/alarms/${id}/ack`, { method: "POST" });
    await pollStatus();
  } catch (err) {
    button.disabled = false;
    say(`alarm: ${err.message}`, "error");
  }
}

export async function pollStatus() {
  try {
    showStatus(await api("/api/status", { timeoutMs: 5000 }));
  } catch (err) {
    const state = $("state");
    state.textContent = "offline";
    state.className = "pill state-fault";
    say(`status: ${err.message}`, "error");
  }
}
