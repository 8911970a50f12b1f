// Fringescope dashboard: one page for the operating room. ES modules, no build step, no CDN.
// One module per panel; this one starts them and hands them the limits (GET /api/limits).

import { api, say } from "./api.js";
import { setupAnalysis } from "./analysis.js";
import { applyLimits as controlsLimits, setupControls } from "./controls.js";
import { applyLimits as depthLimits, setupDepth } from "./depth.js";
import { setupMeasure } from "./measure.js";
import { setupRecording } from "./recording.js";
import { setupSchedule } from "./schedule.js";
import { signedIn, ui } from "./state.js";
import { pollStatus } from "./status.js";
import { setupTexture } from "./texture.js";
import { setupView3d } from "./view3d.js";
import { setupWizard } from "./wizard.js";

async function loadLimits() {
  try {
    ui.limits = await api("/api/limits");
    controlsLimits(ui.limits);
    depthLimits(ui.limits);
  } catch (err) {
    say(`limits: ${err.message}`, "error");
  }
}

function start() {
  setupDepth();
  setupAnalysis();
  setupMeasure();
  setupControls();
  setupRecording();
  setupSchedule();
  setupWizard();
  setupTexture();
  setupView3d();
  loadLimits();
  pollStatus();
  setInterval(pollStatus, 1000);
}

// static/auth.js (a module that runs first) signs in when the server has a token
function begin() {
  signedIn().then(start, (err) => say(String(err.message || err), "error"));
}

if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", begin);
else begin();
