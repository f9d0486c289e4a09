//! What each fuzz target does with its input, shared by the targets (`fuzz_targets/`) and the
//! test of the seeds and regression inputs (`tests/fuzz_inputs.rs`). `run` returns the
//! reader's verdict: Ok when the input was accepted (and what it gave passed the checks a
//! command would run on it), Err when it was refused. A panic, a hang or an unbounded
//! allocation in it is a bug.
use anyhow::{anyhow, Result};

/// Every target: (name, what it reads).
#[allow(dead_code)] // read by tests/fuzz_inputs.rs, not by the targets
pub const TARGETS: [(&str, &str); 13] = [
    ("instgs_parse", ".instgs scene"),
    ("ply_parse", "3DGS PLY, plain and SuperSplat compressed"),
    ("points_ply", "a dataset's points3d.ply"),
    ("spz_parse", "Niantic .spz"),
    ("splat_parse", "antimatter15 .splat"),
    ("sog_parse", "SOG meta.json with its WebP images"),
    ("sog_bundle", "a .sog bundle (zip of meta.json and WebP images)"),
    ("gltf_parse", "glTF (.glb or .gltf JSON) with KHR_gaussian_splatting, plain or instanced"),
    ("colmap_parse", "COLMAP cameras/images/points3D, .bin and .txt"),
    ("json_inputs", "transforms JSON, instances.json, scene graph, labels"),
    ("config_toml", "training, instanced, pipeline and render configurations"),
    ("checkpoint_parse", "training checkpoint"),
    ("mask_png", "instance mask PNG"),
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
        other => panic!("no fuzz target {other}"),
    }
    Ok(())
}

/// `data` with its last 4 bytes replaced by the CRC-32 of the bytes before them (how version-2
/// `.instgs` files and checkpoints end), so mutations reach the parser behind the checksum.
fn with_checksum(data: &[u8]) -> Option<Vec<u8>> {
    let body = data.len().checked_sub(4)?;
    let mut v = data.to_vec();
    v[body..].copy_from_slice(&crc32fast::hash(&data[..body]).to_le_bytes());
    Some(v)
}
