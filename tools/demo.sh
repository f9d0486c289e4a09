#!/usr/bin/env bash
# The main job on the bundled demo: render the guitar from an 8-camera orbit.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
cargo build --release
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
./target/release/instgs-vk render --scene demo/guitar.compressed.ply --orbit 8 --width 640 --height 480 --out out/demo
echo "pictures: out/demo/view_000.png … view_007.png"
echo "player: ./target/release/instgs-vk view demo/guitar.compressed.ply   (no display: add --headless --frames 36 --out out/demo/turntable)"
