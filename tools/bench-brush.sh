#!/usr/bin/env bash
# Side-by-side training against a peer trainer, brush (docs/benchmarking.md): builds it from
# source in a scratch folder outside the repository, gives it a copy of the dataset it can read,
# and trains both on it interleaved, A B A B: per round our plain 3DGS training
# (`instgs-vk train --until plain`), then brush's, for each iteration count. Each side reports
# its own held-out PSNR on the dataset's test views after the same number of iterations and its
# iterations per second (training time over iterations; loading and the final evaluation aside
# where the tool reports them apart).
#
# usage: tools/bench-brush.sh [--rounds R] [--iterations "500 2000"] [--build-only] [DATASET]
#   (default: 1 round, 500 and 2000 iterations, ../shared/data/scenes/ducks6).
#   Results: out/bench-brush/<scene>.json and a table on stdout.
# Environment: PEERS_SCRATCH (scratch folder, default ${TMPDIR:-/tmp}/instgs-peers);
#   BRUSH_GIT, BURN_GIT: where to get brush and its git dependency burn (a URL or a local git
#   directory; default GitHub). burn is taken as the tree of its pinned commit (git archive)
#   and patched in by path, so a local mirror without burn's history works;
#   INSTGS_BIN, BRUSH_BIN: binaries built beforehand (tools/gpu-rows.sh --prepare): nothing is
#   cloned or built; BENCH_OUT: the results folder (default out/bench-brush).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
rounds=1 iterations="500 2000" build_only=0 data=../shared/data/scenes/ducks6
while [[ $# -gt 0 ]]; do
    case $1 in
        --rounds) rounds=$2; shift 2 ;;
        --iterations) iterations=$2; shift 2 ;;
        --build-only) build_only=1; shift ;;
        -*) echo "bench-brush.sh: unknown option $1" >&2; exit 2 ;;
        *) data=$1; shift ;;
    esac
done
scratch=${PEERS_SCRATCH:-${TMPDIR:-/tmp}/instgs-peers}
out=${BENCH_OUT:-$repo/out/bench-brush}
mkdir -p "$scratch" "$out"

if [[ -n ${BRUSH_BIN:-} ]]; then
    brush=$BRUSH_BIN
else

# Pinned commits (../shared/docs/peers.md): brush 83b7c71 and the burn commit its Cargo.lock names.
BRUSH_REV=83b7c71f2148095285d8c2fa2bc961408fcf524d
BURN_REV=89a03e6f08b107f382441e22d1734c217dd9a287
b=$scratch/brush
if [[ ! -d $b/.git ]]; then
    git clone --quiet --no-checkout "${BRUSH_GIT:-https://github.com/ArthurBrussee/brush}" "$b"
fi
if [[ $(git -C "$b" rev-parse HEAD 2> /dev/null) != "$BRUSH_REV" ]]; then
    # (a mirror may lack the Git LFS files below: their checkout fails, the rest is written)
    git -C "$b" -c advice.detachedHead=false checkout --quiet --force $BRUSH_REV 2> /dev/null || true
fi
# Files kept in Git LFS may be missing from a mirror: the LPIPS weights (used only with
# --lpips-loss-weight > 0, off by default) and a test case. Empty stand-ins let it compile.
for f in crates/lpips/burn_mapped.bin crates/brush-bench-test/test_cases/mix_case.safetensors; do
    [[ -f $b/$f ]] || : > "$b/$f"
