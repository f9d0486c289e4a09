#!/usr/bin/env bash
# The main job on the bundled demo: the whole InstGS pipeline (plain 3DGS training, gradient-driven
# segmentation, registration and templates, joint optimisation, evaluation, benchmark) on
# demo/ducks6-mini, a few minutes on two CPU cores. A re-run resumes (finished stages are kept).
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
cargo build --release
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
./target/release/instgs-vk train --data demo/ducks6-mini --out out/demo-run --config configs/demo.toml
echo "report: out/demo-run/report.md (held-out PSNR/SSIM, memory, FPS, segmentation, registration, pictures)"
echo "player: ./target/release/instgs-vk view out/demo-run/scene.instgs --cameras demo/ducks6-mini --up +z"
echo "        (no display: add --headless --frames 36 --out out/demo-run/turntable)"
