#!/usr/bin/env python3
"""Small valid inputs for the fuzz targets (fuzz/make-seeds.sh runs this; standard library only).

  scene OUT.ply             three Gaussians, SH degree 1, binary little-endian Inria PLY
  ascii-scene OUT.ply       the same as ASCII
  sog META.json OUT         a SOG folder packed as sog_parse reads it (u16 length + meta.json,
                            then u32 length + bytes per file, in the order meta.json names them)
  points DIR                points3d.ply seeds (binary float, ASCII with uchar colours)
  colmap DIR                one camera, one image, two points: text and binary, each file
                            prefixed by colmap_parse's pick byte (file & 3, binary & 4)
  json DIR DATASET          transforms, instances.json, scene graph and labels, pick-prefixed
  configs DIR CONFIGS       the shipped configurations, pick-prefixed
  mask DIR                  4x4 masks: 8-bit and 16-bit grey PNG
  checkpoint IN OUT         a plain checkpoint cut down to its first two Gaussians
  gltf-files TINY.gltf SEEDS REGRESSIONS FILES
                            a .gltf naming its buffer file beside it, and hostile names for it
  sog-files META.json SEEDS REGRESSIONS FILES
                            a SOG meta.json naming its images beside it, and hostile names
"""
import base64
import json
import os
import struct
import sys
import zlib

PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{j}" for j in range(9)] + [
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def rows():
    out = []
    for i in range(3):
        r = [0.1 * i, -0.2 * i, 0.3, 0, 0, 0, 0.5, -0.25, 0.125] + [0.01 * (j - 4) for j in range(9)]
        r += [0.5 - i, -3.0, -2.5, -2.0 - 0.1 * i, 1.0, 0.1 * i, 0.0, 0.2]
        out.append(r)
    return out


def header(fmt, n, props, kind="float"):
    h = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
    h += "".join(f"property {kind} {p}\n" for p in props)
    return h + "end_header\n"


def scene(out):
    with open(out, "wb") as f:
        f.write(header("binary_little_endian", 3, PROPS).encode())
        for r in rows():
            f.write(struct.pack(f"<{len(r)}f", *r))


def ascii_scene(out):
    with open(out, "w") as f:
        f.write(header("ascii", 3, PROPS))
        for r in rows():
            f.write(" ".join(f"{v:g}" for v in r) + "\n")


def sog(meta_path, out):
    d = os.path.dirname(meta_path)
    text = open(meta_path, "rb").read()
    meta = json.loads(text)
    names = list(meta["means"]["files"]) + meta["quats"]["files"][:1] + meta["scales"]["files"][:1]
    names += meta["sh0"]["files"][:1]
    if "shN" in meta:
        names += meta["shN"]["files"][:2]
    blob = struct.pack("<H", len(text)) + text
    for n in names:
        b = open(os.path.join(d, n), "rb").read()
        blob += struct.pack("<I", len(b)) + b
    open(out, "wb").write(blob)


