//! Gradient-driven instance segmentation (InstGS paper §4.2, Eq. 3–5) of a trained plain scene
//! with per-view instance masks.
//!
//! For each view and instance mask M, one backward pass through the rasterizer of a masked loss
//! gives per-Gaussian scores GSeg(M); g = Σ_views GSeg(M) − α·Σ_views GSeg(1 − M) (α = 0.8 in
//! the paper). A Gaussian belongs to the instance with the largest positive g, to the
//! background when none is positive. The score of a Gaussian is the colour gradient of
//! L = Σ_pixels M·mean(rgb), i.e. the sum of its blending weights T·α over the mask's pixels
//! (a masked loss with unit residual: what a Gaussian contributes there, whatever the colours).
//! GSeg is linear in the mask, so GSeg(1 − M) = GSeg(1) − GSeg(M): per view one pass over all
//! pixels plus one per visible instance. Views are streamed; the scores live on the GPU.
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::dataset::View;
use crate::gpu::Gpu;
use crate::kernels::Kernels;
use crate::raster::{GpuScene, Grads, Rasterizer};
use crate::scene::Scene;
use crate::shared::{SegArgs, MAX_GROUPS, WG_SIZE};

/// A dataset's groups file (`instances.json`): groups of instance ids. Extra fields ignored.
#[derive(Clone, Debug, PartialEq)]
pub struct InstanceGroup {
    pub name: String,
    pub ids: Vec<u32>,
}

#[derive(serde::Deserialize)]
struct GroupsFile {
    groups: Vec<GroupEntry>,
}

#[derive(serde::Deserialize)]
struct GroupEntry {
    name: String,
    instances: Vec<InstanceEntry>,
}

#[derive(serde::Deserialize)]
struct InstanceEntry {
    id: u32,
}

/// Reads `instances.json`; ids must be positive (0 is the background) and unique.
pub fn read_groups(path: &Path) -> Result<Vec<InstanceGroup>> {
    let what = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    let f: GroupsFile = serde_json::from_str(&text)
        .with_context(|| format!("{what}: not a groups file ({{groups: [{{name, instances: [{{id}}]}}]}})"))?;
    let mut seen = std::collections::BTreeSet::new();
    let groups: Vec<InstanceGroup> = f
        .groups
        .into_iter()
        .map(|g| InstanceGroup { name: g.name, ids: g.instances.iter().map(|i| i.id).collect() })
        .collect();
    for g in &groups {
        for &id in &g.ids {
            if id == 0 {
                bail!("{what}: group {:?} uses id 0, the background's", g.name);
            }
            if !seen.insert(id) {
                bail!("{what}: instance id {id} appears twice");
            }
        }
    }
    Ok(groups)
}

/// Reads one mask (8- or 16-bit grey PNG of instance ids, 0 = background) of `width`×`height`.
pub fn read_mask(path: &Path, width: u32, height: u32) -> Result<Vec<u16>> {
    let what = path.display();
    let img = image::open(path).with_context(|| format!("{what}: cannot read mask"))?;
    let (w, h) = (img.width(), img.height());
    let img: Vec<u16> = match img {
        image::DynamicImage::ImageLuma8(m) => m.pixels().map(|p| p.0[0] as u16).collect(),
        image::DynamicImage::ImageLuma16(m) => m.pixels().map(|p| p.0[0]).collect(),
        other => bail!("{what}: a mask must be 8- or 16-bit greyscale, not {:?}", other.color()),
    };
    if (w, h) != (width, height) {
        bail!("{what}: mask is {w}x{h}, its image {width}x{height}");
    }
    Ok(img)
}

/// The masks of `views` (`masks/<split>/<image name>.png` under `data`), resized views refused.
pub fn load_masks(data: &Path, split: &str, views: &[View]) -> Result<Vec<Vec<u16>>> {
    views
        .iter()
        .map(|v| {
            let name = v.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            read_mask(&data.join("masks").join(split).join(&name), v.camera.width, v.camera.height)
        })
        .collect()
}

/// Per-Gaussian results: the instance id (0 = background) and g per instance.
pub struct Segmentation {
    pub ids: Vec<u32>,
    pub labels: Vec<u32>,
    /// Ids found in the masks that are not instances (their pixels count as background).
    pub unknown_ids: Vec<u32>,
    /// g for each of `ids`, per Gaussian: `g[k][i]`.
    pub g: Vec<Vec<f32>>,
}

