#!/usr/bin/env python3
"""A copy of a NeRF-synthetic scene as a lens with distortion would have photographed it: every
image (bilinear) and mask (nearest) remapped through OpenCV's radial-tangential model with the
given k1, k2, p1, p2, and those written into the transforms (nerfstudio's keys, camera_model
OPENCV). The focal length grows just enough that every photo pixel sees the original image (no
blank border), and is written as fl_x / fl_y. Cameras, points and instances.json are kept.

For measuring undistortion on load (BENCHMARKS.md): train on OUT and on SCENE with the same
iterations; their held-out PSNR should agree.

usage: distort_dataset.py SCENE OUT [--k1 -0.25] [--k2 0.08] [--p1 0.002] [--p2 -0.001]
       (needs numpy and pillow: tools/make-capture.sh's environment has both)
"""
import argparse, json, os, shutil

import numpy as np
from PIL import Image


def distort(x, y, k1, k2, p1, p2):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def undistort(xd, yd, k1, k2, p1, p2):
    """The pinhole point whose distortion is (xd, yd): OpenCV's fixed-point iteration."""
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y


def source_points(w, h, f, cx, cy, m, lens):
    """Where each pixel of the distorted photo (focal f * m) lies in the original (focal f)."""
    v, u = np.mgrid[0:h, 0:w] + 0.5
    xd, yd = (u - cx) / (f * m), (v - cy) / (f * m)
    x, y = undistort(xd, yd, *lens)
    return f * x + cx, f * y + cy


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--k1", type=float, default=-0.25)
    ap.add_argument("--k2", type=float, default=0.08)
    ap.add_argument("--p1", type=float, default=0.002)
    ap.add_argument("--p2", type=float, default=-0.001)
    a = ap.parse_args()
    lens = (a.k1, a.k2, a.p1, a.p2)
    os.makedirs(a.out)
    for f in ("points3d.ply", "instances.json"):
        if os.path.exists(os.path.join(a.scene, f)):
            shutil.copy(os.path.join(a.scene, f), a.out)
    for split in ("train", "test"):
        t = json.load(open(os.path.join(a.scene, f"transforms_{split}.json")))
        w, h, f = int(t["w"]), int(t["h"]), float(t["fl_x"])
        cx, cy = t.get("cx", w / 2), t.get("cy", h / 2)
        assert abs(t.get("fl_y", f) - f) < 1e-6, "one focal length expected"
        # The smallest focal scale whose photo sees only the original image.
        lo, hi = 0.2, 5.0
        for _ in range(50):
            m = (lo * hi) ** 0.5
            us, vs = source_points(w, h, f, cx, cy, m, lens)
            inside = (us >= 0).all() and (us <= w).all() and (vs >= 0).all() and (vs <= h).all()
            lo, hi = (lo, m) if inside else (m, hi)
        us, vs = source_points(w, h, f, cx, cy, hi, lens)
        xi, yi = np.clip(us - 0.5, 0, w - 1), np.clip(vs - 0.5, 0, h - 1)
        x0, y0 = np.floor(xi).astype(int), np.floor(yi).astype(int)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        fx, fy = (xi - x0)[..., None], (yi - y0)[..., None]
        for frame in t["frames"]:
            rel = frame["file_path"]
            src = np.asarray(Image.open(os.path.join(a.scene, rel + ".png")).convert("RGB"), np.float64)
            img = ((src[y0, x0] * (1 - fx) + src[y0, x1] * fx) * (1 - fy)
                   + (src[y1, x0] * (1 - fx) + src[y1, x1] * fx) * fy)
            os.makedirs(os.path.dirname(os.path.join(a.out, rel)), exist_ok=True)
            Image.fromarray(np.round(img).astype(np.uint8)).save(os.path.join(a.out, rel + ".png"))
            mask = os.path.join(a.scene, "masks", rel + ".png")
            if os.path.exists(mask):
                ids = np.asarray(Image.open(mask))
                near = ids[np.minimum(np.floor(vs), h - 1).astype(int), np.minimum(np.floor(us), w - 1).astype(int)]
                os.makedirs(os.path.join(a.out, "masks", split), exist_ok=True)
                Image.fromarray(near.astype(ids.dtype)).save(os.path.join(a.out, "masks", rel + ".png"))
        t["fl_x"] = t["fl_y"] = f * hi
        t["camera_angle_x"] = 2 * np.arctan(w / (2 * f * hi))
        t.update({"camera_model": "OPENCV", "k1": a.k1, "k2": a.k2, "p1": a.p1, "p2": a.p2})
        json.dump(t, open(os.path.join(a.out, f"transforms_{split}.json"), "w"), indent=1)
        print(f"{split}: {len(t['frames'])} photos, focal {f:.2f} -> {f * hi:.2f} px, k1 {a.k1} k2 {a.k2} p1 {a.p1} p2 {a.p2}")


if __name__ == "__main__":
    main()
