#!/usr/bin/env bash
# Every GPU row of BENCHMARKS.md in one command (docs/benchmarking.md, "On a GPU machine").
#
#   tools/gpu-rows.sh --prepare [--only ROW,ROW] [--curve-run RUN --curve-data DATA]
#                                            on a machine with network, before the GPU comes:
#                                            builds what the rows need into out/gpu-kit/ (--only:
#                                            just those rows' binaries and data, a smaller kit)
#   tools/gpu-rows.sh [--budget-min 40] [--only ROW,ROW] [--install-libs]
#                                            on the GPU machine (no network, no Rust needed)
#   tools/gpu-rows.sh --smoke                every row's code path, scaled down, on any device
#                                            (lavapipe in the test command), a few minutes
#
# Rows, in order of priority (each one's time on an H100 in brackets, what the budget plans by;
# measured on 2026-11-27 for the first three, with a margin):
#   forward-1080p      our frame at 1920x1080 beside web-splat's, the shared guitar, biker and
#                      playbot_lod2, 8 orbit cameras (tools/bench-peers.sh; our forward path
#                      `auto`: whichever is faster on the device, named in the row)  [1 min]
#   splats-1m-11m      1M and 11.6M splats (11 and 128 copies of the guitar, expanded into plain
#                      PLYs) at 1920x1080, both forward paths: goals < 2 ms and < 10 ms a frame
#                                                                                     [2 min]
#   equal-quality      InstGS against the plain scene pruned to the same held-out PSNR (a
#                      `curve` run's equal-quality point: the pruned scenes just below and at or
#                      above InstGS's PSNR; --prepare --curve-run RUN --curve-data DATA puts the
#                      scenes and DATA/transforms_test.json in the kit), interleaved, both
#                      forward paths, at the cameras' size and at 1080 lines, the pruned frame
#                      rates interpolated to InstGS's PSNR
#                                                                                     [1 min]
#   training-brush     plain training beside brush on a 2 MP dataset rendered from the biker
#                      (150 + 15 views), 2 000 and 7 000 iterations (tools/bench-brush.sh) [15 min]
#   pipeline-full      `instgs-vk train` with today's defaults, 30 000 + 10 000 iterations, on
#                      the shared ducks6 and tabletop                                 [30 min]
# A row starts only when the budget left holds its planned time (each row is also stopped when
# the budget runs out); rows not run are listed as such. Every row writes
# out/gpu-rows/<row>.json and <row>.md: device, driver, commit, the commands, the times, the
# figures. Peers missing from the kit leave their half of a row empty, said in the row.
#
# The kit (out/gpu-kit/, ignored by git): bin/ (instgs-vk, web-splat-harness, brush, stripped),
# data/ (the ../shared data the rows read: the GPU machine sees the checkout only; equal/: the
# curve run's scenes), debs/ (the Vulkan loader and libglvnd as Debian packages, for
# --install-libs), libs.txt (the shared libraries each binary needs), commit (what was built);
# all of it packed into out/gpu-kit.tar.xz (unpack with tar -C out -xJf out/gpu-kit.tar.xz).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
kit=$repo/out/gpu-kit
out=$repo/out/gpu-rows
budget_min=40 prepare=0 smoke=0 install_libs=0 only="" curve_run="" curve_data=""
while [[ $# -gt 0 ]]; do
    case $1 in
        --prepare) prepare=1; shift ;;
        --smoke) smoke=1; shift ;;
        --budget-min) budget_min=$2; shift 2 ;;
        --only) only=$2; shift 2 ;;
        --install-libs) install_libs=1; shift ;;
        --curve-run) curve_run=$2; shift 2 ;;
        --curve-data) curve_data=$2; shift 2 ;;
        -h | --help) sed -n 2,40p "$0"; exit 0 ;;
        *) echo "gpu-rows.sh: unknown argument $1 (--help lists them)" >&2; exit 2 ;;
    esac