/// Segments `scene` with `masks` (one per view, ids as `ids`); `alpha` weighs the background
/// removal term.
pub fn segment(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    views: &[View],
    masks: &[Vec<u16>],
    ids: &[u32],
    alpha: f32,
) -> Result<Segmentation> {
    if views.len() != masks.len() {
        bail!("{} views but {} masks", views.len(), masks.len());
    }
    for (v, m) in views.iter().zip(masks) {
        if m.len() != (v.camera.width * v.camera.height) as usize {
            bail!(
                "view {}: its mask has {} pixels, the view {}x{}",
                v.camera.name,
                m.len(),
                v.camera.width,
                v.camera.height
            );
        }
    }
    let mut unknown = std::collections::BTreeSet::new();
    for m in masks {
        unknown.extend(m.iter().map(|&x| x as u32).filter(|x| *x != 0 && !ids.contains(x)));
    }
    let gs = GpuScene::new(gpu, scene)?;
    let grads = Grads::new(gpu, &gs)?;
    let n = scene.len();
    let slots = ids.len() + 1;
    let scores = gpu.storage("seg_scores", (n * slots * 4) as u64)?;
    gpu.submit_and_wait(|rec| {
        rec.fill(&scores, 0);
        Ok(())
    })?;
    let mut r = Rasterizer::new(gpu, k)?;
    for (view, mask) in views.iter().zip(masks) {
        let cam = &view.camera;
        r.render(&gs, cam, [0.0; 3])?;
        // Slot `ids.len()`: every pixel; slot j: instance ids[j] where its mask has pixels.
        let mut passes: Vec<(u32, Vec<[f32; 4]>)> = vec![(ids.len() as u32, vec![[1.0, 1.0, 1.0, 0.0]; mask.len()])];
        for (j, &id) in ids.iter().enumerate() {
            if mask.iter().any(|&m| m as u32 == id) {
                let v = mask.iter().map(|&m| if m as u32 == id { [1.0, 1.0, 1.0, 0.0] } else { [0.0; 4] }).collect();
                passes.push((j as u32, v));
            }
        }
        for (slot, v_image) in passes {
            let v = gpu.upload("seg_v_image", &v_image)?;
            gpu.submit_and_wait(|rec| {
                r.record_blend_backward(rec, &gs, &v, &grads)?;
                let args = SegArgs { count: n as u32, slot, weight: 1.0, _pad0: 0 };
                rec.dispatch(
                    &k.seg_accumulate,
                    &[("v_colors", &grads.v_colors), ("scores", &scores)],
                    &args,
                    [(n as u32).div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
                )?;
                rec.end_pass("seg_accumulate")
            })?;
        }
    }
    let s: Vec<f32> = gpu.read(&scores, n * slots)?;
    let all = &s[ids.len() * n..];
    // g = Σ GSeg(M) − α Σ GSeg(1 − M) = (1 + α) Σ GSeg(M) − α Σ GSeg(1).
    let g: Vec<Vec<f32>> =
        (0..ids.len()).map(|j| (0..n).map(|i| (1.0 + alpha) * s[j * n + i] - alpha * all[i]).collect()).collect();
    let labels = (0..n)
        .map(|i| {
            let best = (0..ids.len()).max_by(|&a, &b| g[a][i].total_cmp(&g[b][i]));
            match best {
                Some(j) if g[j][i] > 0.0 => ids[j],
                _ => 0,
            }
        })
        .collect();
    let labels: Vec<u32> = labels;
    for &id in ids {
        if !labels.contains(&id) {
            let pixels: usize = masks.iter().map(|m| m.iter().filter(|&&x| x as u32 == id).count()).sum();
            bail!(
                "instance {id}: no Gaussian belongs to it ({pixels} mask pixels in {} views); is it in the scene, and are the masks aligned with the images?",
                views.len()
            );
        }
    }
    Ok(Segmentation { ids: ids.to_vec(), labels, g, unknown_ids: unknown.into_iter().collect() })
}

/// The Gaussians of `scene` labelled `id`.
pub fn subset(scene: &Scene, labels: &[u32], id: u32) -> Scene {
    let c = scene.sh_coeffs() * 3;
    let keep: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] == id).collect();
    Scene {
        means: keep.iter().map(|&i| scene.means[i]).collect(),
        scales: keep.iter().map(|&i| scene.scales[i]).collect(),
        quats: keep.iter().map(|&i| scene.quats[i]).collect(),
        opacities: keep.iter().map(|&i| scene.opacities[i]).collect(),
        sh: keep.iter().flat_map(|&i| scene.sh[i * c..(i + 1) * c].iter().copied()).collect(),
        sh_degree: scene.sh_degree,
    }
}

/// Per view, the IoU of instance `id`'s rendered visible region and its mask: the whole scene
/// rendered with the instance's Gaussians white and every other Gaussian black (so occluders
/// hide it as in the photos), thresholded at 0.5, against `mask == id`. Views where neither
/// has a pixel are skipped.
pub fn instance_iou(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    labels: &[u32],
    views: &[View],
    masks: &[Vec<u16>],
    id: u32,
) -> Result<Vec<f64>> {
    let mut s = scene.clone();
    s.sh_degree = 0;
    let c0 = crate::scene::SH_C0;
    s.sh = (0..scene.len()).flat_map(|i| [if labels[i] == id { 0.5 / c0 } else { -0.5 / c0 }; 3]).collect();
    let gs = GpuScene::new(gpu, &s)?;
    let mut r = Rasterizer::new(gpu, k)?;
    let mut out = Vec::new();
    for (v, m) in views.iter().zip(masks) {
        let f = r.render(&gs, &v.camera, [0.0; 3])?;
        let (mut inter, mut union) = (0u64, 0u64);
        for (p, &mid) in f.image.iter().zip(m) {
            let (a, b) = (p[0] > 0.5, mid as u32 == id);
            inter += (a && b) as u64;
            union += (a || b) as u64;
        }
        if union > 0 {
            out.push(inter as f64 / union as f64);
        }
    }
    Ok(out)
}
