//! The render check of a registered pose ([`crate::instancing::pose::RenderCheck`]) on the GPU: the
//! reference instance's Gaussians, placed by the pose where the instance stands, and the
//! instance's own Gaussians are each rendered alone (over black) from the training cameras that
//! see the instance best, and compared ([`compare`]): the placed silhouette (alpha > 0.5) with
//! the instance's mask by IoU, the colours with the instance's own render by PSNR after a
//! least-squares non-negative mix of the colour channels (instances of one group may differ by
//! a tint, which the offsets learn later). A collapsed, mirrored or turned pose cannot pass: its
//! silhouette or its colours disagree with the data in the views the instance was trained from.
//!
//! Views: those where the instance's own silhouette covers at least [`MIN_VIEW_PIXELS`]; with
//! masks whose ids are the labels' (`instances.json` datasets), only those where the mask shows
//! at least half of that silhouette (the instance is mostly unoccluded there); the
//! [`MAX_VIEWS`] with the largest silhouettes. A search's cheaper scores ([`Detail`]) take the
//! first [`SEARCH_VIEWS`] of them, at full or half resolution (the instance's own renders and
//! the mask sampled there too).
//!
//! Crops: every render covers only the instance's window in the view ([`window`]: the
//! projected extent of its Gaussians, three standard deviations wide, plus a [`CROP_MARGIN`]),
//! the same pixels as the whole image there. Objects cover a few hundred of a view's 170 000
//! pixels on a walk-through scene (cafe40): the renders, read-backs and comparisons shrink
//! with the crop. The mask's pixels of the instance outside the crop still count in the IoU's
//! union; a placed reference is assumed to show nothing outside it (a pose that moves it past
//! the margin leaves most of the instance's pixels uncovered and fails the IoU anyway).
use std::collections::HashMap;
use std::sync::Arc;

use anyhow::Result;
use glam::Vec3;
use nalgebra::{DMatrix, DVector};

use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::instancing::pose::{sim3_to_similarity, Detail, RenderCheck, RenderScore, MIN_OWN_IOU, SEARCH_VIEWS};
use crate::model::camera::Camera;
use crate::model::instanced::transform_gaussians;
use crate::model::scene::Scene;
use crate::register::Sim3;
use crate::render::raster::{Rasterizer, NEAR_PLANE};
use crate::render::upload::GpuScene;

/// An RGBA render (rgb over black, a = final transmittance), row-major.
type Pixel = [f32; 4];
type Image = Vec<Pixel>;

/// Views compared per instance at most. More views pin a pose down better where each sees
/// the instance small: on the demo (ducks ~30 px wide) the refined poses came within 2.9° with
/// 24 views and 0.9–5.0° with 12, 0.9–5.0° with 6 (BENCHMARKS.md, "The demo").
pub const MAX_VIEWS: usize = 24;
/// A view counts when the instance's own silhouette covers at least this many pixels.
pub const MIN_VIEW_PIXELS: usize = 64;
/// A crop reaches this fraction of the instance's window's larger side (at least
/// [`MIN_CROP_MARGIN`] pixels) past the window on every side.
pub const CROP_MARGIN: f32 = 0.25;
pub const MIN_CROP_MARGIN: f32 = 8.0;

/// One view of an instance kept for its checks: the crop's camera, the instance's own render
/// there, the mask's crop, and the mask's pixels of the instance outside the crop.
struct OwnView {
    camera: Camera,
    image: Image,
    mask: Option<Vec<u16>>,
    truth_outside: usize,
}

/// [`RenderCheck`] on the GPU over a dataset's training cameras.
pub struct ImageCheck {
    gpu: Arc<Gpu>,
    rasterizer: Rasterizer,
    cameras: Vec<Camera>,
    masks: Option<Vec<Vec<u16>>>,
    /// Per instance id and detail: the chosen views, cropped, and the instance's own renders
    /// there.
    own: HashMap<(u32, Detail), Vec<OwnView>>,
}

