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
//! pixels plus one per three visible instances (a colour channel each) that walks only their
//! masks' pixels. Views are streamed; the scores live on the GPU.
pub mod run;

use std::collections::BTreeMap;

use std::sync::Arc;

use anyhow::{bail, Result};

use crate::dataset::masks::InstanceGroup;
use crate::dataset::View;
use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::model::scene::Scene;
use crate::render::raster::backward::Grads;
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;
use crate::shared::{SegArgs, MAX_GROUPS, WG_SIZE};
use crate::util::{Progress, ProgressMode};

/// Per-Gaussian results: the instance id (0 = background) and g per instance.
pub struct Segmentation {
    pub ids: Vec<u32>,
    pub labels: Vec<u32>,
    /// Ids found in the masks that are not instances (their pixels count as background).
    pub unknown_ids: Vec<u32>,
    /// g for each of `ids`, per Gaussian: `g[k][i]`.
    pub g: Vec<Vec<f32>>,
    /// GSeg(1) per Gaussian: its blending weight T·α summed over every pixel of every view —
    /// how much it contributes to the pictures (LightGaussian's global significance without
    /// the volume term). Background pruning keeps the most significant.
    pub weight: Vec<f32>,
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
    segment_with_progress(gpu, k, scene, views, masks, ids, alpha, |_, _| {})
}

/// [`segment`], calling `progress(views done, views)` after each view.
#[allow(clippy::too_many_arguments)]
pub fn segment_with_progress(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    views: &[View],
    masks: &[Vec<u16>],
    ids: &[u32],
    alpha: f32,
    mut progress: impl FnMut(usize, usize),
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
    let n = scene.len();
    let mut scorer = Scorer::new(gpu, k, scene, ids.len() + 1)?;
    for (i, (view, mask)) in views.iter().zip(masks).enumerate() {
        scorer.add_view(view, mask, ids)?;
        progress(i + 1, views.len());
    }
    let s = scorer.read()?;
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
    Ok(Segmentation { ids: ids.to_vec(), labels, g, weight: all.to_vec(), unknown_ids: unknown.into_iter().collect() })
}

/// Each Gaussian's significance over `views`: its blending weight T·α summed over every pixel
/// (GSeg(1), [`Segmentation::weight`] without masks); `progress(views done, views)`.
pub fn significance(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    views: &[View],
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<f32>> {
    let mut scorer = Scorer::new(gpu, k, scene, 1)?;
    for (i, view) in views.iter().enumerate() {
        let none = vec![0u16; (view.camera.width * view.camera.height) as usize];
        scorer.add_view(view, &none, &[])?;
        progress(i + 1, views.len());
    }
    scorer.read()
}

/// One backward pass of [`Scorer`]: its v_image and the (slot, channel) pairs it fills.
type Pass = (Vec<[f32; 4]>, Vec<(u32, u32)>);

/// Per-Gaussian GSeg sums on the GPU: slot j < ids.len() for mask id ids[j], the last slot for
/// every pixel (GSeg(1)); `scores[slot·n + i]`.
struct Scorer<'a> {
    gpu: &'a Arc<Gpu>,
    k: &'a Arc<Kernels>,
    gs: GpuScene,
    grads: Grads,
    scores: crate::gpu::Buffer,
    r: Rasterizer,
    n: usize,
    slots: usize,
}

