#!/usr/bin/env python3
"""How far a capture's training cameras are from the truth, before and after a run's camera
refinement (instgs-vk's RUN/cameras.json; crate::train::cameras).

    camera_error.py CAPTURE/sparse/0 TRUTH/sparse/0 RUN/cameras.json [--json OUT]

CAPTURE is a capture made by tools/make-capture.sh (COLMAP's cameras), TRUTH its
--true-cameras copy (the true cameras in COLMAP's frame). Per training view of cameras.json: the
angle of R_est R_true^T (degrees) and the distance of the camera centres (the capture's units),
for COLMAP's camera and for the corrected one, viewmat = [exp(w) | tau] viewmat_colmap (OpenCV
world-to-camera, w and tau in the camera's frame). Prints rms / median / max of each. Needs
numpy and pycolmap (out/capture-venv).
"""
import argparse
import json
import os

import numpy as np
import pycolmap


def viewmats(model_dir):
    rec = pycolmap.Reconstruction(model_dir)
    out = {}
    for im in rec.images.values():
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        v = np.eye(4)
        v[:3, :4] = pose.matrix()
        out[os.path.splitext(im.name)[0]] = v
    return out


def rotation(w):
    t = np.linalg.norm(w)
    if t < 1e-12:
        return np.eye(3)
    k = w / t
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx


def errors(v, truth):
    # |Ra - Rb|_F = 2 sqrt(2) sin(angle / 2): exact near 0, where acos of the trace is not.
    frob = np.linalg.norm(v[:3, :3] - truth[:3, :3])
    angle = np.degrees(2 * np.arcsin(min(frob / (2 * np.sqrt(2)), 1.0)))
    centre = lambda m: -m[:3, :3].T @ m[:3, 3]
    return angle, np.linalg.norm(centre(v) - centre(truth))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture")
    ap.add_argument("truth")
    ap.add_argument("cameras")
    ap.add_argument("--json")
    a = ap.parse_args()
    est, true = viewmats(a.capture), viewmats(a.truth)
    views = json.load(open(a.cameras))["views"]
    rows = {"colmap": [], "corrected": []}
    for e in views:
        name = e["name"]
        if name not in est or name not in true:
            raise SystemExit(f"{a.cameras}: view {name} is not in both models")
        corr = np.eye(4)
        corr[:3, :3] = rotation(np.array(e["rotation"], dtype=float))
        corr[:3, 3] = e["translation"]
        rows["colmap"].append(errors(est[name], true[name]))
        rows["corrected"].append(errors(corr @ est[name], true[name]))
    summary = {}
    for k, r in rows.items():
        r = np.array(r)
        summary[k] = {
            f"{what}_{stat}": float(f(r[:, i]))
            for i, what in enumerate(["rotation_deg", "centre"])
            for stat, f in [("rms", lambda x: np.sqrt(np.mean(x**2))), ("median", np.median), ("max", np.max)]
        }
        s = summary[k]
        print(
            f"{k:>9}: rotation rms {s['rotation_deg_rms']:.4f} deg (median {s['rotation_deg_median']:.4f}, max "
            f"{s['rotation_deg_max']:.4f}); centre rms {s['centre_rms']:.5f} (median {s['centre_median']:.5f}, "
            f"max {s['centre_max']:.5f})"
        )
    summary["views"] = len(views)
    if a.json:
        json.dump(summary, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
