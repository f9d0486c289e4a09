//! How much of the background an instanced scene keeps, chosen by a quality budget instead of a
//! per-scene number. The background Gaussians are ranked by significance (their blending
//! weight T·α summed over every pixel of the training views — LightGaussian's global
//! significance without the volume term, from the segmentation pass); those near an instance
//! rank first (the instance's outline: the template cannot stand in for them). The kept fraction
//! is the smallest whose pruned plain scene (instances whole, the most significant background)
//! renders the training views within `budget_db` of the whole plain scene's PSNR — measured
//! before the joint optimisation, which then fine-tunes what is kept (LightGaussian's
//! prune-then-fine-tune; InstGS Eq. 6–8 for what is trained).
use std::sync::Arc;

use anyhow::{bail, Result};
use kiddo::SquaredEuclidean;

use crate::dataset::View;
use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::instancing::template::prune_background;
use crate::math::tree;
use crate::model::scene::Scene;
use crate::register::object_size;
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;

/// Training views rendered per trial at most (evenly spread over the split).
pub const BUDGET_VIEWS: usize = 8;
/// The kept fraction is searched to this precision.
const PRECISION: f64 = 1.0 / 128.0;

/// The budget search's outcome.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Budget {
    /// The kept fraction of the background.
    pub keep: f64,
    /// Mean PSNR (dB) of the whole plain scene over the views.
    pub psnr_whole: f64,
    /// ... and of the pruned scene at `keep`.
    pub psnr_pruned: f64,
    pub budget_db: f64,
    pub views: usize,
    /// Background Gaussians near an instance (ranked first).
    pub protected: usize,
    /// (fraction, PSNR) of every trial, in order.
    pub trials: Vec<(f64, f64)>,
}

/// Significance with the background Gaussians within `fraction` × its size ([`object_size`]) of
/// an instance's Gaussian raised above every other background Gaussian (their order kept).
/// Returns the ranking values and how many were raised.
pub fn protect_outlines(scene: &Scene, labels: &[u32], significance: &[f32], fraction: f64) -> (Vec<f32>, usize) {
    let top = significance.iter().copied().filter(|s| s.is_finite()).fold(0.0f32, f32::max);
    let mut out = significance.to_vec();
    let mut ids: Vec<u32> = labels.iter().copied().filter(|&l| l != 0).collect();
    ids.sort_unstable();
    ids.dedup();
    let mut raised = vec![false; scene.len()];
    for id in ids {
        let pts: Vec<[f64; 3]> =
            (0..scene.len()).filter(|&i| labels[i] == id).map(|i| scene.means[i].map(|c| c as f64)).collect();
        let r = fraction * object_size(&pts);
        if r.is_nan() || r <= 0.0 {
            continue;
        }
        let t = tree(&pts);
        for i in 0..scene.len() {
            if labels[i] != 0 || raised[i] {
                continue;
            }
            let p = scene.means[i].map(|c| c as f64);
            if t.nearest_one::<SquaredEuclidean>(&p).distance <= r * r {
                raised[i] = true;
                out[i] = significance[i] + top + 1.0;
            }
        }
    }
    let n = raised.iter().filter(|&&r| r).count();
    (out, n)
}

/// The smallest kept background fraction (to 1/128) whose pruned scene's mean PSNR over up to
/// [`BUDGET_VIEWS`] of `views` is within `budget_db` of the whole scene's; 1 when even that
/// fraction misses it. `ranking`: per Gaussian, higher stays first ([`protect_outlines`]).
#[allow(clippy::too_many_arguments)]
pub fn background_budget(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    labels: &[u32],
    ranking: &[f32],
    protected: usize,
    views: &[View],
    background: [f32; 3],
    budget_db: f64,
    mut progress: impl FnMut(&str),
) -> Result<Budget> {
    if !(budget_db.is_finite() && budget_db >= 0.0) {
        bail!("the background budget must be a non-negative number of dB, not {budget_db}");
    }
    let n = views.len().min(BUDGET_VIEWS);
    if n == 0 {
        bail!("no training views to measure the background budget on");
    }
    let pick: Vec<&View> = (0..n).map(|i| &views[i * views.len() / n]).collect();
    let mut r = Rasterizer::new(gpu, k)?;
    let mut psnr = |s: &Scene| -> Result<f64> {
        let gs = GpuScene::new(gpu, s)?;
        let mut sum = 0.0;
        for v in &pick {
            sum += crate::util::psnr(&r.render(&gs, &v.camera, background)?.image, &v.image);
        }
        Ok(sum / n as f64)
    };
    let whole = psnr(scene)?;
    let mut trials = Vec::new();
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    let mut at_hi = whole;
    while hi - lo > PRECISION {
        let mid = 0.5 * (lo + hi);
        let (pruned, _, _) = prune_background(scene, labels, ranking, mid)?;
        let p = psnr(&pruned)?;
        trials.push((mid, p));
        progress(&format!("background budget: keep {:.1} % → {:.2} dB (whole {whole:.2} dB)", 100.0 * mid, p));
        if whole - p <= budget_db {
            (hi, at_hi) = (mid, p);
        } else {
            lo = mid;
        }
    }
    Ok(Budget { keep: hi, psnr_whole: whole, psnr_pruned: at_hi, budget_db, views: n, protected, trials })
}

/// The "plain, pruned" baseline: `scene`'s most significant Gaussians (by `significance`, the
/// same measure the background budget ranks by, over the whole scene) that fit in `bytes` of
/// GPU memory as a plain scene on `gpu` (what `bench` reports as `scene_gpu_bytes`). What a user
/// would try before instancing: prune a plain scene to the instanced scene's size (LightGaussian's
/// global significance pruning), then fine-tune it. Returns the kept indices, in scene order.
pub fn prune_to_bytes(gpu: &Arc<Gpu>, scene: &Scene, significance: &[f32], bytes: u64) -> Result<Vec<usize>> {
    if significance.len() != scene.len() {
        bail!("{} significance values for {} Gaussians", significance.len(), scene.len());
    }
    let mut order: Vec<usize> = (0..scene.len()).collect();
    order.sort_by(|&a, &b| significance[b].total_cmp(&significance[a]).then(a.cmp(&b)));
    let whole = GpuScene::new(gpu, scene)?.gpu_bytes();
    let mut n = ((scene.len() as f64 * bytes as f64 / whole.max(1) as f64).floor() as usize).min(scene.len());
    loop {
        let mut keep = order[..n].to_vec();
        keep.sort_unstable();
        if n == 0 {
            bail!("a plain scene of one Gaussian already takes more than {bytes} bytes");
        }
        if GpuScene::new(gpu, &scene.select(&keep))?.gpu_bytes() <= bytes {
            return Ok(keep);
        }
        n -= (n / 1000).max(1);
    }
}
