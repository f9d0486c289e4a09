#!/usr/bin/env python3
"""A scene of cafe40's kind with other objects (issue 53: "other scenes of this kind, with other
objects, will be used to check the result"): cafe40's own trained background (the plain scene's
Gaussians its segmentation left unlabelled: floor, walls, the objects' shadows) with 40 copies of
three objects that are not mugs, bricks or ducks — 20 playbots (`playbot_lod6.ply`, on the mugs'
spots), 12 bikers (`biker.ply`, on the bricks') and 8 guitars (`guitar.ply`, on the ducks') from
`../shared/data/splats` — each copy turned about the up axis at random and scaled 0.96–1.05.

With LAYOUT `rows` (a car park or a hall of chairs seen by a drone) the copies stand instead
in six rows of eight, all facing one way (±4° each): three rows of playbots, two of bikers, one
of guitars, 48 in all, 0.55 units apart along a row and 0.6 between rows; OUT also gets the
cameras, 96 training and 12 test views (`transforms_{train,test}.json`, NeRF-synthetic: OpenGL
camera-to-world, world up +z, 480x360 at 45° across like cafe40's) 4.5-6.5 units from points
near the centre at elevations 35-65°, so most views see most copies, each a few dozen pixels.

Writes into OUT: background.ply, one template PLY per object (SH degree 3 like the background,
bands the source lacks zero; biker and guitar cut to their 8 000 and 6 000 most opaque-and-large
Gaussians, as a 0.5-unit figure needs no more at 480x360) and scene_graph.json (the prototype's
convention: world -> template). `tools/other-objects.sh` composes, renders and trains it.

usage: other_objects_scene.py PLAIN.ply LABELS.json INSTANCES.json SPLATS_DIR OUT_DIR [spots|rows]
       (PLAIN.ply, LABELS.json: a cafe40 run's point_cloud.ply and labels.json;
        INSTANCES.json: cafe40's instances.json, for the spots)
"""
import json
import math
import random
import sys

import numpy as np
from orbit_transforms import look_at
from plyfile import PlyData, PlyParseError

NAMES = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)] + [
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
# name: (file, Gaussians kept or None for all, scale, the cafe40 group whose spots it takes)
OBJECTS = {
    "playbot": ("playbot_lod6.ply", None, 0.18, "mug"),
    "biker": ("biker.ply", 8000, 0.17, "lego"),
    "guitar": ("guitar.ply", 6000, 0.12, "duck"),
}
# The rows layout: (object, rows of it), front to back.
ROWS = [("playbot", 3), ("biker", 2), ("guitar", 1)]
PER_ROW, ALONG, ACROSS = 8, 0.55, 0.6


def read(path):
    """The vertex element's properties (all float32, as the Inria layout's) by name, and rows."""
    try:
        vertex = PlyData.read(path)["vertex"]
    except (OSError, KeyError, PlyParseError) as e:
        sys.exit(f"{path}: not a PLY with a vertex element ({e})")
    props = [p.name for p in vertex.properties]
    if any(vertex.data.dtype[p] != np.dtype("<f4") and vertex.data.dtype[p] != np.dtype(">f4") for p in props):
        sys.exit(f"{path}: only float properties are read here")
    arr = np.stack([vertex.data[p].astype("<f4") for p in props], axis=1)
    return {p: i for i, p in enumerate(props)}, arr


def write_degree3(path, props, arr):
    """The Inria layout at SH degree 3 (f_rest channel-major, missing bands zero)."""
    out = np.zeros((len(arr), len(NAMES)), np.float32)
    for q in NAMES:
        if q in props and not q.startswith("f_rest_"):
            out[:, NAMES.index(q)] = arr[:, props[q]]
    bands = sum(q.startswith("f_rest_") for q in props) // 3
    for ch in range(3):
        for k in range(bands):
            out[:, NAMES.index(f"f_rest_{ch * 15 + k}")] = arr[:, props[f"f_rest_{ch * bands + k}"]]
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(out)}\n"
    header += "".join(f"property float {q}\n" for q in NAMES) + "end_header\n"
    open(path, "wb").write(header.encode() + out.astype("<f4").tobytes())


