//! The render check of a registered pose ([`crate::instancing::template::RenderCheck`]) on the GPU: the
//! reference instance's Gaussians, placed by the pose where the instance stands, and the
//! instance's own Gaussians are each rendered alone (over black) from the training cameras that
//! see the instance best, and compared ([`compare`]): the placed silhouette (alpha > 0.5) with
//! the instance's mask by IoU, the colours with the instance's own render by PSNR after a
//! least-squares gain per channel (instances of one group may differ by a tint, which the
//! offsets learn later). A collapsed, mirrored or turned pose cannot pass: its silhouette or its
//! colours disagree with the data in the views the instance was trained from.
//!
//! Views: those where the instance's own silhouette covers at least [`MIN_VIEW_PIXELS`]; with
//! masks whose ids are the labels' (`instances.json` datasets), only those where the mask shows
//! at least half of that silhouette (the instance is mostly unoccluded there); the
//! [`MAX_VIEWS`] with the largest silhouettes.
use std::collections::HashMap;
use std::sync::Arc;

use anyhow::Result;

use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::instancing::template::{sim3_to_similarity, transform_gaussians, RenderCheck, RenderScore};
use crate::model::camera::Camera;
use crate::model::scene::Scene;
use crate::register::Sim3;
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;

/// An RGBA render (rgb over black, a = final transmittance), row-major.
type Pixel = [f32; 4];
type Image = Vec<Pixel>;
/// Renders of one scene: (camera index, image).
type Renders = Vec<(usize, Image)>;

/// Views compared per instance at most. More views pin a pose down better where each sees
/// the instance small: on the demo (ducks ~30 px wide) the refined poses came within 2.9° with
/// 24 views and 0.9–5.0° with 12, 0.9–5.0° with 6 (BENCHMARKS.md, "The demo").
pub const MAX_VIEWS: usize = 24;
/// A view counts when the instance's own silhouette covers at least this many pixels.
pub const MIN_VIEW_PIXELS: usize = 64;

/// [`RenderCheck`] on the GPU over a dataset's training cameras.
pub struct ImageCheck {
    gpu: Arc<Gpu>,
    rasterizer: Rasterizer,
    cameras: Vec<Camera>,
    masks: Option<Vec<Vec<u16>>>,
    /// Per instance id: the chosen views and the instance's own renders there.
    own: HashMap<u32, Renders>,
}

impl ImageCheck {
    /// `masks` (one per camera, ids = the labels' instance ids) restrict the views to those
    /// where the instance is mostly unoccluded; without them every camera may be used.
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, cameras: Vec<Camera>, masks: Option<Vec<Vec<u16>>>) -> Result<Self> {
        Ok(ImageCheck { gpu: gpu.clone(), rasterizer: Rasterizer::new(gpu, k)?, cameras, masks, own: HashMap::new() })
    }

    fn render(&mut self, scene: &Scene, views: impl Iterator<Item = usize>) -> Result<Renders> {
        let gs = GpuScene::new(&self.gpu, scene)?;
        views.map(|v| Ok((v, self.rasterizer.render(&gs, &self.cameras[v], [0.0; 3])?.image))).collect()
    }

    fn own_views(&mut self, instance: &Scene, id: u32) -> Result<&[(usize, Image)]> {
        if !self.own.contains_key(&id) {
            let all = self.render(instance, 0..self.cameras.len())?;
            let mut seen: Vec<(usize, usize, Image)> = Vec::new();
            for (v, img) in all {
                let area = img.iter().filter(|p| silhouette(p)).count();
                let shown = match &self.masks {
                    Some(m) => m[v].iter().filter(|&&x| x as u32 == id).count(),
                    None => area,
                };
                if area >= MIN_VIEW_PIXELS && 2 * shown >= area {
                    seen.push((area, v, img));
                }
            }
            seen.sort_by_key(|s| (std::cmp::Reverse(s.0), s.1));
            seen.truncate(MAX_VIEWS);
            self.own.insert(id, seen.into_iter().map(|(_, v, img)| (v, img)).collect());
        }
        Ok(&self.own[&id])
    }
}

/// A pixel of a render over black belongs to the silhouette (alpha = 1 − T > 0.5).
fn silhouette(p: &[f32; 4]) -> bool {
    p[3] < 0.5
}

impl RenderCheck for ImageCheck {
    fn score(&mut self, reference: &Scene, instance: &Scene, id: u32, x: &Sim3) -> Result<Option<RenderScore>> {
        let own: Renders = self.own_views(instance, id)?.to_vec();
        if own.is_empty() {
            return Ok(None);
        }
        let placed = transform_gaussians(reference, &sim3_to_similarity(&x.inverse()));
        let renders = self.render(&placed, own.iter().map(|(v, _)| *v))?;
        let masks = self.masks.as_ref();
        let views: Vec<Compared> = own
            .iter()
            .zip(&renders)
            .map(|((v, a), (_, b))| Compared { own: a, placed: b, mask: masks.map(|m| m[*v].as_slice()) })
            .collect();
        Ok(Some(compare(&views, id)))
    }
}

/// One view of a render check: the instance's own render, the placed reference's, and the
/// view's mask where the masks' ids are the labels'.
pub struct Compared<'a> {
    pub own: &'a [Pixel],
    pub placed: &'a [Pixel],
    pub mask: Option<&'a [u16]>,
}

/// Scores a pose over the compared views. IoU: the placed reference's silhouette against the
/// mask's pixels of `id` (pixels of other instances — occluders — left out), or against the
/// instance's own silhouette without masks; the median over views. PSNR: the placed
/// reference's colours × a per-channel least-squares gain (clamped to [1/4, 4]: the tint)
/// against the instance's own, over the pixels either silhouette covers (so a slightly turned
/// or shifted pose costs PSNR along the outline: pose refinement climbs this).
pub fn compare(views: &[Compared], id: u32) -> RenderScore {
    let mut ious = Vec::new();
    let (mut ab, mut bb) = ([0.0f64; 3], [0.0f64; 3]);
    for v in views {
        let (mut inter, mut union) = (0usize, 0usize);
        for (i, (p, q)) in v.own.iter().zip(v.placed).enumerate() {
            let (s, t) = (silhouette(p), silhouette(q));
            if s || t {
                for c in 0..3 {
                    ab[c] += p[c] as f64 * q[c] as f64;
                    bb[c] += q[c] as f64 * q[c] as f64;
                }
            }
            let truth = match v.mask {
                Some(m) if m[i] != 0 && m[i] as u32 != id => continue,
                Some(m) => m[i] as u32 == id,
                None => s,
            };
            inter += (truth && t) as usize;
            union += (truth || t) as usize;
        }
        ious.push(if union > 0 { inter as f64 / union as f64 } else { 0.0 });
    }
    let gain: [f64; 3] = std::array::from_fn(|c| if bb[c] > 0.0 { (ab[c] / bb[c]).clamp(0.25, 4.0) } else { 1.0 });
    let (mut sq, mut n) = (0.0f64, 0usize);
    for v in views {
        for (p, q) in v.own.iter().zip(v.placed) {
            if silhouette(p) || silhouette(q) {
                for c in 0..3 {
                    sq += (p[c] as f64 - gain[c] * q[c] as f64).powi(2);
                }
                n += 3;
            }
        }
    }
    let psnr = if n == 0 {
        0.0
    } else {
        let mse = sq / n as f64;
        if mse > 0.0 {
            -10.0 * mse.log10()
        } else {
            f64::INFINITY
        }
    };
    RenderScore { views: views.len(), iou: crate::math::median(&ious), psnr }
}