/// The pixels (x0, y0, x1, y1; half-open, inside the image) where `scene` can show in `cam`:
/// every Gaussian's mean ± three standard deviations of its largest axis, projected, plus the
/// crop margin. The whole image when a Gaussian reaches the near plane (its projection is
/// unbounded); None when none is in front of the camera or the window misses the image.
pub fn window(scene: &Scene, cam: &Camera) -> Option<[u32; 4]> {
    let (w, h) = (cam.width as f32, cam.height as f32);
    let mut b = [f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
    for (m, s) in scene.means.iter().zip(&scene.scales) {
        let r = 3.0 * s[0].max(s[1]).max(s[2]).exp();
        let c = cam.viewmat.transform_point3(Vec3::from(*m));
        if c.z + r <= NEAR_PLANE {
            continue;
        }
        if c.z - r <= NEAR_PLANE {
            return Some([0, 0, cam.width, cam.height]);
        }
        let (u, v) = (cam.fx * c.x / c.z + cam.cx, cam.fy * c.y / c.z + cam.cy);
        let (ru, rv) = (cam.fx * r / (c.z - r), cam.fy * r / (c.z - r));
        b = [b[0].min(u - ru), b[1].min(v - rv), b[2].max(u + ru), b[3].max(v + rv)];
    }
    if !b.iter().all(|v| v.is_finite()) {
        return None;
    }
    let margin = (CROP_MARGIN * (b[2] - b[0]).max(b[3] - b[1])).max(MIN_CROP_MARGIN);
    let x0 = (b[0] - margin).floor().clamp(0.0, w);
    let y0 = (b[1] - margin).floor().clamp(0.0, h);
    let x1 = (b[2] + margin).ceil().clamp(0.0, w);
    let y1 = (b[3] + margin).ceil().clamp(0.0, h);
    (x1 > x0 && y1 > y0).then_some([x0 as u32, y0 as u32, x1 as u32, y1 as u32])
}

impl ImageCheck {
    /// `masks` (one per camera, ids = the labels' instance ids) restrict the views to those
    /// where the instance is mostly unoccluded; without them every camera may be used.
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, cameras: Vec<Camera>, masks: Option<Vec<Vec<u16>>>) -> Result<Self> {
        Ok(ImageCheck { gpu: gpu.clone(), rasterizer: Rasterizer::new(gpu, k)?, cameras, masks, own: HashMap::new() })
    }

    fn render<'a>(&mut self, scene: &Scene, cameras: impl Iterator<Item = &'a Camera>) -> Result<Vec<Image>> {
        let gs = GpuScene::new(&self.gpu, scene)?;
        cameras.map(|c| Ok(self.rasterizer.render(&gs, c, [0.0; 3])?.image)).collect()
    }

    /// The instance's views at `detail` (Full or Coarse), chosen (and rendered) on first use.
    fn own_views(&mut self, instance: &Scene, id: u32, detail: Detail) -> Result<()> {
        if !self.own.contains_key(&(id, detail)) {
            let views = match detail {
                Detail::Coarse => self.coarse_views(instance, id)?,
                _ => self.full_views(instance, id)?,
            };
            self.own.insert((id, detail), views);
        }
        Ok(())
    }

    /// The first [`SEARCH_VIEWS`] full views at half resolution, the instance rendered there.
    fn coarse_views(&mut self, instance: &Scene, id: u32) -> Result<Vec<OwnView>> {
        self.own_views(instance, id, Detail::Full)?;
        let coarse: Vec<(Camera, Option<Vec<u16>>, usize)> = self.own[&(id, Detail::Full)]
            .iter()
            .take(SEARCH_VIEWS)
            .map(|o| {
                let (camera, mask) = half_resolution(&o.camera, o.mask.as_deref());
                (camera, mask, o.truth_outside / 4)
            })
            .collect();
        let images = self.render(instance, coarse.iter().map(|c| &c.0))?;
        Ok(coarse
            .into_iter()
            .zip(images)
            .map(|((camera, mask, truth_outside), image)| OwnView { camera, image, mask, truth_outside })
            .collect())
    }

    /// The views where the instance shows (module docs), largest first, with its own renders.
    fn full_views(&mut self, instance: &Scene, id: u32) -> Result<Vec<OwnView>> {
        let crops: Vec<(usize, [u32; 4], Camera)> = (0..self.cameras.len())
            .filter_map(|v| {
                let [x0, y0, x1, y1] = window(instance, &self.cameras[v])?;
                Some((v, [x0, y0, x1, y1], self.cameras[v].cropped(x0, y0, x1 - x0, y1 - y0)))
            })
            .collect();
        let images = self.render(instance, crops.iter().map(|c| &c.2))?;
        let mut seen: Vec<(usize, usize, OwnView)> = Vec::new();
        for ((v, [x0, y0, x1, y1], camera), image) in crops.into_iter().zip(images) {
            let area = image.iter().filter(|p| silhouette(p)).count();
            let full_width = self.cameras[v].width as usize;
            let (mask, shown, truth_outside) = match &self.masks {
                Some(m) => {
                    let crop: Vec<u16> = (y0..y1)
                        .flat_map(|y| {
                            let row = y as usize * full_width;
                            m[v][row + x0 as usize..row + x1 as usize].iter().copied()
                        })
                        .collect();
                    let shown = m[v].iter().filter(|&&x| x as u32 == id).count();
                    let inside = crop.iter().filter(|&&x| x as u32 == id).count();
                    (Some(crop), shown, shown - inside)
                }
                None => (None, area, 0),
            };
            if area >= MIN_VIEW_PIXELS && 2 * shown >= area {
                seen.push((area, v, OwnView { camera, image, mask, truth_outside }));
            }
        }
        seen.sort_by_key(|s| (std::cmp::Reverse(s.0), s.1));
        seen.truncate(MAX_VIEWS);
        Ok(seen.into_iter().map(|(_, _, o)| o).collect())
    }
}

