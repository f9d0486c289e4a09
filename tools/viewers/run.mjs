// Drives headless Chromium (Debian's, through puppeteer-core) over the viewer pages beside this
// file: serves them, the viewers' npm packages (NODE_MODULES) and the scenes from 127.0.0.1 (no
// CDN), opens each page with each scene and camera, waits for window.__state, and saves the
// canvas as OUT/<viewer>/<scene>/<camera>.png; console errors go to OUT/<viewer>/<scene>/console.txt.
// Prints a JSON summary (per run: ok or the error and the page's console errors).
//
//   node run.mjs --modules NODE_MODULES --out OUT --scenes name=FILE,... --cameras CAMERAS.json
//        --viewers three,babylon,playcanvas[,cesium] [--chromium /usr/bin/chromium] [--timeout S]
//        [--frames N]   (frames three.js, Babylon.js and PlayCanvas draw before the picture; else
//        each page's own, measured count)
// CAMERAS.json: [{"name", "eye": [x,y,z], "target": [x,y,z], "up": [x,y,z], "fovy": degrees,
// "w", "h"}] in glTF's frame. A scene FILE may be a .glb or a tileset.json (Cesium).
import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const here = path.dirname(fileURLToPath(import.meta.url));
const args = Object.fromEntries(process.argv.slice(2).reduce((a, x, i, all) => (x.startsWith('--') ? [...a, [x.slice(2), all[i + 1]]] : a), []));
const modules = path.resolve(args.modules);
const out = path.resolve(args.out);
const scenes = args.scenes.split(',').map((s) => s.split('=')).map(([n, f]) => ({ name: n, file: path.resolve(f) }));
const cameras = JSON.parse(fs.readFileSync(args.cameras, 'utf8'));
const viewers = args.viewers.split(',');
const timeout = 1000 * Number(args.timeout || 180);
const { default: puppeteer } = await import(path.join(modules, 'puppeteer-core/lib/esm/puppeteer/puppeteer-core.js'));

const types = { '.html': 'text/html', '.js': 'text/javascript', '.mjs': 'text/javascript', '.json': 'application/json',
  '.glb': 'model/gltf-binary', '.wasm': 'application/wasm', '.css': 'text/css' };
// /node_modules/… from NODE_MODULES, /scenes/<i>/… from scene i's folder, the rest from here.
const server = http.createServer((req, res) => {
  const url = decodeURIComponent(new URL(req.url, 'http://x').pathname);
  let file;
  if (url.startsWith('/node_modules/')) file = path.join(modules, url.slice('/node_modules/'.length));
  else if (url.startsWith('/scenes/')) {
    const [, , i, ...rest] = url.split('/');
    file = path.join(path.dirname(scenes[Number(i)].file), ...rest);
  } else file = path.join(here, url);
  fs.readFile(file, (err, data) => {
    if (err) { res.writeHead(404); res.end(); return; }
    res.writeHead(200, { 'Content-Type': types[path.extname(file)] || 'application/octet-stream' });
    res.end(data);
  });
});
await new Promise((r) => server.listen(0, '127.0.0.1', r));
const port = server.address().port;
const browser = await puppeteer.launch({
  executablePath: args.chromium || '/usr/bin/chromium',
  headless: true,
  protocolTimeout: 2 * timeout,
  args: ['--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader', '--ignore-gpu-blocklist',
    '--disable-background-networking', '--disable-component-update', '--disable-sync', '--disable-quic',
    '--no-first-run', '--disable-dev-shm-usage'],  // /tmp, not /dev/shm (64 MB in a default container)
});
const summary = [];
for (const viewer of viewers) {
  for (const [i, s] of scenes.entries()) {
    const dir = path.join(out, viewer, s.name);
    fs.mkdirSync(dir, { recursive: true });
    const log = [];
    for (const c of cameras) {
      const page = await browser.newPage();
      page.on('console', (m) => { if (m.type() === 'error') log.push(`${c.name}: ${m.text()}`); });
      page.on('pageerror', (e) => log.push(`${c.name}: ${e.message}`));
      await page.setViewport({ width: c.w, height: c.h });
      const q = new URLSearchParams({ scene: `/scenes/${i}/${path.basename(s.file)}`, eye: c.eye.join(','),
        target: c.target.join(','), up: c.up.join(','), fovy: String(c.fovy), w: String(c.w), h: String(c.h) });
      if (args.frames) q.set('frames', args.frames);
      const started = Date.now();
      let state;
      try {
        await page.goto(`http://127.0.0.1:${port}/${viewer}.html?${q}`);
        await page.waitForFunction(() => window.__state, { timeout, polling: 200 });
        state = await page.evaluate(() => window.__state);
      } catch (e) {
        state = { error: `no picture within ${timeout / 1000} s (${e.message.split('\n')[0]})` };
      }
      // The page's frames are submitted, not necessarily drawn: SwiftShader's work lands in
      // the screenshot (minutes for Cesium's 727 k guitar splats). A failure there is this
      // run's, not the whole script's.
      if (state.drawn) {
        try {
          const canvas = await page.$('canvas');
          await canvas.screenshot({ path: path.join(dir, `${c.name}.png`) });
        } catch (e) {
          state = { error: `drawn, but no screenshot (${e.message.split('\n')[0]})` };
        }
      }
      summary.push({ viewer, scene: s.name, camera: c.name, ok: !!state.drawn, error: state.error || null,
        seconds: (Date.now() - started) / 1000 });
      await page.close();
    }
    fs.writeFileSync(path.join(dir, 'console.txt'), log.join('\n'));
    summary.filter((r) => r.viewer === viewer && r.scene === s.name && !r.ok).forEach((r) => { r.console = log; });
  }
}
await browser.close();
server.close();
console.log(JSON.stringify(summary, null, 1));
