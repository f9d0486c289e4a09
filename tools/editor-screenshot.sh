#!/usr/bin/env bash
# docs/editor.png: the player editing an instanced scene (three guitars composed from the bundled
# demo splat), under a virtual X server driven by xdotool: instance 1 (the middle one, under the
# window's centre) selected, dragged, turned twice, duplicated and the copy turned back, the overlay showing the
# selection and the unsaved edits. Needs xvfb-run and xdotool (tools/install-deps.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cat > "$work/graph.json" <<'JSON'
[{"template_id": "guitar", "instances": [
  {"instance_id": "1", "transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
  {"instance_id": "2", "transform": [[1,0,0,-2.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
  {"instance_id": "3", "transform": [[1,0,0,2.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}]
JSON
./target/release/instgs-vk compose --template guitar=demo/guitar.compressed.ply \
  --scene-graph "$work/graph.json" --out "$work/row.instgs"
xvfb-run -a -s "-screen 0 1024x768x24" bash -c '
  w8() { for i in $(seq 1200); do grep -q "$1" '"$work"'/err && return 0; sleep 0.1; done; return 1; }
  timeout 600 ./target/release/instgs-vk view '"$work"'/row.instgs --up +z --width 640 --height 480 \
    --out '"$work"' 2> '"$work"'/err &
  w8 "swapchain 640x480"
  win=$(xdotool search --sync --name instgs-vk | head -1); xdotool windowfocus --sync $win
  xdotool mousemove --window $win 320 240 click 5 click 5; sleep 1
  xdotool click 1; w8 "selected instance"
  xdotool mousemove --window $win 320 240 mousedown 1; sleep 0.5
  xdotool mousemove --window $win 360 250; sleep 0.5; xdotool mousemove --window $win 400 262; sleep 0.5
  xdotool mouseup 1; w8 "moved instance"
  xdotool key bracketright; w8 "turned by"
  xdotool key bracketright; sleep 0.5
  xdotool key ctrl+d; w8 "duplicated"
  xdotool key bracketleft; sleep 1; xdotool key p; w8 screenshot
  xdotool key Escape; xdotool key Escape; xdotool key Escape; wait $!'
cp "$work/screenshot_000.png" docs/editor.png
cat "$work/err"
echo "wrote docs/editor.png"
