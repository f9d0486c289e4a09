#!/usr/bin/env bash
# A scene of cafe40's kind with other objects (tools/other_objects_scene.py): cafe40's trained
# background with 20 playbots, 12 bikers and 8 guitars on the objects' spots, composed
# (`instgs-vk compose`, offsets drawn at 0.002), rendered from cafe40's 96 training and 12 test
# cameras (`instgs-vk render`) and given instance masks, instances.json and points3d.ply
# (tools/instance_dataset.rs), in cafe40's layout; then train it as cafe40:
#   instgs-vk train --data OUT/data --out RUN --config configs/lavapipe-walkthrough.toml
# With `rows` the 48 copies stand in rows, all facing one way, and a drone's 96 + 12 cameras see
# them from above (other_objects_scene.py says how); trained the same way.
# usage: bash tools/other-objects.sh CAFE40_RUN OUT [rows]   (CAFE40_RUN: a `train` run on
#        ../shared/data/scenes/cafe40 through its segment stage, for its plain scene and labels;
#        17 minutes here)
set -euo pipefail
cd "$(dirname "$0")/.."
[[ $# -eq 2 || ( $# -eq 3 && $3 == rows ) ]] || { echo "usage: bash tools/other-objects.sh CAFE40_RUN OUT [rows]" >&2; exit 2; }
run=$1 out=$2 layout=${3:-spots} cafe40=../shared/data/scenes/cafe40
venv=out/capture-venv
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import numpy, plyfile" 2>/dev/null; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet numpy==2.4.6 plyfile==1.1.5 >&2
fi
cargo build --release --quiet --bin instgs-vk --example instance_dataset
bin=./target/release/instgs-vk
rm -rf "$out"; mkdir -p "$out/parts" "$out/data/train" "$out/data/test"
"$venv/bin/python" tools/other_objects_scene.py "$run/point_cloud.ply" "$run/labels.json" \
    "$cafe40/instances.json" ../shared/data/splats "$out/parts" "$layout"
"$bin" compose --template playbot="$out/parts/playbot.ply" --template biker="$out/parts/biker.ply" \
    --template guitar="$out/parts/guitar.ply" --scene-graph "$out/parts/scene_graph.json" \
    --background "$out/parts/background.ply" --random-offsets 0.002 --seed 1 --out "$out/truth.instgs"
cameras=$cafe40; [[ $layout == rows ]] && cameras=$out/parts
for split in train test; do
    cp "$cameras/transforms_$split.json" "$out/data/"
    "$bin" render --scene "$out/truth.instgs" --cameras "$out/data/transforms_$split.json" --out "$out/data/$split" > /dev/null
done
./target/release/examples/instance_dataset "$out/truth.instgs" "$out/data"
