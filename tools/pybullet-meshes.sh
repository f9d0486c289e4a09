#!/usr/bin/env bash
# The meshes and textures the shared scenes were rendered from (instances.json's `mesh`, `parts`,
# `texture`: pybullet's pybullet_data folder, pybullet 3.2.x) for the robustness study's
# symmetry-aware pose errors (`robustness RUN DIR --meshes out/pybullet_data`). Fetches the
# pybullet wheel from PyPI once (~100 MB) and unpacks only pybullet_data; prints its path.
set -euo pipefail
cd "$(dirname "$0")/.."
dest=out/pybullet_data
if [ ! -f "$dest/soccerball.obj" ]; then
    tmp=$(mktemp -d)
    trap 'rm -rf "$tmp"' EXIT
    python3 -m pip download --quiet --no-deps --only-binary=:all: --dest "$tmp" pybullet==3.2.7 >&2
    python3 - "$tmp" out <<'PY'
import glob, sys, zipfile
wheel = glob.glob(sys.argv[1] + "/pybullet-*.whl")[0]
with zipfile.ZipFile(wheel) as z:
    z.extractall(sys.argv[2], [n for n in z.namelist() if n.startswith("pybullet_data/")])
PY
fi
echo "$dest"