done
burn=$scratch/burn
if [[ $(cat "$burn/.instgs-rev" 2> /dev/null) != "$BURN_REV" ]]; then
    src=${BURN_GIT:-https://github.com/tracel-ai/burn}
    rm -rf "$burn"
    mkdir -p "$burn"
    if [[ -d $src ]]; then
        git --git-dir="$src" archive $BURN_REV | tar -x -C "$burn"
    else
        tmp=$scratch/burn-git
        git init --quiet "$tmp"
        git -C "$tmp" fetch --quiet --depth 1 "$src" $BURN_REV
        git -C "$tmp" archive FETCH_HEAD | tar -x -C "$burn"
    fi
    echo $BURN_REV > "$burn/.instgs-rev"
fi
mkdir -p "$b/.cargo"
{
    echo "[patch.\"https://github.com/tracel-ai/burn\"]"
    for c in burn burn-cubecl burn-fusion burn-ir burn-store burn-wgpu; do
        echo "$c = { path = \"$burn/crates/$c\" }"
    done
} > "$b/.cargo/config.toml"
echo "building brush $BRUSH_REV in $b (~40 min the first time on two cores)" >&2
# (from inside the checkout: cargo reads .cargo/config.toml from the working directory up)
(cd "$b" && cargo build --release --quiet -p brush-app) 2> "$scratch/brush-build.log" \
    || { tail -30 "$scratch/brush-build.log" >&2; exit 1; }
brush=$b/target/release/brush
fi
[[ $build_only == 0 ]] || exit 0

if [[ -n ${INSTGS_BIN:-} ]]; then
    ours=$INSTGS_BIN
else
    cargo build --release --quiet --bin instgs-vk
    ours=$repo/target/release/instgs-vk
fi
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
name=$(basename "$data")
work=$scratch/brush-$name
# brush's NeRF-synthetic loader drops frames whose file_path has no extension, and it reads a
# masks/ folder as alpha masks: a copy with ".png" added and without masks/.
rm -rf "$work/data"
mkdir -p "$work/data"
for d in "$data"/*; do
    case $(basename "$d") in
        masks | transforms_*.json) ;;
        *) ln -s "$(realpath "$d")" "$work/data/" ;;
    esac
done
for split in train test; do
    python3 - "$data/transforms_$split.json" "$work/data/transforms_$split.json" <<'EOF'
import json, sys
t = json.load(open(sys.argv[1]))
for f in t["frames"]:
    if not f["file_path"].lower().endswith((".png", ".jpg", ".jpeg")):
        f["file_path"] += ".png"
json.dump(t, open(sys.argv[2], "w"), indent=1)
EOF
done

for r in $(seq 1 "$rounds"); do
    for n in $iterations; do
        run=$work/ours-$n-$r
        rm -rf "$run"
        # Held-out PSNR once, after the last iteration (metrics.csv: test_psnr).
        printf 'test_interval = %d\n' "$n" > "$work/ours-$n.toml"
        "$ours" train --data "$data" --out "$run" --iterations "$n" --until plain --quiet \
            --config "$work/ours-$n.toml" > "$run.log" 2>&1
        log=$work/brush-$n-$r.log
        rm -rf "$work/brush-export"
        RUST_LOG=info "$brush" "$work/data" --total-train-iters "$n" --eval-every "$n" --export-every "$n" \
            --export-path "$work/brush-export" > "$log" 2>&1
    done
done

echo "| scene | iterations | ours held-out PSNR | brush held-out PSNR | ours it/s | brush it/s | ours / brush it/s | it/s after the start-up: ours / brush (iterations) |"
echo "|---|---|---|---|---|---|---|---|"
python3 - "$work" "$rounds" "$iterations" "$out/$name.json" "$name" $BRUSH_REV <<'EOF'
import csv, json, re, statistics, sys
from datetime import datetime
work, rounds, iters, path, name, rev = sys.argv[1:7]
med = statistics.median
res = {"scene": name, "brush": rev, "runs": []}


def stamp(log, pattern):
    t = re.search(r"\[(\S+)Z [^]]*\] " + pattern, log).group(1)
    return datetime.fromisoformat(t)


for n in map(int, iters.split()):
    runs = []
    for r in range(1, int(rounds) + 1):
        m = {int(row["iteration"]): row for row in csv.DictReader(open(f"{work}/ours-{n}-{r}/metrics.csv"))}
        log = open(f"{work}/brush-{n}-{r}.log").read()
        # brush's own "Took" reads the CPU side of wgpu's asynchronous queue (77 s for a 473 s
        # run on lavapipe): its training time is its log's wall-clock stamps from the training
        # loop's start to the final evaluation's start (its kernels' autotuning included).
        secs = (stamp(log, f"Running evaluation for iteration {n}") - stamp(log, "Start training loop")).total_seconds()
        # After the start-up: between its first and last densification steps (every 200
        # iterations, logged with a stamp), and ours over the same iterations.
        refines = [int(i) for i in re.findall(r"Refine iter (\d+),", log)]
        steady = None
        if len(refines) >= 2:
            a, b = refines[0], refines[-1]
            brush_dt = (stamp(log, f"Refine iter {b},") - stamp(log, f"Refine iter {a},")).total_seconds()
            ours_dt = float(m[b]["elapsed_s"]) - float(m[a]["elapsed_s"])
            steady = {"from": a, "to": b, "ours": (b - a) / ours_dt, "brush": (b - a) / brush_dt}
        runs.append({"ours_psnr": float(m[n]["test_psnr"]), "ours_it_per_s": n / float(m[n]["elapsed_s"]),
                     "brush_psnr": float(re.findall(r"Eval iter \d+: PSNR ([0-9.]+)", log)[-1]),
                     "brush_it_per_s": n / secs, "steady": steady})
    res["runs"].append({"iterations": n, "rounds": runs})
    get = lambda k: med([r[k] for r in runs])
    st = [r["steady"] for r in runs if r["steady"]]
    steady = (f"{med([s['ours'] for s in st]):.2f} / {med([s['brush'] for s in st]):.2f} "
              f"({st[0]['from']}–{st[0]['to']})") if st else "—"
    print(f"| {name} | {n} | {get('ours_psnr'):.2f} | {get('brush_psnr'):.2f} | {get('ours_it_per_s'):.2f} | "
          f"{get('brush_it_per_s'):.2f} | {get('ours_it_per_s') / get('brush_it_per_s'):.2f}x | {steady} |")
json.dump(res, open(path, "w"), indent=1)
EOF
