#!/usr/bin/env bash
# Checks our scene files against the reference implementation, PlayCanvas splat-transform
# (pinned below; installed from the npm registry into a scratch folder, never a dependency of
# the crate). For each scene and each format both tools share, both ways:
#   ours → it → ours: we write the format from the source PLY, splat-transform reads it and
#                     writes a PLY, we read that PLY;
#   it → ours:        splat-transform writes the format from the source PLY, we read it.
# Each result is rendered beside the source PLY from the same 4 orbit cameras (`bench
# --compare`, 320×240, worst view's PSNR). .glb is written by splat-transform only (it does not
# read glTF): its first direction is our .glb read back by us. .spz: splat-transform applies no
# axis change, the Niantic specification (which we follow) stores y up, z back; the table has
# both our readings (`--spz-frame spec`, `--spz-frame as-stored`). SOG's k-means runs on the CPU
# (`-g cpu`: no WebGPU adapter on lavapipe machines).
# Then our .glb files (a plain one, an instanced one, its --quantize twin and the tiles of its
# tileset) go through the Khronos glTF validator
# (npm gltf-validator, pinned, same scratch folder): it does not know KHR_gaussian_splatting, so
# each of the extension's attribute names is an error (MESH_PRIMITIVE_INVALID_ATTRIBUTE, as for
# splat-transform's own .glb); any other error or warning fails. Infos pass: the extensions it
# does not know, a tile's SPZ buffer view that only the SPZ extension names (UNUSED_OBJECT). Every
# UNUSED_OBJECT is listed; an unused accessor fails.
# Usage: bash tools/interop.sh [--quick] [SPLAT...]   (default: the shared fruit_drops_minimal,
# playbot_lod6 and guitar; --quick: fruit_drops only, what CI runs). Prints a Markdown table;
# exits 1 when a row the specification and splat-transform agree on is below 30 dB (every format
# here loses less; a frame or convention error gives under 20).
set -euo pipefail
cd "$(dirname "$0")/.."
version=3.7.0
validator=2.0.0-dev.3.10
if ! command -v node > /dev/null || ! command -v npm > /dev/null; then
    echo "interop: node/npm not found on this machine: splat-transform not run, nothing checked"
    exit 0
