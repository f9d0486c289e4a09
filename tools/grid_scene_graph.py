#!/usr/bin/env python3
"""Writes a scene_graph.json (the InstGS prototype's convention) placing K copies of one
template on a square grid in the X-Z plane, each turned about the Y axis (the up axis of
COLMAP-style captures) by a different angle and uniformly scaled 0.8-1.2. The file's transforms
map world points onto the template (world -> template), the inverse of each copy's
template -> world similarity p = s R p_t + t.

--jitter DEG DIST FRAC SEED perturbs every copy but the first like a registration error: a
rotation by DEG degrees about a random axis, a shift of DIST scene units in a random direction
and a scale error of FRAC (relative).

usage: grid_scene_graph.py K SPACING OUT.json [TEMPLATE_ID] [--jitter DEG DIST FRAC SEED]
"""
import json
import math
import random
import sys


def matmul(a, b):
    return [[sum(a[r][k] * b[k][c] for k in range(3)) for c in range(3)] for r in range(3)]


def axis_angle(axis, angle):
    x, y, z = axis
    c, s, t = math.cos(angle), math.sin(angle), 1.0 - math.cos(angle)
    return [[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, t * z * z + c]]


def unit(rng):
    v = [rng.gauss(0.0, 1.0) for _ in range(3)]
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


def main():
    args = sys.argv[1:]
    jitter = None
    if "--jitter" in args:
        i = args.index("--jitter")
        jitter = (float(args[i + 1]), float(args[i + 2]), float(args[i + 3]), int(args[i + 4]))
        args = args[:i] + args[i + 5:]
    k, spacing, out = int(args[0]), float(args[1]), args[2]
    template_id = args[3] if len(args) > 3 else "1"
    rng = random.Random(jitter[3] if jitter else 0)
    side = math.ceil(math.sqrt(k))
    instances = []
    for i in range(k):
        a = 0.0 if i == 0 else 2.399963 * i  # golden angle: no two copies turned alike
        s = 1.0 if i == 0 else 0.8 + 0.4 * ((i * 0.618034) % 1.0)
        t = [(i % side) * spacing, 0.0, (i // side) * spacing]
        r = axis_angle([0.0, 1.0, 0.0], a)
        if jitter and i > 0:
            deg, dist, frac, _ = jitter
            r = matmul(axis_angle(unit(rng), math.radians(deg)), r)
            d = unit(rng)
            t = [t[q] + dist * d[q] for q in range(3)]
            s *= 1.0 + frac
        # Inverse: p_t = (1/s) R^T (p - t).
        m = [[r[q][p] / s for q in range(3)] for p in range(3)]
        mt = [-sum(m[p][q] * t[q] for q in range(3)) for p in range(3)]
        rows = [m[p] + [mt[p]] for p in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
        instances.append({"instance_id": str(i + 1), "transform": rows})
    with open(out, "w") as f:
        json.dump([{"template_id": template_id, "instances": instances}], f, indent=1)


if __name__ == "__main__":
    main()