done
rows=(forward-1080p splats-1m-11m equal-quality training-brush pipeline-full)
declare -A planned_min=([forward-1080p]=1 [splats-1m-11m]=2 [equal-quality]=1 [training-brush]=15 [pipeline-full]=30)
for r in ${only//,/ }; do
    [[ " ${rows[*]} " == *" $r "* ]] || { echo "gpu-rows.sh: --only: no row $r (rows: ${rows[*]})" >&2; exit 2; }
done
wanted() { [[ -z $only || ",$only," == *",$1,"* ]]; }
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}

# ---------------------------------------------------------------------------------------------
# --prepare: build and gather everything, with network.
if [[ $prepare == 1 ]]; then
    if wanted equal-quality && [[ -z $curve_run || ! -f $curve_data/transforms_test.json ]]; then
        echo "gpu-rows.sh: the equal-quality row needs --curve-run RUN (a finished \`instgs-vk curve\` run) and --curve-data DATA (its dataset, with transforms_test.json), or leave it out with --only" >&2
        exit 2
    fi
    rm -rf "$kit/bin" "$kit/data"
    mkdir -p "$kit/bin" "$kit/data/splats" "$kit/data/scenes" "$kit/debs"
    bash tools/install-deps.sh
    cargo build --release --bin instgs-vk
    cp target/release/instgs-vk "$kit/bin/"
    scratch=$kit/peers-src
    if wanted forward-1080p; then
        PEERS_SCRATCH=$scratch bash tools/bench-peers.sh --build-only
        cp "$scratch/web-splat-harness/target/release/web-splat-harness" "$kit/bin/"
    fi
    if wanted training-brush; then
        PEERS_SCRATCH=$scratch bash tools/bench-brush.sh --build-only
        cp "$scratch/brush/target/release/brush" "$kit/bin/"
    fi
    strip "$kit/bin/"*
    splats=()
    wanted forward-1080p && splats+=(guitar.ply biker.ply playbot_lod2.ply)
    wanted splats-1m-11m && splats+=(guitar.ply)
    wanted training-brush && splats+=(biker.ply)
    for f in $(printf '%s\n' "${splats[@]}" | sort -u); do cp ../shared/data/splats/$f "$kit/data/splats/"; done
    if wanted pipeline-full; then
        for s in ducks6 tabletop; do cp -r ../shared/data/scenes/$s "$kit/data/scenes/"; done
    fi
    if wanted equal-quality; then
        # The curve's InstGS scene, the pruned scenes about its PSNR and the held-out cameras.
        mkdir -p "$kit/data/equal"
        cp "$curve_data/transforms_test.json" "$kit/data/equal/"
        python3 - "$curve_run" "$kit/data/equal" <<'EOF'
import json, os, shutil, sys
run, dst = sys.argv[1:]
try:
    eq = json.load(open(os.path.join(run, "rate_distortion.json")))["equal_quality"]
except (OSError, ValueError, KeyError) as e:
    sys.exit(f"gpu-rows.sh: {run}: not a finished curve run ({e})")
if not eq:
    sys.exit(f"gpu-rows.sh: {run}: the curve found no equal-quality point")
shutil.copy(os.path.join(run, "scene.instgs"), os.path.join(dst, "instgs.instgs"))
shutil.copy(eq["above"]["scene"]["file"], os.path.join(dst, "pruned.ply"))
if eq.get("below"):
    shutil.copy(eq["below"]["scene"]["file"], os.path.join(dst, "pruned-below.ply"))
json.dump({"run": run, **eq}, open(os.path.join(dst, "equal.json"), "w"), indent=1)
EOF
    fi
    # The loader and libglvnd (wgpu's peers need libEGL/libGL through libglvnd on NVIDIA).
    (cd "$kit/debs" && apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 > /dev/null)
    for b in "$kit/bin/"*; do echo "== $(basename "$b")"; ldd "$b"; done > "$kit/libs.txt"
    git rev-parse HEAD > "$kit/commit"
    du -sh "$kit/bin" "$kit/data" "$kit/debs"
    # One packed file for machines that take little (PLYs and binaries shrink to about a third).
    tar -C "$repo/out" -cf - gpu-kit/bin gpu-kit/data gpu-kit/debs gpu-kit/libs.txt gpu-kit/commit | xz -6 -T2 > "$kit.tar.xz"
    echo "kit ready$([[ -n $only ]] && echo " for rows $only"): $kit, packed into $kit.tar.xz ($(du -m "$kit.tar.xz" | cut -f1) MiB;"
    echo "  without peers-src/). On the GPU machine, in the checkout: tar -C out -xJf out/gpu-kit.tar.xz; tools/gpu-rows.sh"
    exit 0
