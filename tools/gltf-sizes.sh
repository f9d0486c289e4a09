#!/usr/bin/env bash
# The instanced glTF against the other ways to store an instanced scene (BENCHMARKS.md
# "Instanced scenes as glTF"): for each .instgs scene, the file bytes of the .instgs itself, our
# instanced .glb (templates shared, a node per instance), the expanded .glb (one plain splat
# primitive, what any exporter without instancing writes) and the expanded Inria PLY; and our
# render of the instanced .glb against our render of the .instgs (both instanced and exact, from
# the same 4 orbit cameras, 320×240, worst view); and the instanced .glb with --quantize (16-bit
# positions and rotations), its bytes against the float one's and its render against the
# .instgs. Scenes: the given .instgs files, then copies
# of shared splats composed on a grid (guitar, SH 0: K = 8 and 32; fruit_drops, SH 3: K = 32;
# random offsets σ = 0.01, f32).
# Usage: bash tools/gltf-sizes.sh [SCENE.instgs ...]   (prints a Markdown table)
set -euo pipefail
cd "$(dirname "$0")/.."
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo build --release --quiet
bin=./target/release/instgs-vk
work=out/gltf-sizes
mkdir -p "$work"
scenes=("$@")
for case in guitar:8 guitar:32 fruit_drops_minimal:32; do
    t=${case%:*}; k=${case#*:}
    python3 tools/grid_scene_graph.py "$k" 3.0 "$work/${t}-K${k}_graph.json" "$t"
    "$bin" compose --template "$t=../shared/data/splats/$t.ply" --scene-graph "$work/${t}-K${k}_graph.json" \
        --random-offsets 0.01 --out "$work/$t-K$k.instgs" 2> /dev/null
    scenes+=("$work/$t-K$k.instgs")
done
size() { stat -c %s "$1"; }
mb() { awk -v b="$1" 'BEGIN { printf "%.2f", b / 1e6 }'; }
echo "| scene | splats (rows) | .instgs MB | instanced .glb MB | expanded .glb MB | PLY MB | instanced .glb / expanded | our render, .glb vs .instgs | --quantize .glb MB | quantised / float instanced .glb | our render, quantised .glb vs .instgs |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
for s in "${scenes[@]}"; do
    name=$(basename "$(dirname "$s")")/$(basename "$s" .instgs)
    "$bin" convert "$s" "$work/x.glb" 2> /dev/null
    "$bin" convert --expand "$s" "$work/x-expanded.glb" 2> /dev/null
    "$bin" convert --quantize "$s" "$work/x-quantized.glb" 2> /dev/null
    "$bin" convert "$s" "$work/x.ply" 2> /dev/null
    counts=$("$bin" info --json "$s" | python3 -c 'import json,sys; v=json.load(sys.stdin); print("%d (%d)" % (v["splats"], v["parameter_rows"]))')
    db=$("$bin" bench --scene "$s" --compare "$work/x.glb" --exact --compare-exact --orbit 4 --width 320 --height 240 \
        --frames 1 --warmup 0 2> /dev/null | sed -n 's/^A against B: PSNR .* dB mean, \(.*\) dB worst view/\1/p')
    dbq=$("$bin" bench --scene "$s" --compare "$work/x-quantized.glb" --exact --compare-exact --orbit 4 --width 320 --height 240 \
        --frames 1 --warmup 0 2> /dev/null | sed -n 's/^A against B: PSNR .* dB mean, \(.*\) dB worst view/\1/p')
    a=$(size "$s"); b=$(size "$work/x.glb"); c=$(size "$work/x-expanded.glb"); d=$(size "$work/x.ply"); q=$(size "$work/x-quantized.glb")
    printf '| %s | %s | %s | %s | %s | %s | %s | %s dB | %s | %s | %s dB |\n' "$name" "$counts" "$(mb "$a")" "$(mb "$b")" "$(mb "$c")" "$(mb "$d")" \
        "$(awk -v b="$b" -v c="$c" 'BEGIN { printf "%.3f", b / c }')" "$db" \
        "$(mb "$q")" "$(awk -v q="$q" -v b="$b" 'BEGIN { printf "%.3f", q / b }')" "$dbq"
done