/// A pixel of a render over black belongs to the silhouette (alpha = 1 − T > 0.5).
fn silhouette(p: &[f32; 4]) -> bool {
    p[3] < 0.5
}

/// `camera` at half its resolution (rounded up; the same rays through pixel-centre-scaled
/// intrinsics) and `mask` sampled there (each half-resolution pixel takes the mask's pixel at
/// its top-left full-resolution pixel).
fn half_resolution(camera: &Camera, mask: Option<&[u16]>) -> (Camera, Option<Vec<u16>>) {
    let (w, h) = (camera.width.div_ceil(2), camera.height.div_ceil(2));
    let half = Camera {
        width: w,
        height: h,
        fx: camera.fx / 2.0,
        fy: camera.fy / 2.0,
        cx: camera.cx / 2.0,
        cy: camera.cy / 2.0,
        ..camera.clone()
    };
    let full_width = camera.width as usize;
    let mask = mask
        .map(|m| (0..h as usize).flat_map(|y| (0..w as usize).map(move |x| m[2 * y * full_width + 2 * x])).collect());
    (half, mask)
}

impl RenderCheck for ImageCheck {
    fn score_at(
        &mut self,
        reference: &Scene,
        instance: &Scene,
        id: u32,
        x: &Sim3,
        detail: Detail,
    ) -> Result<Option<RenderScore>> {
        // Fine: the first of the full views (they are kept largest silhouette first).
        let (key, views) = match detail {
            Detail::Fine => ((id, Detail::Full), SEARCH_VIEWS),
            _ => ((id, detail), usize::MAX),
        };
        self.own_views(instance, id, key.1)?;
        // Out of the map while the rasterizer renders (no copy of the images).
        let own = self.own.remove(&key).unwrap_or_default();
        let score = self.score_own(reference, &own[..own.len().min(views)], id, x);
        self.own.insert(key, own);
        score
    }

    /// From the instance's own renders alone (no render: placed where it is, the instance
    /// renders as its own).
    fn own_iou(&mut self, instance: &Scene, id: u32) -> Result<Option<f64>> {
        self.own_views(instance, id, Detail::Full)?;
        let own = &self.own[&(id, Detail::Full)];
        let compared: Vec<Compared> = own
            .iter()
            .map(|o| Compared {
                own: &o.image,
                placed: &o.image,
                mask: o.mask.as_deref(),
                truth_outside: o.truth_outside,
            })
            .collect();
        Ok((!compared.is_empty()).then(|| compare(&compared, id).own_iou))
    }
}

