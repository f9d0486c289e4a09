#!/usr/bin/env bash
# Registration robustness on other object types (BENCHMARKS.md "Registration robustness"): K
# copies of a trained splat composed on a grid at known transforms (turned about the up axis,
# scaled 0.8-1.2, small random offsets), rendered from an orbit into a NeRF-synthetic dataset
# with instance masks and ground truth (tools/instance_dataset.rs), then trained, segmented and
# registered like any capture (the main job up to its instance stage, default configuration),
# and the robustness study run on that run.
# usage: [ONLY=CASE,CASE] tools/bench-objects.sh NAME TEMPLATE.ply [K] [ITERATIONS] [WIDTH HEIGHT] [SEEDS]
#        (defaults: 4 copies, 1500 plain iterations, 200x150, 2 seeds)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
name=$1; template=$2; k=${3:-4}; its=${4:-1500}; w=${5:-200}; h=${6:-150}; seeds=${7:-2}
cargo build --release --quiet --examples
bin=./target/release/instgs-vk
out=out/bench-objects/$name
rm -rf "$out"; mkdir -p "$out/data"
size=$("$bin" info "$template" --json | python3 -c '
import json, sys
v = json.load(sys.stdin); lo, hi = v["bounds_min_p2"], v["bounds_max_p98"]
print(max(h - l for l, h in zip(lo, hi)))')
spacing=$(python3 -c "print(1.6 * $size)")
python3 tools/grid_scene_graph.py "$k" "$spacing" "$out/truth.json" "$name"
"$bin" compose --template "$name=$template" --scene-graph "$out/truth.json" \
  --random-offsets 0.002 --seed 1 --out "$out/truth.instgs"
# The orbit looks at the composed scene's centre (copies turn about the origin, which need not
# be the template's centre) from 1.3 × its extent.
"$bin" convert "$out/truth.instgs" "$out/truth.ply" 2> /dev/null
read -r gx gy gz dist < <("$bin" info "$out/truth.ply" --json | python3 -c '
import json, sys
v = json.load(sys.stdin); lo, hi = v["bounds_min_p2"], v["bounds_max_p98"]
print(*[(l + h) / 2 for l, h in zip(lo, hi)], 1.3 * max(h - l for l, h in zip(lo, hi)))')
python3 tools/orbit_transforms.py "$out/data" 24 6 "$gx" "$gy" "$gz" "$dist" 30 "$w" "$h" 50
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_train.json" --out "$out/data/train" > /dev/null
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_test.json" --out "$out/data/test" > /dev/null
./target/release/examples/instance_dataset "$out/truth.instgs" "$out/data"
"$bin" train --data "$out/data" --out "$out/run" --iterations "$its" --until instance --quiet
./target/release/examples/robustness "$out/run" "$out/data" --seeds "$seeds" --up y ${ONLY:+--only "$ONLY"} | tee "$out/robustness.md"
