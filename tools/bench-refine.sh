#!/usr/bin/env bash
# Does refining instance transforms help? (BENCHMARKS.md "Refining instance transforms".)
# Ground truth: 4 copies of a trained splat (default ../shared/data/splats/playbot_lod6.ply,
# 1,873 Gaussians, SH degree 2; TEMPLATE=FILE.ply to change) on a grid with small random offsets,
# rendered from an orbit into a NeRF-synthetic dataset (24 training, 6 held-out views, 160×120). Start: the same scene with
# registration-like pose errors (every copy but the first turned by DEG°, shifted by DIST,
# scaled by 1+FRAC). Joint optimisation with refine_transforms off and on, same iterations;
# held-out PSNR of both, and of the start and the truth.
# usage: tools/bench-refine.sh [ITERATIONS] [DEG DIST FRAC]   (default: 1000, 2 0.05 0.02)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo build --release --quiet
bin=./target/release/instgs-vk
its=${1:-1000}; deg=${2:-2}; dist=${3:-0.05}; frac=${4:-0.02}
template=${TEMPLATE:-../shared/data/splats/playbot_lod6.ply}
out=out/bench-refine
rm -rf "$out"; mkdir -p "$out/data"
# Grid spacing and cameras from the template's robust bounds (2nd-98th percentile).
read -r size cx cy cz < <("$bin" info "$template" --json | python3 -c '
import json, sys
v = json.load(sys.stdin); lo, hi = v["bounds_min_p2"], v["bounds_max_p98"]
size = max(h - l for l, h in zip(lo, hi))
print(size, *[(l + h) / 2 for l, h in zip(lo, hi)])')
spacing=$(python3 -c "print(1.5 * $size)")
python3 tools/grid_scene_graph.py 4 "$spacing" "$out/truth.json" obj
python3 tools/grid_scene_graph.py 4 "$spacing" "$out/start.json" obj --jitter "$deg" "$dist" "$frac" 7
for s in truth start; do
  "$bin" compose --template obj="$template" --scene-graph "$out/$s.json" \
    --random-offsets 0.002 --seed 1 --out "$out/$s.instgs"
done
# Copies at x, z in {0, spacing}: the orbit looks at the grid's centre.
read -r gx gy gz dist < <(python3 -c "s=$spacing; print($cx + s/2, $cy, $cz + s/2, 2.4 * (s + $size))")
python3 tools/orbit_transforms.py "$out/data" 24 6 "$gx" "$gy" "$gz" "$dist" 25 160 120 50
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_train.json" --out "$out/data/train" > /dev/null
"$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_test.json" --out "$out/data/test" > /dev/null
for refine in false true; do
  printf 'iterations = %s\ntest_interval = %s\nrefine_transforms = %s\n' "$its" "$its" "$refine" > "$out/refine_$refine.toml"
  "$bin" train --data "$out/data" --init "$out/start.instgs" --config "$out/refine_$refine.toml" \
    --out "$out/run_$refine" --quiet 2> "$out/run_$refine.log"
done
for s in "$out/truth.instgs" "$out/start.instgs" "$out/run_false/scene.instgs" "$out/run_true/scene.instgs"; do
  printf '%-40s ' "$s"
  "$bin" eval --scene "$s" --data "$out/data" --json 2> /dev/null | python3 -c '
import json, sys
v = json.load(sys.stdin)
print("test PSNR %.2f dB  SSIM %.4f" % (v["psnr_mean"], v["ssim_mean"]))'
done
grep -h "iterations," "$out"/run_*.log
