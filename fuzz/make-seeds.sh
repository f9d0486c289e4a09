#!/usr/bin/env bash
# Writes the fuzz targets' seed inputs (fuzz/seeds/<target>/): small valid files of every
# format, made with the release binary (`cargo build --release` first) and tools/fuzz_seeds.py.
# Run from the repository root: bash fuzz/make-seeds.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/instgs-vk
seeds=fuzz/seeds
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$seeds"/{ply_parse,points_ply,spz_parse,splat_parse,sog_parse,gltf_parse,colmap_parse,json_inputs,config_toml,checkpoint_parse,mask_png}
# Plain scenes of every format from one three-Gaussian PLY (SH degree 1).
python3 tools/fuzz_seeds.py scene "$tmp/tiny.ply"
cp "$tmp/tiny.ply" "$seeds/ply_parse/tiny.ply"
python3 tools/fuzz_seeds.py ascii-scene "$seeds/ply_parse/tiny_ascii.ply"
"$bin" convert "$tmp/tiny.ply" "$seeds/ply_parse/tiny.compressed.ply" 2>/dev/null
# convert_any reads the PLY seeds and writes every format.
mkdir -p "$seeds/convert_any"
cp "$seeds"/ply_parse/*.ply "$seeds/convert_any/"
"$bin" convert "$tmp/tiny.ply" "$seeds/spz_parse/tiny.spz" 2>/dev/null
"$bin" convert "$tmp/tiny.ply" "$seeds/splat_parse/tiny.splat" 2>/dev/null
"$bin" convert "$tmp/tiny.ply" "$seeds/gltf_parse/tiny.glb" 2>/dev/null
"$bin" convert "$tmp/tiny.ply" "$seeds/gltf_parse/tiny.gltf" 2>/dev/null
"$bin" convert "$seeds/instgs_parse/f32.instgs" "$seeds/gltf_parse/instanced.glb" 2>/dev/null
# Quantised (KHR_mesh_quantization: 16-bit positions dequantised by the node, snorm16 rotations).
"$bin" convert "$tmp/tiny.ply" "$seeds/gltf_parse/tiny-quantized.glb" --quantize 2>/dev/null
"$bin" convert "$seeds/instgs_parse/f32.instgs" "$seeds/gltf_parse/instanced-quantized.glb" --quantize 2>/dev/null
"$bin" convert "$tmp/tiny.ply" "$tmp/sog/meta.json" 2>/dev/null
python3 tools/fuzz_seeds.py sog "$tmp/sog/meta.json" "$seeds/sog_parse/tiny.sog-fuzz"
# The *_files targets read from a folder (fuzz/inputs.rs): its real files go to fuzz/files/, the
# documents naming them to the seeds, those naming hostile paths to the regression inputs.
mkdir -p "$seeds"/{gltf_files,sog_files} fuzz/regressions/{gltf_files,sog_files} fuzz/files
python3 tools/fuzz_seeds.py gltf-files "$seeds/gltf_parse/tiny.gltf" "$seeds/gltf_files" fuzz/regressions/gltf_files fuzz/files
python3 tools/fuzz_seeds.py sog-files "$tmp/sog/meta.json" "$seeds/sog_files" fuzz/regressions/sog_files fuzz/files
python3 tools/fuzz_seeds.py points "$seeds/points_ply"
python3 tools/fuzz_seeds.py colmap "$seeds/colmap_parse"
python3 tools/fuzz_seeds.py json "$seeds/json_inputs" demo/ducks6-mini
python3 tools/fuzz_seeds.py configs "$seeds/config_toml" configs
python3 tools/fuzz_seeds.py mask "$seeds/mask_png"
# A checkpoint: two iterations on the demo, cut down to its first two Gaussians.
INSTGS_DEVICE=llvmpipe "$bin" train --data demo/ducks6-mini --out "$tmp/run" --until plain --iterations 2 \
    --downscale 4 --quiet 2>/dev/null
python3 tools/fuzz_seeds.py checkpoint "$tmp/run/checkpoint.bin" "$seeds/checkpoint_parse/two-v2.ckpt"
# .instgs version 2 (with its checksum) beside the version-1 seeds, which must still read.
python3 tools/fuzz_seeds.py instgs-v2 "$seeds/instgs_parse/f32.instgs" "$seeds/instgs_parse/f32-v2.instgs"
# .instgs version 4: the same scene compressed (`convert --compress`: one SOG bundle, q8 offsets).
# sog-v3.instgs (a SOG bundle per part) was written by an earlier build and is kept: it must still read.
"$bin" convert "$seeds/instgs_parse/f32-v2.instgs" "$seeds/instgs_parse/compressed-v4.instgs" --compress
ls -R "$seeds" | head -60
