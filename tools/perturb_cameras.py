#!/usr/bin/env python3
"""A copy of a COLMAP capture whose training cameras are moved off their poses at random, the
held-out ones (every 8th image by name, as instgs-vk holds out) left as they are: for measuring
what camera refinement ([cameras] in the training config) recovers when only the training poses
are wrong, e.g. on tools/make-capture.sh's --true-cameras copy.

    perturb_cameras.py CAPTURE OUT [--rotation-deg 0.3] [--centre 0.02] [--seed 0]

Each training camera is rotated about its centre by an angle drawn from N(0, rotation-deg) about
a random axis, and its centre moved by a random direction times N(0, centre) (the capture's
units). Images, masks, points and ground truth are copied unchanged. Needs numpy and pycolmap
(out/capture-venv).
"""
import argparse
import json
import os
import shutil

import numpy as np
import pycolmap


def rotation(axis, angle):
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture")
    ap.add_argument("out")
    ap.add_argument("--rotation-deg", type=float, default=0.3)
    ap.add_argument("--centre", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if os.path.exists(a.out):
        raise SystemExit(f"{a.out}: exists; choose another folder")
    rng = np.random.default_rng(a.seed)
    rec = pycolmap.Reconstruction(os.path.join(a.capture, "sparse", "0"))
    names = sorted(im.name for im in rec.images.values())
    held_out = {n for k, n in enumerate(names) if k % 8 == 0}
    moved = {}
    for im in sorted(rec.images.values(), key=lambda im: im.name):
        if im.name in held_out:
            continue
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        m = pose.matrix()
        r, t = m[:, :3], m[:, 3]
        centre = -r.T @ t
        angle = np.radians(rng.normal(0.0, a.rotation_deg))
        direction = rng.normal(size=3)
        shift = direction / np.linalg.norm(direction) * abs(rng.normal(0.0, a.centre))
        r2 = r @ rotation(rng.normal(size=3), angle).T
        c2 = centre + shift
        rec.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(r2), -r2 @ c2)
        moved[os.path.splitext(im.name)[0]] = {"rotation_deg": float(abs(np.degrees(angle))), "centre": float(np.linalg.norm(shift))}
    os.makedirs(os.path.join(a.out, "sparse", "0"))
    rec.write(os.path.join(a.out, "sparse", "0"))
    for d in ("images", "masks"):
        shutil.copytree(os.path.join(a.capture, d), os.path.join(a.out, d))
    for f in ("ground_truth.json", "instances.json"):
        if os.path.exists(os.path.join(a.capture, f)):
            shutil.copy(os.path.join(a.capture, f), os.path.join(a.out, f))
    record = json.load(open(os.path.join(a.capture, "capture.json")))
    record["perturbed_from"] = {"capture": a.capture, "seed": a.seed, "rotation_deg": a.rotation_deg,
                                "centre": a.centre, "moved": moved}
    json.dump(record, open(os.path.join(a.out, "capture.json"), "w"), indent=1)
    rot = np.array([v["rotation_deg"] for v in moved.values()])
    cen = np.array([v["centre"] for v in moved.values()])
    print(f"{a.out}: {len(moved)} training cameras moved (rotation rms {np.sqrt(np.mean(rot**2)):.3f} deg, "
          f"centre rms {np.sqrt(np.mean(cen**2)):.4f}), {len(held_out)} held out unchanged")


if __name__ == "__main__":
    main()
