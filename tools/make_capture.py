#!/usr/bin/env python3
"""Turns a shared scene (NeRF-synthetic layout with instance masks, ../shared/data/scenes/*) into
a capture as a user's phone or drone would give it, for measuring the pipeline on photos:

- photos (JPEG, quality 90) with the effects of a real camera: exposure that differs from photo to
  photo (+-0.2 EV), white balance (+-3 % per channel), the lens's vignetting (-25 % at the
  corners) and sensor noise (shot and read noise), applied in linear light;
- COLMAP poses, intrinsics (one PINHOLE camera) and points from SIFT features and exhaustive
  matching (pycolmap's incremental mapper): the cameras are estimated, not the true ones;
- per-frame masks as a 2D segmenter writes them (SAM, Gaussian Grouping, SAGA):
  masks/<split>/<stem>.png with ids that mean nothing across frames, masks/<split>/<stem>.json
  naming each id's category, some instances missed (10 %, and every one under 40 pixels) and
  boundaries off by a pixel (each mask dilated or eroded at random); --global-masks keeps the
  scene's ids and writes instances.json instead;
- ground_truth.json: the scene's instances.json with every object pose mapped into COLMAP's
  frame, so pose errors can be measured against the truth. COLMAP's cameras are off by a few
  hundredths of the scene (cafe40: 0.021 units rms, 0.14 at worst, after the similarity that best
  aligns their centres with the true ones), and not by one similarity: each object is placed
  through the cameras that see it (its pose relative to each true camera, put in front of that
  camera as COLMAP estimated it, at the similarity's scale; the mean over those cameras weighted
  by the object's pixels, rotations averaged by their chordal mean), where the reconstruction,
  trained through those cameras, puts it. The one similarity alone would misplace cafe40's lego
  bricks by up to 2.8 % of their size (BENCHMARKS.md, "Where sharing pays");
- capture.json: the seed, each photo's exposure and white balance, the alignment residual and
  how far the per-object placement moved each object from the one similarity's.

The split follows what `instgs-vk` holds out of a COLMAP dataset: every 8th image by name.
With --clean DIR, the same capture without the photo effects (same COLMAP model, same masks) is
written to DIR too: the reference for what the effects cost. With --true-cameras DIR, an
existing capture is copied to DIR with COLMAP's cameras replaced by the true ones (poses mapped
into COLMAP's frame by the camera-centre similarity, the scene's focal length) and its ground
truth written through them: the reference for what COLMAP's camera errors cost; with --clean
DIR2 as well, a second such copy without the photo effects.

usage: make_capture.py SCENE_DIR OUT_DIR [--seed N] [--global-masks] [--clean DIR]
       make_capture.py SCENE_DIR OUT_DIR --truth-only [--global-masks]
         (an existing capture of SCENE_DIR: writes its ground truth again from its COLMAP model)
       make_capture.py SCENE_DIR OUT_DIR --true-cameras DIR [--clean DIR2] [--global-masks]
         (an existing capture of SCENE_DIR, copied to DIR with the true cameras; to DIR2 also
         without the photo effects)
       (tools/make-capture.sh runs it with pinned pycolmap, numpy and pillow)
"""
import argparse, json, os, shutil, sys

import numpy as np
import pycolmap
from PIL import Image

EV = 0.2  # exposure spread, +-EV stops
WB = 0.03  # white balance spread per channel
VIGNETTE = 0.25  # light lost at the image corners
SHOT, READ = 0.0004, 1e-5  # noise variance = SHOT * x + READ (linear light)
MISS, MIN_PIXELS = 0.10, 40  # segmenter: instances missed at random, and below this size
JPEG_QUALITY = 90
MIN_VIEW_PIXELS = 50  # a camera places an object when this many of its mask's pixels show


def srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def photo_effects(rgb8, rng):
    """The camera's effects on one photo (uint8 sRGB in and out) and what was drawn."""
    h, w, _ = rgb8.shape
    x = srgb_to_linear(rgb8.astype(np.float64) / 255.0)
    ev = rng.uniform(-EV, EV)
    wb = 1.0 + rng.uniform(-WB, WB, size=3)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    x = x * (2.0 ** ev) * wb[None, None, :] * (1.0 - VIGNETTE * r2)[:, :, None]
    x = x + rng.normal(size=x.shape) * np.sqrt(SHOT * np.clip(x, 0, None) + READ)
    out = np.round(linear_to_srgb(x) * 255.0).astype(np.uint8)
    return out, {"exposure_ev": ev, "white_balance": wb.tolist()}


def shift(m, dy, dx):
    out = np.zeros_like(m)
    h, w = m.shape
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = m[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def segmenter_masks(ids, rng):
    """Per-frame masks from a true id mask: random ids, misses, boundaries off by a pixel."""
    out = np.zeros(ids.shape, np.uint16)
    cats = {}
    present = [int(i) for i in np.unique(ids) if i != 0]
    new_ids = rng.choice(np.arange(1, 65536), size=len(present), replace=False)
    for true_id, new in zip(present, new_ids):
        m = ids == true_id
        if m.sum() < MIN_PIXELS or rng.uniform() < MISS:
            continue
        grow = rng.integers(-1, 2)  # -1 erode, 0 keep, 1 dilate (3x3)
        if grow != 0:
            nb = [shift(m, dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
            m = np.logical_or.reduce(nb) if grow > 0 else np.logical_and.reduce(nb)
        out[m & (out == 0)] = new
        cats[str(int(new))] = true_id
    return out, cats


def umeyama(src, dst):
    """s, R, t with dst ~ s R src + t (least squares)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    s_ = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_[2, 2] = -1
    r = u @ s_ @ vt
    s = np.trace(np.diag(d) @ s_) / (a ** 2).sum(1).mean()
    return s, r, md - s * r @ ms


def chordal_mean(rotations, weights):
    """The rotation nearest (Frobenius) to the weighted mean of the rotation matrices."""
    u, _, vt = np.linalg.svd(sum(w * r for w, r in zip(weights, rotations)))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    return u @ d @ vt


def scene_cameras(scene_dir):
    """The scene's true cameras by image path: camera-to-world (OpenCV axes) and horizontal field
    of view."""
    c2w, fov = {}, {}
    for split in ("train", "test"):
        t = json.load(open(os.path.join(scene_dir, f"transforms_{split}.json")))
        for f in t["frames"]:
            c2w[f["file_path"]] = np.array(f["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])
            fov[f["file_path"]] = f.get("camera_angle_x", t.get("camera_angle_x"))
    return c2w, fov


def colmap_to_scene(rec, record, c2w):
    """The registered images by name, their source paths and the similarity (s, R, t) that maps
    COLMAP's frame onto the scene's (camera centres, least squares)."""
    images = sorted(rec.images.values(), key=lambda i: i.name)
    sources = [record["photos"][i.name[:-4]]["source"] for i in images]
    est = np.array([i.projection_center() for i in images])
    return images, sources, est, umeyama(est, np.array([c2w[src][:3, 3] for src in sources]))


def write_truth(scene_dir, outs, rec, record, global_masks):
    """Ground truth in COLMAP's frame (module docstring): each object through the cameras that
    see it; records the camera-centre alignment and how far that moved the objects."""
    scene = json.load(open(os.path.join(scene_dir, "instances.json")))
    c2w_true, _ = scene_cameras(scene_dir)
    images, sources, est, (s, r, t) = colmap_to_scene(rec, record, c2w_true)
    true = np.array([c2w_true[src][:3, 3] for src in sources])
    residual = np.linalg.norm((s * (r @ est.T)).T + t - true, axis=1)
    record["alignment"] = {"scale": s, "rms_camera_centre_error": float(np.sqrt((residual ** 2).mean())),
                           "max_camera_centre_error": float(residual.max())}
    # COLMAP's frame from the scene's by the similarity: x_colmap = (R^T (x_world - t)) / s.
    inv = np.eye(4)
    inv[:3, :3] = r.T / s
    inv[:3, 3] = -(r.T @ t) / s
    # Per camera: the scene's world into the true camera, shrunk to COLMAP's scale, out of the
    # camera as COLMAP placed it (OpenCV axes both).
    shrink = np.diag([1 / s, 1 / s, 1 / s, 1.0])
    through = []
    for img, src in zip(images, sources):
        c2w_colmap = np.linalg.inv(np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]]))
        ids = np.array(Image.open(os.path.join(scene_dir, "masks", src + ".png")))
        through.append((c2w_colmap @ shrink @ np.linalg.inv(c2w_true[src]), np.bincount(ids.ravel())))
    gt = json.loads(json.dumps(scene))
    moved = []
    for g in gt["groups"]:
        size = float(np.linalg.norm(np.subtract(*g["canonical_bbox"][::-1])))
        for i in g["instances"]:
            x = np.array(i["object_to_world"])
            # Points of the object in the scene's world: its centre, and where it stands (the
            # shared scenes' "translation"; a scene may leave it out).
            points = {k: np.append(i[k], 1.0) for k in ("center_world", "translation") if k in i}
            seen = [(m, int(px[i["id"]])) for m, px in through if i["id"] < len(px) and px[i["id"]] >= MIN_VIEW_PIXELS]
            if seen:
                ms, ws = [m for m, _ in seen], np.array([w for _, w in seen], float)
                placed = [m @ x for m in ms]
                linear = np.cbrt(np.linalg.det(x[:3, :3])) / s
                o2w = np.eye(4)
                o2w[:3, :3] = linear * chordal_mean([p[:3, :3] / linear for p in placed], ws)
                o2w[:3, 3] = sum(w * p[:3, 3] for w, p in zip(ws, placed)) / ws.sum()
                placed_points = {k: sum(w * (m @ v)[:3] for w, m in zip(ws, ms)) / ws.sum() for k, v in points.items()}
            else:  # no photo shows it: the one similarity
                o2w, placed_points = inv @ x, {k: (inv @ v)[:3] for k, v in points.items()}
            one = (inv @ points["center_world"])[:3]
            moved.append(float(np.linalg.norm(placed_points["center_world"] - one) * s / (size * i.get("scale", 1.0))))
            i["object_to_world"] = o2w.tolist()
            for k, v in placed_points.items():
                i[k] = v.tolist()
            i["scale"] = i.get("scale", 1.0) / s
            i["views"] = len(seen)
    gt["frame"] = ("COLMAP's (sparse/0): each object through the cameras that see it, at the scale "
                   "of the camera-centre alignment in capture.json")
    record["alignment"]["objects_moved_from_the_similarity"] = {
        "max_fraction_of_size": max(moved), "mean_fraction_of_size": float(np.mean(moved))}
    for o in outs:
        json.dump(gt, open(os.path.join(o, "instances.json" if global_masks else "ground_truth.json"), "w"), indent=1)


def true_cameras(scene_dir, cap, out, global_masks, clean=None):
    """A copy of the capture `cap` in `out` whose cameras are the scene's true ones, in COLMAP's
    frame (module docstring); with `clean`, a second copy there whose photos are the scene's
    renders without the photo effects (JPEG as the capture's)."""
    for o in [out] + ([clean] if clean else []):
        if os.path.exists(o):
            sys.exit(f"{o}: exists; choose another folder")
    rec = pycolmap.Reconstruction(os.path.join(cap, "sparse", "0"))
    record = json.load(open(os.path.join(cap, "capture.json")))
    before = record["alignment"]["rms_camera_centre_error"]
    c2w, fov = scene_cameras(scene_dir)
    images, sources, _, (s, r, t) = colmap_to_scene(rec, record, c2w)
    for img, src in zip(images, sources):
        cam = rec.cameras[img.camera_id]
        if cam.model.name != "PINHOLE":
            sys.exit(f"{cap}: camera {img.camera_id} is {cam.model.name}; --true-cameras writes PINHOLE cameras only")
        # COLMAP's frame from the scene's: x_colmap = R^T (x_world - t) / s.
        centre = r.T @ (c2w[src][:3, 3] - t) / s
        world_from_cam = r.T @ c2w[src][:3, :3]
        rec.frames[img.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(world_from_cam.T), -world_from_cam.T @ centre)
        f = 0.5 * cam.width / np.tan(0.5 * fov[src])
        cam.params = [f, f, cam.width / 2, cam.height / 2]
    os.makedirs(os.path.join(out, "sparse", "0"))
    rec.write(os.path.join(out, "sparse", "0"))
    for d in ("images", "masks"):
        shutil.copytree(os.path.join(cap, d), os.path.join(out, d))
    record["true_cameras_from"] = cap
    write_truth(scene_dir, [out], rec, record, global_masks)
    json.dump(record, open(os.path.join(out, "capture.json"), "w"), indent=1)
    print(f"{out}: {cap} with the true cameras; camera centres {before:.4f} units rms from the truth before, "
          f"{record['alignment']['rms_camera_centre_error']:.1e} now")
    if clean:
        shutil.copytree(out, clean)
        for name, photo in record["photos"].items():
            path = os.path.join(clean, "images", name + ".jpg")
            if os.path.exists(path):
                rgb = np.array(Image.open(os.path.join(scene_dir, photo["source"] + ".png")).convert("RGB"))
                Image.fromarray(rgb).save(path, quality=JPEG_QUALITY)
        print(f"{clean}: the same without the photo effects")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--global-masks", action="store_true")
    ap.add_argument("--clean")
    ap.add_argument("--truth-only", action="store_true")
    ap.add_argument("--true-cameras")
    a = ap.parse_args()
    if a.true_cameras:
        if a.truth_only:
            sys.exit("--true-cameras copies one existing capture; it does not take --truth-only")
        true_cameras(a.scene, a.out, a.true_cameras, a.global_masks, a.clean)
        return
    if a.truth_only:
        if a.clean:
            sys.exit("--truth-only writes one capture's truth; run it on the --clean folder too")
        for need in ("capture.json", os.path.join("sparse", "0")):
            if not os.path.exists(os.path.join(a.out, need)):
                sys.exit(f"{a.out}: no {need}; --truth-only needs a capture this script made")
        record = json.load(open(os.path.join(a.out, "capture.json")))
        write_truth(a.scene, [a.out], pycolmap.Reconstruction(os.path.join(a.out, "sparse", "0")), record, a.global_masks)
        json.dump(record, open(os.path.join(a.out, "capture.json"), "w"), indent=1)
        moved = record["alignment"]["objects_moved_from_the_similarity"]
        print(f"{a.out}: ground truth written again; objects {100 * moved['mean_fraction_of_size']:.2f} % of their "
              f"size from the camera-centre similarity's placement on average, {100 * moved['max_fraction_of_size']:.2f} % at most")
        return
    rng = np.random.default_rng(a.seed)
    scene = json.load(open(os.path.join(a.scene, "instances.json")))
    group_of = {i["id"]: g["name"] for g in scene["groups"] for i in g["instances"]}
    frames = []
    for split in ("train", "test"):
        t = json.load(open(os.path.join(a.scene, f"transforms_{split}.json")))
        frames += [(split, f) for f in t["frames"]]
    if os.path.exists(a.out):
        sys.exit(f"{a.out}: exists; choose another folder")
    outs = [a.out] + ([a.clean] if a.clean else [])
    for o in outs:
        os.makedirs(os.path.join(o, "images"))
    record = {"scene": os.path.abspath(a.scene), "seed": a.seed, "photos": {}}
    for k, (split, f) in enumerate(frames):
        name = f"img_{k:03d}"
        rgb = np.array(Image.open(os.path.join(a.scene, f["file_path"] + ".png")).convert("RGB"))
        shot, drawn = photo_effects(rgb, rng)
        Image.fromarray(shot).save(os.path.join(a.out, "images", name + ".jpg"), quality=JPEG_QUALITY)
        if a.clean:
            Image.fromarray(rgb).save(os.path.join(a.clean, "images", name + ".jpg"), quality=JPEG_QUALITY)
        record["photos"][name] = dict(drawn, source=f["file_path"])
    # COLMAP: SIFT, exhaustive matching, incremental mapping, on the photos with effects.
    work = os.path.join(a.out, "colmap-work")
    os.makedirs(work)
    db = os.path.join(work, "database.db")
    # Small photos (320x240) give few SIFT features with COLMAP's defaults: a lower peak
    # threshold, domain-size pooling, guided matching and a mapper that accepts fewer inliers
    # register them all (the settings COLMAP's documentation suggests for few-texture scenes).
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.peak_threshold = 0.004
    extraction.sift.domain_size_pooling = True
    pycolmap.extract_features(db, os.path.join(a.out, "images"), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.guided_matching = True
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.random_seed = a.seed
    mapping.mapper.init_min_num_inliers = 50
    mapping.mapper.abs_pose_min_num_inliers = 15
    mapping.mapper.abs_pose_min_inlier_ratio = 0.15
    maps = pycolmap.incremental_mapping(db, os.path.join(a.out, "images"), work, options=mapping)
    if not maps:
        sys.exit("COLMAP registered no images")
    rec = max(maps.values(), key=lambda r: r.num_reg_images())
    sparse = os.path.join(a.out, "sparse", "0")
    os.makedirs(sparse)
    rec.write_binary(sparse)
    shutil.rmtree(work)
    names = sorted(img.name for img in rec.images.values())
    record["registered"] = len(names)
    record["photos_taken"] = len(frames)
    write_truth(a.scene, outs, rec, record, a.global_masks)
    # Masks: every photo COLMAP registered, in the split instgs-vk will put it in.
    for k, n in enumerate(names):
        stem = n[:-4]
        split = "test" if k % 8 == 0 else "train"
        src = record["photos"][stem]["source"]
        ids = np.array(Image.open(os.path.join(a.scene, "masks", src + ".png")))
        for o in outs:
            os.makedirs(os.path.join(o, "masks", split), exist_ok=True)
        if a.global_masks:
            m, cats = ids.astype(np.uint16), None
        else:
            m, cats = segmenter_masks(ids, rng)
        for o in outs:
            Image.fromarray(m).save(os.path.join(o, "masks", split, stem + ".png"))
            if cats is not None:
                json.dump({i: group_of[c] for i, c in cats.items()}, open(os.path.join(o, "masks", split, stem + ".json"), "w"))
    for o in outs:
        json.dump(record, open(os.path.join(o, "capture.json"), "w"), indent=1)
    if a.clean:
        shutil.copytree(os.path.join(a.out, "sparse"), os.path.join(a.clean, "sparse"))
        # Only the photos COLMAP registered, as in the capture.
        for f in os.listdir(os.path.join(a.clean, "images")):
            if f not in names:
                os.remove(os.path.join(a.clean, "images", f))
    for f in os.listdir(os.path.join(a.out, "images")):
        if f not in names:
            os.remove(os.path.join(a.out, "images", f))
    al = record["alignment"]
    print(f"{a.out}: {len(names)} of {len(frames)} photos registered; camera centres within "
          f"{al['max_camera_centre_error']:.4f} (rms {al['rms_camera_centre_error']:.4f}) scene units of the truth; "
          f"objects placed through the cameras that see them, up to "
          f"{100 * al['objects_moved_from_the_similarity']['max_fraction_of_size']:.2f} % of their size from the similarity's placement")


if __name__ == "__main__":
    main()
