#!/usr/bin/env bash
# What limits the instances on a capture (issue 44, §5): the pipeline once per capture with
# configs/lavapipe-2k.toml (2 000 plain + 2 000 joint iterations), then each variant of the
# joint stage (or of the template choice) redone from that run, all on one device. Each run's
# report.md, eval.json, instance.json, pruned.json and pipeline.json are gathered into
# OUT/results.tgz as the runs finish; OUT/summary.tsv has one line per run.
#
#   tools/joint-study.sh [--bin BIN] [--iterations N] [--joint N] [--variants A,B|none]
#                        [--config FILE] CAPTURES OUT [CAPTURE...]
#
# CAPTURES holds tools/make_capture.py's captures (default: ducks6 tabletop). --iterations and
# --joint shorten both schedules for a smoke run; --variants picks some (none: the default run
# only); --config replaces configs/lavapipe-2k.toml as the default run's configuration.
# Variants (configs/study/*.toml, each the lavapipe-2k schedule plus one change):
#   default     configs/lavapipe-2k.toml as it is
#   refine      [joint] refine_transforms = true   (R, t, s learned by the joint stage)
#   joint4k     4 000 joint iterations             (the schedule's length)
#   lr2x        [joint.lr] sh0, opacity and position rates doubled (templates and offsets)
#   init-merge  [instance] init = "merge"          (the template choice; redone from `instance`)
#   no-rebalance [instance] rebalance = false      (the background budget alone; from `instance`)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/instgs-vk iterations=2000 joint="" pick="" base_config=configs/lavapipe-2k.toml
while [[ $# -gt 0 ]]; do
    case $1 in
        --bin) bin=$2; shift 2 ;;
        --iterations) iterations=$2; shift 2 ;;
        --joint) joint=$2; shift 2 ;;
        --variants) pick=$2; shift 2 ;;
        --config) base_config=$2; shift 2 ;;
        -h | --help) sed -n 2,20p "$0"; exit 0 ;;
        -*) echo "joint-study.sh: unknown argument $1" >&2; exit 2 ;;
        *) break ;;
    esac
done
[[ $# -ge 2 ]] || { echo "usage: tools/joint-study.sh [--bin BIN] CAPTURES OUT [CAPTURE...]" >&2; exit 2; }
captures=$1 out=$2; shift 2
names=("$@"); [[ ${#names[@]} -gt 0 ]] || names=(ducks6 tabletop)
mkdir -p "$out/runs"
out=$(cd "$out" && pwd)
variants=(refine joint4k lr2x init-merge)
if [[ $pick == none ]]; then variants=(); elif [[ -n $pick ]]; then IFS=, read -r -a variants <<< "$pick"; fi

# A variant's configuration: the study file, with the joint schedule shortened for a smoke run.
config_of() {
    local src=configs/study/$1.toml
    [[ $1 == default ]] && src=$base_config
    if [[ -z $joint ]]; then echo "$PWD/$src"; return; fi
    local f=$out/runs/$1.toml
    sed -e "s/^iterations = [0-9]*/iterations = $joint/" -e "s/^position_max_steps = [0-9]*/position_max_steps = $joint/" "$src" > "$f"
    echo "$f"
}

gather() {
    (cd "$out/runs" && find . -maxdepth 2 \( -name report.md -o -name eval.json -o -name instance.json \
        -o -name pruned.json -o -name pipeline.json -o -name '*.log' \) -print0 |
        tar czf "$out/results.tgz.tmp" --null -T -) && mv "$out/results.tgz.tmp" "$out/results.tgz"
}

summary_line() {
    python3 - "$1" "$2" "$3" <<'EOF'
import json, sys
cap, var, run = sys.argv[1:]
try:
    e = json.load(open(f"{run}/eval.json"))
except Exception as err:
    print(f"{cap}\t{var}\tno eval.json ({err})"); sys.exit()
parts = []
for name in ("plain", "pruned", "instgs"):
    s = e.get(name) or {}
    f = lambda k: "%.2f" % s[k] if isinstance(s.get(k), (int, float)) else "-"
    parts.append(f"{name} {f('psnr_mean')} inst {f('psnr_instances_mean')} bg {f('psnr_background_mean')} comp {f('psnr_compensated_mean')}")
print(f"{cap}\t{var}\t" + "\t".join(parts))
EOF
}

run_capture() {
    local cap=$1 base=$out/runs/$1-default
    local t0=$SECONDS
    "$bin" train --data "$captures/$cap" --out "$base" --iterations "$iterations" \
        --config "$(config_of default)" > "$out/runs/$cap-default.log" 2>&1 || echo "$cap default failed" >&2
    echo "$cap default: $((SECONDS - t0)) s" >&2
    summary_line "$cap" default "$base" >> "$out/summary.tsv"
    gather
    for v in ${variants[@]+"${variants[@]}"}; do
        (
            local run=$out/runs/$cap-$v from=joint t1=$SECONDS
            grep -q '^\[instance\]' "configs/study/$v.toml" && from=instance
            cp -r "$base" "$run"
            "$bin" train --data "$captures/$cap" --out "$run" --iterations "$iterations" \
                --config "$(config_of "$v")" --from $from > "$out/runs/$cap-$v.log" 2>&1 || echo "$cap $v failed" >&2
            echo "$cap $v: $((SECONDS - t1)) s" >&2
            summary_line "$cap" "$v" "$run" >> "$out/summary.tsv"
            rm -f "$run/checkpoint.bin" "$run/point_cloud.ply"
            gather
        ) &
    done
    wait
}

for c in "${names[@]}"; do run_capture "$c" & done
wait
gather
cat "$out/summary.tsv"
