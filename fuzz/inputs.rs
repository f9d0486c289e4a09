//! What each fuzz target does with its input, shared by the targets (`fuzz_targets/`) and the
//! test of the seeds and regression inputs (`tests/fuzz_inputs.rs`). `run` returns the
//! reader's verdict: Ok when the input was accepted (and what it gave passed the checks a
//! command would run on it), Err when it was refused. A panic, a hang or an unbounded
//! allocation in it is a bug.
use anyhow::{anyhow, Result};

/// Every target: (name, what it reads).
#[allow(dead_code)] // read by tests/fuzz_inputs.rs, not by the targets
pub const TARGETS: [(&str, &str); 16] = [
    ("instgs_parse", ".instgs scene"),
    ("ply_parse", "3DGS PLY, plain and SuperSplat compressed"),
    ("points_ply", "a dataset's points3d.ply"),
    ("spz_parse", "Niantic .spz"),
    ("splat_parse", "antimatter15 .splat"),
    ("sog_parse", "SOG meta.json with its WebP images"),
    ("sog_bundle", "a .sog bundle (zip of meta.json and WebP images)"),
    ("gltf_parse", "glTF (.glb or .gltf JSON) with KHR_gaussian_splatting, plain or instanced"),
    ("gltf_files", "a .gltf/.glb file in a folder, its buffer URIs resolved there"),
    ("sog_files", "a SOG meta.json file in a folder, its images resolved there"),
    ("colmap_parse", "COLMAP cameras/images/points3D, .bin and .txt"),
    ("json_inputs", "transforms JSON, instances.json, scene graph, labels"),
    ("config_toml", "training, instanced, pipeline and render configurations"),
    ("checkpoint_parse", "training checkpoint"),
    ("mask_png", "instance mask PNG"),
    ("convert_any", "a 3DGS PLY that reads, written to every format `convert` writes and read back"),
];

