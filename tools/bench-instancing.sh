#!/usr/bin/env bash
# Memory and speed of instancing (BENCHMARKS.md "Instanced scenes"): K copies of
# ../shared/data/splats/guitar.ply on a grid (varied turns and scales, random offsets of
# sigma 0.01) as .instgs scenes (offsets f32, f16, pq8) against the pq8 scene expanded into a
# plain PLY (the same splats), rendered from the same orbit cameras interleaved in one run
# (bench --compare):
#   K<k>.json      pq8 instanced, exact (culling only), against the expanded PLY
#   K<k>_lod.json  pq8 instanced with template level of detail against itself rendered exactly
#   K<k>_pq.json   pq8 against f32 offsets (both instanced, exact): what quantising costs
# and prints Markdown tables.
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
cams=(--orbit 4 --width "$w" --height "$h" --frames 4)
for k in "${ks[@]}"; do
  python3 tools/grid_scene_graph.py "$k" 3.0 "$out/K${k}_graph.json" guitar
  for dtype in f32 f16 pq8; do
    "$bin" compose --template guitar=../shared/data/splats/guitar.ply --scene-graph "$out/K${k}_graph.json" \
      --random-offsets 0.01 --offset-dtype $dtype --out "$out/K${k}_$dtype.instgs"
  done
  "$bin" convert "$out/K${k}_pq8.instgs" "$out/K$k.ply"
  "$bin" bench --scene "$out/K${k}_pq8.instgs" --exact --compare "$out/K$k.ply" "${cams[@]}" \
    --json "$out/K$k.json" > "$out/K$k.txt" 2>&1 || echo "K=$k exact pair: $(grep error: "$out/K$k.txt")"
  if ! "$bin" bench --scene "$out/K${k}_pq8.instgs" --compare "$out/K${k}_pq8.instgs" --compare-exact "${cams[@]}" \
      --json "$out/K${k}_lod.json" > "$out/K${k}_lod.txt" 2>&1; then
    echo "K=$k LOD pair: $(grep error: "$out/K${k}_lod.txt")"
    "$bin" bench --scene "$out/K${k}_pq8.instgs" "${cams[@]}" --json "$out/K${k}_alone.json" > "$out/K${k}_alone.txt" 2>&1 \
      || echo "K=$k LOD alone: $(grep error: "$out/K${k}_alone.txt")"
  fi
  "$bin" bench --scene "$out/K${k}_pq8.instgs" --exact --compare "$out/K${k}_f32.instgs" --orbit 4 \
    --width "$w" --height "$h" --frames 1 --json "$out/K${k}_pq.json" > "$out/K${k}_pq.txt" 2>&1 \
    || echo "K=$k pq8/f32 pair: $(grep error: "$out/K${k}_pq.txt")"
done
python3 - "$out" "${ks[@]}" <<'PY'
import json, os, sys
out, ks = sys.argv[1], sys.argv[2:]
mb = lambda b: f"{b / 1e6:.1f}"
def load(name):
    p = os.path.join(out, name)
    return json.load(open(p)) if os.path.exists(p) else None
size = lambda p: os.path.getsize(os.path.join(out, p))
print("| K | splats | .instgs f32 / f16 / pq8 (MB) | PLY (MB) | file ratio f32 / f16 / pq8 | GPU scene pq8 / plain (MB) | GPU ratio | FPS pq8 / plain | FPS ratio | PSNR pq8 vs f32 offsets (dB) |")
print("|---|---|---|---|---|---|---|---|---|---|")
for k in ks:
    r, q = load(f"K{k}.json"), load(f"K{k}_pq.json")
    f32, f16, pq8 = (size(f"K{k}_{d}.instgs") for d in ("f32", "f16", "pq8"))
    ply = size(f"K{k}.ply")
    files = f"{mb(f32)} / {mb(f16)} / {mb(pq8)} | {mb(ply)} | {f32/ply:.3f} / {f16/ply:.3f} / {pq8/ply:.3f}"
    pq = f"{q['psnr_a_vs_b']['mean']:.1f}" if q and "psnr_a_vs_b" in q else "-"
    if not r or "compare" not in r:
        a = load(f"K{k}_lod.json") or load(f"K{k}_alone.json")
        n = a["splats"] if a else 0
        gpu = f"{mb(a['scene_gpu_bytes'])} / ({mb(56 * n)}, does not fit)" if a else "does not fit"
        ratio = f"{a['scene_gpu_bytes'] / (56 * n):.3f}" if a else "-"
        print(f"| {k} | {n:,} | {files} | {gpu} | {ratio} | - | - | {pq} |"); continue
    i, p = r, r["compare"]
    print(f"| {k} | {i['splats']:,} | {files} | "
          f"{mb(i['scene_gpu_bytes'])} / {mb(p['scene_gpu_bytes'])} | {r['ratios']['scene_gpu_bytes']:.3f} | "
          f"{i['fps_median']:.2f} / {p['fps_median']:.2f} | {r['ratios']['fps']:.3f} | {pq} |")
print()
print("| K | intersections LOD / exact | frame ms LOD / exact | FPS ratio | PSNR LOD vs exact (dB, mean / worst) | PSNR vs 2x reference LOD / exact (dB) | GPU scene LOD / exact (MB) |")
print("|---|---|---|---|---|---|---|")
for k in ks:
    r = load(f"K{k}_lod.json")
    if not r or "compare" not in r:
        a = load(f"K{k}_alone.json")
        alone = f"{a['intersections']:,.0f} / - | {a['frame_ms_median']:.1f} / does not fit" if a else "does not fit | "
        print(f"| {k} | {alone} | - | - | - | {mb(a['scene_gpu_bytes']) if a else '-'} / - |"); continue
    e, ref = r["compare"], r["psnr_vs_reference"]
    print(f"| {k} | {r['intersections']:,.0f} / {e['intersections']:,.0f} | {r['frame_ms_median']:.1f} / {e['frame_ms_median']:.1f} | "
          f"{r['ratios']['fps']:.2f} | {r['psnr_a_vs_b']['mean']:.2f} / {r['psnr_a_vs_b']['min']:.2f} | "
          f"{ref['a']:.2f} / {ref['b']:.2f} | {mb(r['scene_gpu_bytes'])} / {mb(e['scene_gpu_bytes'])} |")
PY