def row_spots():
    """Object name -> its spots in the rows layout (x along a row, y across, on the floor z = 0)."""
    spots, row, rows = {}, 0, sum(n for _, n in ROWS)
    for name, n in ROWS:
        for _ in range(n):
            y = (row - (rows - 1) / 2) * ACROSS
            spots.setdefault(name, []).extend([[(c - (PER_ROW - 1) / 2) * ALONG, y, 0.0] for c in range(PER_ROW)])
            row += 1
    return spots


def drone_cameras(out):
    """transforms_train.json (96 views) and transforms_test.json (12) for the rows layout."""
    width, height, fov = 480, 360, math.pi / 4
    focal = width / 2 / math.tan(fov / 2)
    for split, count, seed in (("train", 96, 11), ("test", 12, 12)):
        rng, frames = random.Random(seed), []
        for k in range(count):
            azimuth = k * math.pi * (3.0 - math.sqrt(5.0)) + rng.uniform(0.0, 0.3)
            elevation = math.radians(35.0 + 30.0 * rng.random())
            distance, r, a = rng.uniform(4.5, 6.5), 1.0 * math.sqrt(rng.random()), rng.uniform(0.0, 2.0 * math.pi)
            target = np.array([r * math.cos(a), r * math.sin(a), 0.1])
            eye = target + distance * np.array([math.cos(elevation) * math.cos(azimuth),
                                                math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
            m = look_at(eye.tolist(), target.tolist(), [0.0, 0.0, 1.0])
            frames.append({"file_path": f"{split}/r_{k:03d}", "transform_matrix": m})
        json.dump({"camera_angle_x": fov, "w": width, "h": height, "fl_x": focal, "fl_y": focal,
                   "cx": width / 2, "cy": height / 2, "frames": frames},
                  open(f"{out}/transforms_{split}.json", "w"), indent=1)


def main():
    if len(sys.argv) not in (6, 7) or sys.argv[6:] not in ([], ["spots"], ["rows"]):
        sys.exit("\n".join(__doc__.strip().splitlines()[-3:]))
    plain, labels, instances, splats, out = sys.argv[1:6]
    rows = sys.argv[6:] == ["rows"]
    props, arr = read(plain)
    lab = np.array(json.load(open(labels))["labels"])
    if len(lab) != len(arr):
        sys.exit(f"{labels}: {len(lab)} labels for the {len(arr)} Gaussians of {plain}")
    write_degree3(f"{out}/background.ply", props, arr[lab == 0])
    if rows:
        spots = row_spots()
        drone_cameras(out)
    else:
        cafe40 = {g["name"]: [i["translation"] for i in g["instances"]] for g in json.load(open(instances))["groups"]}
        spots = {name: cafe40[where] for name, (_, _, _, where) in OBJECTS.items()}
    rng = random.Random(7)
    graph, next_id = [], 0
    for name, (file, keep, scale, _) in OBJECTS.items():
        props, arr = read(f"{splats}/{file}")
        if keep:
            opacity = 1.0 / (1.0 + np.exp(-arr[:, props["opacity"]]))
            volume = np.exp(arr[:, props["scale_0"]] + arr[:, props["scale_1"]] + arr[:, props["scale_2"]])
            arr = arr[np.argsort(-opacity * volume ** (2.0 / 3.0))[:keep]]
        write_degree3(f"{out}/{name}.ply", props, arr)
        # The sources' up is -y, their base at the 98th percentile of y: the base's centre goes
        # onto the spot, up onto +z.
        xyz = arr[:, [props["x"], props["y"], props["z"]]]
        lo, hi = np.percentile(xyz, 2, axis=0), np.percentile(xyz, 98, axis=0)
        base = np.array([(lo[0] + hi[0]) / 2, hi[1], (lo[2] + hi[2]) / 2])
        up = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
        group = {"template_id": name, "instances": []}
        for spot in spots[name]:
            next_id += 1
            yaw = math.radians(rng.uniform(-4.0, 4.0)) if rows else rng.uniform(0.0, 2.0 * math.pi)
            s = scale * rng.uniform(0.96, 1.05)
            turn = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
            m = np.eye(4)
            m[:3, :3] = s * turn @ up
            m[:3, 3] = np.array([spot[0], spot[1], 0.0]) - m[:3, :3] @ base
            group["instances"].append({"instance_id": str(next_id), "transform": np.linalg.inv(m).tolist()})
        graph.append(group)
    json.dump(graph, open(f"{out}/scene_graph.json", "w"), indent=1)


if __name__ == "__main__":
    main()
