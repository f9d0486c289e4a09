#!/usr/bin/env bash
# How the instance stage grows with the number of copies: `instgs-vk instance` on the segmented
# plain scene of a pipeline run (RUN/point_cloud.ply, RUN/labels.json) with K = 10, 20 and 40 of
# its instances (the first ones of each group in the same proportions as the whole scene; the
# others stay background), render check and pose graph on, as the pipeline runs it (without the
# pipeline's background budget and rebalance, which do not depend on K's registrations).
# Writes OUT/k<K>.json (the stage's report, with its "timing") and OUT/scaling.json and
# OUT/scaling.md: seconds per step and registrations per K, and the growth from one K to the next.
#
#   bash tools/instance-scaling.sh RUN DATA OUT [K...]     (e.g. out/cafe40 ../shared/data/scenes/cafe40 out/scaling)
set -euo pipefail
cd "$(dirname "$0")/.."
run=$1 data=$2 out=$3
shift 3
ks=("$@")
[ ${#ks[@]} -eq 0 ] && ks=(10 20 40)
bin=target/release/instgs-vk
[ -x "$bin" ] || cargo build --release
mkdir -p "$out"
for k in "${ks[@]}"; do
    # The first round(K × group size / total) instances of each group (at least 2 per group).
    ids=$(python3 - "$data/instances.json" "$k" <<'PY'
import json, sys
groups = json.load(open(sys.argv[1]))["groups"]
k = int(sys.argv[2])
total = sum(len(g["instances"]) for g in groups)
pick = []
for g in groups:
    n = max(2, round(k * len(g["instances"]) / total))
    pick += [i["id"] for i in g["instances"][:n]]
print(",".join(str(i) for i in pick))
PY
)
    echo "== K = $k: instances $ids" >&2
    start=$(date +%s)
    "$bin" instance --scene "$run/point_cloud.ply" --labels "$run/labels.json" --data "$data" \
        --instances "$ids" --report "$out/k$k.json" --out "$out/k$k.instgs" > "$out/k$k.log" 2>&1
    echo "   $(( $(date +%s) - start )) s wall; $(tail -2 "$out/k$k.log" | head -1)" >&2
done
python3 - "$out" "${ks[@]}" <<'PY'
import json, sys
out, ks = sys.argv[1], [int(k) for k in sys.argv[2:]]
steps = ["candidates_s", "registration_s", "synchronisation_s", "render_checks_s", "templates_s"]
rows = []
for k in ks:
    r = json.load(open(f"{out}/k{k}.json"))
    t = r["timing"]
    shared = sum(1 for i in r["instances"] if i["status"] in ("accepted", "reference"))
    rows.append({"k": k, "instances": len(r["instances"]), "shared": shared, **{s: t[s] for s in steps},
                 "total_s": sum(t[s] for s in steps), "registrations": t["registrations"],
                 "edges": t["edges"], "render_checks": t["render_checks"]})
json.dump({"rows": rows}, open(f"{out}/scaling.json", "w"), indent=1)
md = ["| K | shared | total (s) | registration (s) | synchronisation (s) | render checks (s, count) | registrations | graph edges | growth from the K before |",
      "|---|---|---|---|---|---|---|---|---|"]
top = max(r["total_s"] for r in rows)
for i, r in enumerate(rows):
    growth = f"×{r['total_s'] / rows[i - 1]['total_s']:.2f} for ×{r['k'] / rows[i - 1]['k']:.0f} copies" if i else "—"
    md.append(f"| {r['k']} | {r['shared']} of {r['instances']} | {r['total_s']:.0f} | {r['registration_s']:.0f} | "
              f"{r['synchronisation_s']:.0f} | {r['render_checks_s']:.0f} ({r['render_checks']}) | {r['registrations']} | "
              f"{r['edges']} | {growth} |")
md.append("")
md.append("```")
for r in rows:
    md.append(f"K = {r['k']:>3}  {'█' * max(1, round(50 * r['total_s'] / top))} {r['total_s']:.0f} s")
md.append("```")
open(f"{out}/scaling.md", "w").write("\n".join(md) + "\n")
print("\n".join(md))
PY
