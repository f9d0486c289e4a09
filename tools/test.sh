#!/usr/bin/env bash
# Installs what a fresh machine lacks, then runs every test (validation layers on, lavapipe
# when no GPU is present). Then the tests of the GPU kernels once more on lavapipe
# (INSTGS_DEVICE=llvmpipe, also on a GPU machine) with subgroups 4 and 16 lanes wide
# (LP_NATIVE_VECTOR_WIDTH 128 and 512 bits; lavapipe's default is 8 lanes, NVIDIA's 32), so a
# kernel that assumes one subgroup size fails here. 32 lanes (1024 bits) is past Mesa's
# LP_MAX_VECTOR_WIDTH (512): lavapipe itself breaks there, so it is not a test of ours.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo test --release
RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --quiet   # the public docs build without a broken link
echo "== interop with splat-transform (tools/interop.sh --quick; needs node, skipped without it)"
bash tools/interop.sh --quick
echo "== web viewers (tools/viewers.sh --quick: three.js, Babylon.js, PlayCanvas in headless Chromium; skipped without node or chromium)"
bash tools/viewers.sh --quick out/viewers-quick
echo "== GPU rows, smoke run (every row's code path, scaled down: tools/gpu-rows.sh)"
bash tools/gpu-rows.sh --smoke > /dev/null
kernel_tests=(--test gpu --test sort --test raster --test grad --test loss --test instgs --test segment --test lod)
for width in 128 512; do
    echo "== kernel tests again, lavapipe vector width $width bits (subgroup size $((width / 32)))"
    INSTGS_DEVICE=llvmpipe LP_NATIVE_VECTOR_WIDTH=$width cargo test --release "${kernel_tests[@]}"
done
