#!/usr/bin/env bash
# Checks our scene writers (.compressed.ply, .spz, .splat, SOG) against an independent reader, PlayCanvas splat-transform (from the
# npm registry through npx; not part of CI): for each shared splat and each format we write, our
# file is decoded by splat-transform to a plain PLY and by us, and the two decodings are
# rendered from the same 4 orbit cameras (`bench --compare`, "A against B" in dB). Then the
# other way: splat-transform writes each format from the source PLY and we read it back.
# .spz is stored y-up, z-back; a decoder that does not turn it into the PLY frame gives the
# scene with y and z negated, so for .spz the check also tries that turn (-r 180,0,0) and says
# which convention splat-transform used.
# Usage: bash tools/check-formats.sh [SPLAT_TRANSFORM_VERSION]   (default 2.7.1)
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v npx > /dev/null; then
    echo "npx not found: nothing checked"
    exit 0
fi
st=(npx -y "@playcanvas/splat-transform@${1:-2.7.1}")
cargo build --release --quiet
bin=./target/release/instgs-vk
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"

# "A against B: PSNR X dB mean, Y dB worst view" → Y
agreement() {
    "$bin" bench --scene "$1" --compare "$2" --orbit 4 --width 320 --height 240 --frames 1 --warmup 0 2> /dev/null \
        | sed -n 's/^A against B: PSNR .* dB mean, \(.*\) dB worst view/\1/p'
}

failed=0
check() { # what, dB
    local ok
    ok=$(awk -v d="$2" 'BEGIN { print (d >= 45.0) ? "ok" : "LOW" }')
    printf '%-58s %8s dB  %s\n' "$1" "$2" "$ok"
    [ "$ok" = ok ] || failed=1
}

for src in ../shared/data/splats/playbot_lod2.ply ../shared/data/splats/fruit_drops_minimal.ply; do
    name=$(basename "$src" .ply)
    for ext in compressed.ply spz splat; do
        ours="$work/$name.$ext"
        "$bin" convert "$src" "$ours" 2> /dev/null
        "$bin" convert "$ours" "$work/ours.ply" 2> /dev/null
        "${st[@]}" -w "$ours" "$work/st.ply" > /dev/null 2>&1
        db=$(agreement "$work/ours.ply" "$work/st.ply")
        if [ "$ext" = spz ]; then
            "${st[@]}" -w "$ours" -r 180,0,0 "$work/st-turned.ply" > /dev/null 2>&1
            turned=$(agreement "$work/ours.ply" "$work/st-turned.ply")
            echo "  (.spz: splat-transform's decoding as is $db dB, turned 180° about x $turned dB)"
            db=$(printf '%s\n%s\n' "$db" "$turned" | sort -g | tail -1)
        fi
        check "$name: our .$ext, read by splat-transform vs by us" "$db"
    done
    for ext in compressed.ply spz; do
        theirs="$work/$name.st.$ext"
        "${st[@]}" -w "$src" "$theirs" > /dev/null 2>&1
        "$bin" convert "$theirs" "$work/ours.ply" 2> /dev/null
        "${st[@]}" -w "$theirs" "$work/st.ply" > /dev/null 2>&1
        db=$(agreement "$work/ours.ply" "$work/st.ply")
        if [ "$ext" = spz ]; then
            "${st[@]}" -w "$theirs" -r 180,0,0 "$work/st-turned.ply" > /dev/null 2>&1
            turned=$(agreement "$work/ours.ply" "$work/st-turned.ply")
            db=$(printf '%s\n%s\n' "$db" "$turned" | sort -g | tail -1)
        fi
        check "$name: splat-transform's .$ext, read by us vs by it" "$db"
    done
    # SOG's writer clusters the SH bands (k-means, on the CPU here: -g cpu, no WebGPU on
    # lavapipe), minutes for playbot's 125k Gaussians: fruit_drops (4.7k, degree 3) only.
    [ "$name" = fruit_drops_minimal ] || continue
    mkdir -p "$work/sog"
    "${st[@]}" -w -g cpu "$src" "$work/sog/meta.json" > /dev/null 2>&1  # -g cpu: no WebGPU on lavapipe
    "$bin" convert "$work/sog" "$work/ours.ply" 2> /dev/null
    "${st[@]}" -w "$work/sog/meta.json" "$work/st.ply" > /dev/null 2>&1
    check "$name: splat-transform's SOG, read by us vs by it" "$(agreement "$work/ours.ply" "$work/st.ply")"
    mkdir -p "$work/oursog"
    "$bin" convert "$src" "$work/oursog/meta.json" 2> /dev/null
    "$bin" convert "$work/oursog" "$work/ours.ply" 2> /dev/null
    "${st[@]}" -w "$work/oursog/meta.json" "$work/st.ply" > /dev/null 2>&1
    check "$name: our SOG, read by splat-transform vs by us" "$(agreement "$work/ours.ply" "$work/st.ply")"
done
exit $failed