impl<'a> Scorer<'a> {
    fn new(gpu: &'a Arc<Gpu>, k: &'a Arc<Kernels>, scene: &Scene, slots: usize) -> Result<Scorer<'a>> {
        let gs = GpuScene::new(gpu, scene)?;
        let grads = Grads::new(gpu, &gs)?;
        let n = scene.len();
        let scores = gpu.storage("seg_scores", (n * slots * 4) as u64)?;
        let r = Rasterizer::new(gpu, k)?;
        let s = Scorer { gpu, k, gs, grads, scores, r, n, slots };
        s.clear()?;
        Ok(s)
    }

    fn clear(&self) -> Result<()> {
        self.gpu.submit_and_wait(|rec| {
            rec.fill(&self.scores, 0);
            Ok(())
        })
    }

    /// Adds one view: GSeg(1) to the last slot, GSeg(mask == ids[j]) to slot j for each id with
    /// pixels in the mask. A backward pass carries three instance masks, one per colour channel
    /// (the gradient's channels are independent): on a walk-through view of 30 instances, 11
    /// passes instead of 31.
    fn add_view(&mut self, view: &View, mask: &[u16], ids: &[u32]) -> Result<()> {
        let (gpu, k, n) = (self.gpu, self.k, self.n);
        self.r.render(&self.gs, &view.camera, [0.0; 3])?;
        // (v_image, [(slot, channel)]): the all-pixels pass in every channel, then the shown
        // instances three at a time.
        let mut passes: Vec<Pass> = vec![(vec![[1.0, 1.0, 1.0, 0.0]; mask.len()], vec![(self.slots as u32 - 1, 3)])];
        let mut present = std::collections::BTreeSet::new();
        present.extend(mask.iter().map(|&m| m as u32));
        let shown: Vec<(usize, u32)> = ids.iter().copied().enumerate().filter(|(_, id)| present.contains(id)).collect();
        for three in shown.chunks(3) {
            let v = mask
                .iter()
                .map(|&m| {
                    let mut p = [0.0; 4];
                    for (c, &(_, id)) in three.iter().enumerate() {
                        if m as u32 == id {
                            p[c] = 1.0;
                        }
                    }
                    p
                })
                .collect();
            passes.push((v, three.iter().enumerate().map(|(c, &(j, _))| (j as u32, c as u32)).collect()));
        }
        // A pass of instance masks walks only their pixels (the frame's `last` counts, 0
        // elsewhere): the same scores, a fraction of the frame's work.
        let last = if passes.len() > 1 { self.r.read_last()? } else { Vec::new() };
        for (i, (v_image, slots)) in passes.into_iter().enumerate() {
            let v = gpu.upload("seg_v_image", &v_image)?;
            let masked_last = if i == 0 {
                None
            } else {
                let l: Vec<u32> =
                    last.iter().zip(&v_image).map(|(&l, p)| if p[..3] == [0.0; 3] { 0 } else { l }).collect();
                Some(gpu.upload("seg_last", &l)?)
            };
            gpu.submit_and_wait(|rec| {
                match &masked_last {
                    None => self.r.record_blend_backward(rec, &self.gs, &v, &self.grads)?,
                    Some(l) => self.r.record_blend_backward_from(rec, &self.gs, &v, &self.grads, l)?,
                }
                for &(slot, channel) in &slots {
                    let args = SegArgs { count: n as u32, slot, weight: 1.0, channel };
                    rec.dispatch(
                        &k.seg_accumulate,
                        &[("v_colours", &self.grads.v_colours), ("scores", &self.scores)],
                        &args,
                        [(n as u32).div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
                    )?;
                    rec.end_pass("seg_accumulate")?;
                }
                Ok(())
            })?;
        }
        Ok(())
    }

    fn read(&self) -> Result<Vec<f32>> {
        self.gpu.read(&self.scores, self.n * self.slots)
    }
}

/// The Gaussians of `scene` labelled `id`.
pub fn subset(scene: &Scene, labels: &[u32], id: u32) -> Scene {
    let keep: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] == id).collect();
    scene.select(&keep)
}

/// Per view, the IoU of an instance's rendered visible region ([`instance_regions`]) and its
/// mask `mask == id`. Views where neither has a pixel are skipped.
pub fn instance_iou(regions: &[Vec<bool>], masks: &[Vec<u16>], id: u32) -> Vec<f64> {
    regions.iter().zip(masks).filter_map(|(r, m)| iou(r, m, |mid| mid as u32 == id)).collect()
}

/// [`instance_iou`] against masks whose ids mean nothing across frames (a 2D segmenter's): in
/// each view the instance's region is associated with the mask of its own `category` that
/// overlaps it most (`categories[view]`: per-frame id → category); views where no mask of that
/// category overlaps the region are skipped (the segmenter missed it, or the instance is out of
/// sight).
pub fn instance_iou_per_frame(
    regions: &[Vec<bool>],
    masks: &[Vec<u16>],
    categories: &[BTreeMap<u16, String>],
    category: &str,
) -> Vec<f64> {
    regions
        .iter()
        .zip(masks)
        .zip(categories)
        .filter_map(|((r, m), cats)| {
            cats.iter()
                .filter(|(_, c)| c.as_str() == category)
                .filter_map(|(&mid, _)| iou(r, m, |x| x == mid))
                .filter(|&v| v > 0.0)
                .max_by(f64::total_cmp)
        })
        .collect()
}