fi

# ---------------------------------------------------------------------------------------------
# The binaries and data: the kit's; a smoke run takes this checkout's build and ../shared (and the
# kit's peers where it has them).
bin=$kit/bin/instgs-vk data=$kit/data
if [[ $smoke == 1 ]]; then
    bin=$repo/target/release/instgs-vk data=$repo/../shared/data
    [[ -x $bin ]] || cargo build --release --quiet --bin instgs-vk
elif [[ ! -x $bin ]]; then
    echo "gpu-rows.sh: no kit at $kit: run tools/gpu-rows.sh --prepare on a machine with network first" >&2
    exit 1
fi
harness=$kit/bin/web-splat-harness
brush=$kit/bin/brush
commit=$(git rev-parse HEAD)
[[ $smoke == 1 ]] || commit=$(cat "$kit/commit")

# Before any row: the libraries. Ours loads the Vulkan loader at run time (not in ldd), the peers
# (wgpu) too, and EGL/GL through libglvnd.
if [[ $install_libs == 1 ]]; then
    for f in "$kit"/debs/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
missing=""
for b in "$bin" "$harness" "$brush"; do
    [[ -x $b ]] || continue
    m=$(ldd "$b" | awk '/not found/ {print $1}' | tr '\n' ' ')
    [[ -z $m ]] || missing+="$(basename "$b") needs ${m}; "
done
# (Held in a variable: `ldconfig -p | grep -q` fails under pipefail whenever grep's early exit
# cuts ldconfig off with SIGPIPE.)
cache=$(ldconfig -p)
[[ $cache == *libvulkan.so.1* ]] || missing+="the Vulkan loader libvulkan.so.1; "
if [[ (-x $harness || -x $brush) && $cache != *libEGL.so.1* ]]; then
    missing+="libEGL.so.1 (libglvnd) for the wgpu peers; "
fi
if [[ -n $missing ]]; then
    echo "gpu-rows.sh: missing libraries: ${missing}run again with --install-libs (unpacks $kit/debs, made by --prepare)" >&2
    exit 1
fi

mkdir -p "$out"
work=$out/work
mkdir -p "$work"
# Device and driver, once (every row runs on them).
"$bin" bench --scene "$data/splats/guitar.ply" --orbit 1 --width 64 --height 48 --frames 1 --warmup 0 \
    --json "$work/device.json" > /dev/null 2>&1 || { echo "gpu-rows.sh: instgs-vk cannot render on this machine:" >&2; "$bin" info "$data/splats/guitar.ply" >&2; exit 1; }
{ read -r device; read -r driver; } < <(python3 -c 'import json,sys; v=json.load(open(sys.argv[1])); print(json.dumps(v["device"])); print(json.dumps(v["driver"]))' "$work/device.json")
echo "device: $device, driver: $driver, commit $commit; budget $budget_min min$([[ $smoke == 1 ]] && echo ', smoke run')" >&2

start=$(date +%s)
left_s() { echo $((budget_min * 60 - ($(date +%s) - start))); }
declare -A status

