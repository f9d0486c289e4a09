#!/usr/bin/env bash
# Does refining instance transforms help? (BENCHMARKS.md "Refining instance transforms".)
# Ground truth: K copies of ../shared/data/splats/guitar.ply on a grid with small random
# offsets, rendered from an orbit into a NeRF-synthetic dataset. Start: the same scene with
# registration-like pose errors (every copy but the first turned by DEG°, shifted by DIST,
# scaled by 1+FRAC). Joint optimisation with refine_transforms off and on, same iterations;
# held-out PSNR of both, and of the start and the truth.
# usage: tools/bench-refine.sh [ITERATIONS] [DEG DIST FRAC]   (default: 300, 2 0.05 0.02)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo build --release --quiet
bin=./target/release/instgs-vk
its=${1:-300}; deg=${2:-2}; dist=${3:-0.05}; frac=${4:-0.02}
out=out/bench-refine
rm -rf "$out"; mkdir -p "$out/data"
python3 tools/grid_scene_graph.py 4 3.0 "$out/truth.json" guitar
python3 tools/grid_scene_graph.py 4 3.0 "$out/start.json" guitar --jitter "$deg" "$dist" "$frac" 7
for s in truth start; do
  "$bin" compose --template guitar=../shared/data/splats/guitar.ply --scene-graph "$out/$s.json" \
    --random-offsets 0.002 --seed 1 --out "$out/$s.instgs"
done
# The grid's centre: copies at x, z in {0, 3}; the guitar spans y in about [-4.3, 0.1].
python3 tools/orbit_transforms.py "$out/data" 24 6 1.5 -2.1 1.5 9.0 20 160 120 50
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_train.json" --out "$out/data/train" > /dev/null
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_test.json" --out "$out/data/test" > /dev/null
for refine in false true; do
  printf 'iterations = %s\ntest_interval = %s\nrefine_transforms = %s\n' "$its" "$its" "$refine" > "$out/refine_$refine.toml"
  "$bin" train --data "$out/data" --init "$out/start.instgs" --config "$out/refine_$refine.toml" \
    --out "$out/run_$refine" --quiet 2> "$out/run_$refine.log"
done
for s in "$out/truth.instgs" "$out/start.instgs" "$out/run_false/scene.instgs" "$out/run_true/scene.instgs"; do
  printf '%-40s ' "$s"; "$bin" eval --scene "$s" --data "$out/data" --json | python3 -c 'import json,sys; v=json.load(sys.stdin); print(f"test PSNR {v[\"psnr_mean\"]:.2f} dB  SSIM {v[\"ssim_mean\"]:.4f}")'
done
grep -h "iterations," "$out"/run_*.log
