// PSNR (dB, RGB, 8-bit) between pairs of PNG pictures of one size: node compare.mjs MODULES
// PAIRS.json, where PAIRS.json is [{"key": …, "a": PATH, "b": PATH}]; prints [{"key", "psnr"}]
// (null where a picture is missing or the sizes differ; 100 for identical pictures).
import fs from 'node:fs';
import path from 'node:path';
const [modules, pairsFile] = process.argv.slice(2);
const { PNG } = (await import(path.join(modules, 'pngjs/lib/png.js'))).default;
const read = (p) => (fs.existsSync(p) ? PNG.sync.read(fs.readFileSync(p)) : null);
const out = JSON.parse(fs.readFileSync(pairsFile, 'utf8')).map(({ key, a, b }) => {
  const [x, y] = [read(a), read(b)];
  if (!x || !y || x.width !== y.width || x.height !== y.height) return { key, psnr: null };
  let sq = 0;
  for (let i = 0; i < x.data.length; i += 4) {
    for (let c = 0; c < 3; c++) {
      const d = (x.data[i + c] - y.data[i + c]) / 255;
      sq += d * d;
    }
  }
  const mse = sq / (3 * x.width * x.height);
  return { key, psnr: mse === 0 ? 100 : Math.min(100, -10 * Math.log10(mse)) };
});
console.log(JSON.stringify(out));
