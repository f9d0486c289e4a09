#!/usr/bin/env bash
# Memory and speed of instancing (BENCHMARKS.md "Instanced scenes"): K copies of
# ../shared/data/splats/guitar.ply on a grid as an .instgs scene against the same scene expanded
# into a plain PLY, rendered from the same orbit cameras interleaved in one run (bench --compare).
# Writes out/bench-instancing/K<k>.json (K<k>_instgs.json alone where the pair does not fit) and
# prints a Markdown table.
# usage: tools/bench-instancing.sh [K ...]   (default: 2 8 32 128)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo build --release --quiet
bin=./target/release/instgs-vk
out=out/bench-instancing
mkdir -p "$out"
ks=("$@")
[ ${#ks[@]} -gt 0 ] || ks=(2 8 32 128)
for k in "${ks[@]}"; do
  python3 tools/grid_scene_graph.py "$k" 3.0 "$out/K$k.json" guitar
  for dtype in f32 f16; do
    "$bin" compose --template guitar=../shared/data/splats/guitar.ply --scene-graph "$out/K$k.json" \
      --offset-dtype $dtype --out "$out/K${k}_$dtype.instgs"
  done
  "$bin" convert "$out/K${k}_f32.instgs" "$out/K$k.ply"
  if ! "$bin" bench --scene "$out/K${k}_f32.instgs" --compare "$out/K$k.ply" --orbit 4 --width 320 \
      --height 240 --frames 3 --json "$out/K$k.json" > "$out/K$k.txt" 2>&1; then
    echo "K=$k pair: $(grep error: "$out/K$k.txt")"
    "$bin" bench --scene "$out/K${k}_f32.instgs" --orbit 4 --width 320 --height 240 --frames 3 \
      --json "$out/K${k}_instgs.json" > "$out/K${k}_instgs.txt" 2>&1 || echo "K=$k instgs: $(grep error: "$out/K${k}_instgs.txt")"
  fi
done
python3 - "$out" "${ks[@]}" <<'PY'
import json, os, sys
out, ks = sys.argv[1], sys.argv[2:]
print("| K | splats | .instgs f32 / f16 (MB) | plain PLY (MB) | GPU scene instgs / plain (MB) | per-frame GPU (MB) | FPS instgs / plain |")
print("|---|---|---|---|---|---|---|")
mb = lambda b: f"{b / 1e6:.1f}"
for k in ks:
    size = lambda p: os.path.getsize(os.path.join(out, p))
    def load(name):
        p = os.path.join(out, name)
        return json.load(open(p)) if os.path.exists(p) else None
    pair = load(f"K{k}.json")
    i, p = (pair, pair.get("compare")) if pair else (load(f"K{k}_instgs.json"), None)
    g = lambda r, key, f: f(r[key]) if r else "does not fit"
    print(f"| {k} | {i['splats'] if i else '-'} | {mb(size(f'K{k}_f32.instgs'))} / {mb(size(f'K{k}_f16.instgs'))} | "
          f"{mb(size(f'K{k}.ply'))} | {g(i, 'scene_gpu_bytes', mb)} / {g(p, 'scene_gpu_bytes', mb)} | "
          f"{g(i, 'frame_gpu_bytes', mb)} | {g(i, 'fps_median', lambda v: f'{v:.2f}')} / {g(p, 'fps_median', lambda v: f'{v:.2f}')} |")
PY
