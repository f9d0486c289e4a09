#!/usr/bin/env python3
"""Makes a copy of a shared scene whose instance masks carry per-frame ids with no cross-frame
meaning, as a 2D segmenter (SAM) would give: every frame renumbers its instances at random
(1..65535) and writes masks/<split>/<stem>.json = {"<id>": "<group name>"}. Images, cameras and
points are symlinked. The secret key (per split and frame: new id -> true id) goes to KEY.json,
for tools/eval_association.py only; `instgs-vk segment --per-frame-ids` never sees it.

usage: scramble_masks.py SCENE_DIR OUT_DIR KEY.json [--seed N]      (needs pillow and numpy)
"""
import json, os, random, sys

import numpy as np
from PIL import Image


def main():
    args = sys.argv[1:]
    seed = 0
    if "--seed" in args:
        i = args.index("--seed")
        seed = int(args[i + 1])
        del args[i : i + 2]
    src, dst, key_path = args
    rng = random.Random(seed)
    groups = json.load(open(os.path.join(src, "instances.json")))["groups"]
    category = {inst["id"]: g["name"] for g in groups for inst in g["instances"]}
    os.makedirs(dst, exist_ok=True)
    for name in os.listdir(src):
        if name not in ("masks", "instances.json") and not os.path.exists(os.path.join(dst, name)):
            os.symlink(os.path.abspath(os.path.join(src, name)), os.path.join(dst, name))
    key = {}
    for split in sorted(os.listdir(os.path.join(src, "masks"))):
        os.makedirs(os.path.join(dst, "masks", split), exist_ok=True)
        key[split] = {}
        for f in sorted(os.listdir(os.path.join(src, "masks", split))):
            if not f.endswith(".png"):
                continue
            m = np.array(Image.open(os.path.join(src, "masks", split, f)))
            ids = [int(i) for i in np.unique(m) if i != 0]
            new = rng.sample(range(1, 65536), len(ids))
            out = np.zeros(m.shape, dtype=np.uint16)
            for old, n in zip(ids, new):
                out[m == old] = n
            Image.fromarray(out).save(os.path.join(dst, "masks", split, f))
            stem = f[:-4]
            cats = {str(n): category[old] for old, n in zip(ids, new)}
            json.dump(cats, open(os.path.join(dst, "masks", split, stem + ".json"), "w"))
            key[split][stem] = {str(n): old for old, n in zip(ids, new)}
    json.dump(key, open(key_path, "w"))


main()