fi
quick=0
if [ "${1:-}" = --quick ]; then quick=1; shift; fi
splats=("$@")
if [ ${#splats[@]} -eq 0 ]; then
    splats=(../shared/data/splats/fruit_drops_minimal.ply)
    [ $quick = 1 ] || splats+=(../shared/data/splats/playbot_lod6.ply ../shared/data/splats/guitar.ply)
fi
scratch="${INSTGS_INTEROP_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/instgs-vk/splat-transform-$version}"
if [ ! -x "$scratch/node_modules/.bin/splat-transform" ]; then
    mkdir -p "$scratch"
    npm install --prefix "$scratch" --no-save --no-audit --no-fund "@playcanvas/splat-transform@$version" > "$scratch/npm.log" 2>&1 \
        || { echo "interop: npm install of splat-transform $version failed (see $scratch/npm.log)"; exit 1; }
fi
if [ ! -d "$scratch/node_modules/gltf-validator" ]; then
    npm install --prefix "$scratch" --no-save --no-audit --no-fund "@playcanvas/splat-transform@$version" "gltf-validator@$validator" \
        > "$scratch/npm.log" 2>&1 || { echo "interop: npm install of gltf-validator $validator failed (see $scratch/npm.log)"; exit 1; }
fi
st() { "$scratch/node_modules/.bin/splat-transform" -q -w -g cpu "$@" > /dev/null 2>&1; }
cargo build --release --quiet
bin=./target/release/instgs-vk
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"

# Worst view's PSNR of scene $2 against $1 ("-" when it cannot be read).
agreement() {
    "$bin" "${@:3}" bench --scene "$1" --compare "$2" --orbit 4 --width 320 --height 240 --frames 1 --warmup 0 2> /dev/null \
        | sed -n 's/^A against B: PSNR .* dB mean, \(.*\) dB worst view/\1/p' | grep . || echo "-"
}
failed=0
low() { awk -v d="$1" 'BEGIN { exit !(d == "-" || d < 30.0) }'; }
row() { # scene format ours-it-ours it-ours checked [note after ours-it-ours]
    printf '| %s | %s | %s%s | %s |\n' "$1" "$2" "$3" "${6:+ $6}" "$4"
    if [ "$5" = checked ] && { low "$3" || low "$4"; }; then failed=1; fi
}

echo "splat-transform $version; PSNR (dB, worst of 4 orbit views, 320×240) against the source PLY"
echo
echo "| scene | format | ours → splat-transform → ours | splat-transform → ours |"
echo "|---|---|---|---|"
for src in "${splats[@]}"; do
    name=$(basename "$src" .ply)
    for fmt in ply compressed.ply sog meta.json spz glb; do
        case $fmt in meta.json) ours="$work/ours-sog/meta.json"; theirs="$work/st-sog/meta.json"; mkdir -p "$work/ours-sog" "$work/st-sog" ;;
                     *) ours="$work/ours.$fmt"; theirs="$work/st.$fmt" ;; esac
        rm -f "$work/back.ply"
        "$bin" convert "$src" "$ours" 2> /dev/null
        st "$src" "$theirs"
        if [ $fmt = glb ]; then
            a=$(agreement "$src" "$ours")
        else
            st "$ours" "$work/back.ply" && a=$(agreement "$src" "$work/back.ply") || a="-"
        fi
        b=$(agreement "$src" "$theirs")
        label=$fmt; [ $fmt = meta.json ] && label="SOG folder (meta.json)"; [ $fmt = sog ] && label="SOG bundle (.sog)"
        if [ $fmt = spz ]; then
            row "$name" ".spz, our reading by the spec (default)" "$a" "$b" unchecked
            "$bin" --spz-frame as-stored convert "$src" "$ours" 2> /dev/null
            st "$ours" "$work/back.ply" && a=$(agreement "$src" "$work/back.ply") || a="-"
            b=$(agreement "$src" "$theirs" --spz-frame as-stored)
            row "$name" ".spz, --spz-frame as-stored" "$a" "$b" checked
        else
            note=""; [ $fmt = glb ] && note="(ours → ours: it reads no glTF)"
            row "$name" "$label" "$a" "$b" checked "$note"
        fi
    done
done

echo
echo "Khronos glTF validator $validator on our .glb (errors and warnings other than the extension's attribute names; unused objects):"
"$bin" convert "${splats[0]}" "$work/plain.glb" 2> /dev/null
"$bin" convert fuzz/seeds/instgs_parse/f32.instgs "$work/instanced.glb" 2> /dev/null
"$bin" convert --quantize fuzz/seeds/instgs_parse/f32.instgs "$work/quantized.glb" 2> /dev/null
"$bin" convert fuzz/seeds/instgs_parse/f32.instgs "$work/tiles/tileset.json" 2> /dev/null
for f in "$work/plain.glb" "$work/instanced.glb" "$work/quantized.glb" "$work"/tiles/tile-*.glb; do
    NODE_PATH="$scratch/node_modules" node -e '
const v = require("gltf-validator"), fs = require("fs"), f = process.argv[1];
v.validateBytes(new Uint8Array(fs.readFileSync(f)), { maxIssues: 0 }).then((r) => {
  const other = r.issues.messages.filter((m) => m.severity <= 1 && m.code !== "MESH_PRIMITIVE_INVALID_ATTRIBUTE");
  const names = r.issues.messages.filter((m) => m.code === "MESH_PRIMITIVE_INVALID_ATTRIBUTE").length;
  const unused = r.issues.messages.filter((m) => m.code === "UNUSED_OBJECT").map((m) => m.pointer);
  const accessors = unused.filter((p) => p.startsWith("/accessors/"));
  console.log(`  ${f.split("/").pop()}: ${names} attribute-name errors, ${other.length} others` + other.map((m) => ` [${m.code} ${m.pointer}]`).join("")
    + `; unused: ${unused.join(" ") || "nothing"}`);
  process.exit(other.length || accessors.length ? 1 : 0);
});' "$f" || failed=1
done
exit $failed
