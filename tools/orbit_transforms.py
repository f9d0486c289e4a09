#!/usr/bin/env python3
"""Writes NeRF-synthetic transforms_train.json and transforms_test.json with N and M cameras on
a ring around CENTER (OpenGL camera-to-world, row-major), world up -Y (COLMAP-style captures),
test cameras offset half a step from the training ones.

usage: orbit_transforms.py OUT_DIR N M CX CY CZ DISTANCE ELEVATION_DEG WIDTH HEIGHT FOV_X_DEG
"""
import json
import math
import os
import sys


def norm(v):
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def look_at(eye, target, up):
    """Row-major OpenGL camera-to-world (x right, y up, z back) at `eye` looking at `target`."""
    f = norm([target[q] - eye[q] for q in range(3)])
    r = norm(cross(f, up))
    u = cross(r, f)
    return [[r[q], u[q], -f[q], eye[q]] for q in range(3)] + [[0.0, 0.0, 0.0, 1.0]]


def frames(split, n, phase, center, dist, elev, elev_step):
    out = []
    for i in range(n):
        az = 2 * math.pi * (i + phase) / n
        el = math.radians(elev + elev_step * ((i % 3) - 1))
        # World up is -Y: the camera rises towards -Y.
        eye = [center[0] + dist * math.cos(el) * math.cos(az), center[1] - dist * math.sin(el),
               center[2] + dist * math.cos(el) * math.sin(az)]
        m = look_at(eye, center, [0.0, -1.0, 0.0])
        out.append({"file_path": f"{split}/r_{i:03d}", "transform_matrix": m})
    return out


def main():
    a = sys.argv[1:]
    out, n, m = a[0], int(a[1]), int(a[2])
    center, dist, elev = [float(x) for x in a[3:6]], float(a[6]), float(a[7])
    w, h, fov = int(a[8]), int(a[9]), math.radians(float(a[10]))
    os.makedirs(out, exist_ok=True)
    for split, count, phase in [("train", n, 0.0), ("test", m, 0.5 * n / max(m, 1))]:
        tf = {"camera_angle_x": fov, "w": w, "h": h, "frames": frames(split, count, phase, center, dist, elev, 10.0)}
        with open(os.path.join(out, f"transforms_{split}.json"), "w") as f:
            json.dump(tf, f, indent=1)


if __name__ == "__main__":
    main()