pub fn run(target: &str, data: &[u8]) -> Result<()> {
    use instgs_vk::{dataset, formats, instancing, model, render, train};
    let what = "fuzz";
    match target {
        "instgs_parse" => {
            // The parser behind the checksum too: the input with its last 4 bytes made its
            // CRC-32 (only for the panics; the verdict is the input's own).
            if let Some(fixed) = with_checksum(data) {
                if let Ok(scene) = formats::instgs::from_bytes(&fixed, what) {
                    scene.validate(what).expect("the reader validates");
                }
            }
            let scene = formats::instgs::from_bytes(data, what)?;
            // What parses writes back and reads again to the same scene.
            let bytes = formats::instgs::to_bytes(&scene, formats::instgs::Dtype::F32);
            assert_eq!(formats::instgs::from_bytes(&bytes, what).unwrap(), scene);
            // The compressed writer (`convert --compress`, the player's save of a compressed
            // scene) on any scene that reads: what it writes reads back, with the same structure.
            if let Ok(packed) = formats::instgs::to_bytes_stored(&scene, formats::instgs::Storage::COMPRESSED) {
                let back = formats::instgs::from_bytes(&packed, what).expect("a compressed scene reads back");
                let shape = |s: &model::instanced::InstancedScene| {
                    let groups: Vec<_> = s.groups.iter().map(|g| (g.template.len(), g.instances.len())).collect();
                    (s.sh_degree, s.background.len(), groups)
                };
                assert_eq!(shape(&back), shape(&scene));
            }
            // pq8 offsets (`--offset-dtype pq8`): k-means codebooks, which must read back too.
            let pq8 = formats::instgs::Storage::offsets(formats::instgs::Dtype::Pq8);
            if let Ok(packed) = formats::instgs::to_bytes_stored(&scene, pq8) {
                formats::instgs::from_bytes(&packed, what).expect("a pq8 scene reads back");
            }
        }
        "ply_parse" => formats::ply::from_bytes(data, what)?.validate(what).expect("the reader validates"),
        "points_ply" => {
            let p = dataset::points_from_bytes(data, what)?;
            assert_eq!(p.positions.len(), p.colours.len());
            assert!(p.positions.iter().flatten().all(|v| v.is_finite()));
            assert!(p.colours.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
        }
        "spz_parse" => formats::spz::read_spz(what, data)?.validate(what)?,
        "splat_parse" => formats::splat::read_splat(what, data)?.validate(what)?,
        "sog_parse" => {
            // u16 length + meta.json, then u32 length + bytes per file; the n-th name meta.json
            // asks for gets the n-th file.
            let n = u16::from_le_bytes(data.get(..2).ok_or_else(|| anyhow!("short"))?.try_into()?) as usize;
            let meta = std::str::from_utf8(data.get(2..2 + n).ok_or_else(|| anyhow!("short"))?)?;
            let mut rest = &data[2 + n..];
            let mut files = Vec::new();
            while rest.len() >= 4 {
                let len = u32::from_le_bytes(rest[..4].try_into()?) as usize;
                let file = &rest[4..4 + len.min(rest.len() - 4)];
                files.push(file);
                rest = &rest[4 + file.len()..];
            }
            let mut next = files.into_iter();
            let mut load = |name: &str| {
                let file = next.next().ok_or_else(|| anyhow!("{name}: missing"))?;
                Ok((name.to_string(), file.to_vec()))
            };
            formats::sog::sog_from_meta(meta, what, &mut load)?.validate(what)?;
        }
        "sog_bundle" => formats::sog::sog_from_bundle(data, what)?.validate(what)?,
        "gltf_parse" => match formats::gltf::from_bytes(data, what, None)? {
            formats::gltf::GltfScene::Plain(s) => s.validate(what).expect("the reader validates"),
            formats::gltf::GltfScene::Instanced(s) => s.validate(what).expect("the reader validates"),
        },
        "gltf_files" => {
            let path = in_folder("scene.gltf", data)?;
            match formats::gltf::read(&path)? {
                formats::gltf::GltfScene::Plain(s) => s.validate(what).expect("the reader validates"),
                formats::gltf::GltfScene::Instanced(s) => s.validate(what).expect("the reader validates"),
            }
        }
        "sog_files" => formats::sog::read_sog(&in_folder("meta.json", data)?)?.validate(what)?,
        "colmap_parse" => {
            // First byte: the file (& 3: cameras, images, points3D, cameras), binary (& 4).
            let (&pick, content) = data.split_first().ok_or_else(|| anyhow!("empty"))?;
            let file = ["cameras", "images", "points3D", "cameras"][(pick & 3) as usize];
            let mut m = dataset::ColmapModel::default();
            dataset::read_colmap_file(&mut m, file, pick & 4 != 0, content, what)?;
            for cam in m.cameras.values() {
                dataset::colmap_intrinsics(cam, what)?;
            }
            assert!(m.points.positions.iter().flatten().all(|v| v.is_finite()));
        }
        "json_inputs" => {
            let (&pick, content) = data.split_first().ok_or_else(|| anyhow!("empty"))?;
            let text = std::str::from_utf8(content)?;
            match pick & 3 {
                0 => {
                    let dir = std::path::Path::new("/nonexistent-fuzz-dir");
                    for (c, _) in model::camera::transforms_from_str(text, dir, what)? {
                        c.validate().expect("the reader validates its cameras");
                    }
                }
                1 => {
                    dataset::masks::groups_from_str(text, what)?;
                }
                2 => {
                    model::instanced::scene_graph_from_str(text, what)?;
                }
                _ => {
                    instancing::labels::labels_from_bytes(content, "json", what, 4)?;
                }
            }
        }
        "config_toml" => {
            let (&pick, content) = data.split_first().ok_or_else(|| anyhow!("empty"))?;
            let text = std::str::from_utf8(content)?;
            match pick & 3 {
                0 => train::config::Config::from_toml(text, what)?.validate().expect("the reader validates"),
                1 => {
                    train::config::Config::instanced_from_toml(text, what)?;
                }
                2 => {
                    train::config::PipelineConfig::from_toml(text, what)?;
                }
                _ => {
                    render::lod::RenderConfig::from_toml(text, what)?;
                }
            }
        }
        "checkpoint_parse" => {
            if let Some(fixed) = with_checksum(data) {
                if let Ok((state, _)) = train::checkpoint_from_bytes(&fixed, what) {
                    state.scene.validate(what).expect("the reader validates");
                }
            }
            let (state, _) = train::checkpoint_from_bytes(data, what)?;
            state.scene.validate(what).expect("the reader validates");
        }
        "mask_png" => assert_eq!(dataset::masks::mask_from_bytes(data, what, 4, 4)?.len(), 16),
        "convert_any" => {
            // What reads converts: a writer may refuse a scene it cannot hold (a position past
            // .spz's fixed point), leaving no file; what it writes reads back, every Gaussian.
            let scene = formats::ply::from_bytes(data, what)?;
            scene.validate(what).expect("the reader validates");
            let stem = folder().join(format!("{}-convert", thread_name()));
            std::fs::create_dir_all(stem.join("sog")).unwrap();
            let outputs = ["s.ply", "s.compressed.ply", "s.spz", "s.sog", "s.glb", "s.gltf", "s.splat", "q.glb"];
            for name in outputs.iter().copied().chain(["sog/meta.json"]) {
                let out = stem.join(name);
                let _ = std::fs::remove_file(&out);
                let written = if name == "q.glb" {
                    formats::gltf::write_gltf(&scene, &out, formats::gltf::Accessors::Quantized)
                } else {
                    formats::write_scene(&scene, &out)
                };
                match written {
                    Ok(()) => {
                        let back =
                            formats::read_scene(&out).unwrap_or_else(|e| panic!("{name} written, not read: {e:#}"));
                        assert_eq!(back.len(), scene.len(), "{name}");
                    }
                    Err(_) if name != "sog/meta.json" => assert!(!out.exists(), "{name}: refused, a file left"),
                    Err(_) => {}
                }
            }
        }
        other => panic!("no fuzz target {other}"),
    }
    Ok(())
}

/// The *_files targets' folder, made once per process: the files
/// their seeds name (`fuzz/files/`: a glTF buffer, a SOG's images, also in `sub/`), and beside
/// them what a hostile file may name instead (`fuzz/regressions/*_files/`): a link to /dev/zero,
/// a FIFO (opening it would block), a folder, a link out of the folder to `../outside.bin`.
/// Reads in these processes are held to a 256 MiB budget (`--max-memory`), under the fuzzer's
/// 2 GiB RSS limit, so an allocation the budget lets through is one the fuzzer catches.
fn folder() -> &'static std::path::Path {
    use std::os::unix::fs::symlink;
    static FOLDER: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    FOLDER.get_or_init(|| {
        instgs_vk::limits::set(instgs_vk::limits::Limits { allow_outside: false, max_memory: 256 << 20 });
        // Under `cargo test`, cargo's temporary directory (the same folder every run); in a
        // fuzzing process, a folder of its own in the system's.
        let root = match option_env!("CARGO_TARGET_TMPDIR") {
            Some(dir) => std::path::Path::new(dir).join("fuzz-files"),
            None => std::env::temp_dir().join(format!("instgs-fuzz-files-{}", std::process::id())),
        };
        let dir = root.join("files");
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        std::fs::create_dir_all(dir.join("dir.bin")).unwrap();
        std::fs::write(root.join("outside.bin"), vec![7u8; 4096]).unwrap();
        let files: [(&str, &[u8]); 8] = [
            ("a.bin", include_bytes!("files/a.bin")),
            ("means_l.webp", include_bytes!("files/means_l.webp")),
            ("means_u.webp", include_bytes!("files/means_u.webp")),
            ("quats.webp", include_bytes!("files/quats.webp")),
            ("scales.webp", include_bytes!("files/scales.webp")),
            ("sh0.webp", include_bytes!("files/sh0.webp")),
            ("shN_centroids.webp", include_bytes!("files/shN_centroids.webp")),
            ("shN_labels.webp", include_bytes!("files/shN_labels.webp")),
        ];
        for (name, bytes) in files {
            std::fs::write(dir.join(name), bytes).unwrap();
            std::fs::write(dir.join("sub").join(name), bytes).unwrap();
        }
        for (link, target) in [("zero.bin", "/dev/zero"), ("link-out.bin", "../outside.bin")] {
            let _ = symlink(target, dir.join(link));
        }
        let fifo = dir.join("fifo.bin");
        if !fifo.exists() {
            let status = std::process::Command::new("mkfifo").arg(&fifo).status().unwrap();
            assert!(status.success(), "mkfifo {}", fifo.display());
        }
        dir
    })
}

/// This thread's name for its files in [`folder`].
fn thread_name() -> String {
    format!("{:?}", std::thread::current().id()).replace(|c: char| !c.is_ascii_alphanumeric(), "")
}

/// Writes `data` as the file `name` (one per thread) in [`folder`] and returns its path.
fn in_folder(name: &str, data: &[u8]) -> Result<std::path::PathBuf> {
    let path = folder().join(format!("{}-{name}", thread_name()));
    std::fs::write(&path, data)?;
    Ok(path)
}

/// `data` with its last 4 bytes replaced by the CRC-32 of the bytes before them (how version-2
/// `.instgs` files and checkpoints end), so mutations reach the parser behind the checksum.
fn with_checksum(data: &[u8]) -> Option<Vec<u8>> {
    let body = data.len().checked_sub(4)?;
    let mut v = data.to_vec();
    v[body..].copy_from_slice(&crc32fast::hash(&data[..body]).to_le_bytes());
    Some(v)
}
