// The texture panel: the latest texture image (A + B), polled once a second.

import { $, api } from "./api.js";
import { ui } from "./state.js";

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

export function setupTexture() {
  setInterval(pollTexture, 1000);
}