# One row's record: out/gpu-rows/<row>.json and .md from the row's own results file
# ($work/<row>/result.json: {"table": [[header...], [row...], ...], "figures": {...}}).
record() { # row status seconds commands-file
    python3 - "$1" "$2" "$3" "$4" "$work/$1/result.json" "$out" "$device" "$driver" "$commit" "$smoke" <<'EOF'
import json, os, sys
row, status, secs, cmds, result, out, device, driver, commit, smoke = sys.argv[1:]
res = json.load(open(result)) if os.path.exists(result) else {}
rec = {"row": row, "status": status, "seconds": float(secs), "device": json.loads(device),
       "driver": json.loads(driver), "commit": commit, "smoke": smoke == "1",
       "commands": open(cmds).read().splitlines() if os.path.exists(cmds) else [], **res}
json.dump(rec, open(os.path.join(out, row + ".json"), "w"), indent=1)
md = [f"### {row}{' (smoke run, scaled down)' if smoke == '1' else ''}", "",
      f"{rec['device']}, {rec['driver']}; commit {commit[:10]}; {status}, {float(secs):.0f} s.", ""]
table = res.get("table")
if table:
    md += ["| " + " | ".join(table[0]) + " |", "|" + "---|" * len(table[0])]
    md += ["| " + " | ".join(str(c) for c in r) + " |" for r in table[1:]]
    md.append("")
md += [f"- {n}" for n in res.get("notes", [])]
md += ["", "```sh"] + rec["commands"] + ["```", ""]
open(os.path.join(out, row + ".md"), "w").write("\n".join(md))
EOF
}

# Runs a command of a row under the budget left, logging it to the row's commands file.
run() { # row command...
    local row=$1
    shift
    printf '%q ' "$@" >> "$work/$row/commands"
    echo >> "$work/$row/commands"
    timeout "$(left_s)" "$@" >> "$work/$row/log" 2>&1
}

