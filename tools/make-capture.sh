#!/usr/bin/env bash
# tools/make_capture.py with its Python packages pinned, in a virtual environment of its own
# (out/capture-venv, made once from PyPI): a shared scene as a user's capture (photo effects,
# COLMAP poses and points, segmenter masks). Arguments go to make_capture.py, e.g.
#   bash tools/make-capture.sh ../shared/data/scenes/ducks6 out/captures/ducks6 --clean out/captures/ducks6-clean
set -euo pipefail
cd "$(dirname "$0")/.."
venv=out/capture-venv
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import pycolmap, numpy, PIL" 2>/dev/null; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet pycolmap==4.2.1 numpy==2.4.6 pillow==13.0.0 >&2
fi
exec "$venv/bin/python" tools/make_capture.py "$@"
