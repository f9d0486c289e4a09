//! How much of the background an instanced scene keeps, chosen by a quality budget instead of a
//! per-scene number, and how its bytes are then shared between templates and background
//! ([`rebalance`]). The background Gaussians are ranked by significance (their blending
//! weight T·α summed over every pixel of the training views — LightGaussian's global
//! significance without the volume term, from the segmentation pass); those near an instance
//! rank first (the instance's outline: the template cannot stand in for them). The kept fraction
//! is the smallest whose pruned plain scene (instances whole, the most significant background)
//! renders the training views (photos through their learned colour transforms, as in training)
//! within `budget_db` of the whole plain scene's PSNR — measured before the joint optimisation,
//! which then fine-tunes what is kept (LightGaussian's prune-then-fine-tune; InstGS Eq. 6–8 for
//! what is trained).
use std::sync::Arc;

use anyhow::{bail, Result};
use kiddo::SquaredEuclidean;

use crate::dataset::View;
use crate::formats::instgs::Dtype;
use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::instancing::template::prune_background;
use crate::math::tree;
use crate::model::instanced::{Group, InstancedScene, Offsets};
use crate::model::scene::Scene;
use crate::register::object_size;
use crate::render::appearance::{ColourTransform, PhotoAppearance, Vignetting, NO_VIGNETTING};
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
/// `colours`: the photos' colour transforms (one per view) and the lens's vignetting the training
/// learned (captures), applied to each render before it is scored, as in training; None for
/// renders.
#[allow(clippy::too_many_arguments)]
pub fn background_budget(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &Scene,
    labels: &[u32],
    ranking: &[f32],
    protected: usize,
    views: &[View],
    colours: Option<&PhotoAppearance>,
    background: [f32; 3],
    budget_db: f64,
    mut progress: impl FnMut(&str),
) -> Result<Budget> {
    if !(budget_db.is_finite() && budget_db >= 0.0) {
        bail!("the background budget must be a non-negative number of dB, not {budget_db}");
    }
    let mut check = ViewCheck::new(gpu, k, views, colours, background, "measure the background budget on")?;
    let n = check.pick.len();
    let mut psnr = |s: &Scene| check.psnr(&GpuScene::new(gpu, s)?);
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

/// What [`rebalance`] decided (instance.json's `rebalance`).
#[derive(Clone, Debug, serde::Serialize)]
pub struct Rebalance {
    /// GPU bytes of the instanced scene (every pair rendered, offsets as stored): the budget,
    /// and after.
    pub bytes_before: u64,
    pub bytes_after: u64,
    pub template_gaussians_before: usize,
    pub template_gaussians_after: usize,
    pub background_before: usize,
    pub background_after: usize,
    /// Mean PSNR (dB) over up to [`BUDGET_VIEWS`] training views before and after: the check.
    pub psnr_before: f64,
    pub psnr_after: f64,
    pub views: usize,
    /// The rebalanced scene was kept: within the budget and no worse on the views.
    pub accepted: bool,
}

/// Every Gaussian of an instanced scene ranked for one memory budget: each background
/// Gaussian by its significance (blending weight T·α over every pixel of the views,
/// [`crate::segment::significance`] on the expanded scene; those within `outline_fraction` of
/// an instance first, as [`protect_outlines`]) per Gaussian's bytes, each template Gaussian by
/// its significance summed over its instances per Gaussian's bytes plus one offset row per
/// instance. Each template keeps at least its most significant Gaussian. [`Spending::at`] keeps
/// the best that fit a budget. Bytes are counted with the offsets as the scene will be stored
/// (`storage`, [`GpuScene::stored_bytes`]): an f16 pair costs half an f32 one. `render_weight`
/// also charges every splat a Gaussian draws (one per instance for a template's) as that many
/// Gaussian rows: 0 ranks by memory alone; 1 weighs a drawn splat as much as a stored row, as a
/// pruned plain scene's ranking does (each of its rows draws one splat).
pub struct Spending {
    cand: InstancedScene,
    /// (forced, value per cost, which), best first.
    items: Vec<(bool, f64, Item)>,
    /// Bytes of one Gaussian row and of one offset row (estimates from the device's layout).
    row: f64,
    pair: f64,
    storage: Dtype,
}

impl Spending {
    /// Ranks the Gaussians of `cand` (templates whole, every background Gaussian a budget
    /// might keep) over `views`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        gpu: &Arc<Gpu>,
        k: &Arc<Kernels>,
        cand: InstancedScene,
        views: &[View],
        outline_fraction: f64,
        render_weight: f64,
        storage: Dtype,
        mut progress: impl FnMut(&str),
    ) -> Result<Spending> {
        if !(render_weight.is_finite() && render_weight >= 0.0) {
            bail!("the render weight must be a non-negative number, not {render_weight}");
        }
        let nb = cand.background.len();
        let expanded = cand.expand();
        let sig = crate::segment::significance(gpu, k, &expanded, views, |d, all| {
            if d % 10 == 0 || d == all {
                progress(&format!("significance {d}/{all} views"));
            }
        })?;
        // Labels of the expanded splats (0: background; one id per instance) for the outlines.
        let mut labels = vec![0u32; nb];
        let mut id = 0;
        for g in &cand.groups {
            for _ in &g.instances {
                id += 1;
                labels.extend(std::iter::repeat_n(id, g.template.len()));
            }
        }
        let (ranking, _) = protect_outlines(&expanded, &labels, &sig, outline_fraction);
        let top = sig.iter().copied().filter(|s| s.is_finite()).fold(0.0f32, f32::max);
        let whole = GpuScene::stored_bytes(gpu, &cand, storage)? as f64;
        let row = GpuScene::new(gpu, &cand.background)?.gpu_bytes() as f64 / nb.max(1) as f64;
        let pairs: usize = cand.groups.iter().map(|g| g.template.len() * g.instances.len()).sum();
        let pair = ((whole - row * cand.rows() as f64) / pairs.max(1) as f64).max(0.0);
        // A Gaussian's cost: its bytes, plus `render_weight` rows per splat it draws.
        let cost = |bytes: f64, drawn: f64| bytes + render_weight * row * drawn;
        // Items: (forced, value per cost, which). which: Err(i) background i, Ok((g, j)) template.
        let mut items: Vec<(bool, f64, Item)> = Vec::new();
        for (i, &r) in ranking.iter().enumerate().take(nb) {
            items.push((r > top, sig[i] as f64 / cost(row, 1.0), Err(i)));
        }
        let mut first = nb;
        for (gi, g) in cand.groups.iter().enumerate() {
            let t = g.template.len();
            let value: Vec<f64> =
                (0..t).map(|j| (0..g.instances.len()).map(|k| sig[first + k * t + j] as f64).sum()).collect();
            let best = (0..t).max_by(|&a, &b| value[a].total_cmp(&value[b]));
            let drawn = g.instances.len() as f64;
            let cost = cost(row + pair * drawn, drawn);
            for (j, v) in value.iter().enumerate() {
                items.push((Some(j) == best, v / cost, Ok((gi, j))));
            }
            first += t * g.instances.len();
        }
        items.sort_by(|a, b| b.0.cmp(&a.0).then(b.1.total_cmp(&a.1)));
        Ok(Spending { cand, items, row, pair, storage })
    }

    /// How the offsets are counted.
    pub fn storage(&self) -> Dtype {
        self.storage
    }

    /// The scene of the most valuable Gaussians whose GPU bytes (the device's own count) fit
    /// `budget`; at least the forced ones (a Gaussian per template).
    pub fn at(&self, gpu: &Arc<Gpu>, budget: u64) -> Result<InstancedScene> {
        let (cand, items) = (&self.cand, &self.items);
        let cost = |item: &Item| match item {
            Err(_) => self.row,
            Ok((g, _)) => self.row + self.pair * cand.groups[*g].instances.len() as f64,
        };
        let mut take = 0;
        let mut spent = 0.0;
        while take < items.len() && spent + cost(&items[take].2) <= budget as f64 {
            spent += cost(&items[take].2);
            take += 1;
        }
        let forced = items.iter().filter(|i| i.0).count();
        let bytes_of = |s: &InstancedScene| GpuScene::stored_bytes(gpu, s, self.storage);
        // The estimate's take, then the most items whose scene the device's own count fits in
        // the budget (bytes grow with every item kept).
        let fits =
            |take: usize| -> Result<bool> { Ok(bytes_of(&keep_items(cand, &items[..take.max(forced)]))? <= budget) };
        let (mut lo, mut hi) = if fits(take)? { (take, items.len() + 1) } else { (forced, take) };
        if lo == forced && !fits(forced)? {
            hi = forced;
        }
        while hi - lo > 1 {
            let mid = (lo + hi) / 2;
            if fits(mid)? {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let out = keep_items(cand, &items[..lo.max(forced).min(items.len())]);
        out.validate("scene within the memory budget")?;
        Ok(out)
    }
}

/// One memory budget for the templates and the background. The background budget above prunes
/// the background only and keeps every template whole, while a pruned plain scene of the same
/// bytes ranks every Gaussian, objects' included, by one measure — and so spends its bytes
/// better (BENCHMARKS.md, "Photos as users take them"). Here every background Gaussian, kept
/// (`inst.background`) or dropped (`dropped`), and every template Gaussian compete for the
/// instanced scene's own GPU bytes with its offsets stored as `storage` ([`Spending`]). Checked
/// before it is trusted: the result is kept only when it renders up to [`BUDGET_VIEWS`] of the
/// views at least as well as `inst` (mean PSNR; `colours` as for [`background_budget`]) within
/// `inst`'s bytes; otherwise `inst` is returned unchanged, and the report says so.
#[allow(clippy::too_many_arguments)]
pub fn rebalance(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    inst: &InstancedScene,
    dropped: &Scene,
    views: &[View],
    colours: Option<&PhotoAppearance>,
    background: [f32; 3],
    outline_fraction: f64,
    render_weight: f64,
    storage: Dtype,
    mut progress: impl FnMut(&str),
) -> Result<(InstancedScene, Rebalance)> {
    let n = views.len().min(BUDGET_VIEWS);
    let mut cand = inst.clone();
    cand.background = inst.background.concat(dropped);
    let spending = Spending::new(gpu, k, cand, views, outline_fraction, render_weight, storage, |l| {
        progress(&format!("rebalance: {l}"))
    })?;
    let bytes_of = |s: &InstancedScene| GpuScene::stored_bytes(gpu, s, storage);
    let budget = bytes_of(inst)?;
    let out = spending.at(gpu, budget)?;
    let mut check = ViewCheck::new(gpu, k, views, colours, background, "rebalance the scene's memory on")?;
    let (psnr_before, psnr_after) =
        (check.psnr(&GpuScene::instanced(gpu, inst)?)?, check.psnr(&GpuScene::instanced(gpu, &out)?)?);
    let bytes_after = bytes_of(&out)?;
    let accepted = bytes_after <= budget && psnr_after >= psnr_before;
    let t = |s: &InstancedScene| s.groups.iter().map(|g| g.template.len()).sum::<usize>();
    let report = Rebalance {
        bytes_before: budget,
        bytes_after,
        template_gaussians_before: t(inst),
        template_gaussians_after: t(&out),
        background_before: inst.background.len(),
        background_after: out.background.len(),
        psnr_before,
        psnr_after,
        views: n,
        accepted,
    };
    progress(&format!(
        "rebalance: templates {} → {} Gaussians, background {} → {}, {:.2} → {:.2} MB, {:.2} → {:.2} dB on {n} training views: {}",
        report.template_gaussians_before,
        report.template_gaussians_after,
        report.background_before,
        report.background_after,
        budget as f64 / 1e6,
        bytes_after as f64 / 1e6,
        psnr_before,
        psnr_after,
        if accepted { "kept" } else { "refused (the scene as instanced stays)" }
    ));
    Ok((if accepted { out } else { inst.clone() }, report))
}

/// A Gaussian [`rebalance`] may keep: `Err(i)` background Gaussian i, `Ok((g, j))` Gaussian j of
/// group g's template.
type Item = std::result::Result<(usize, usize), usize>;

/// `cand` with only the background and template Gaussians of `items` (each template's offset rows
/// with it), in their original order.
fn keep_items(cand: &InstancedScene, items: &[(bool, f64, Item)]) -> InstancedScene {
    let mut bg = Vec::new();
    let mut keep: Vec<Vec<usize>> = vec![Vec::new(); cand.groups.len()];
    for item in items {
        match item.2 {
            Err(i) => bg.push(i),
            Ok((g, j)) => keep[g].push(j),
        }
    }
    bg.sort_unstable();
    let groups = cand
        .groups
        .iter()
        .zip(&mut keep)
        .map(|(g, js)| {
            js.sort_unstable();
            let t = g.template.len();
            let rows: Vec<usize> = (0..g.instances.len()).flat_map(|k| js.iter().map(move |j| k * t + j)).collect();
            let pick3 = |v: &[[f32; 3]]| rows.iter().map(|&r| v[r]).collect();
            let offsets = Offsets {
                d_means: pick3(&g.offsets.d_means),
                d_sh0: pick3(&g.offsets.d_sh0),
                d_opacities: rows.iter().map(|&r| g.offsets.d_opacities[r]).collect(),
            };
            Group { name: g.name.clone(), template: g.template.select(js), instances: g.instances.clone(), offsets }
        })
        .collect();
    InstancedScene { sh_degree: cand.sh_degree, background: cand.background.select(&bg), groups }
}

/// The decisions' check: up to [`BUDGET_VIEWS`] of the training views, evenly spread, rendered
/// (through each photo's colour transform when there are some) and scored.
struct ViewCheck<'a> {
    pick: Vec<(&'a View, Option<&'a ColourTransform>)>,
    vignetting: Vignetting,
    r: Rasterizer,
    background: [f32; 3],
}

impl<'a> ViewCheck<'a> {
    /// `purpose` completes "no training views to …" when there are none.
    fn new(
        gpu: &Arc<Gpu>,
        k: &Arc<Kernels>,
        views: &'a [View],
        colours: Option<&'a PhotoAppearance>,
        background: [f32; 3],
        purpose: &str,
    ) -> Result<ViewCheck<'a>> {
        let n = views.len().min(BUDGET_VIEWS);
        if n == 0 {
            bail!("no training views to {purpose}");
        }
        if let Some(c) = colours.filter(|c| c.colours.len() != views.len()) {
            bail!("{} colour transforms for {} training views (to {purpose})", c.colours.len(), views.len());
        }
        let pick = (0..n).map(|i| i * views.len() / n).map(|j| (&views[j], colours.map(|c| &c.colours[j]))).collect();
        let vignetting = colours.map_or(NO_VIGNETTING, |c| c.vignetting);
        Ok(ViewCheck { pick, vignetting, r: Rasterizer::new(gpu, k)?, background })
    }

    /// Mean PSNR (dB) of `gs` over the picked views.
    fn psnr(&mut self, gs: &GpuScene) -> Result<f64> {
        let mut sum = 0.0;
        for (v, colour) in &self.pick {
            let image = self.r.render(gs, &v.camera, self.background)?.image;
            let image = match colour {
                Some(t) => crate::render::appearance::apply_photo(t, &self.vignetting, &v.camera, &image),
                None => image,
            };
            sum += crate::util::psnr(&image, &v.image);
        }
        Ok(sum / self.pick.len() as f64)
    }
}
