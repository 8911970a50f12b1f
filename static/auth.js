// Fringescope dashboard sign-in (issue 16). An ES module with no dependencies.
//
// When the server has a token (FRINGESCOPE_API_TOKEN; always off loopback) every data route
// needs it. The page asks for it once, sends it to POST /api/login, which sets an HttpOnly
// SameSite=Strict session cookie: <img>, the MJPEG/WebSocket streams and the 3-D iframe then
// work without headers. The token itself is kept in sessionStorage (this tab's browser
// session) for the state-changing requests, which need the bearer header (a cookie never
// authorises a change). Nothing is kept after the browser session ends.

export const TOKEN_KEY = "fringescope_token";

export function storedToken() {
  try {
    return sessionStorage.getItem(TOKEN_KEY) || "";
  } catch (_) {
    return "";
  }
}

function keep(token) {
  try {
    if (token) sessionStorage.setItem(TOKEN_KEY, token);
    else sessionStorage.removeItem(TOKEN_KEY);
  } catch (_) { /* storage disabled: the cookie still works for reads */ }
}

async function state() {
  const r = await fetch("/api/auth", { cache: "no-store", credentials: "same-origin" });
  if (!r.ok) return { token_required: false, authenticated: true };
  return r.json();
}

async function login(token) {
  const r = await fetch("/api/login", {
    method: "POST", cache: "no-store", credentials: "same-origin",
    headers: { Authorization: "Bearer " + token },
  });
  return r.ok;
}

/**
 * Resolve once the page may call the API: no token needed, or the session cookie is set and
 * the token is kept. Prompts (window.prompt, or `ask` if given) until a token is accepted;
 * rejects if the user cancels.
 */
export async function ensureSignedIn(ask = (msg) => window.prompt(msg)) {
  const st = await state();
  if (!st.token_required) return "";
  let token = storedToken();
  if (token && st.authenticated) return token;
  let message = "Fringescope access token (FRINGESCOPE_API_TOKEN):";
  for (;;) {
    if (!token) token = ask(message);
    if (token === null || token === undefined) throw new Error("sign-in cancelled");
    token = String(token).trim();
    if (token && (await login(token))) {
      keep(token);
      return token;
    }
    keep("");
    token = "";
    message = "That token was not accepted. Fringescope access token:";
  }
}

export async function signOut() {
  keep("");
  await fetch("/api/logout", { method: "POST", credentials: "same-origin" });
}

// The hook for app.js: it waits for this promise before its first request.
window.fringescopeSignIn = ensureSignedIn().catch((err) => {
  document.body.dataset.auth = "failed";
  throw err;
});
