#!/usr/bin/env python3
"""Writes a scene_graph.json (the InstGS prototype's convention) placing K copies of one
template on a square grid in the X-Z plane, each turned about the Y axis (the up axis of
COLMAP-style captures) by a different angle and uniformly scaled 0.8-1.2. The file's transforms map world points onto the template (world -> template), the
inverse of each copy's template -> world similarity p = s R p_t + t.

usage: grid_scene_graph.py K SPACING OUT.json [TEMPLATE_ID]
"""
import json
import math
import sys


def main():
    k, spacing, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    template_id = sys.argv[4] if len(sys.argv) > 4 else "1"
    side = math.ceil(math.sqrt(k))
    instances = []
    for i in range(k):
        a = 0.0 if i == 0 else 2.399963 * i  # golden angle: no two copies turned alike
        s = 1.0 if i == 0 else 0.8 + 0.4 * ((i * 0.618034) % 1.0)
        t = [(i % side) * spacing, 0.0, (i // side) * spacing]
        c, n = math.cos(a), math.sin(a)
        # Inverse: p_t = (1/s) R^T (p - t), R = rotation about y by a.
        rt = [[c, 0.0, -n], [0.0, 1.0, 0.0], [n, 0.0, c]]
        m = [[rt[r][q] / s for q in range(3)] for r in range(3)]
        mt = [-sum(m[r][q] * t[q] for q in range(3)) for r in range(3)]
        rows = [m[r] + [mt[r]] for r in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
        instances.append({"instance_id": str(i + 1), "transform": rows})
    with open(out, "w") as f:
        json.dump([{"template_id": template_id, "instances": instances}], f, indent=1)


if __name__ == "__main__":
    main()
