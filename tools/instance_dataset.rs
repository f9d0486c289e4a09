//! Instance masks and ground truth for a dataset rendered from an instanced scene, in the layout
//! of the shared scenes (`../shared/data/README.md`), so that any object type can go through the
//! main job like a capture (BENCHMARKS.md "Registration robustness", other object types):
//! - `DIR/masks/{train,test}/NAME.png`: 16-bit instance ids (0 background; 1.. the scene's
//!   instances in file order). A pixel takes the instance whose splats carry the largest share of
//!   its blending weight, if that share is at least one half: each instance is rendered alone in
//!   white over black with every other splat black (same opacities, so occlusion is kept), and
//!   the red channel is that instance's weight.
//! - `DIR/instances.json`: per group its name and `canonical_bbox` (the template means' 2nd–98th
//!   percentile box, template space); per instance its id, `object_to_world` (its template →
//!   world transform, row-major), `center_world` (the box centre placed) and `scale` (the
//!   transform's, so that the pose errors' object size is the instance's world size).
//! - `DIR/points3d.ply`: a stand-in for a structure-from-motion cloud: the means of every
//!   fourth expanded Gaussian with opacity ≥ 0.5, coloured by its base colour.
//!
//! The images themselves come from `instgs-vk render` (`tools/bench-objects.sh` does it all).
//!
//! ```sh
//! cargo run --release --example instance_dataset -- SCENE.instgs DIR   # DIR/transforms_{train,test}.json
//! ```
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use instgs_vk::gpu::kernels::Kernels;
use instgs_vk::gpu::{Gpu, GpuOptions};
use instgs_vk::math::SH_C0_F32;
use instgs_vk::model::instanced::{mat4_to_rows, InstancedScene};
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::render::upload::GpuScene;

/// `scene` with every splat black except instance `only` (global index), white; no
/// view-dependent colour.
fn weight_scene(scene: &InstancedScene, only: usize) -> InstancedScene {
    let mut s = scene.clone();
    let (black, white) = (-0.5 / SH_C0_F32, 0.5 / SH_C0_F32);
    let coeffs = s.background.sh_coeffs();
    let paint = |sh: &mut [f32], v: f32| {
        for (i, c) in sh.iter_mut().enumerate() {
            *c = if i % (coeffs * 3) < 3 { v } else { 0.0 };
        }
    };
    paint(&mut s.background.sh, black);
    let mut index = 0;
    for g in &mut s.groups {
        let t = g.template.len();
        paint(&mut g.template.sh, 0.0);
        for k in 0..g.instances.len() {
            let v = if index == only { white } else { black };
            for j in 0..t {
                let sh0 = &g.template.sh[j * coeffs * 3..j * coeffs * 3 + 3];
                g.offsets.d_sh0[k * t + j] = [v - sh0[0], v - sh0[1], v - sh0[2]];
            }
            index += 1;
        }
    }
    s
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [scene_path, dir] = args.as_slice() else {
        bail!("usage: instance_dataset SCENE.instgs DIR  (DIR holds transforms_train.json and transforms_test.json)")
    };
    let dir = PathBuf::from(dir);
    let scene = instgs_vk::formats::instgs::read(scene_path.as_ref())?;
    let gpu = Gpu::new(&GpuOptions::from_env(None))?;
    let k = Kernels::new(&gpu)?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    let instances: usize = scene.groups.iter().map(|g| g.instances.len()).sum();
    if instances > u16::MAX as usize {
        bail!("{instances} instances do not fit 16-bit ids");
    }
    let scenes: Vec<GpuScene> =
        (0..instances).map(|i| GpuScene::instanced(&gpu, &weight_scene(&scene, i))).collect::<Result<_>>()?;
    for split in ["train", "test"] {
        let cams = instgs_vk::model::camera::load_transforms(&dir.join(format!("transforms_{split}.json")))?;
        let out = dir.join("masks").join(split);
        std::fs::create_dir_all(&out).with_context(|| format!("{}: cannot create", out.display()))?;
        for cam in &cams {
            let n = (cam.width * cam.height) as usize;
            let (mut best, mut ids) = (vec![0.5f32; n], vec![0u16; n]);
            for (i, gs) in scenes.iter().enumerate() {
                let f = r.render(gs, cam, [0.0; 3])?;
                for (p, px) in f.image.iter().enumerate() {
                    if px[0] >= best[p] {
                        best[p] = px[0];
                        ids[p] = i as u16 + 1;
                    }
                }
            }
            let img =
                image::ImageBuffer::<image::Luma<u16>, _>::from_raw(cam.width, cam.height, ids).context("mask size")?;
            img.save(out.join(format!("{}.png", cam.name)))?;
        }
        eprintln!("{split}: {} masks", cams.len());
    }
    let mut id = 0;
    let groups: Vec<serde_json::Value> = scene
        .groups
        .iter()
        .map(|g| {
            let (lo, hi) = g.template.robust_bounds(0.02);
            let centre = 0.5 * (lo + hi);
            let instances: Vec<serde_json::Value> = g
                .instances
                .iter()
                .map(|inst| {
                    id += 1;
                    let x = &inst.transform;
                    let c: Vec3 = x.rotation * (centre * x.scale) + x.translation;
                    serde_json::json!({
                        "id": id, "object_to_world": mat4_to_rows(x.to_mat4()),
                        "center_world": c.to_array(), "scale": x.scale,
                    })
                })
                .collect();
            serde_json::json!({"name": g.name, "canonical_bbox": [lo.to_array(), hi.to_array()], "instances": instances})
        })
        .collect();
    let json = serde_json::json!({"num_instances": instances, "mask_background_id": 0, "groups": groups});
    std::fs::write(dir.join("instances.json"), serde_json::to_string_pretty(&json)?)?;
    eprintln!("wrote {}", dir.join("instances.json").display());
    let plain = scene.expand();
    let c = plain.sh_coeffs() * 3;
    let mut ply = Vec::new();
    let mut n = 0;
    for (i, m) in plain.means.iter().enumerate().step_by(4) {
        if instgs_vk::math::sigmoid(plain.opacities[i]) < 0.5 {
            continue;
        }
        let rgb = [0, 1, 2].map(|a| ((0.5 + SH_C0_F32 * plain.sh[i * c + a]).clamp(0.0, 1.0) * 255.0).round() as u8);
        ply.extend(m.iter().flat_map(|v| v.to_le_bytes()));
        ply.extend(rgb);
        n += 1;
    }
    let header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    );
    std::fs::write(dir.join("points3d.ply"), [header.into_bytes(), ply].concat())?;
    eprintln!("wrote {} ({n} points)", dir.join("points3d.ply").display());
    let m = gpu.take_validation_messages();
    if !m.is_empty() {
        bail!("{} Vulkan validation message(s), first: {}", m.len(), m[0]);
    }
    Ok(())
}
