// Recording: start/stop with an optional name, and the list of recordings as zip downloads.

import { $, act, api, el, say } from "./api.js";
import { ui } from "./state.js";
import { onStatus, pollStatus } from "./status.js";

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

function showRecording(st) {
  const rec = $("btn-record");
  if (ui.recording !== (st.recording ?? null)) {
    ui.recording = st.recording ?? null;
    refreshRecordings();
  }
  rec.textContent = ui.recording ? `Stop recording (${ui.recording})` : "Record";
  rec.classList.toggle("recording", Boolean(ui.recording));
}

export function setupRecording() {
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
  onStatus(showRecording);
  refreshRecordings();
}
