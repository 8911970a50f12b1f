// What the panels share: the latest status, the sensor size, the colour range, stream state.

export const ui = {
  status: null,
  limits: null, // GET /api/limits: LEDs, exposure range, bit depths, default depth range
  sensor: null, // [W, H] of the depth maps, sensor pixels
  range: null, // [min, max] mm of the colour map: the default from /api/limits, then the user's
  sigmaRange: [0, 0.1], // [min, max] mm of the σ colour map (the server's default for field=sigma)
  framesShown: 0,
  lastFrameAt: 0,
  streamKind: "none", // "stream" | "poll" | "none"
  ws: null,
  wsRetry: null,
  decoding: false,
  pendingBlob: null,
  crop: null, // {sw, sh}: the depth part of the received image, image pixels
  roi: null, // [x0, y0, x1, y1] sensor pixels
  drag: null,
  exposureTouchedAt: 0,
  textureUrl: null,
  recording: null,
};
window.fringescope = ui; // for tests and the curious

// static/auth.js (a module that runs before js/main.js) leaves its sign-in promise on window
export function signedIn() {
  return window.fringescopeSignIn || Promise.resolve();
}
