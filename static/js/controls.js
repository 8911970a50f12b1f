// Acquisition, exposure and LED: start/stop, exposure slider and auto-exposure, LED, rolling
// mode, the calibration line. The ranges (LED names, exposure range) come from /api/limits.

import { $, act, api, el, fmt, say } from "./api.js";
import { ui } from "./state.js";
import { onStatus, pollStatus } from "./status.js";

/** Slider range and LED choices from GET /api/limits. */
export function applyLimits(limits) {
  const slider = $("exposure");
  const [lo, hi] = limits.exposure_ms;
  slider.min = String(lo);
  slider.max = String(hi);
  const led = $("led");
  const current = led.value || (ui.status && ui.status.led);
  led.replaceChildren(...limits.leds.map((name) => {
    const opt = el("option", name);
    opt.value = name;
    return opt;
  }));
  if (current) led.value = current;
}

function showControls(st) {
  $("acq-state").textContent = st.acquiring ? "acquiring" : "stopped";
  $("btn-start").disabled = st.acquiring;
  $("btn-stop").disabled = !st.acquiring;
  if (performance.now() - ui.exposureTouchedAt > 3000) {
    $("exposure").value = String(st.exposure_ms);
    $("exposure-value").textContent = fmt(st.exposure_ms, 0);
  }
  if (document.activeElement !== $("led")) $("led").value = st.led;
  $("rolling").checked = st.mode === "rolling";
  const cal = st.calibration;
  $("calib-line").textContent = cal
    ? `calibration: ${cal.name ?? "?"} · ${cal.poses} poses · ` +
      `${fmt(cal.height_range_mm[0], 1)}–${fmt(cal.height_range_mm[1], 1)} mm · model ${cal.model ?? "eq5"}` +
      (cal.held_out?.[cal.model]?.rms_mm != null ? ` (held-out RMS ${fmt(cal.held_out[cal.model].rms_mm, 4)} mm)` : "")
    : st.state === "calibrating" ? "calibration: being created…" : "calibration: none active";
}

export function setupControls() {
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
  onStatus(showControls);
}