/// Per instance of `ids`, per view: its rendered visible region — the whole scene rendered
/// with the instance's Gaussians white and every other Gaussian black (so occluders hide it as
/// in the photos), thresholded at 0.5. Three instances share a render, one per colour channel
/// (the blending weights do not depend on the colours, so each channel is that instance's
/// render exactly). Holds a region per instance, view and pixel: callers pass a few ids at a
/// time.
pub fn instance_regions(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    labels: &[u32],
    views: &[View],
    ids: &[u32],
) -> Result<Vec<Vec<Vec<bool>>>> {
    let mut regions = vec![Vec::with_capacity(views.len()); ids.len()];
    let mut r = Rasterizer::new(gpu, k)?;
    let c0 = crate::math::SH_C0_F32;
    for (chunk, three) in ids.chunks(3).enumerate() {
        let mut s = scene.clone();
        s.sh_degree = 0;
        s.sh = labels
            .iter()
            .flat_map(|&l| {
                let mut rgb = [-0.5 / c0; 3];
                for (c, &id) in three.iter().enumerate() {
                    if l == id {
                        rgb[c] = 0.5 / c0;
                    }
                }
                rgb
            })
            .collect();
        let gs = GpuScene::new(gpu, &s)?;
        for v in views {
            let image = r.render(&gs, &v.camera, [0.0; 3])?.image;
            for c in 0..three.len() {
                regions[3 * chunk + c].push(image.iter().map(|p| p[c] > 0.5).collect());
            }
        }
    }
    Ok(regions)
}

/// IoU of a region and the mask pixels `hit` selects; None when neither has a pixel.
fn iou(region: &[bool], mask: &[u16], hit: impl Fn(u16) -> bool) -> Option<f64> {
    let (mut inter, mut union) = (0u64, 0u64);
    for (&a, &mid) in region.iter().zip(mask) {
        let b = hit(mid);
        inter += (a && b) as u64;
        union += (a || b) as u64;
    }
    (union > 0).then(|| inter as f64 / union as f64)
}

/// Parameters of [`associate`].
#[derive(Clone, Debug)]
pub struct AssociateOptions {
    /// α of the per-view lifting (as in [`segment`]).
    pub alpha: f32,
    /// A Gaussian counts as seen in a view, or claimed by a mask, with at least this much
    /// blending weight summed over pixels.
    pub min_weight: f32,
    /// Two masks join when their view-consensus rate is at least this.
    pub threshold: f64,
    /// Instances need masks in at least this many views; masks of smaller clusters are dropped.
    pub min_views: usize,
}

impl Default for AssociateOptions {
    fn default() -> Self {
        AssociateOptions { alpha: 0.8, min_weight: 0.05, threshold: 0.5, min_views: 3 }
    }
}

/// Cross-frame association of per-frame masks.
#[derive(Clone, Debug)]
pub struct Association {
    /// One group per category, its instances numbered 1.. across groups.
    pub groups: Vec<InstanceGroup>,
    /// The masks rewritten with instance ids (0 where a mask joined no instance).
    pub masks: Vec<Vec<u16>>,
    /// Per instance id, its masks: (view index, per-frame id).
    pub members: BTreeMap<u32, Vec<(usize, u16)>>,
    /// Masks that joined no instance of at least `min_views` views.
    pub dropped: Vec<(usize, u16)>,
}

type Bits = Vec<u64>;

fn bits_from(n: usize, f: impl Fn(usize) -> bool) -> Bits {
    let mut b = vec![0u64; n.div_ceil(64)];
    for i in 0..n {
        if f(i) {
            b[i / 64] |= 1 << (i % 64);
        }
    }
    b
}

fn count_and(a: &Bits, b: &Bits) -> usize {
    a.iter().zip(b).map(|(x, y)| (x & y).count_ones() as usize).sum()
}