row_forward() {
    local size=1920x1080 cams=8 rounds=2 scenes=("$data/splats/guitar.ply" "$data/splats/biker.ply" "$data/splats/playbot_lod2.ply")
    [[ $smoke == 0 ]] || { size=160x120 cams=2 rounds=1 scenes=("$data/splats/guitar.ply"); }
    if [[ -x $harness ]]; then
        run forward-1080p env INSTGS_BIN="$bin" WEB_SPLAT_HARNESS="$harness" BENCH_OUT="$work/forward-1080p" \
            PEERS_SCRATCH="$work/forward-1080p/scratch" bash tools/bench-peers.sh --rounds $rounds --frames 3 \
            --forward auto --size $size --cameras $cams "${scenes[@]}"
    else
        for s in "${scenes[@]}"; do
            run forward-1080p "$bin" bench --scene "$s" --orbit $cams --width ${size%x*} --height ${size#*x} \
                --frames 3 --forward auto --json "$work/forward-1080p/$(basename "$s" .ply)-ours.json"
        done
    fi
    python3 - "$work/forward-1080p" "$size" "$( [[ -x $harness ]] && echo 1 || echo 0)" <<'EOF'
import glob, json, os, sys
d, size, peer = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
table = [["scene", "size", "our forward path", "ours (ms)", "web-splat (ms)", "ours / web-splat"]]
for f in sorted(glob.glob(os.path.join(d, "*.json"))):
    v = json.load(open(f))
    if f.endswith("-ours.json"):
        table.append([os.path.basename(f)[:-10], size, v["forward"], f"{v['frame_ms_median']:.2f}", "—", "—"])
    elif "ratio_median" in v:
        med = lambda x: sorted(x)[len(x) // 2]
        table.append([v["scene"], size, v["forward"], f"{med(v['ours_frame_ms']):.2f}", f"{med(v['web_splat_frame_ms']):.2f}",
                      f"{v['ratio_median']:.2f}"])
notes = [] if peer else ["web-splat is not in the kit (tools/gpu-rows.sh --prepare builds it): ours alone."]
notes.append("brush has no offscreen frame timer (its viewer is interactive): not timed here.")
json.dump({"table": table, "notes": notes}, open(os.path.join(d, "result.json"), "w"), indent=1)
EOF
}

row_splats() {
    local size=1920x1080 ks=(11 128)
    [[ $smoke == 0 ]] || { size=160x120 ks=(1 2); }
    local d=$work/splats-1m-11m
    for k in "${ks[@]}"; do
        run splats-1m-11m python3 tools/grid_scene_graph.py "$k" 3.0 "$d/K$k.json" guitar
        run splats-1m-11m "$bin" compose --template guitar="$data/splats/guitar.ply" --scene-graph "$d/K$k.json" \
            --random-offsets 0.01 --out "$d/K$k.instgs"
        run splats-1m-11m "$bin" convert "$d/K$k.instgs" "$d/K$k.ply"
        run splats-1m-11m "$bin" bench --scene "$d/K$k.ply" --orbit 8 --width ${size%x*} --height ${size#*x} \
            --frames 5 --compare-forward quads --json "$d/K$k-bench.json" || true
        rm -f "$d/K$k.ply"
    done
    python3 - "$d" "$size" "${ks[@]}" <<'EOF'
import json, os, sys
d, size, ks = sys.argv[1], sys.argv[2], sys.argv[3:]
table = [["copies", "splats", "size", "compute: frame median (ms)", "p90 (ms)", "quads: frame median (ms)", "p90 (ms)", "goal"]]
goals = {0: "< 2 ms", 1: "< 10 ms"}
for i, k in enumerate(ks):
    p = os.path.join(d, f"K{k}-bench.json")
    if not os.path.exists(p):
        table.append([k, "—", size, "failed (see log)", "—", "—", "—", goals.get(i, "")])
        continue
    v = json.load(open(p))
    q = v["compare"]
    table.append([k, v["splats"], size, f"{v['frame_ms_median']:.2f}", f"{v['frame_ms_p90']:.2f}",
                  f"{q['frame_ms_median']:.2f}", f"{q['frame_ms_p90']:.2f}", goals.get(i, "")])
json.dump({"table": table}, open(os.path.join(d, "result.json"), "w"), indent=1)
EOF
}

row_equal() {
    local d=$work/equal-quality e=$data/equal sizes=("" 1440x1080) frames=5 a b cams versus
    a=$e/instgs.instgs b=$e/pruned.ply cams=$e/transforms_test.json
    if [[ $smoke == 1 ]]; then
        # The code path on what any checkout has: one copy of the demo guitar against itself.
        sizes=("" 96x72) frames=1
        run equal-quality python3 tools/grid_scene_graph.py 1 3.0 "$d/K1.json" guitar
        run equal-quality "$bin" compose --template guitar="$repo/demo/guitar.compressed.ply" \
            --scene-graph "$d/K1.json" --out "$d/K1.instgs"
        a=$d/K1.instgs b=$repo/demo/guitar.compressed.ply cams=$repo/demo/ducks6-mini/transforms_test.json
        printf '{"smoke": true}\n' > "$d/equal.json"
    elif [[ ! -f $a ]]; then
        echo "no curve run in the kit (tools/gpu-rows.sh --prepare --curve-run RUN)" >> "$d/log"
        return 1
    else
        cp "$e/equal.json" "$d/equal.json"
    fi
    # InstGS (A) against each pruned scene (B: at or above InstGS's PSNR, then the one below),
    # interleaved, each forward path, each size.
    versus=(above="$b")
    [[ -f $e/pruned-below.ply ]] && versus+=(below="$e/pruned-below.ply")
    for forward in compute quads; do
        for size in "${sizes[@]}"; do
            for v in "${versus[@]}"; do
                run equal-quality "$bin" bench --scene "$a" --compare "${v#*=}" --cameras "$cams" --forward "$forward" \
                    ${size:+--width ${size%x*} --height ${size#*x}} --frames $frames \
                    --json "$d/${v%%=*}-$forward-${size:-native}.json" || true
            done
        done
    done
    python3 - "$d" <<'EOF'
import glob, json, os, sys
d = sys.argv[1]
eq = json.load(open(os.path.join(d, "equal.json")))
table = [["forward path", "size", "pruned scene", "InstGS (ms)", "pruned (ms)", "InstGS FPS / pruned FPS", "GPU bytes ratio"]]
ratio = {}
for f in sorted(glob.glob(os.path.join(d, "*-*-*.json"))):
    v = json.load(open(f))
    which = os.path.basename(f).split("-")[0]
    size = f"{v['width']}x{v['height']}"
    ratio[(which, v["forward"], size)] = v["ratios"]["fps"]
    table.append([v["forward"], size, which, f"{v['frame_ms_median']:.2f}",
                  f"{v['compare']['frame_ms_median']:.2f}", f"{v['ratios']['fps']:.2f}",
                  f"{v['ratios']['scene_gpu_bytes']:.2f}"])
notes = []
if "instgs_psnr" in eq:
    up, lo, t = eq["above"], eq.get("below"), eq["instgs_psnr"]
    notes.append(f"From the curve run {eq['run']}: InstGS {t:.2f} dB held-out at {eq['instgs_gpu_bytes'] / 1e6:.2f} MB; "
                 f"the plain scene pruned to {up['scene']['gpu_bytes'] / 1e6:.2f} MB {up['scene']['psnr']:.2f} dB"
                 + (f" and to {lo['scene']['gpu_bytes'] / 1e6:.2f} MB {lo['scene']['psnr']:.2f} dB" if lo else "")
                 + f"; on lavapipe InstGS rendered at {eq['fps_ratio']:.2f}x the pruned FPS at its PSNR.")
    for (which, forward, size), r in sorted(ratio.items()):
        if which == "above" and lo and ("below", forward, size) in ratio:
            s = (t - lo["scene"]["psnr"]) / (up["scene"]["psnr"] - lo["scene"]["psnr"])
            r = ratio[("below", forward, size)] + s * (r - ratio[("below", forward, size)])
            notes.append(f"{forward} {size}: InstGS FPS over the pruned FPS at its PSNR (interpolated) {r:.2f}x")
json.dump({"table": table, "notes": notes}, open(os.path.join(d, "result.json"), "w"), indent=1)
EOF
}

row_training() {
    local size=1920x1080 n=150 m=15 its="2000 7000"
    [[ $smoke == 0 ]] || { size=96x64 n=6 m=2 its="10"; }
    local d=$work/training-brush
    run training-brush env INSTGS_BIN="$bin" bash tools/render-dataset.sh "$data/splats/biker.ply" "$d/biker-data" $size $n $m
    if [[ -x $brush ]]; then
        run training-brush env INSTGS_BIN="$bin" BRUSH_BIN="$brush" BENCH_OUT="$d" PEERS_SCRATCH="$d/scratch" \
            bash tools/bench-brush.sh --iterations "$its" "$d/biker-data"
    else
        for i in $its; do
            printf 'test_interval = %d\n' "$i" > "$d/ours-$i.toml"
            run training-brush "$bin" train --data "$d/biker-data" --out "$d/ours-$i" --iterations "$i" --quiet \
                --config "$d/ours-$i.toml"
        done
    fi
    python3 - "$d" "$size" "$its" "$( [[ -x $brush ]] && echo 1 || echo 0)" <<'EOF'
import csv, json, os, sys
d, size, its, peer = sys.argv[1], sys.argv[2], sys.argv[3].split(), sys.argv[4] == "1"
table = [["dataset", "iterations", "ours held-out PSNR", "ours it/s", "brush held-out PSNR", "brush it/s"]]
b = json.load(open(os.path.join(d, "biker-data.json"))) if os.path.exists(os.path.join(d, "biker-data.json")) else None
for n in map(int, its):
    if b:
        r = next(x for x in b["runs"] if x["iterations"] == n)["rounds"][0]
        table.append([f"biker {size}", n, f"{r['ours_psnr']:.2f}", f"{r['ours_it_per_s']:.2f}",
                      f"{r['brush_psnr']:.2f}", f"{r['brush_it_per_s']:.2f}"])
    else:
        rows = list(csv.DictReader(open(os.path.join(d, f"ours-{n}", "metrics.csv"))))
        last = rows[-1]
        table.append([f"biker {size}", n, last["test_psnr"] or "—", f"{n / float(last['elapsed_s']):.2f}", "—", "—"])
notes = [] if peer else ["brush is not in the kit (tools/gpu-rows.sh --prepare builds it): ours alone."]
json.dump({"table": table, "notes": notes}, open(os.path.join(d, "result.json"), "w"), indent=1)
EOF
}

row_pipeline() {
    local d=$work/pipeline-full scenes=("$data/scenes/ducks6" "$data/scenes/tabletop") cfg=()
    if [[ $smoke == 1 ]]; then
        scenes=("$repo/demo/ducks6-mini")
        printf 'iterations = 40\ntest_interval = 20\n[densify]\nfrom_iter = 10\nuntil_iter = 30\ninterval = 10\nopacity_reset_interval = 0\n[joint]\niterations = 10\ntest_interval = 10\n[joint.lr]\nposition_max_steps = 10\n[instance]\nsynchronise = false\n[bench]\nframes = 1\nwarmup = 0\n' > "$d/smoke.toml"
        cfg=(--config "$d/smoke.toml" --downscale 2)
    fi
    for s in "${scenes[@]}"; do
        run pipeline-full "$bin" train --data "$s" --out "$d/$(basename "$s")" --quiet "${cfg[@]}" || true
    done
    python3 - "$d" "${scenes[@]}" <<'EOF'
import json, os, sys
d, scenes = sys.argv[1], sys.argv[2:]
table = [["scene", "plain PSNR", "plain, pruned PSNR", "InstGS PSNR", "InstGS − plain (dB)", "memory ratio", "FPS ratio", "stage times (s)"]]
for s in scenes:
    run = os.path.join(d, os.path.basename(s))
    try:
        e = json.load(open(os.path.join(run, "eval.json")))
        b = json.load(open(os.path.join(run, "bench.json")))
        st = json.load(open(os.path.join(run, "pipeline.json")))["stages"]
    except (OSError, ValueError, KeyError):
        table.append([os.path.basename(s), "did not finish (see log)", "", "", "", "", "", ""])
        continue
    p, i = e["plain"]["psnr_mean"], e["instgs"]["psnr_mean"]
    q = e.get("pruned", {}).get("psnr_mean")
    order = ["plain", "segment", "instance", "joint", "pruned", "eval", "bench"]
    times = ", ".join(f"{k} {st[k]['seconds']:.0f}" for k in order if k in st)
    table.append([os.path.basename(s), f"{p:.2f}", f"{q:.2f}" if q else "—", f"{i:.2f}", f"{i - p:+.2f}",
                  f"{b['ratios']['scene_gpu_bytes']:.3f}x", f"{b['ratios']['fps']:.2f}x", times])
json.dump({"table": table}, open(os.path.join(d, "result.json"), "w"), indent=1)
EOF
}

declare -A fn=([forward-1080p]=row_forward [splats-1m-11m]=row_splats [equal-quality]=row_equal [training-brush]=row_training [pipeline-full]=row_pipeline)
for row in "${rows[@]}"; do
    if ! wanted "$row"; then
        status[$row]="not asked (--only)"
        continue
    fi
    need=$((planned_min[$row] * 60))
    [[ $smoke == 1 ]] && need=0
    if (($(left_s) < need)); then
        status[$row]="not run: ${planned_min[$row]} min planned, $(($(left_s) / 60)) min of the budget left"
        continue
    fi
    rm -rf "${work:?}/$row"
    mkdir -p "$work/$row"
    echo "== $row (planned ${planned_min[$row]} min, $(($(left_s) / 60)) min of the budget left)" >&2
    t0=$(date +%s)
    if ${fn[$row]}; then status[$row]=done; else status[$row]="failed (out/gpu-rows/work/$row/log)"; fi
    (($(left_s) > 0)) || status[$row]="stopped by the budget"
    record "$row" "${status[$row]}" $(($(date +%s) - t0)) "$work/$row/commands"
done

{
    echo "# GPU rows ($device, $driver; commit ${commit:0:10})"
    echo
    for row in "${rows[@]}"; do
        echo "- $row: ${status[$row]}"
    done
    echo
    for row in "${rows[@]}"; do
        [[ -f $out/$row.md && ${status[$row]} != not* ]] && cat "$out/$row.md"
    done
} > "$out/summary.md"
cat "$out/summary.md"
failed=0
for row in "${rows[@]}"; do [[ ${status[$row]} == failed* ]] && failed=1; done
exit $failed
