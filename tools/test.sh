#!/usr/bin/env bash
# Installs what a fresh machine lacks, then runs every test (validation layers on, lavapipe
# when no GPU is present).
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/install-deps.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
cargo test --release