def points(d):
    pts = [(0.0, 0.0, 0.0, 255, 0, 0), (1.0, 0.5, -0.5, 0, 255, 0), (-1.0, 2.0, 0.25, 0, 0, 255)]
    with open(os.path.join(d, "points_float.ply"), "wb") as f:
        f.write(header("binary_little_endian", 3, ["x", "y", "z", "red", "green", "blue"]).encode())
        for p in pts:
            f.write(struct.pack("<6f", *p[:3], *(c / 255 for c in p[3:])))
    with open(os.path.join(d, "points_uchar.ply"), "w") as f:
        f.write("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n")
        f.write("property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
        for p in pts:
            f.write(" ".join(str(v) for v in p) + "\n")


def colmap(d):
    cams = "# Camera list\n1 PINHOLE 64 48 50 50 32 24\n"
    imgs = "# Image list\n1 1 0 0 0 0.1 0.2 3 1 a.png\n10 20 -1\n"
    pts = "# 3D point list\n1 0.5 0.25 1.0 255 128 0 0.3 1 0\n2 -0.5 0 2 0 0 255 0.1\n"
    for pick, text in [(0, cams), (1, imgs), (2, pts)]:
        open(os.path.join(d, f"{pick}.txt"), "wb").write(bytes([pick]) + text.encode())
    cam_bin = struct.pack("<QiiQQ4d", 1, 1, 1, 64, 48, 50, 50, 32, 24)
    img_bin = struct.pack("<Qi4d3di", 1, 1, 1, 0, 0, 0, 0.1, 0.2, 3, 1) + b"a.png\0"
    img_bin += struct.pack("<Q", 1) + struct.pack("<ddQ", 10, 20, 2**64 - 1)
    pt_bin = struct.pack("<Q", 2)
    pt_bin += struct.pack("<Q3d3BdQ", 1, 0.5, 0.25, 1.0, 255, 128, 0, 0.3, 1) + struct.pack("<ii", 1, 0)
    pt_bin += struct.pack("<Q3d3BdQ", 2, -0.5, 0, 2, 0, 0, 255, 0.1, 0)
    for pick, b in [(4, cam_bin), (5, img_bin), (6, pt_bin)]:
        open(os.path.join(d, f"{pick}.bin"), "wb").write(bytes([pick]) + b)


def json_inputs(d, dataset):
    t = open(os.path.join(dataset, "transforms_test.json"), "rb").read()
    open(os.path.join(d, "0_transforms.json"), "wb").write(b"\0" + t)
    g = open(os.path.join(dataset, "instances.json"), "rb").read()
    open(os.path.join(d, "1_instances.json"), "wb").write(b"\1" + g)
    graph = [{"template_id": "duck", "instances": [
        {"instance_id": "a", "transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
        {"instance_id": "b", "transform": [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]}]}]
    open(os.path.join(d, "2_scene_graph.json"), "wb").write(b"\2" + json.dumps(graph).encode())
    labels = {"ids": [1, 2], "labels": [0, 1, 2, 1]}
    open(os.path.join(d, "3_labels.json"), "wb").write(b"\3" + json.dumps(labels).encode())


def configs(d, src):
    for pick, name in enumerate(["default.toml", "instanced.toml", "pipeline.toml", "render.toml"]):
        text = open(os.path.join(src, name), "rb").read()
        open(os.path.join(d, f"{pick}_{name}"), "wb").write(bytes([pick]) + text)


def png(w, h, depth, pixels):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    fmt = ">" + ("B" if depth == 8 else "H") * w
    raw = b"".join(b"\0" + struct.pack(fmt, *pixels[y * w:(y + 1) * w]) for y in range(h))
    ihdr = struct.pack(">IIBBBBB", w, h, depth, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def mask(d):
    ids = [0, 0, 1, 1, 0, 2, 2, 1, 0, 2, 2, 0, 3, 3, 0, 0]
    open(os.path.join(d, "mask8.png"), "wb").write(png(4, 4, 8, ids))
    open(os.path.join(d, "mask16.png"), "wb").write(png(4, 4, 16, [i * 1000 for i in ids]))


def checkpoint(src, out):
    data = open(src, "rb").read()
    assert data[:8] == b"INSTGSCK"
    (version,) = struct.unpack("<I", data[8:12])
    if version >= 2:
        data = data[:-4]  # the CRC-32 of the rest, written again below
    (hlen,) = struct.unpack("<Q", data[12:20])
    h = json.loads(data[20:20 + hlen])
    n, keep = h["gaussians"], 2
    strides = [3, 3, 4, 1, 3 * (h["sh_degree"] + 1) ** 2]
    pos, body = 20 + hlen, b""
    for s in strides * 3 + [1, 1, 1]:  # parameters, both Adam moments, gradient statistics
        body += data[pos:pos + 4 * s * keep]
        pos += 4 * s * n
    assert pos == len(data), "a plain checkpoint"
    h["gaussians"] = keep
    hb = json.dumps(h).encode()
    out_bytes = data[:12] + struct.pack("<Q", len(hb)) + hb + body
    if version >= 2:
        out_bytes += struct.pack("<I", zlib.crc32(out_bytes))
    open(out, "wb").write(out_bytes)


def instgs_v2(src, out):
    """A version-1 .instgs file as version 2: the same sections, the header's version 2, and the
    CRC-32 of every byte before it at the end."""
    data = open(src, "rb").read()
    assert data[:8] == b"INSTGS\0\0"
    (hlen,) = struct.unpack("<I", data[8:12])
    h = json.loads(data[12:12 + hlen])
    assert h["version"] == 1
    sections = data[(12 + hlen + 15) // 16 * 16:]
    h["version"] = 2
    hb = json.dumps(h).encode()
    head = data[:8] + struct.pack("<I", len(hb)) + hb
    head += b"\0" * (-len(head) % 16)
    body = head + sections
    open(out, "wb").write(body + struct.pack("<I", zlib.crc32(body)))


# The hostile names a file may give for another file (fuzz/regressions/*_files/): a parent, an
# absolute path, a device, a FIFO, a folder, links out of the folder, undecodable escapes. The
# *_files targets' folder holds each (fuzz/inputs.rs, `folder`).
HOSTILE = ["../outside.bin", "/etc/passwd", "/dev/zero", "zero.bin", "fifo.bin", "dir.bin",
           "link-out.bin", "sub/../../outside.bin", "%FF.bin", "%2E%2E/outside.bin", "file:///etc/passwd"]


def gltf_files(tiny_gltf, seeds, regressions, files):
    """A .gltf whose buffer is the file a.bin beside it (its seed; a.bin into FILES), and the same
    document naming each HOSTILE path instead (regression inputs, all to be refused)."""
    doc = json.load(open(tiny_gltf))
    uri = doc["buffers"][0]["uri"]
    open(os.path.join(files, "a.bin"), "wb").write(base64.b64decode(uri.split(";base64,", 1)[1]))
    doc["buffers"][0]["uri"] = "a.bin"
    json.dump(doc, open(os.path.join(seeds, "beside.gltf"), "w"))
    doc["buffers"][0]["uri"] = "sub/a.bin"
    json.dump(doc, open(os.path.join(seeds, "in-a-subfolder.gltf"), "w"))
    for i, name in enumerate(HOSTILE):
        doc["buffers"][0]["uri"] = name
        json.dump(doc, open(os.path.join(regressions, f"uri-{i:02d}.gltf"), "w"))


def sog_files(meta_path, seeds, regressions, files):
    """A SOG meta.json with its WebP images (into FILES), and the same meta.json naming each
    HOSTILE path for one of them (regression inputs)."""
    d = os.path.dirname(meta_path)
    meta = json.load(open(meta_path))
    for n in sorted(os.listdir(d)):
        if n.endswith(".webp"):
            open(os.path.join(files, n), "wb").write(open(os.path.join(d, n), "rb").read())
    json.dump(meta, open(os.path.join(seeds, "meta.json"), "w"))
    for i, name in enumerate(HOSTILE):
        meta["quats"]["files"] = [name]
        json.dump(meta, open(os.path.join(regressions, f"image-{i:02d}.json"), "w"))


if __name__ == "__main__":
    cmd, args = sys.argv[1], sys.argv[2:]
    {"scene": scene, "ascii-scene": ascii_scene, "sog": sog, "points": points, "colmap": colmap,
     "json": json_inputs, "configs": configs, "mask": mask, "checkpoint": checkpoint,
     "instgs-v2": instgs_v2, "gltf-files": gltf_files, "sog-files": sog_files}[cmd](*args)
