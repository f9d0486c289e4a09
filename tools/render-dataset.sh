#!/usr/bin/env bash
# A training dataset at real scale from a trained splat (issue 23): the scene rendered from N
# training and M held-out cameras on three rings around its robust bounds (elevations 15°, 25°
# and 35° in turn, held-out cameras half a step between training ones; world up −Y, as the shared
# splats), written as a NeRF-synthetic folder (transforms_train.json, transforms_test.json,
# train/r_*.png, test/r_*.png; OpenGL camera-to-world matrices), ready for
# `instgs-vk train --data OUT`.
# usage: tools/render-dataset.sh PLY OUT [WIDTHxHEIGHT] [N] [M]
#   (default 1920x1080 — 2.07 MP —, 150 training and 15 held-out cameras)
# The shared biker at 1920x1080: ~6 min on lavapipe (two cores), 1.9 GB of PNGs.
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
[[ $# -ge 2 ]] || { sed -n 8,9p "$0" >&2; exit 2; }
ply=$1 out=$2 size=${3:-1920x1080} n=${4:-150} m=${5:-15}
width=${size%x*} height=${size#*x}
if [[ -n ${INSTGS_BIN:-} ]]; then
    bin=$INSTGS_BIN   # built beforehand (tools/gpu-rows.sh)
else
    cargo build --release --quiet
    bin=./target/release/instgs-vk
fi
mkdir -p "$out"
# Centre and distance from the robust bounds (2nd–98th percentile of the means), as `render
# --orbit` frames a scene: the bounding sphere fits the narrower field of view (50° across).
read -r cx cy cz dist < <("$bin" info "$ply" --json | python3 -c '
import json, math, sys
w, h = '"$width"', '"$height"'
v = json.load(sys.stdin); lo, hi = v["bounds_min_p2"], v["bounds_max_p98"]
c = [(a + b) / 2 for a, b in zip(lo, hi)]
r = max(0.5 * math.dist(lo, hi), 1e-3)
fov = math.radians(50.0)
fov_min = 2 * math.atan(math.tan(fov / 2) * min(w, h) / w)
print(*c, r / math.sin(fov_min / 2) * 1.05)')
python3 tools/orbit_transforms.py "$out" "$n" "$m" "$cx" "$cy" "$cz" "$dist" 25 "$width" "$height" 50
for split in train test; do
    "$bin" render --scene "$ply" --cameras "$out/transforms_$split.json" --out "$out/$split" > /dev/null
done
echo "$out: $n training and $m held-out views of $ply at ${width}x${height}"
