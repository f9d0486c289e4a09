//! The bad-input table: every reader and command given input a careless or hostile user would
//! give ends in exit status 1, exactly one `error:` line naming the file (or the flag) and the
//! problem, no panic, and no file written (the case's folder holds the same files before and
//! after). Validation layers are on (`INSTGS_VALIDATION=1`).
mod common;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use common::*;

/// The 3DGS PLY header of `ply_with`: one vertex, the 14 core properties as floats.
const HEADER: &str = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nproperty float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\nproperty float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n";

fn ply_with(header: &str, values: &[f32]) -> Vec<u8> {
    let mut b = header.as_bytes().to_vec();
    for v in values {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

/// One valid Gaussian's 14 core values.
const ONE: [f32; 14] = [0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 1.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0];

const POSE: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";

fn transforms(head: &str, frames: &[&str]) -> String {
    let frames: Vec<String> =
        frames.iter().map(|f| format!(r#"{{"file_path": "{f}", "transform_matrix": {POSE}}}"#)).collect();
    format!(r#"{{{head} "frames": [{}]}}"#, frames.join(","))
}

struct Case {
    name: String,
    dir: PathBuf,
    args: Vec<String>,
    needles: Vec<String>,
}

struct Table {
    root: PathBuf,
    cases: Vec<Case>,
}

impl Table {
    /// A fresh folder for a case.
    fn dir(&self, name: &str) -> PathBuf {
        let d = self.root.join(name);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    /// Writes `bytes` to `name` in the case's folder.
    fn put(&self, case: &str, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
        let p = self.dir(case).join(name);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(&p, bytes).unwrap();
        p
    }

    /// A case: `args` (`{d}` is the case's folder), and the words its error line must hold.
    fn case<S: AsRef<str>>(&mut self, name: &str, args: &[S], needles: &[&str]) {
        let dir = self.dir(name);
        let d = dir.to_str().unwrap().to_string();
        self.cases.push(Case {
            name: name.into(),
            args: args.iter().map(|a| a.as_ref().replace("{d}", &d)).collect(),
            needles: needles.iter().map(|n| n.replace("{d}", &d)).collect(),
            dir,
        });
    }
}

fn files_under(dir: &Path) -> BTreeSet<PathBuf> {
    fn walk(d: &Path, out: &mut BTreeSet<PathBuf>) {
        for e in std::fs::read_dir(d).into_iter().flatten() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            }
            out.insert(p);
        }
    }
    let mut s = BTreeSet::new();
    walk(dir, &mut s);
    s
}

/// A copy of the bundled demo dataset, `edit` applied to it.
fn demo_copy(dir: &Path, edit: impl FnOnce(&Path)) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("demo/ducks6-mini");
    let to = dir.join("data");
    fn copy(a: &Path, b: &Path) {
        std::fs::create_dir_all(b).unwrap();
        for e in std::fs::read_dir(a).unwrap() {
            let p = e.unwrap().path();
            let q = b.join(p.file_name().unwrap());
            if p.is_dir() {
                copy(&p, &q);
            } else {
                std::fs::copy(&p, &q).unwrap();
            }
        }
    }
    copy(&src, &to);
    edit(&to);
    to
}

fn colmap_dir(t: &Table, case: &str, cameras: &str, images: &str, points: &str) {
    t.put(case, "m/sparse/0/cameras.txt", cameras);
    t.put(case, "m/sparse/0/images.txt", images);
    t.put(case, "m/sparse/0/points3D.txt", points);
}

const CAMERAS: &str = "1 PINHOLE 64 48 50 50 32 24\n";
const IMAGES: &str = "1 1 0 0 0 0 0 3 1 a.png\n\n";
const POINTS: &str = "1 0 0 0 255 0 0 0.1\n";

#[test]
fn bad_input_table() {
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("bad_input");
    let _ = std::fs::remove_dir_all(&root);
    let mut t = Table { root, cases: Vec::new() };
    let tiny = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/ply_parse/tiny.ply");
    let tiny = tiny.to_str().unwrap();
    let good = std::fs::read(tiny).unwrap();

    // ---- 3DGS PLY (plain and compressed), through `info`.
    t.put("ply_truncated", "s.ply", &good[..good.len() - 7]);
    t.case("ply_truncated", &["info", "{d}/s.ply"], &["s.ply", "truncated"]);
    let mut nan = ONE;
    nan[0] = f32::NAN;
    t.put("ply_nan", "s.ply", ply_with(HEADER, &nan));
    t.case("ply_nan", &["info", "{d}/s.ply"], &["s.ply", "non-finite position"]);
    t.put("ply_missing", "s.ply", ply_with(&HEADER.replace("property float opacity\n", ""), &ONE[..13]));
    t.case("ply_missing", &["info", "{d}/s.ply"], &["s.ply", "'opacity' is missing"]);
    t.put("ply_empty", "s.ply", HEADER.replace("vertex 1", "vertex 0"));
    t.case("ply_empty", &["info", "{d}/s.ply"], &["s.ply", "no Gaussians"]);
    t.put("ply_garbage", "s.ply", "not a ply at all");
    t.case("ply_garbage", &["info", "{d}/s.ply"], &["s.ply", "not a scene file we read (text)"]);
    t.case("ply_absent", &["info", "{d}/absent.ply"], &["absent.ply", "cannot open"]);
    let twice = HEADER.replace("end_header\n", "element vertex 1\nproperty float x\nend_header\n");
    t.put("ply_element_twice", "s.ply", ply_with(&twice, &[ONE.as_slice(), &[0.0]].concat()));
    t.case("ply_element_twice", &["info", "{d}/s.ply"], &["s.ply", "element 'vertex' is declared twice"]);
    let twice = HEADER.replace("property float rot_3\n", "property float rot_3\nproperty float x\n");
    t.put("ply_property_twice", "s.ply", ply_with(&twice, &[ONE.as_slice(), &[0.0]].concat()));
    t.case(
        "ply_property_twice",
        &["info", "{d}/s.ply"],
        &["s.ply", "property 'x' of element 'vertex' is declared twice"],
    );
    t.put("ply_list", "s.ply", ply_with(&HEADER.replace("property float x\n", "property list uchar float x\n"), &[]));
    t.case(
        "ply_list",
        &["info", "{d}/s.ply"],
        &["s.ply", "'x' is declared list uchar float; expected float or double"],
    );
    let mut ints = ply_with(&HEADER.replace("property float opacity", "property int opacity"), &ONE[..6]);
    ints.extend_from_slice(&3i32.to_le_bytes());
    ints.extend(ONE[7..].iter().flat_map(|v| v.to_le_bytes()));
    t.put("ply_int", "s.ply", ints);
    t.case("ply_int", &["info", "{d}/s.ply"], &["s.ply", "'opacity' is declared int"]);
    let rest: String = (0..5).map(|j| format!("property float f_rest_{j}\n")).collect();
    let five = HEADER.replace("end_header\n", &format!("{rest}end_header\n"));
    t.put("ply_rest_count", "s.ply", ply_with(&five, &[ONE.as_slice(), &[0.0; 5]].concat()));
    t.case("ply_rest_count", &["info", "{d}/s.ply"], &["s.ply", "5 f_rest properties"]);
    t.put("ply_trailing", "s.ply", [ply_with(HEADER, &ONE), vec![0; 8]].concat());
    t.case("ply_trailing", &["info", "{d}/s.ply"], &["s.ply", "data continues past"]);
    let ascii = HEADER.replace("binary_little_endian", "ascii") + "0 0 0 0.5 0.5 0.5 1 -3 -3 -3 one 0 0 0\n";
    t.put("ply_ascii_word", "s.ply", ascii);
    t.case("ply_ascii_word", &["info", "{d}/s.ply"], &["s.ply", "vertex data"]);
    let compressed =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/ply_parse/tiny.compressed.ply")).unwrap();
    let text = String::from_utf8_lossy(&compressed).into_owned();
    let swap = |from: &str, to: &str| {
        let mut b = compressed.clone();
        let at = text.find(from).unwrap();
        b.splice(at..at + from.len(), to.bytes());
        b
    };
    t.put("compressed_packed_float", "s.ply", swap("property uint packed_position", "property float packed_position"));
    t.case(
        "compressed_packed_float",
        &["info", "{d}/s.ply"],
        &["s.ply", "'packed_position' is declared float; expected uint"],
    );
    t.put("compressed_chunk_int", "s.ply", swap("property float min_x", "property int min_x  "));
    t.case("compressed_chunk_int", &["info", "{d}/s.ply"], &["s.ply", "'min_x' is declared int"]);
    t.put("compressed_no_chunks", "s.ply", swap("element chunk 1", "element chunk 0"));
    t.case("compressed_no_chunks", &["info", "{d}/s.ply"], &["s.ply", "0 chunks cannot hold 3 splats"]);

    // ---- .spz, .splat, SOG.
    t.put("spz_gzip_not_spz", "s.spz", [0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 3, 3, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
    t.case("spz_gzip_not_spz", &["info", "{d}/s.spz"], &["s.spz"]);
    let spz = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/spz_parse/tiny.spz")).unwrap();
    t.put("spz_truncated", "s.spz", &spz[..spz.len() / 2]);
    t.case("spz_truncated", &["info", "{d}/s.spz"], &["s.spz"]);
    t.put("splat_odd_length", "s.splat", [0u8; 33]);
    t.case("splat_odd_length", &["info", "{d}/s.splat"], &["s.splat", "32-byte rows"]);
    let mut row = [0u8; 32];
    row[12..16].copy_from_slice(&(-1.0f32).to_le_bytes());
    t.put("splat_negative_scale", "s.splat", row);
    t.case("splat_negative_scale", &["info", "{d}/s.splat"], &["s.splat", "negative or NaN scale"]);
    t.put("sog_not_json", "meta.json", "{ not json");
    t.case("sog_not_json", &["info", "{d}/meta.json"], &["meta.json", "not a SOG meta.json"]);
    let meta = r#"{"version": 3, "count": 1, "means": {"mins": [0,0,0], "maxs": [1,1,1], "files": ["a.webp", "b.webp"]},
        "scales": {"files": ["s.webp"]}, "quats": {"files": ["q.webp"]}, "sh0": {"files": ["c.webp"]}}"#;
    t.put("sog_version", "meta.json", meta);
    t.case("sog_version", &["info", "{d}/meta.json"], &["meta.json", "SOG version 3"]);
    let meta2 = meta.replace(r#""version": 3"#, r#""version": 2"#).replace(
        r#""scales": {"files""#,
        &format!(r#""scales": {{"codebook": [{}], "files""#, vec!["0"; 256].join(",")),
    );
    let meta2 = meta2
        .replace(r#""sh0": {"files""#, &format!(r#""sh0": {{"codebook": [{}], "files""#, vec!["0"; 256].join(",")));
    t.put("sog_missing_image", "meta.json", &meta2);
    t.case("sog_missing_image", &["info", "{d}/meta.json"], &["meta.json", "\"a.webp\"", "cannot read"]);
    // A meta.json may name only files beside it.
    for (name, file, needle) in [
        ("sog_names_parent", "../x.webp", "outside the file's folder"),
        ("sog_names_dev_zero", "/dev/zero", "outside the file's folder"),
    ] {
        t.put(name, "meta.json", meta2.replace("a.webp", file));
        t.case(name, &["info", "{d}/meta.json"], &["meta.json", file, needle]);
    }
    let bundle = |files: &[(&str, &[u8])]| {
        let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        for (name, bytes) in files {
            w.start_file(*name, zip::write::SimpleFileOptions::default()).unwrap();
            std::io::Write::write_all(&mut w, bytes).unwrap();
        }
        w.finish().unwrap().into_inner()
    };
    t.put("sog_bundle_no_meta", "s.sog", bundle(&[("a.webp", b"RIFF")]));
    t.case("sog_bundle_no_meta", &["info", "{d}/s.sog"], &["s.sog", "a zip archive without a SOG meta.json"]);
    t.put("sog_bundle_missing_image", "s.sog", bundle(&[("meta.json", meta2.as_bytes())]));
    t.case("sog_bundle_missing_image", &["info", "{d}/s.sog"], &["s.sog", "no a.webp in the bundle"]);
    let whole = bundle(&[("meta.json", meta2.as_bytes())]);
    t.put("sog_bundle_truncated", "s.sog", &whole[..whole.len() - 30]);
    t.case("sog_bundle_truncated", &["info", "{d}/s.sog"], &["s.sog", "zip archive"]);

    // ---- glTF (the fuzz seed: three splats, SH degree 1, its buffer a data: URI).
    let seed = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/gltf_parse/tiny.gltf");
    let gltf = |edit: &dyn Fn(&mut serde_json::Value, &mut Vec<u8>)| {
        let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&seed).unwrap()).unwrap();
        let uri = doc["buffers"][0]["uri"].as_str().unwrap().to_string();
        let mut bin = base64::decode(&uri[uri.find(',').unwrap() + 1..]).unwrap();
        edit(&mut doc, &mut bin);
        doc["buffers"][0]["uri"] = format!("data:application/octet-stream;base64,{}", base64::encode(&bin)).into();
        serde_json::to_vec(&doc).unwrap()
    };
    let attr = |doc: &serde_json::Value, name: &str| {
        doc["meshes"][0]["primitives"][0]["attributes"][name].as_u64().unwrap() as usize
    };
    let glb = {
        let d = t.dir("gltf_seed");
        let bin = env!("CARGO_BIN_EXE_instgs-vk");
        let out = d.join("s.glb");
        assert!(std::process::Command::new(bin).arg("convert").arg(&seed).arg(&out).output().unwrap().status.success());
        std::fs::read(&out).unwrap()
    };
    // ---- 3D Tiles (the glTF seed as a tileset: one SPZ-compressed tile of three splats).
    let tileset = |d: PathBuf, edit: &dyn Fn(&mut serde_json::Value)| {
        let bin = env!("CARGO_BIN_EXE_instgs-vk");
        let out = d.join("tileset.json");
        assert!(std::process::Command::new(bin).arg("convert").arg(&seed).arg(&out).output().unwrap().status.success());
        let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
        edit(&mut doc);
        std::fs::write(&out, serde_json::to_vec(&doc).unwrap()).unwrap();
    };
    tileset(t.dir("tiles_content_outside"), &|d| {
        d["root"]["children"][0]["content"]["uri"] = "../gltf_seed/s.glb".into()
    });
    t.case(
        "tiles_content_outside",
        &["info", "{d}/tileset.json"],
        &["tileset.json", "root.children[0]'s content uri", "outside the file's folder"],
    );
    tileset(t.dir("tiles_sheared"), &|d| {
        d["root"]["children"][0]["transform"] =
            serde_json::json!([2.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    });
    t.case(
        "tiles_sheared",
        &["info", "{d}/tileset.json"],
        &["tileset.json", "root.children[0]'s transform", "not a rotation times a uniform scale"],
    );
    // The tile's accessors say 4 splats; its SPZ data holds 3 (checked before decoding).
    tileset(t.dir("tiles_spz_count"), &|_| ());
    {
        let tile = t.dir("tiles_spz_count").join("tile-0.glb");
        let bytes = std::fs::read(&tile).unwrap();
        let mut edited = bytes.clone();
        let (json_len, start) = (u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize, 20);
        let json = String::from_utf8(bytes[start..start + json_len].to_vec()).unwrap();
        assert!(json.contains("\"count\":3,"));
        let json = json.replace("\"count\":3,", "\"count\":4,");
        edited[start..start + json_len].copy_from_slice(json.as_bytes());
        std::fs::write(&tile, edited).unwrap();
    }
    t.case(
        "tiles_spz_count",
        &["info", "{d}/tileset.json"],
        &["tile-0.glb", "KHR_gaussian_splatting_compression_spz_2", "holds 3 Gaussians, its accessors say 4"],
    );

    t.put("glb_truncated", "s.glb", &glb[..glb.len() - 10]);
    t.case("glb_truncated", &["info", "{d}/s.glb"], &["s.glb", "not a valid GLB"]);
    t.put(
        "gltf_requires_draco",
        "s.gltf",
        gltf(&|d, _| d["extensionsRequired"] = serde_json::json!(["KHR_draco_mesh_compression"])),
    );
    t.case(
        "gltf_requires_draco",
        &["info", "{d}/s.gltf"],
        &["s.gltf", "requires the glTF extension KHR_draco_mesh_compression"],
    );
    t.put("gltf_triangles", "s.gltf", gltf(&|d, _| d["meshes"][0]["primitives"][0]["mode"] = 4.into()));
    t.case("gltf_triangles", &["info", "{d}/s.gltf"], &["s.gltf", "must have mode POINTS (0)"]);
    t.put(
        "gltf_no_splats",
        "s.gltf",
        gltf(&|d, _| d["meshes"][0]["primitives"][0].as_object_mut().unwrap().remove("extensions").map(drop).unwrap()),
    );
    t.case("gltf_no_splats", &["info", "{d}/s.gltf"], &["s.gltf", "without KHR_gaussian_splatting primitives"]);
    let without = |name: &'static str| {
        gltf(&move |d, _| {
            d["meshes"][0]["primitives"][0]["attributes"].as_object_mut().unwrap().remove(name).unwrap();
        })
    };
    t.put("gltf_no_opacity", "s.gltf", without("KHR_gaussian_splatting:OPACITY"));
    t.case("gltf_no_opacity", &["info", "{d}/s.gltf"], &["s.gltf", "no KHR_gaussian_splatting:OPACITY attribute"]);
    t.put("gltf_partial_sh", "s.gltf", without("KHR_gaussian_splatting:SH_DEGREE_1_COEF_2"));
    t.case("gltf_partial_sh", &["info", "{d}/s.gltf"], &["s.gltf", "SH degree 1 is partly defined"]);
    t.put(
        "gltf_log_scale",
        "s.gltf",
        gltf(&|d, bin| {
            // The review draft's log-space scales: negative numbers.
            let view = d["accessors"][attr(d, "KHR_gaussian_splatting:SCALE")]["bufferView"].as_u64().unwrap() as usize;
            let at = d["bufferViews"][view]["byteOffset"].as_u64().unwrap() as usize;
            bin[at..at + 4].copy_from_slice(&(-4.6f32).to_le_bytes());
        }),
    );
    t.case("gltf_log_scale", &["info", "{d}/s.gltf"], &["s.gltf", "SCALE of splat 0 is -4.6", "log-space"]);
    t.put(
        "gltf_accessor_past_view",
        "s.gltf",
        gltf(&|d, _| {
            let p = attr(d, "POSITION");
            d["accessors"][p]["byteOffset"] = 24.into()
        }),
    );
    t.case("gltf_accessor_past_view", &["info", "{d}/s.gltf"], &["s.gltf", "reaches past its buffer view"]);
    t.put(
        "gltf_sheared_node",
        "s.gltf",
        gltf(&|d, _| {
            d["nodes"][0]["matrix"] = serde_json::json!([1, 0, 0, 0, 0.5, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
        }),
    );
    t.case(
        "gltf_sheared_node",
        &["info", "{d}/s.gltf"],
        &["s.gltf", "node 0's world matrix", "not a rotation times a uniform scale"],
    );
    // Buffers named by their uri: only regular files in the glTF's folder, read with limits.
    // The seed's document with its buffer's uri replaced (after `gltf` embeds the buffer).
    let with_uri = |doc: Vec<u8>, uri: &str, length: Option<usize>| {
        let mut v: serde_json::Value = serde_json::from_slice(&doc).unwrap();
        v["buffers"][0]["uri"] = uri.into();
        if let Some(n) = length {
            v["buffers"][0]["byteLength"] = n.into();
        }
        serde_json::to_vec(&v).unwrap()
    };
    let external = |uri: &str| with_uri(gltf(&|_, _| {}), uri, None);
    let bin_of = |doc: &[u8]| {
        let v: serde_json::Value = serde_json::from_slice(doc).unwrap();
        let uri = v["buffers"][0]["uri"].as_str().unwrap().to_string();
        base64::decode(&uri[uri.find(',').unwrap() + 1..]).unwrap()
    };
    let bin = bin_of(&gltf(&|_, _| {}));
    for (name, uri, needles) in [
        ("gltf_uri_bad_escape", "%FF.bin", vec!["buffer 0's uri", "%FF.bin", "does not decode to a UTF-8 path"]),
        ("gltf_uri_dev_zero", "/dev/zero", vec!["buffer 0's uri", "/dev/zero", "outside the file's folder"]),
        ("gltf_uri_parent", "../x.bin", vec!["buffer 0's uri", "../x.bin", "outside the file's folder"]),
        ("gltf_uri_scheme", "file:///etc/passwd", vec!["buffer 0's uri", "not a relative path"]),
        ("gltf_uri_folder", "sub", vec!["buffer 0's uri", "not a regular file"]),
        ("gltf_uri_link_out", "out.bin", vec!["buffer 0's uri", "leads outside the file's folder"]),
    ] {
        t.put(name, "s.gltf", external(uri));
        t.put(name, "sub/keep", "");
        t.put(name, "../gltf_outside/x.bin", &bin);
        std::os::unix::fs::symlink(t.dir(name).join("../gltf_outside/x.bin"), t.dir(name).join("out.bin")).unwrap();
        t.case(name, &["info", "{d}/s.gltf"], &[&["s.gltf"], needles.as_slice()].concat());
    }
    // The memory budget: a buffer larger than it, and a node graph that reuses its children
    // (two parents per level, 2^18 visits of one 3-splat mesh at the leaves) — both refused
    // before they are read or expanded.
    t.put("gltf_buffer_over_budget", "s.gltf", with_uri(gltf(&|_, _| {}), "big.bin", Some(bin.len() + 3_000_000)));
    t.put("gltf_buffer_over_budget", "big.bin", [&bin[..], &vec![0u8; 3_000_000][..]].concat());
    t.case(
        "gltf_buffer_over_budget",
        &["--max-memory", "2MB", "info", "{d}/s.gltf"],
        &["s.gltf", "its buffers would hold", "memory budget of 2.0 MB", "--max-memory"],
    );
    t.put(
        "gltf_node_graph_dag",
        "s.gltf",
        gltf(&|d, _| {
            let depth = 18;
            let mut nodes = Vec::new();
            for level in 0..depth {
                for _ in 0..2 {
                    let next = 2 * (level + 1);
                    nodes.push(if level + 1 < depth {
                        serde_json::json!({"children": [next, next + 1]})
                    } else {
                        serde_json::json!({"mesh": 0})
                    });
                }
            }
            d["nodes"] = nodes.into();
            d["scenes"] = serde_json::json!([{"nodes": [0, 1]}]);
            d["scene"] = 0.into();
        }),
    );
    t.case(
        "gltf_node_graph_dag",
        &["--max-memory", "64MiB", "info", "{d}/s.gltf"],
        &["s.gltf", "splat primitive visits", "memory budget"],
    );
    t.put(
        "gltf_colour_space",
        "s.gltf",
        gltf(&|d, _| {
            d["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]["colorSpace"] = "acescg".into()
        }),
    );
    t.case("gltf_colour_space", &["info", "{d}/s.gltf"], &["s.gltf", "colorSpace \"acescg\" is not read"]);
    t.put(
        "gltf_indices_past_vertices",
        "s.gltf",
        gltf(&|d, bin| {
            let at = bin.len();
            bin.extend_from_slice(&[0, 7, 1, 0]);
            d["bufferViews"]
                .as_array_mut()
                .unwrap()
                .push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": 4}));
            let view = d["bufferViews"].as_array().unwrap().len() - 1;
            d["accessors"]
                .as_array_mut()
                .unwrap()
                .push(serde_json::json!({"bufferView": view, "componentType": 5121, "count": 3, "type": "SCALAR"}));
            let acc = d["accessors"].as_array().unwrap().len() - 1;
            d["meshes"][0]["primitives"][0]["indices"] = acc.into();
            d["buffers"][0]["byteLength"] = bin.len().into();
        }),
    );
    t.case("gltf_indices_past_vertices", &["info", "{d}/s.gltf"], &["s.gltf", "names vertex 7", "the primitive has 3"]);
    t.case("max_memory_not_a_size", &["--max-memory", "lots", "info", tiny], &["--max-memory", "not a size"]);

    // ---- .instgs.
    t.put("instgs_bad_header", "s.instgs", b"INSTGS\0\0\x05\0\0\0{\"a\":");
    t.case("instgs_bad_header", &["info", "{d}/s.instgs"], &["s.instgs", "malformed JSON header"]);
    t.put("instgs_cut_short", "s.instgs", b"INSTGS\0\0\x05");
    t.case("instgs_cut_short", &["info", "{d}/s.instgs"], &["s.instgs", "cut short"]);
    t.put("instgs_no_magic", "s.instgs", b"PLY no magic here");
    t.case("instgs_no_magic", &["info", "{d}/s.instgs"], &["s.instgs", "not a scene file we read (text)"]);
    t.case(
        "instgs_as_plain",
        &["segment", "--scene", "{d}/../instgs_bad_header/s.instgs", "--data", "{d}", "--out", "{d}/l.json"],
        &["s.instgs"],
    );

    // ---- Cameras (transforms JSON), through `render`.
    let render = |c: &str| ["render", "--scene", tiny, "--cameras", c, "--out", "{d}/out"].map(String::from);
    for (name, head, frames, needles) in [
        ("cameras_no_frames", r#""camera_angle_x": 0.8, "w": 64, "h": 48,"#, vec![], vec!["t.json", "no frames"]),
        ("cameras_zero_width", r#""camera_angle_x": 0.8, "w": 0, "h": 48,"#, vec!["a"], vec!["t.json", "empty"]),
        ("cameras_wide", r#""camera_angle_x": 7.0, "w": 64, "h": 48,"#, vec!["a"], vec!["t.json", "camera_angle_x"]),
        ("cameras_no_focal", r#""w": 64, "h": 48,"#, vec!["a"], vec!["t.json", "neither fl_x nor camera_angle_x"]),
        (
            "cameras_twins",
            r#""camera_angle_x": 0.8, "w": 64, "h": 48,"#,
            vec!["x/a.png", "y/a.png"],
            vec!["t.json", "two cameras are named \"a\""],
        ),
        ("cameras_not_json", "oops", vec![], vec!["t.json", "not a transforms JSON"]),
        (
            "cameras_huge_width",
            r#""camera_angle_x": 0.8, "w": 1e10, "h": 48,"#,
            vec!["a"],
            vec!["t.json: frame 0", "w 10000000000 is not an image side"],
        ),
        (
            "cameras_fractional_height",
            r#""camera_angle_x": 0.8, "w": 64, "h": 47.5,"#,
            vec!["a"],
            vec!["t.json: frame 0", "h 47.5 is not an image side"],
        ),
        (
            // No w/h: the first frame's image would be opened for its size.
            "cameras_image_outside",
            r#""camera_angle_x": 0.8,"#,
            vec!["../../etc/passwd"],
            vec!["t.json", "frame 0's file_path", "outside the file's folder"],
        ),
    ] {
        t.put(name, "t.json", transforms(head, &frames));
        let args = render("{d}/t.json");
        t.case(name, &args, &needles);
    }
    t.put(
        "cameras_infinite",
        "t.json",
        transforms(r#""camera_angle_x": 0.8, "w": 64, "h": 48,"#, &["a"]).replace("[0,0,1,4]", "[0,0,1,1e39]"),
    );
    t.case(
        "cameras_infinite",
        &["render", "--scene", tiny, "--cameras", "{d}/t.json", "--out", "{d}/out"],
        &["t.json"],
    );

    // ---- COLMAP, through `cameras`.
    let colmap = [
        (
            "colmap_unknown_model",
            "1 WEIRD 64 48 1 2 3\n",
            IMAGES,
            POINTS,
            "cameras.txt: line 1: unknown camera model WEIRD",
        ),
        ("colmap_param_count", "1 PINHOLE 64 48 50 50 32\n", IMAGES, POINTS, "PINHOLE takes 4 parameters, got 3"),
        (
            "colmap_camera_twice",
            "1 PINHOLE 64 48 50 50 32 24\n1 PINHOLE 64 48 50 50 32 24\n",
            IMAGES,
            POINTS,
            "camera 1 is listed twice",
        ),
        ("colmap_zero_size", "1 PINHOLE 0 48 50 50 32 24\n", IMAGES, POINTS, "camera 1 is 0x48 pixels"),
        ("colmap_nan_param", "1 PINHOLE 64 48 nan 50 32 24\n", IMAGES, POINTS, "non-finite parameter"),
        ("colmap_image_line", CAMERAS, "1 1 0 0 0 0 0 3\n\n", POINTS, "images.txt: line 1: expected IMAGE_ID"),
        ("colmap_zero_quat", CAMERAS, "1 0 0 0 0 0 0 3 1 a.png\n\n", POINTS, "zero rotation quaternion"),
        ("colmap_unknown_camera", CAMERAS, "1 1 0 0 0 0 0 3 7 a.png\n\n", POINTS, "refers to camera 7"),
        (
            "colmap_nan_point",
            CAMERAS,
            IMAGES,
            "1 nan 0 0 255 0 0 0.1\n",
            "points3D.txt: line 1: the point's position is not finite",
        ),
        ("colmap_colour_range", CAMERAS, IMAGES, "1 0 0 0 300 0 0 0.1\n", "colour is not in 0..255"),
        ("colmap_no_images", CAMERAS, "# nothing\n", POINTS, "no registered images"),
        (
            "colmap_full_opencv",
            "1 FULL_OPENCV 64 48 50 50 32 24 0.5 0.1 0 0 0 0 0 0\n",
            IMAGES,
            POINTS,
            "camera model FULL_OPENCV cannot be undistorted here",
        ),
    ];
    for (name, cams, imgs, pts, needle) in colmap {
        colmap_dir(&t, name, cams, imgs, pts);
        t.case(name, &["cameras", "{d}/m", "--out", "{d}/c.json"], &[needle]);
    }
    let mut cam_bin = 1u64.to_le_bytes().to_vec();
    cam_bin.extend_from_slice(&1i32.to_le_bytes());
    t.put("colmap_bin_truncated", "m/sparse/0/cameras.bin", &cam_bin);
    t.put("colmap_bin_truncated", "m/sparse/0/images.bin", 0u64.to_le_bytes());
    t.case("colmap_bin_truncated", &["cameras", "{d}/m", "--out", "{d}/c.json"], &["cameras.bin", "claims 1 entries"]);
    // points3D.bin with a NaN position (once a panic in the k-d tree of the initial scales).
    let mut points = 1u64.to_le_bytes().to_vec();
    points.extend_from_slice(&7u64.to_le_bytes());
    for v in [f64::NAN, 0.0, 0.0] {
        points.extend_from_slice(&v.to_le_bytes());
    }
    points.extend_from_slice(&[255, 0, 0]);
    points.extend_from_slice(&0.5f64.to_le_bytes());
    points.extend_from_slice(&0u64.to_le_bytes());
    let mut cameras = 1u64.to_le_bytes().to_vec();
    cameras.extend([1i32, 1].iter().flat_map(|v| v.to_le_bytes()));
    cameras.extend([64u64, 48].iter().flat_map(|v| v.to_le_bytes()));
    cameras.extend([50.0f64, 50.0, 32.0, 24.0].iter().flat_map(|v| v.to_le_bytes()));
    let mut images = 1u64.to_le_bytes().to_vec();
    images.extend_from_slice(&1i32.to_le_bytes());
    images.extend([1.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0].iter().flat_map(|v| v.to_le_bytes()));
    images.extend_from_slice(&1i32.to_le_bytes());
    images.extend_from_slice(b"a.png\0");
    images.extend_from_slice(&0u64.to_le_bytes());
    t.put("colmap_bin_nan_point", "m/sparse/0/cameras.bin", &cameras);
    t.put("colmap_bin_nan_point", "m/sparse/0/images.bin", &images);
    t.put("colmap_bin_nan_point", "m/sparse/0/points3D.bin", &points);
    t.put("colmap_bin_nan_point", "m/images/a.png", []);
    t.case(
        "colmap_bin_nan_point",
        &["train", "--data", "{d}/m", "--out", "{d}/run"],
        &["points3D", "non-finite position"],
    );
    let mut trailing = 0u64.to_le_bytes().to_vec();
    trailing.extend_from_slice(&[1, 2, 3]);
    t.put("colmap_bin_trailing", "m/sparse/0/cameras.bin", &trailing);
    t.put("colmap_bin_trailing", "m/sparse/0/images.bin", 0u64.to_le_bytes());
    t.case(
        "colmap_bin_trailing",
        &["cameras", "{d}/m", "--out", "{d}/c.json"],
        &["cameras.bin", "3 bytes follow the last entry"],
    );

    // ---- Datasets, through `train` (refused before anything is trained or written).
    let train = |data: &str| ["train", "--data", data, "--out", "{d}/run", "--iterations", "2"].map(String::from);
    t.case("dataset_absent", &train("{d}/nothing"), &["nothing", "no such directory"]);
    t.dir("dataset_not_one");
    t.put("dataset_not_one", "empty/readme.txt", "x");
    t.case("dataset_not_one", &train("{d}/empty"), &["empty", "not a dataset"]);
    type Edit = Box<dyn Fn(&Path)>;
    let dataset_cases: Vec<(&str, Edit, Vec<&str>, Vec<&str>)> = vec![
        (
            "dataset_missing_image",
            Box::new(|d: &Path| std::fs::remove_file(d.join("train/r_002.png")).unwrap()),
            vec![],
            vec!["r_002.png", "is missing"],
        ),
        (
            "dataset_image_size",
            Box::new(|d: &Path| image::RgbImage::new(20, 20).save(d.join("train/r_002.png")).unwrap()),
            vec![],
            vec!["r_002.png", "image is 20x20, the camera says 160x120"],
        ),
        (
            "dataset_downscale",
            Box::new(|_: &Path| {}),
            vec!["--downscale", "1000"],
            vec!["--downscale 1000", "160x120"],
        ),
        (
            // An image named outside the dataset (a copy of a real one, so only confinement refuses).
            "dataset_image_outside",
            Box::new(|d: &Path| {
                std::fs::copy(d.join("train/r_002.png"), d.join("../outside.png")).unwrap();
                let f = d.join("transforms_train.json");
                let text = std::fs::read_to_string(&f).unwrap().replace("\"train/r_002\"", "\"../outside\"");
                std::fs::write(f, text).unwrap()
            }),
            vec![],
            vec!["transforms_train.json", "the image of view 'outside'", "leads outside the file's folder"],
        ),
        (
            "dataset_points_nan",
            Box::new(|d: &Path| {
                let mut b = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec();
                b.extend_from_slice(b"nan 0 0\n");
                std::fs::write(d.join("points3d.ply"), b).unwrap()
            }),
            vec![],
            vec!["points3d.ply", "not a PLY file: Line 8"],
        ),
        (
            "dataset_points_list",
            Box::new(|d: &Path| {
                let b = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty list uchar uchar red\nend_header\n0 0 0 1 7\n";
                std::fs::write(d.join("points3d.ply"), b).unwrap()
            }),
            vec![],
            vec!["points3d.ply", "'red' must be a uchar, float or double"],
        ),
        (
            "groups_id_zero",
            Box::new(|d: &Path| {
                std::fs::write(d.join("instances.json"), r#"{"groups": [{"name": "duck", "instances": [{"id": 0}]}]}"#)
                    .unwrap()
            }),
            vec![],
            vec!["instances.json", "uses id 0"],
        ),
        (
            "groups_id_twice",
            Box::new(|d: &Path| {
                std::fs::write(
                    d.join("instances.json"),
                    r#"{"groups": [{"name": "a", "instances": [{"id": 1}]}, {"name": "b", "instances": [{"id": 1}]}]}"#,
                )
                .unwrap()
            }),
            vec![],
            vec!["instances.json", "instance id 1 appears twice"],
        ),
        (
            "mask_size",
            Box::new(|d: &Path| image::GrayImage::new(7, 5).save(d.join("masks/train/r_002.png")).unwrap()),
            vec![],
            vec!["r_002.png", "mask is 7x5, its image 160x120"],
        ),
        (
            "mask_colour",
            Box::new(|d: &Path| image::RgbImage::new(160, 120).save(d.join("masks/train/r_002.png")).unwrap()),
            vec![],
            vec!["r_002.png", "8- or 16-bit greyscale"],
        ),
        (
            "config_unknown_key",
            Box::new(|d: &Path| std::fs::write(d.join("c.toml"), "iterationz = 5\n").unwrap()),
            vec!["--config", "{d}/data/c.toml"],
            vec!["c.toml", "iterationz"],
        ),
        (
            "config_not_toml",
            Box::new(|d: &Path| std::fs::write(d.join("c.toml"), "[[[\n").unwrap()),
            vec!["--config", "{d}/data/c.toml"],
            vec!["c.toml"],
        ),
        (
            "config_wrong_type",
            Box::new(|d: &Path| std::fs::write(d.join("c.toml"), "iterations = \"many\"\n").unwrap()),
            vec!["--config", "{d}/data/c.toml"],
            vec!["c.toml", "iterations"],
        ),
    ];
    for (name, edit, extra, needles) in dataset_cases {
        let data = demo_copy(&t.dir(name), edit);
        let mut args = train(data.to_str().unwrap()).to_vec();
        args.extend(extra.iter().map(|s| s.to_string()));
        t.case(name, &args, &needles);
    }

    // ---- Checkpoints, through `train --resume` on the demo without masks (plain training).
    use instgs_vk::dataset::DatasetIdentity;
    use instgs_vk::train::config::Config;
    use instgs_vk::train::{write_checkpoint, TrainState};
    let mut rng = Rng::new(24);
    let state = TrainState::new(random_scene(&mut rng, 8, 3));
    let cfg = Config::load(None).unwrap();
    let plain = |d: &Path| std::fs::remove_dir_all(d.join("masks")).unwrap();
    let demo_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("demo/ducks6-mini");
    for name in [
        "resume_none",
        "resume_nan",
        "resume_other_data",
        "resume_other_config",
        "resume_truncated",
        "resume_flipped_byte",
    ] {
        let data = demo_copy(&t.dir(name), plain);
        let run = t.dir(name).join("run");
        std::fs::create_dir_all(&run).unwrap();
        let ckpt = run.join("checkpoint.bin");
        match name {
            "resume_none" => {}
            "resume_other_data" => {
                let other = DatasetIdentity {
                    path: "/elsewhere".into(),
                    cameras: "00".into(),
                    train_views: 3,
                    test_views: 1,
                    width: 64,
                    height: 48,
                    images: None,
                };
                write_checkpoint(&ckpt, &state, &cfg, Some(&other)).unwrap();
            }
            "resume_other_config" => {
                let changed = Config { seed: cfg.seed + 1, ..cfg.clone() };
                write_checkpoint(&ckpt, &state, &changed, None).unwrap();
            }
            _ => {
                write_checkpoint(&ckpt, &state, &cfg, None).unwrap();
                let mut b = std::fs::read(&ckpt).unwrap();
                let hlen = u64::from_le_bytes(b[12..20].try_into().unwrap()) as usize;
                if name == "resume_nan" {
                    // A NaN written with a matching checksum: the values are checked too.
                    b[20 + hlen + 12..20 + hlen + 16].copy_from_slice(&f32::NAN.to_le_bytes());
                    let body = b.len() - 4;
                    let crc = crc32fast::hash(&b[..body]);
                    b[body..].copy_from_slice(&crc.to_le_bytes());
                } else if name == "resume_flipped_byte" {
                    let at = b.len() / 2;
                    b[at] ^= 0x10;
                } else {
                    b.truncate(b.len() - 5);
                }
                std::fs::write(&ckpt, b).unwrap();
            }
        }
        let needles: &[&str] = match name {
            "resume_none" => &["checkpoint.bin", "cannot read checkpoint"],
            "resume_nan" => &["checkpoint.bin", "non-finite"],
            "resume_other_data" => &["checkpoint.bin", "trained on other data: /elsewhere (3 training / 1 test views)"],
            "resume_other_config" => &["checkpoint.bin", "another configuration"],
            _ => &["checkpoint.bin", "is damaged", "checksum"],
        };
        t.case(
            name,
            &["train", "--data", data.to_str().unwrap(), "--out", "{d}/run", "--resume", "--iterations", "2"],
            needles,
        );
    }
    // A pipeline pointed at a folder holding another dataset's finished plain run.
    let other = DatasetIdentity {
        path: "/elsewhere".into(),
        cameras: "00".into(),
        train_views: 24,
        test_views: 6,
        width: 160,
        height: 120,
        images: None,
    };
    let run = t.dir("pipeline_other_run").join("run");
    std::fs::create_dir_all(&run).unwrap();
    write_checkpoint(&run.join("checkpoint.bin"), &state, &cfg, Some(&other)).unwrap();
    t.case(
        "pipeline_other_run",
        &["train", "--data", demo_dir.to_str().unwrap(), "--out", "{d}/run", "--until", "plain", "--iterations", "2"],
        &["checkpoint of stage plain was trained on other data: /elsewhere", "the cameras of"],
    );
    t.put("checkpoint_not_one", "run/checkpoint.bin", "hello");
    let data = demo_copy(&t.dir("checkpoint_not_one"), plain);
    t.case(
        "checkpoint_not_one",
        &["train", "--data", data.to_str().unwrap(), "--out", "{d}/run", "--resume"],
        &["checkpoint.bin", "not an instgs-vk checkpoint"],
    );

    // ---- Labels and scene graphs: `instance`, `compose`.
    let demo = Path::new(env!("CARGO_MANIFEST_DIR")).join("demo/ducks6-mini");
    let demo = demo.to_str().unwrap();
    let instance = |labels: &str| {
        ["instance", "--scene", tiny, "--labels", labels, "--data", demo, "--out", "{d}/s.instgs"].map(String::from)
    };
    // A run's learned lens beside its scene (`eval` scores through it): a falloff no lens has.
    t.put("appearance_vignetting", "s.ply", &good);
    t.put("appearance_vignetting", "appearance.json", r#"{"views": [], "vignetting": {"k1": 50.0, "k2": 0.0}}"#);
    t.case(
        "appearance_vignetting",
        &["eval", "--scene", "{d}/s.ply", "--data", demo],
        &["appearance.json", "vignetting k1 = 50, k2 = 0 is not a lens's falloff"],
    );
    for (name, file, bytes, needle) in [
        ("labels_odd_bytes", "l.bin", vec![0u8; 6], "6 bytes is not a whole number of u32 labels"),
        ("labels_count", "l.bin", vec![0u8; 8], "2 labels for a scene of 3 Gaussians"),
        ("labels_not_json", "l.json", b"[1,2".to_vec(), "not a labels file"),
        ("labels_extension", "l.txt", b"1 2 3".to_vec(), "labels must be .json or .bin"),
    ] {
        t.put(name, file, bytes);
        let args = instance(&format!("{{d}}/{file}"));
        t.case(name, &args, &[file, needle]);
    }
    let compose = |graph: &str| {
        ["compose", "--template", &format!("t={tiny}"), "--scene-graph", graph, "--out", "{d}/s.instgs"]
            .map(String::from)
    };
    let identity = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    for (name, graph, needle) in [
        ("graph_empty", "[]".to_string(), "no groups"),
        ("graph_not_json", "{".to_string(), "not a scene graph"),
        ("graph_no_instances", r#"[{"template_id": "t", "instances": []}]"#.to_string(), "has no instances"),
        (
            "graph_singular",
            format!(
                r#"[{{"template_id": "t", "instances": [{{"instance_id": "1", "transform": {identity}}}, {{"instance_id": "2", "transform": [[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,1]]}}]}}]"#
            ),
            "instance \"2\"",
        ),
        (
            "graph_unknown_template",
            format!(r#"[{{"template_id": "cup", "instances": [{{"instance_id": "1", "transform": {identity}}}]}}]"#),
            "cup",
        ),
    ] {
        t.put(name, "g.json", graph);
        let args = compose("{d}/g.json");
        t.case(name, &args, &[needle]);
    }
    t.put("compose_f16_overflow", "g.json", format!(r#"[{{"template_id": "t", "instances": [{{"instance_id": "1", "transform": {identity}}}, {{"instance_id": "2", "transform": {identity}}}]}}]"#));
    let mut args = compose("{d}/g.json").to_vec();
    args.extend(["--random-offsets", "100000", "--offset-dtype", "f16"].map(String::from));
    t.case("compose_f16_overflow", &args, &["s.instgs", "does not fit f16"]);

    // ---- Command-line values: our own error naming the flag and the accepted range.
    let orbit = |flag: &str, v: &str| {
        ["render", "--scene", tiny, "--orbit", "2", flag, v, "--out", "{d}/out"].map(String::from)
    };
    for (name, args, needles) in [
        (
            "flag_orbit_negative",
            orbit("--width", "64").map(|a| if a == "2" { "-3".into() } else { a }).to_vec(),
            vec!["--orbit", "'-3' is not a whole number ≥ 1"],
        ),
        ("flag_width_zero", orbit("--width", "0").to_vec(), vec!["--width", "'0' is not a whole number ≥ 1"]),
        ("flag_background", orbit("--background", "2,0,0").to_vec(), vec!["--background", "[0, 1]"]),
        ("flag_background_negative", orbit("--background", "-1,0,0").to_vec(), vec!["--background", "[0, 1]"]),
        (
            "flag_downscale_negative",
            ["train", "--data", demo, "--out", "{d}/run", "--downscale", "-5"].map(String::from).to_vec(),
            vec!["--downscale", "'-5' is not a whole number ≥ 1"],
        ),
        (
            "flag_iterations_zero",
            ["train", "--data", demo, "--out", "{d}/run", "--iterations", "0"].map(String::from).to_vec(),
            vec!["--iterations", "'0'"],
        ),
        (
            "flag_alpha_nan",
            ["segment", "--scene", tiny, "--data", demo, "--alpha", "NaN", "--out", "{d}/l.json"]
                .map(String::from)
                .to_vec(),
            vec!["--alpha", "'NaN' is not a finite number ≥ 0"],
        ),
        (
            "flag_alpha_negative",
            ["segment", "--scene", tiny, "--data", demo, "--alpha", "-0.5", "--out", "{d}/l.json"]
                .map(String::from)
                .to_vec(),
            vec!["--alpha", "'-0.5'"],
        ),
        (
            "flag_min_fitness",
            instance("x.bin").into_iter().chain(["--min-fitness".into(), "1.5".into()]).collect(),
            vec!["--min-fitness", "[0, 1]"],
        ),
        ("flag_bits", ["bench-sort", "--bits", "40"].map(String::from).to_vec(), vec!["--bits", "from 1 to 32"]),
        (
            "flag_frames_zero",
            ["bench", "--scene", tiny, "--orbit", "1", "--frames", "0"].map(String::from).to_vec(),
            vec!["--frames"],
        ),
        (
            "flag_random_offsets",
            compose("g.json").into_iter().chain(["--random-offsets".into(), "-1".into()]).collect(),
            vec!["--random-offsets", "finite number ≥ 0"],
        ),
    ] {
        t.case(name, &args, &needles);
    }

    // ---- Outputs: a writer refuses a name it cannot write.
    t.case("convert_unknown_extension", &["convert", tiny, "{d}/x.txt"], &["x.txt", ".ply"]);
    t.case("convert_plain_to_instgs", &["convert", tiny, "{d}/x.instgs"], &["x.instgs", "instanced scene", "plain"]);
    t.case(
        "compress_not_instgs",
        &["convert", tiny, "{d}/x.ply", "--compress"],
        &["x.ply", "--compress", ".instgs only"],
    );

    // ---- Issue 45: cameras we cannot model are refused, never drawn as pinholes.
    let head = r#""camera_angle_x": 0.8, "w": 64, "h": 48,"#;
    for (name, edit, needles) in [
        ("cameras_reflection", ("[[1,0,0,0]", "[[-1,0,0,0]"), vec!["t.json: frame 0", "reflection"]),
        ("cameras_shear", ("[[1,0,0,0]", "[[1,0.4,0,0]"), vec!["t.json: frame 0", "sheared"]),
        ("cameras_last_row", ("[0,0,0,1]]", "[0,0,2,1]]"), vec!["t.json: frame 0", "last row"]),
        (
            "cameras_equirectangular",
            (head, &format!(r#"{head} "camera_model": "EQUIRECTANGULAR","#)),
            vec!["t.json: frame 0", "EQUIRECTANGULAR"],
        ),
        (
            "cameras_fisheye_tangential",
            (head, &format!(r#"{head} "camera_model": "OPENCV_FISHEYE", "p1": 0.01,"#)),
            vec!["t.json: frame 0", "OPENCV_FISHEYE takes k1..k4 only"],
        ),
    ] {
        t.put(name, "t.json", transforms(head, &["a"]).replacen(edit.0, edit.1, 1));
        let args = render("{d}/t.json");
        t.case(name, &args, &needles);
    }
    for (name, cams, needle) in [
        ("colmap_fov", "1 FOV 64 48 50 50 32 24 0.1\n", "camera model FOV cannot be undistorted"),
        ("colmap_thin_prism", "1 THIN_PRISM_FISHEYE 64 48 50 50 32 24 0 0 0 0 0 0 0 0\n", "THIN_PRISM_FISHEYE cannot"),
    ] {
        colmap_dir(&t, name, cams, IMAGES, POINTS);
        t.case(name, &["cameras", "{d}/m", "--out", "{d}/c.json"], &["camera 1", needle]);
    }
    // A lens whose distortion folds over inside the image: training refuses its photos.
    let data = demo_copy(&t.dir("dataset_lens_folds"), |d| {
        for split in ["train", "test"] {
            let p = d.join(format!("transforms_{split}.json"));
            let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
            v["k1"] = (-3.0).into();
            std::fs::write(&p, v.to_string()).unwrap();
        }
    });
    t.case("dataset_lens_folds", &train(data.to_str().unwrap()), &["r_000.png", "OPENCV distortion folds over"]);
    // Tangential terms that fold the image along one axis only (the radius along the diagonal
    // still grows): the Jacobian's grid over the whole image finds it.
    let data = demo_copy(&t.dir("dataset_lens_folds_tangentially"), |d| {
        for split in ["train", "test"] {
            let p = d.join(format!("transforms_{split}.json"));
            let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
            v["p1"] = (0.9).into();
            v["p2"] = (-0.9).into();
            std::fs::write(&p, v.to_string()).unwrap();
        }
    });
    t.case(
        "dataset_lens_folds_tangentially",
        &train(data.to_str().unwrap()),
        &["r_000.png", "OPENCV distortion folds over near pixel"],
    );

    // ---- What we wrote, we can prove we wrote: a changed byte is refused.
    let v2 =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/instgs_parse/f32-v2.instgs")).unwrap();
    let mut flipped = v2.clone();
    let at = flipped.len() - 40;
    flipped[at] ^= 0x04;
    t.put("instgs_flipped_byte", "s.instgs", flipped);
    t.case("instgs_flipped_byte", &["info", "{d}/s.instgs"], &["s.instgs", "damaged", "checksum"]);
    let mut v5 = v2.clone();
    let at = v5.windows(12).position(|w| w == b"\"version\": 2").expect("the seed's version") + 11;
    v5[at] = b'5';
    t.put("instgs_version_5", "s.instgs", v5);
    t.case("instgs_version_5", &["info", "{d}/s.instgs"], &["s.instgs", "version 5 is not supported"]);

    // ---- Every readable file means one thing.
    {
        use std::io::Write;
        // .spz version 2 (gzip) whose header counts 1 Gaussian and whose data holds 2.
        let mut raw = b"NGSP".to_vec();
        raw.extend_from_slice(&2u32.to_le_bytes());
        raw.extend_from_slice(&1u32.to_le_bytes());
        raw.extend_from_slice(&[0, 12, 0, 0]);
        raw.extend(std::iter::repeat_n(0u8, 2 * (9 + 1 + 3 + 3 + 3)));
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        gz.write_all(&raw).unwrap();
        t.put("spz_count_small", "s.spz", gz.finish().unwrap());
        t.case("spz_count_small", &["info", "{d}/s.spz"], &["s.spz", "the count is wrong"]);
    }
    // SOG images of one scene in two sizes.
    let sog = t.dir("sog_sizes_differ");
    assert!(run_bin(&["convert", tiny, sog.join("src/meta.json").to_str().unwrap()], &[]).ok);
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sog.join("src/meta.json")).unwrap()).unwrap();
    let quats = meta["quats"]["files"][0].as_str().unwrap().to_string();
    image::RgbaImage::new(8, 8).save_with_format(sog.join("src").join(&quats), image::ImageFormat::WebP).unwrap();
    t.case("sog_sizes_differ", &["info", "{d}/src/meta.json"], &[quats.as_str(), "share one size"]);
    // compose: one template name twice; SH degrees that differ; a scale past any similarity's.
    t.put(
        "compose_name_twice",
        "g.json",
        format!(r#"[{{"template_id": "t", "instances": [{{"instance_id": "1", "transform": {identity}}}]}}]"#),
    );
    let mut args = compose("{d}/g.json").to_vec();
    args.extend(["--template".to_string(), format!("t={tiny}")]);
    t.case("compose_name_twice", &args, &["--template t=", "given twice"]);
    t.put("compose_sh_degrees", "zero.ply", ply_with(HEADER, &ONE));
    t.put(
        "compose_sh_degrees",
        "g.json",
        format!(
            r#"[{{"template_id": "t", "instances": [{{"instance_id": "1", "transform": {identity}}}]}}, {{"template_id": "z", "instances": [{{"instance_id": "2", "transform": {identity}}}]}}]"#
        ),
    );
    let mut args = compose("{d}/g.json").to_vec();
    args.extend(["--template".into(), "z={d}/zero.ply".into()]);
    t.case("compose_sh_degrees", &args, &["zero.ply", "template \"z\" has SH degree 0", "degree 1"]);
    t.put(
        "graph_huge_scale",
        "g.json",
        r#"[{"template_id": "t", "instances": [{"instance_id": "1", "transform": [[1e30,0,0,0],[0,1e30,0,0],[0,0,1e30,0],[0,0,0,1]]}]}]"#,
    );
    t.case("graph_huge_scale", &compose("{d}/g.json"), &["scale", "out of range"]);
    // Configuration values out of their range: the key and the file named.
    for (name, text, needles) in [
        (
            "config_grad_threshold",
            "[densify]\ngrad_threshold = -1\n",
            vec!["c.toml", "densify.grad_threshold must be above 0"],
        ),
        (
            "config_min_opacity",
            "[densify]\nmin_opacity = 1.5\n",
            vec!["c.toml", "densify.min_opacity must be in [0, 1]"],
        ),
        ("config_ssim_weight", "ssim_weight = 2.0\n", vec!["c.toml", "ssim_weight must be in [0, 1]"]),
        ("config_background", "background = [0.0, 2.0, 0.0]\n", vec!["c.toml", "background must be in [0, 1]"]),
        ("config_percent_dense", "[densify]\npercent_dense = -0.1\n", vec!["c.toml", "densify.percent_dense"]),
        ("config_appearance_model", "[appearance]\nmodel = \"sometimes\"\n", vec!["c.toml", "appearance.model"]),
        (
            "config_appearance_lr",
            "[appearance]\nlr_init = -0.1\n",
            vec!["c.toml", "appearance.lr_init must be above 0"],
        ),
        ("config_joint_rate", "[joint.lr]\nopacity = -1.0\n", vec!["c.toml [joint]", "lr.opacity must be at least 0"]),
        (
            "config_render_views",
            "[instance]\nmin_render_views = 0\n",
            vec!["c.toml", "instance.min_render_views must be at least 1"],
        ),
        ("config_budget", "[instance]\nbackground_budget_db = -3.0\n", vec!["c.toml", "instance.background_budget_db"]),
    ] {
        let data = demo_copy(&t.dir(name), |d| std::fs::write(d.join("c.toml"), text).unwrap());
        let mut args = train(data.to_str().unwrap()).to_vec();
        args.extend(["--config".to_string(), "{d}/data/c.toml".to_string()]);
        t.case(name, &args, &needles);
    }

    // ---- An error a user can act on.
    let far = [ONE.as_slice(), &[1e30, 0.0, 0.0, 0.5, 0.5, 0.5, 1.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0]].concat();
    t.put("scene_far_point", "s.ply", ply_with(&HEADER.replace("vertex 1", "vertex 2"), &far));
    t.case(
        "scene_far_point",
        &["render", "--scene", "{d}/s.ply", "--orbit", "2", "--out", "{d}/out"],
        &["s.ply", "too large to frame"],
    );
    // Outputs appear whole or not at all: an output that cannot be made leaves nothing behind.
    t.put("render_out_is_file", "out", "a file, not a folder");
    t.case("render_out_is_file", &["render", "--scene", tiny, "--orbit", "2", "--out", "{d}/out"], &["out"]);
    t.put("sog_out_is_file", "dir", "a file");
    t.case("sog_out_is_file", &["convert", tiny, "{d}/dir/meta.json"], &["dir"]);
    t.put("train_out_under_file", "f", "a file");
    t.case("train_out_under_file", &["train", "--data", demo, "--out", "{d}/f/run", "--iterations", "2"], &["f/run"]);

    // Run the table.
    assert!(t.cases.len() >= 90, "{} cases", t.cases.len());
    let mut failures = Vec::new();
    for c in &t.cases {
        let before = files_under(&c.dir);
        let args: Vec<&str> = c.args.iter().map(String::as_str).collect();
        let o = run_bin(&args, &[("INSTGS_VALIDATION", "1")]);
        let errors: Vec<&str> = o.stderr.lines().filter(|l| !l.starts_with("device:") && !l.is_empty()).collect();
        let mut why = Vec::new();
        if o.code != Some(1) {
            why.push(format!("exit status {:?}", o.code));
        }
        if o.stderr.contains("panicked") {
            why.push("a panic".into());
        }
        // Progress and information lines may come first; the error is one line, the last
        // (clap's "For more information" hint aside).
        let clap_hint = |l: &&str| l.starts_with("For more information") || l.starts_with("  tip:");
        let lines: Vec<&&str> = errors.iter().filter(|l| !clap_hint(l)).collect();
        let error_lines = lines.iter().filter(|l| l.starts_with("error:")).count();
        match lines.last() {
            Some(last) if error_lines == 1 && last.starts_with("error: ") => {
                for n in &c.needles {
                    if !last.contains(n.as_str()) {
                        why.push(format!("no '{n}'"));
                    }
                }
            }
            _ => why.push(format!("{error_lines} error lines, the last line not one")),
        }
        let after = files_under(&c.dir);
        let new: Vec<_> = after.difference(&before).collect();
        if !new.is_empty() {
            why.push(format!("wrote {new:?}"));
        }
        if !why.is_empty() {
            failures.push(format!("{}: {} — stderr: {}", c.name, why.join(", "), o.stderr.trim()));
        }
    }
    eprintln!("{} bad inputs, {} refused as they should be", t.cases.len(), t.cases.len() - failures.len());
    assert!(failures.is_empty(), "{} case(s) failed:\n{}", failures.len(), failures.join("\n"));
}
