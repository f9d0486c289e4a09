// What every viewer page shares: the camera (glTF frame: +Y up, right-handed), the scene URL and
// optionally the frames to draw (else the page's own count) from the page's query string, and
// how a page says it has drawn (window.__state).
export function camera() {
  const q = new URLSearchParams(location.search);
  const v = (k) => q.get(k).split(',').map(Number);
  return { scene: q.get('scene'), eye: v('eye'), target: v('target'), up: v('up'), fovy: Number(q.get('fovy')),
           width: Number(q.get('w')), height: Number(q.get('h')), frames: q.get('frames') ? Number(q.get('frames')) : null };
}
export function done(canvas) {
  window.__state = { drawn: true, width: canvas.width, height: canvas.height };
}
export function fail(e) {
  console.error(String(e && e.stack || e));
  window.__state = { error: String(e && e.message || e) };
}