impl ImageCheck {
    fn score_own(&mut self, reference: &Scene, own: &[OwnView], id: u32, x: &Sim3) -> Result<Option<RenderScore>> {
        if own.is_empty() {
            return Ok(None);
        }
        let placed = transform_gaussians(reference, &sim3_to_similarity(&x.inverse()));
        let renders = self.render(&placed, own.iter().map(|o| &o.camera))?;
        let compared: Vec<Compared> = own
            .iter()
            .zip(&renders)
            .map(|(o, placed)| Compared {
                own: &o.image,
                placed,
                mask: o.mask.as_deref(),
                truth_outside: o.truth_outside,
            })
            .collect();
        Ok(Some(compare(&compared, id)))
    }
}

/// One view of a render check: the instance's own render, the placed reference's, and the
/// view's mask where the masks' ids are the labels'.
pub struct Compared<'a> {
    pub own: &'a [Pixel],
    pub placed: &'a [Pixel],
    pub mask: Option<&'a [u16]>,
    /// The mask's pixels of the instance outside these (a crop's): in the IoU's union.
    pub truth_outside: usize,
}

/// Scores a pose over the compared views. IoU: the placed reference's silhouette against the
/// mask's pixels of `id` (pixels of other instances — occluders — left out), or against the
/// instance's own silhouette without masks; the median over views; the instance's own
/// silhouette's IoU with the mask, and the placed one's relative to it, the same way. PSNR: the placed
/// reference's colours mapped by the least-squares non-negative mix of its channels that best
/// matches (a tint changes the diffuse colour, not the white highlights) against the instance's
/// own, over the pixels either silhouette covers (so a slightly turned or shifted pose costs
/// PSNR along the outline); the same after a gain per channel alone for choosing and refining
/// poses (`pose_psnr`).
pub fn compare(views: &[Compared], id: u32) -> RenderScore {
    let (mut ious, mut own_ious, mut relative) = (Vec::new(), Vec::new(), Vec::new());
    let mut fit = ColourMap::default();
    for v in views {
        let (mut inter, mut union) = (0usize, v.truth_outside);
        let (mut own_inter, mut own_union) = (0usize, v.truth_outside);
        for (i, (p, q)) in v.own.iter().zip(v.placed).enumerate() {
            let (s, t) = (silhouette(p), silhouette(q));
            if s || t {
                fit.add(p, q);
            }
            let truth = match v.mask {
                Some(m) if m[i] != 0 && m[i] as u32 != id => continue,
                Some(m) => m[i] as u32 == id,
                None => s,
            };
            inter += (truth && t) as usize;
            union += (truth || t) as usize;
            own_inter += (truth && s) as usize;
            own_union += (truth || s) as usize;
        }
        let iou = if union > 0 { inter as f64 / union as f64 } else { 0.0 };
        let own = if own_union > 0 { own_inter as f64 / own_union as f64 } else { 0.0 };
        ious.push(iou);
        own_ious.push(own);
        relative.push(iou / own.max(MIN_OWN_IOU));
    }
    let db = |mse: Option<f64>| match mse {
        None => 0.0,
        Some(mse) if mse > 0.0 => -10.0 * mse.log10(),
        Some(_) => f64::INFINITY,
    };
    RenderScore {
        views: views.len(),
        iou: crate::math::median(&ious),
        own_iou: crate::math::median(&own_ious),
        relative_iou: crate::math::median(&relative),
        psnr: db(fit.mse()),
        pose_psnr: db(fit.gain_mse()),
    }
}

/// The least-squares colour map from the placed reference's render q to the instance's own p:
/// each output channel a non-negative mix of q's three channels, `p_c ≈ Σ_k m_ck q_k`, m ≥ 0.
/// Instances of a group differ by a tint of the diffuse colour while highlights stay white
/// (tabletop's mugs: yellow, blue, green and pink, channel ratios up to 6×), so a gain per
/// channel cannot map one onto another: `0.83·d + s` (yellow's green) is
/// `a·(d + s) + b·(0.22·d + s) + c·(0.78·d + s)` from pink's with `a + b + c = 1`, not a
/// multiple of pink's green. A mix cannot move or reshape anything, so a wrongly placed
/// reference still disagrees with the instance's own render; non-negative so that no map
/// inverts the shading.
#[derive(Default)]
struct ColourMap {
    /// Σ q qᵀ (symmetric), Σ p_c q, Σ p_c², pixel count.
    qq: [[f64; 3]; 3],
    pq: [[f64; 3]; 3],
    pp: [f64; 3],
    n: usize,
}

