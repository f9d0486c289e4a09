#!/usr/bin/env bash
# The shared trained splats alone (BENCHMARKS.md "Forward rasterizer"): per-pass GPU medians and
# FPS from 4 orbit views at 640x480 and 1280x720. Writes out/bench-splats/<scene>_<size>.json
# and prints a Markdown table.
# usage: tools/bench-splats.sh [scene ...]   (default: guitar biker playbot_lod2)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo build --release --quiet
out=out/bench-splats
mkdir -p "$out"
scenes=("$@")
[ ${#scenes[@]} -gt 0 ] || scenes=(guitar biker playbot_lod2)
for s in "${scenes[@]}"; do
  for size in 640x480 1280x720; do
    ./target/release/instgs-vk bench --scene "../shared/data/splats/$s.ply" --orbit 4 --width "${size%x*}" \
      --height "${size#*x}" --frames 5 --json "$out/${s}_$size.json" > "$out/${s}_$size.txt" 2>&1
  done
done
python3 - "$out" "${scenes[@]}" <<'PY'
import json, sys
out, scenes = sys.argv[1], sys.argv[2:]
passes = ["preprocess", "scan", "depth_sort", "emit", "tile_sort", "ranges", "blend"]
print("| scene | size | splats | intersections | " + " | ".join(passes) + " | frame (ms) | FPS |")
print("|---|---|---|---|" + "---|" * len(passes) + "---|---|")
for s in scenes:
    for size in ("640x480", "1280x720"):
        d = json.load(open(f"{out}/{s}_{size}.json"))
        p = d["passes"]
        cells = " | ".join(f"{p.get(n, float('nan')):.1f}" for n in passes)
        print(f"| {s} | {size} | {d['splats']:,} | {d['intersections']:,.0f} | {cells} | {d['frame_ms_median']:.1f} | {d['fps_median']:.2f} |")
PY