/// Associates per-frame masks across views (view consensus, after MaskClustering, the InstGS
/// paper's reference \[53\]): each mask is lifted to the Gaussians it claims in its view (g > 0
/// of Eq. 5 over that view alone); for two masks a, b of different views and one category the
/// consensus rate is min(|A∩B| / |A ∩ seen(b's view)|, |A∩B| / |B ∩ seen(a's view)|) — of the
/// Gaussians one mask claims that the other view sees, the share the other mask claims too.
/// Pairs are merged greedily from the highest rate down to `threshold`, never joining two masks
/// of one view; clusters spanning at least `min_views` views become instances (numbered by
/// their first view and id), the rest is dropped. `progress` (label, mode) reports the lifting
/// per view and the pairing per mask.
#[allow(clippy::too_many_arguments)]
pub fn associate(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    views: &[View],
    masks: &[Vec<u16>],
    categories: &[BTreeMap<u16, String>],
    o: &AssociateOptions,
    progress: (&str, ProgressMode),
) -> Result<Association> {
    if views.len() != masks.len() || views.len() != categories.len() {
        bail!("{} views, {} masks, {} category maps", views.len(), masks.len(), categories.len());
    }
    let n = scene.len();
    let frame_ids: Vec<Vec<u32>> =
        masks.iter().map(|m| crate::dataset::masks::mask_ids(m).into_iter().map(u32::from).collect()).collect();
    let slots = frame_ids.iter().map(Vec::len).max().unwrap_or(0) + 1;
    let mut scorer = Scorer::new(gpu, k, scene, slots)?;
    // Lifted masks: (view, id, category, claimed Gaussians); seen Gaussians per view.
    let mut lifted: Vec<(usize, u16, &str, Bits)> = Vec::new();
    let mut seen: Vec<Bits> = Vec::new();
    let label = format!("{}association: lifting masks: ", progress.0);
    let mut bar = Progress::new(&label, "view", "views/s", views.len() as u64, 0, progress.1);
    for (v, (view, mask)) in views.iter().zip(masks).enumerate() {
        bar.set(v as u64, "");
        scorer.clear()?;
        scorer.add_view(view, mask, &frame_ids[v])?;
        let s = scorer.read()?;
        let all = &s[(slots - 1) * n..];
        seen.push(bits_from(n, |i| all[i] >= o.min_weight));
        for (j, &id) in frame_ids[v].iter().enumerate() {
            let sj = &s[j * n..(j + 1) * n];
            let claimed = bits_from(n, |i| sj[i] >= o.min_weight && (1.0 + o.alpha) * sj[i] - o.alpha * all[i] > 0.0);
            let cat = categories[v].get(&(id as u16)).map(String::as_str).unwrap_or("");
            lifted.push((v, id as u16, cat, claimed));
        }
    }
    bar.set(views.len() as u64, "");
    bar.finish();
    let label = format!("{}association: pairing masks: ", progress.0);
    let mut bar = Progress::new(&label, "mask", "masks/s", lifted.len() as u64, 0, progress.1);
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for a in 0..lifted.len() {
        bar.set(a as u64, "");
        for b in a + 1..lifted.len() {
            let (la, lb) = (&lifted[a], &lifted[b]);
            if la.0 == lb.0 || la.2 != lb.2 {
                continue;
            }
            let inter = count_and(&la.3, &lb.3);
            let (da, db) = (count_and(&la.3, &seen[lb.0]), count_and(&lb.3, &seen[la.0]));
            if da < 8 || db < 8 {
                continue;
            }
            let rate = (inter as f64 / da as f64).min(inter as f64 / db as f64);
            if rate >= o.threshold {
                pairs.push((rate, a, b));
            }
        }
    }
    bar.set(lifted.len() as u64, "");
    bar.finish();
    pairs.sort_by(|x, y| y.0.total_cmp(&x.0).then((x.1, x.2).cmp(&(y.1, y.2))));
    // Union-find with the set of views of every cluster at its root.
    let mut parent: Vec<usize> = (0..lifted.len()).collect();
    let mut cluster_views: Vec<std::collections::BTreeSet<usize>> =
        lifted.iter().map(|l| std::collections::BTreeSet::from([l.0])).collect();
    fn root(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    for (_, a, b) in pairs {
        let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
        if ra == rb || !cluster_views[ra].is_disjoint(&cluster_views[rb]) {
            continue;
        }
        let (keep, gone) = (ra.min(rb), ra.max(rb));
        parent[gone] = keep;
        let moved = std::mem::take(&mut cluster_views[gone]);
        cluster_views[keep].extend(moved);
    }
    let mut clusters: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..lifted.len() {
        let r = root(&mut parent, i);
        clusters.entry(r).or_default().push(i);
    }
    let mut members = BTreeMap::new();
    let mut dropped = Vec::new();
    let mut groups: Vec<InstanceGroup> = Vec::new();
    let mut new_id: BTreeMap<(usize, u16), u16> = BTreeMap::new();
    // Roots are each cluster's smallest index: clusters come in (view, id) order of their first mask.
    for list in clusters.values() {
        let ms: Vec<(usize, u16)> = list.iter().map(|&i| (lifted[i].0, lifted[i].1)).collect();
        if list.len() < o.min_views {
            dropped.extend(ms);
            continue;
        }
        let id = members.len() as u32 + 1;
        if id > u16::MAX as u32 {
            bail!("more than 65535 associated instances");
        }
        let cat = lifted[list[0]].2.to_string();
        match groups.iter_mut().find(|g| g.name == cat) {
            Some(g) => g.ids.push(id),
            None => groups.push(InstanceGroup { name: cat, ids: vec![id] }),
        }
        for m in &ms {
            new_id.insert(*m, id as u16);
        }
        members.insert(id, ms);
    }
    let masks = masks
        .iter()
        .enumerate()
        .map(|(v, m)| m.iter().map(|&x| if x == 0 { 0 } else { new_id.get(&(v, x)).copied().unwrap_or(0) }).collect())
        .collect();
    Ok(Association { groups, masks, members, dropped })
}
