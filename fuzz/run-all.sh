#!/usr/bin/env bash
# Runs every fuzz target for RUNS inputs (default 1 000 000) on one core, one after another,
# starting from its seeds and regression inputs (fuzz/seeds/<target>/, fuzz/regressions/<target>/,
# copied into the working corpus fuzz/corpus/<target>/), and prints one line per target: inputs, seconds, result. A crash
# stops that target and leaves its input in fuzz/artifacts/<target>/; once fixed, keep the input
# in fuzz/regressions/<target>/ (tests/fuzz_inputs.rs checks it is refused).
# Needs a nightly toolchain and cargo-fuzz (cargo install cargo-fuzz). Usage, from the
# repository root: bash fuzz/run-all.sh [RUNS] [TARGET...]
set -uo pipefail
cd "$(dirname "$0")/.."
runs=${1:-1000000}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(instgs_parse ply_parse points_ply spz_parse splat_parse sog_parse sog_bundle gltf_parse gltf_files sog_files colmap_parse json_inputs
             config_toml checkpoint_parse mask_png convert_any)
fi
cargo +nightly fuzz build -O
for t in "${targets[@]}"; do
    mkdir -p "fuzz/corpus/$t" "fuzz/artifacts/$t"
    cp -n fuzz/seeds/"$t"/* "fuzz/corpus/$t/" 2>/dev/null
    cp -n fuzz/regressions/"$t"/* "fuzz/corpus/$t/" 2>/dev/null   # refused inputs are starts too
    log="fuzz/artifacts/$t/last-run.log"
    start=$(date +%s)
    cargo +nightly fuzz run -O "$t" "fuzz/corpus/$t" -- -runs="$runs" -timeout=10 -rss_limit_mb=2048 \
        -max_len=65536 -print_final_stats=1 >"$log" 2>&1
    rc=$?
    secs=$(( $(date +%s) - start ))
    done_runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
    result="ok"
    [ $rc -ne 0 ] && result="CRASH (exit $rc): $(grep -m1 -E 'panicked|ERROR' "$log")"
    echo "$t: ${done_runs:-?} inputs in ${secs} s: $result"
done