impl ColourMap {
    fn add(&mut self, p: &Pixel, q: &Pixel) {
        for c in 0..3 {
            self.pp[c] += p[c] as f64 * p[c] as f64;
            for k in 0..3 {
                self.qq[c][k] += q[c] as f64 * q[k] as f64;
                self.pq[c][k] += p[c] as f64 * q[k] as f64;
            }
        }
        self.n += 1;
    }

    /// The mean squared error per channel value of the best map; None without pixels.
    fn mse(&self) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let sse: f64 = (0..3).map(|c| self.best_channel(c)).sum();
        Some(sse.max(0.0) / (3 * self.n) as f64)
    }

    /// The mean squared error per channel value after a least-squares gain per channel
    /// (clamped to [1/4, 4]) alone: fewer colour degrees of freedom, so less of a misplaced
    /// pose's error is absorbed by the colours ([`RenderScore::pose_psnr`]).
    fn gain_mse(&self) -> Option<f64> {
        if self.n == 0 {
            return None;
        }
        let sse: f64 = (0..3)
            .map(|c| {
                let (pq, qq) = (self.pq[c][c], self.qq[c][c]);
                let g = if qq > 0.0 { (pq / qq).clamp(0.25, 4.0) } else { 1.0 };
                self.pp[c] - 2.0 * g * pq + g * g * qq
            })
            .sum();
        Some(sse.max(0.0) / (3 * self.n) as f64)
    }

    /// Non-negative least squares for one output channel over three inputs, exactly: the best
    /// over the input subsets whose unconstrained solution is non-negative (the empty map, 0,
    /// included), since the optimum is the unconstrained optimum on its support.
    fn best_channel(&self, c: usize) -> f64 {
        let mut best = self.pp[c];
        for support in 1u32..8 {
            let idx: Vec<usize> = (0..3).filter(|k| support >> k & 1 == 1).collect();
            let a = DMatrix::from_fn(idx.len(), idx.len(), |i, j| self.qq[idx[i]][idx[j]]);
            let b = DVector::from_iterator(idx.len(), idx.iter().map(|&i| self.pq[c][i]));
            // Singular: a channel the reference's render never lights (it is left out in
            // a smaller support).
            let Some(m) = a.clone().cholesky().map(|ch| ch.solve(&b)) else { continue };
            if m.iter().any(|x| *x < 0.0) {
                continue;
            }
            // SSE = Σp² − 2 mᵀb + mᵀ A m, in full: a nearly singular solve's m is then
            // scored by what it really leaves.
            let sse = self.pp[c] - 2.0 * m.dot(&b) + (&a * &m).dot(&m);
            best = best.min(sse);
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instancing::options::Acceptance;

    /// A shaded, highlighted object tinted two ways: diffuse d·tint plus a white highlight h.
    fn tinted(tint: [f32; 3], n: usize) -> Vec<Pixel> {
        (0..n)
            .map(|i| {
                let d = 0.2 + 0.6 * ((i as f32 * 0.37).sin() * 0.5 + 0.5);
                let h = if i % 7 == 0 { 0.3 } else { 0.0 };
                [d * tint[0] + h, d * tint[1] + h, d * tint[2] + h, 0.0]
            })
            .collect()
    }

    fn psnr(own: &[Pixel], placed: &[Pixel]) -> f64 {
        compare(&[Compared { own, placed, mask: None, truth_outside: 0 }], 1).psnr
    }

    #[test]
    fn a_tint_with_white_highlights_maps_far_better_than_a_gain_per_channel() {
        // tabletop's yellow mug from its green and pink ones. Yellow's blue (0.19 of the
        // diffuse) lies below every channel of pink's (0.22–1), so no non-negative mix of pink
        // with its highlight gives it exactly; green's (0.17–1) does.
        let yellow = tinted([1.0, 0.8261, 0.1916], 500);
        for (tint, at_least) in [([0.1668, 1.0, 0.4042], 60.0), ([1.0, 0.2219, 0.7783], 40.0)] {
            let other = tinted(tint, 500);
            let score = compare(&[Compared { own: &yellow, placed: &other, mask: None, truth_outside: 0 }], 1);
            let (mix_psnr, gain_psnr) = (score.psnr, score.pose_psnr);
            assert!(mix_psnr > at_least && mix_psnr > gain_psnr + 10.0, "mix {mix_psnr} dB, gain {gain_psnr} dB");
        }
    }

    #[test]
    fn a_silhouette_is_judged_against_what_the_instance_itself_reaches() {
        // A 10 × 10 view: the instance's own silhouette covers rows 0–5, its mask rows 0–7
        // (a semi-transparent base its Gaussians render under alpha 0.5): own IoU 0.75.
        let rows = |r: usize| -> Vec<Pixel> {
            (0..100).map(|i| [0.5, 0.5, 0.5, if i < 10 * r { 0.0 } else { 1.0 }]).collect()
        };
        let (own, mask): (Vec<Pixel>, Vec<u16>) = (rows(6), (0..100).map(|i| (i < 80) as u16).collect());
        let at = |placed: &[Pixel], mask: Option<&[u16]>| {
            compare(&[Compared { own: &own, placed, mask, truth_outside: 0 }], 1)
        };
        // The same silhouette placed: IoU 0.75, all the instance itself reaches.
        let s = at(&own, Some(&mask));
        assert!((s.iou - 0.75).abs() < 1e-12 && (s.own_iou - 0.75).abs() < 1e-12, "{s:?}");
        assert!((s.relative_iou - 1.0).abs() < 1e-12, "{s:?}");
        assert!(s
            .failure(&Acceptance { min_render_psnr: 0.0, min_render_views: 1, ..Acceptance::default() })
            .is_none());
        // Rows 0–3 only: IoU 0.5, two thirds of the own: refused.
        let s = at(&rows(4), Some(&mask));
        assert!((s.relative_iou - 0.5 / 0.75).abs() < 1e-12, "{s:?}");
        let why = s.failure(&Acceptance { min_render_psnr: 0.0, min_render_views: 1, ..Acceptance::default() });
        assert!(why.is_some_and(|w| w.contains("render IoU 0.50, 0.67 of the instance's own 0.75")));
        // Without masks the own silhouette is the truth: own IoU 1.
        let s = at(&rows(4), None);
        assert!((s.own_iou - 1.0).abs() < 1e-12 && (s.relative_iou - s.iou).abs() < 1e-12, "{s:?}");
        // An own silhouette that misses its mask counts as MIN_OWN_IOU.
        let s = at(&rows(6), Some(&(0..100).map(|i| (i >= 90) as u16).collect::<Vec<_>>()));
        assert_eq!(s.own_iou, 0.0);
        assert_eq!(s.relative_iou, s.iou / MIN_OWN_IOU);
    }

    #[test]
    fn half_resolution_sees_the_same_rays_and_samples_the_mask() {
        let cam = Camera::from_c2w_opengl("c", glam::Mat4::IDENTITY, 7, 5, [6.0, 6.0, 3.5, 2.5]);
        let mask: Vec<u16> = (0..35).collect();
        let (half, m) = half_resolution(&cam, Some(&mask));
        assert_eq!((half.width, half.height), (4, 3));
        let p = Vec3::new(0.3, -0.2, -2.0);
        let (a, b) = (cam.project(p).unwrap(), half.project(p).unwrap());
        assert!((a[0] / 2.0 - b[0]).abs() < 1e-6 && (a[1] / 2.0 - b[1]).abs() < 1e-6, "{a:?} {b:?}");
        // Each half-resolution pixel takes its top-left full-resolution pixel's id.
        assert_eq!(m.unwrap(), [0, 2, 4, 6, 14, 16, 18, 20, 28, 30, 32, 34]);
    }

    #[test]
    fn a_map_cannot_move_the_shading_nor_invert_it() {
        let a = tinted([0.9, 0.6, 0.3], 500);
        let shifted: Vec<Pixel> = (0..500).map(|i| a[(i + 9) % 500]).collect();
        assert!(psnr(&a, &shifted) < 25.0, "{}", psnr(&a, &shifted));
        let inverted: Vec<Pixel> = a.iter().map(|p| [1.0 - p[0], 1.0 - p[1], 1.0 - p[2], 0.0]).collect();
        // The best non-negative map of an inverted render is no better than a flat grey.
        assert!(psnr(&a, &inverted) < 20.0, "{}", psnr(&a, &inverted));
    }
}
