#!/usr/bin/env bash
# Memory and speed of instancing (BENCHMARKS.md "Instanced scenes"): K copies of
# ../shared/data/splats/guitar.ply on a grid (varied turns and scales, random offsets) as an
# .instgs scene against the same scene expanded into a plain PLY, rendered from the same orbit
# cameras interleaved in one run (bench --compare):
#   K<k>.json      instanced (exact: culling only) against the expanded PLY
#   K<k>_lod.json  instanced with template level of detail against itself rendered exactly
# and prints two Markdown tables.
# usage: tools/bench-instancing.sh [--size WxH] [K ...]   (default: 640x480, K = 8 32 128)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
size=640x480
if [ "${1:-}" = --size ]; then size=$2; shift 2; fi
w=${size%x*}; h=${size#*x}
cargo build --release --quiet
bin=./target/release/instgs-vk
out=out/bench-instancing
mkdir -p "$out"
ks=("$@")
[ ${#ks[@]} -gt 0 ] || ks=(8 32 128)
cams=(--orbit 4 --width "$w" --height "$h" --frames 3)
for k in "${ks[@]}"; do
  python3 tools/grid_scene_graph.py "$k" 3.0 "$out/K${k}_graph.json" guitar
  for dtype in f32 f16; do
    "$bin" compose --template guitar=../shared/data/splats/guitar.ply --scene-graph "$out/K${k}_graph.json" \
      --random-offsets 0.01 --offset-dtype $dtype --out "$out/K${k}_$dtype.instgs"
  done
  "$bin" convert "$out/K${k}_f32.instgs" "$out/K$k.ply"
  "$bin" bench --scene "$out/K${k}_f32.instgs" --exact --compare "$out/K$k.ply" "${cams[@]}" \
    --json "$out/K$k.json" > "$out/K$k.txt" 2>&1 || echo "K=$k exact pair: $(grep error: "$out/K$k.txt")"
  "$bin" bench --scene "$out/K${k}_f32.instgs" --compare "$out/K${k}_f32.instgs" --compare-exact "${cams[@]}" \
    --json "$out/K${k}_lod.json" > "$out/K${k}_lod.txt" 2>&1 || echo "K=$k LOD pair: $(grep error: "$out/K${k}_lod.txt")"
done
python3 - "$out" "${ks[@]}" <<'PY'
import json, os, sys
out, ks = sys.argv[1], sys.argv[2:]
mb = lambda b: f"{b / 1e6:.1f}"
def load(name):
    p = os.path.join(out, name)
    return json.load(open(p)) if os.path.exists(p) else None
size = lambda p: os.path.getsize(os.path.join(out, p))
print("| K | splats | .instgs f32 / f16 / PLY (MB) | file ratio f32 / f16 | GPU scene instgs / plain (MB) | GPU ratio | FPS instgs / plain | FPS ratio |")
print("|---|---|---|---|---|---|---|---|")
for k in ks:
    r = load(f"K{k}.json")
    if not r or "compare" not in r:
        print(f"| {k} | does not fit | | | | | | |"); continue
    i, p = r, r["compare"]
    f32, f16, ply = size(f"K{k}_f32.instgs"), size(f"K{k}_f16.instgs"), size(f"K{k}.ply")
    print(f"| {k} | {i['splats']:,} | {mb(f32)} / {mb(f16)} / {mb(ply)} | {f32/ply:.3f} / {f16/ply:.3f} | "
          f"{mb(i['scene_gpu_bytes'])} / {mb(p['scene_gpu_bytes'])} | {r['ratios']['scene_gpu_bytes']:.3f} | "
          f"{i['fps_median']:.2f} / {p['fps_median']:.2f} | {r['ratios']['fps']:.3f} |")
print()
print("| K | intersections LOD / exact | frame ms LOD / exact | FPS ratio | PSNR LOD vs exact (dB, mean / worst) | GPU scene LOD / exact (MB) |")
print("|---|---|---|---|---|---|")
for k in ks:
    r = load(f"K{k}_lod.json")
    if not r or "compare" not in r:
        print(f"| {k} | does not fit | | | | |"); continue
    e = r["compare"]
    print(f"| {k} | {r['intersections']:,.0f} / {e['intersections']:,.0f} | {r['frame_ms_median']:.1f} / {e['frame_ms_median']:.1f} | "
          f"{r['ratios']['fps']:.2f} | {r['psnr_a_vs_b']['mean']:.2f} / {r['psnr_a_vs_b']['min']:.2f} | "
          f"{mb(r['scene_gpu_bytes'])} / {mb(e['scene_gpu_bytes'])} |")
PY
