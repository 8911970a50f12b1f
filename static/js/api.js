// The api-client module: every REST call of the page goes through api().
//
// api() adds "Authorization: Bearer <token>" when a token is stored (sessionStorage, set by
// auth.js, or localStorage) under "fringescope_token"; WebSockets and the 3-D iframe cannot send headers, so they
// carry ?token= via withToken() (the server then sets its cookie).

const TOKEN_KEY = "fringescope_token";

export const $ = (id) => document.getElementById(id);

export function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

export const fmt = (x, digits) => (typeof x === "number" && isFinite(x) ? x.toFixed(digits) : "–");

function storedToken() {
  try {
    // static/auth.js keeps the token for the browser session
    return sessionStorage.getItem(TOKEN_KEY) || localStorage.getItem(TOKEN_KEY) || "";
  } catch (_) {
    return "";
  }
}

export function withToken(url) {
  const token = storedToken();
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}

export class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

/** fetch() with the bearer token, JSON in/out; throws ApiError with the server's detail. */
export async function api(path, { method = "GET", json, timeoutMs = 20000, blob = false } = {}) {
  const headers = {};
  const token = storedToken();
  if (token) headers["Authorization"] = "Bearer " + token;
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  }
  const ctrl = new AbortController();
  const timer = setTimeout(() => ctrl.abort(), timeoutMs);
  let resp;
  try {
    resp = await fetch(path, { method, headers, body, signal: ctrl.signal, cache: "no-store" });
  } catch (err) {
    throw new ApiError(0, err.name === "AbortError" ? "timed out" : "server unreachable");
  } finally {
    clearTimeout(timer);
  }
  if (!resp.ok) {
    let detail = resp.statusText || "error " + resp.status;
    try {
      const data = await resp.json();
      detail = typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail);
    } catch (_) { /* not JSON */ }
    throw new ApiError(resp.status, detail);
  }
  if (blob) return resp.blob();
  const type = resp.headers.get("content-type") || "";
  return type.includes("json") ? resp.json() : resp.text();
}

let messageTimer = null;
/** A line in the footer: info for 6 s, errors for 15 s. */
export function say(text, kind = "info") {
  const msg = $("message");
  msg.textContent = text;
  msg.className = "message " + kind;
  clearTimeout(messageTimer);
  messageTimer = setTimeout(() => { msg.textContent = ""; }, kind === "error" ? 15000 : 6000);
}

/** Run an action from a button: disable it meanwhile, report errors on the page. */
export async function act(button, label, fn) {
  if (button) button.disabled = true;
  try {
    return await fn();
  } catch (err) {
    // the server's reason often names the same subject already ("schedule: …"): say it once
    const text = err.message.startsWith(`${label}:`) ? err.message : `${label}: ${err.message}`;
    say(text, "error");
    return undefined;
  } finally {
    if (button) button.disabled = false;
  }
}
