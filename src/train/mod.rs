//! Plain 3DGS training on the GPU, Inria's recipe: one random training view per iteration,
//! L = (1 − λ) L1 + λ (1 − SSIM), Adam per parameter group with the position learning rate
//! decaying exponentially, SH degree raised every `sh_increase_interval` iterations, and
//! clone / split / prune densification with periodic opacity resets (on the CPU, between
//! iterations). Forward, loss, backward and Adam run on the GPU; the host reads back only the
//! rendered image (for the training PSNR) and the loss sums, plus the whole state at
//! densification steps and checkpoints.
//!
//! Instanced scenes (`--init scene.instgs`, InstGS joint optimisation): templates, offsets and
//! background are optimised together through the instancing rasterizer, without densification
//! (`configs/instanced.toml`); the run writes `scene.instgs`.
//!
//! Differences from Inria, on purpose: the Adam step also runs on densification iterations
//! (Inria skips it for the replaced tensors). The screen-size prune is off by default, as in
//! effect in Inria (its radii are zeroed just before they are read, so it never fires); when on
//! (`max_screen_size > 0`) it uses the radii seen since the last densification.

pub mod config;
pub mod eval;
pub mod optim;
pub mod plot;
pub mod session;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

use crate::dataset::{Dataset, View};
use crate::gpu::kernels::Kernels;
use crate::gpu::{CommandBuffer, Gpu};
use crate::math::SH_C0_F32;
use crate::math::{logit, sigmoid};
use crate::model::instanced::{
    xform_from_params, xform_param_grads, xform_params, Group, Instance, InstancedScene, Offsets, Similarity,
};
use crate::model::scene::Scene;
use crate::render::raster::{GpuScene, Grads, Rasterizer};
use crate::train::config::Config;
use crate::train::optim::{
    offset_buffers, param_buffers, record_adam, record_loss, AdamState, LearningRates, LossBufs,
};
use crate::util::{Progress, ProgressMode};

/// Parameters per Gaussian of the five parameter groups (means, scales, quats, opacities, sh).
fn strides(sh_degree: u32) -> [usize; 5] {
    [3, 3, 4, 1, 3 * ((sh_degree + 1) * (sh_degree + 1)) as usize]
}

/// A scene from its five flat parameter arrays (means, scales, quats, opacities, sh).
fn scene_from_params(p: [Vec<f32>; 5], sh_degree: u32) -> Scene {
    let [means, scales, quats, opacities, sh] = p;
    Scene {
        means: bytemuck::pod_collect_to_vec(&means),
        scales: bytemuck::pod_collect_to_vec(&scales),
        quats: bytemuck::pod_collect_to_vec(&quats),
        opacities,
        sh,
        sh_degree,
    }
}

/// How an instanced run's parameter rows and offsets form groups (the data lives in
/// [`TrainState`]): background rows first, then each group's template rows.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Layout {
    pub background: usize,
    pub groups: Vec<LayoutGroup>,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LayoutGroup {
    pub name: String,
    pub template_gaussians: usize,
    /// (id, template→world 4×4 row-major).
    pub instances: Vec<(String, [[f32; 4]; 4])>,
}

impl Layout {
    fn pairs(&self) -> usize {
        self.groups.iter().map(|g| g.template_gaussians * g.instances.len()).sum()
    }
}

/// Everything that defines a training run at an iteration boundary (what a checkpoint holds).
#[derive(Clone, Debug, PartialEq)]
pub struct TrainState {
    /// Iterations completed.
    pub iteration: u64,
    pub active_sh_degree: u32,
    /// Parameter rows (a plain scene; an instanced run's background then templates).
    pub scene: Scene,
    /// Adam moments per parameter group, layouts as the scene's arrays.
    pub exp_avg: [Vec<f32>; 5],
    pub exp_avg_sq: [Vec<f32>; 5],
    /// Densification statistics per splat (plain runs; empty for instanced ones).
    pub grad2d_accum: Vec<f32>,
    pub grad2d_count: Vec<u32>,
    pub max_radii: Vec<u32>,
    /// Instanced runs: the groups, every group's offsets (pair order) and their Adam moments
    /// (d_means, d_sh0, d_opacities).
    pub layout: Option<Layout>,
    pub offsets: Offsets,
    pub offset_exp_avg: [Vec<f32>; 3],
    pub offset_exp_avg_sq: [Vec<f32>; 3],
    /// Instanced runs: every instance's transform parameters ([`xform_params`]: raw quaternion,
    /// translation, ln s; what rendering uses) and their Adam moments (used when refining).
    pub xform_params: Vec<[f32; 8]>,
    pub xform_exp_avg: Vec<[f32; 8]>,
    pub xform_exp_avg_sq: Vec<[f32; 8]>,
}

impl TrainState {
    /// A fresh state for `scene` (zero moments and statistics).
    pub fn new(scene: Scene) -> TrainState {
        let n = scene.len();
        let st = strides(scene.sh_degree);
        let zeros = |k: usize| vec![0.0f32; n * st[k]];
        TrainState {
            iteration: 0,
            active_sh_degree: 0,
            exp_avg: [zeros(0), zeros(1), zeros(2), zeros(3), zeros(4)],
            exp_avg_sq: [zeros(0), zeros(1), zeros(2), zeros(3), zeros(4)],
            grad2d_accum: vec![0.0; n],
            grad2d_count: vec![0; n],
            max_radii: vec![0; n],
            scene,
            layout: None,
            offsets: Offsets::default(),
            offset_exp_avg: Default::default(),
            offset_exp_avg_sq: Default::default(),
            xform_params: Vec::new(),
            xform_exp_avg: Vec::new(),
            xform_exp_avg_sq: Vec::new(),
        }
    }

    /// A fresh state for joint optimisation of an instanced scene.
    pub fn instanced(scene: &InstancedScene) -> TrainState {
        let rows = crate::render::raster::scene_rows(scene);
        let offsets = crate::render::raster::all_offsets(scene);
        let n = rows.len();
        let st = strides(rows.sh_degree);
        let zeros = |k: usize| vec![0.0f32; n * st[k]];
        let pairs = offsets.len();
        let instances = scene.groups.iter().map(|g| g.instances.len()).sum();
        let ozeros = || [vec![0.0f32; 3 * pairs], vec![0.0f32; 3 * pairs], vec![0.0f32; pairs]];
        TrainState {
            iteration: 0,
            // A trained scene is fine-tuned at its full SH degree from the first iteration (Inria's
            // load_ply sets the active degree to the maximum; the InstGS prototype fine-tunes so).
            active_sh_degree: rows.sh_degree,
            exp_avg: [zeros(0), zeros(1), zeros(2), zeros(3), zeros(4)],
            exp_avg_sq: [zeros(0), zeros(1), zeros(2), zeros(3), zeros(4)],
            grad2d_accum: Vec::new(),
            grad2d_count: Vec::new(),
            max_radii: Vec::new(),
            scene: rows,
            layout: Some(Layout {
                background: scene.background.len(),
                groups: scene
                    .groups
                    .iter()
                    .map(|g| LayoutGroup {
                        name: g.name.clone(),
                        template_gaussians: g.template.len(),
                        instances: g
                            .instances
                            .iter()
                            .map(|i| (i.id.clone(), crate::model::instanced::mat4_to_rows(i.transform.to_mat4())))
                            .collect(),
                    })
                    .collect(),
            }),
            offsets,
            offset_exp_avg: ozeros(),
            offset_exp_avg_sq: ozeros(),
            xform_params: scene.groups.iter().flat_map(|g| &g.instances).map(|i| xform_params(&i.transform)).collect(),
            xform_exp_avg: vec![[0.0; 8]; instances],
            xform_exp_avg_sq: vec![[0.0; 8]; instances],
        }
    }

    /// The instanced scene of an instanced run (None for a plain run); checks the transforms.
    pub fn to_instanced(&self) -> Result<Option<InstancedScene>> {
        let Some(layout) = self.layout.as_ref() else { return Ok(None) };
        let rows = |from: usize, n: usize| -> Scene {
            let c = self.scene.sh_coeffs() * 3;
            let r = from..from + n;
            Scene {
                means: self.scene.means[r.clone()].to_vec(),
                scales: self.scene.scales[r.clone()].to_vec(),
                quats: self.scene.quats[r.clone()].to_vec(),
                opacities: self.scene.opacities[r].to_vec(),
                sh: self.scene.sh[from * c..(from + n) * c].to_vec(),
                sh_degree: self.scene.sh_degree,
            }
        };
        let mut row = layout.background;
        let mut pair = 0;
        let mut groups = Vec::new();
        for g in &layout.groups {
            let t = g.template_gaussians;
            let m = t * g.instances.len();
            let o = &self.offsets;
            groups.push(Group {
                name: g.name.clone(),
                template: rows(row, t),
                instances: g
                    .instances
                    .iter()
                    .map(|(id, m)| {
                        let what = format!("group {:?} instance {id:?}", g.name);
                        let transform = Similarity::from_mat4(crate::model::instanced::mat4_from_rows(m), &what)?;
                        Ok(Instance { id: id.clone(), transform })
                    })
                    .collect::<Result<_>>()?,
                offsets: Offsets {
                    d_means: o.d_means[pair..pair + m].to_vec(),
                    d_sh0: o.d_sh0[pair..pair + m].to_vec(),
                    d_opacities: o.d_opacities[pair..pair + m].to_vec(),
                },
            });
            row += t;
            pair += m;
        }
        Ok(Some(InstancedScene { sh_degree: self.scene.sh_degree, background: rows(0, layout.background), groups }))
    }

    fn offset_arrays(&self) -> [&[f32]; 3] {
        let o = &self.offsets;
        [bytemuck::cast_slice(&o.d_means), bytemuck::cast_slice(&o.d_sh0), &o.d_opacities]
    }

    fn params(&self) -> [&[f32]; 5] {
        let s = &self.scene;
        [
            bytemuck::cast_slice(&s.means),
            bytemuck::cast_slice(&s.scales),
            bytemuck::cast_slice(&s.quats),
            &s.opacities,
            &s.sh,
        ]
    }

    /// Checks that every parameter and moment is finite; names the first bad one.
    pub fn check_finite(&self) -> Result<()> {
        let names = ["means", "scales", "quats", "opacities", "sh"];
        for (k, p) in self.params().iter().enumerate() {
            let st = strides(self.scene.sh_degree)[k];
            for (arr, what) in [(*p, ""), (&self.exp_avg[k][..], " (Adam m)"), (&self.exp_avg_sq[k][..], " (Adam v)")] {
                if let Some(j) = arr.iter().position(|v| !v.is_finite()) {
                    bail!("non-finite {}{what} of Gaussian {} at iteration {}", names[k], j / st, self.iteration);
                }
            }
        }
        let names = ["d_means", "d_sh0", "d_opacities"];
        for (k, p) in self.offset_arrays().iter().enumerate() {
            let moments = [(&self.offset_exp_avg[k][..], " (Adam m)"), (&self.offset_exp_avg_sq[k][..], " (Adam v)")];
            for (arr, what) in [(*p, "")].into_iter().chain(moments) {
                if let Some(j) = arr.iter().position(|v| !v.is_finite()) {
                    let pair = j / [3, 3, 1][k];
                    bail!("non-finite offset {}{what} (pair {pair}) at iteration {}", names[k], self.iteration);
                }
            }
        }
        for arr in [&self.xform_params, &self.xform_exp_avg, &self.xform_exp_avg_sq] {
            if let Some(k) = arr.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
                bail!("non-finite transform of instance {k} at iteration {}", self.iteration);
            }
        }
        Ok(())
    }

    /// The state restricted to the rows `rows` (source index, kept Adam moments?).
    fn gather(&self, rows: &[(usize, bool)]) -> TrainState {
        let st = strides(self.scene.sh_degree);
        let params = self.params();
        let mut p: [Vec<f32>; 5] = Default::default();
        let mut m: [Vec<f32>; 5] = Default::default();
        let mut v: [Vec<f32>; 5] = Default::default();
        for &(i, keep) in rows {
            for k in 0..5 {
                let r = i * st[k]..(i + 1) * st[k];
                p[k].extend_from_slice(&params[k][r.clone()]);
                if keep {
                    m[k].extend_from_slice(&self.exp_avg[k][r.clone()]);
                    v[k].extend_from_slice(&self.exp_avg_sq[k][r]);
                } else {
                    m[k].extend(std::iter::repeat_n(0.0, st[k]));
                    v[k].extend(std::iter::repeat_n(0.0, st[k]));
                }
            }
        }
        TrainState {
            iteration: self.iteration,
            active_sh_degree: self.active_sh_degree,
            scene: scene_from_params(p, self.scene.sh_degree),
            exp_avg: m,
            exp_avg_sq: v,
            grad2d_accum: rows.iter().map(|&(i, _)| self.grad2d_accum[i]).collect(),
            grad2d_count: rows.iter().map(|&(i, _)| self.grad2d_count[i]).collect(),
            max_radii: rows.iter().map(|&(i, keep)| if keep { self.max_radii[i] } else { 0 }).collect(),
            // Densification is for plain runs only: no instancing parts.
            ..TrainState::new(Scene::default())
        }
    }
}

/// What one densification step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensifyStats {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
}

/// Inria's densify_and_prune on the host: clone small splats and split large ones whose mean
/// view-space gradient passes the threshold (at most `max_splats` in all, highest gradients
/// first), then prune transparent and oversized ones; statistics are reset. `rng` draws the
/// split positions (normal with the splat's scales, rotated).
pub fn densify(st: &TrainState, cfg: &Config, extent: f32, rng: &mut rand_pcg::Pcg64) -> (TrainState, DensifyStats) {
    let d = &cfg.densify;
    let n = st.scene.len();
    let grads: Vec<f32> = (0..n)
        .map(|i| if st.grad2d_count[i] > 0 { st.grad2d_accum[i] / st.grad2d_count[i] as f32 } else { 0.0 })
        .collect();
    let max_scale = |i: usize| st.scene.scales[i].iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
    let small = d.percent_dense * extent;
    let mut candidates: Vec<usize> = (0..n).filter(|&i| grads[i] >= d.grad_threshold).collect();
    // A clone adds one splat, a split net one: cap the growth.
    let budget = d.max_splats.saturating_sub(n);
    if candidates.len() > budget {
        candidates.sort_by(|&a, &b| grads[b].total_cmp(&grads[a]).then(a.cmp(&b)));
        candidates.truncate(budget);
        candidates.sort_unstable();
    }
    let mut is_split = vec![false; n];
    let mut rows: Vec<(usize, bool)> = Vec::new();
    let mut clones = Vec::new();
    let mut splits = Vec::new();
    for &i in &candidates {
        if max_scale(i) <= small {
            clones.push(i);
        } else {
            splits.push(i);
            is_split[i] = true;
        }
    }
    rows.extend((0..n).filter(|&i| !is_split[i]).map(|i| (i, true)));
    rows.extend(clones.iter().map(|&i| (i, false)));
    let n_kept = rows.len();
    for &i in &splits {
        rows.push((i, false));
        rows.push((i, false));
    }
    let mut out = st.gather(&rows);
    // Split children: positions sampled from the parent, scales / (0.8 · 2).
    for (j, &i) in splits.iter().enumerate() {
        let s = Vec3::from(st.scene.scales[i]).exp();
        let r = crate::math::quat_to_mat(st.scene.quats[i]);
        for c in 0..2 {
            let z: [f32; 3] = [0, 1, 2].map(|_| StandardNormal.sample(rng));
            let p = r * (Vec3::from(z) * s) + Vec3::from(st.scene.means[i]);
            let row = n_kept + 2 * j + c;
            out.scene.means[row] = p.to_array();
            out.scene.scales[row] = st.scene.scales[i].map(|v| v - (0.8f32 * 2.0).ln());
        }
    }
    // Prune.
    let after_reset = st.iteration > d.opacity_reset_interval;
    let keep: Vec<(usize, bool)> = (0..out.scene.len())
        .filter(|&i| {
            let transparent = sigmoid(out.scene.opacities[i]) < d.min_opacity;
            let big_screen = after_reset && d.max_screen_size > 0 && out.max_radii[i] > d.max_screen_size;
            let big_world = after_reset
                && out.scene.scales[i].iter().fold(f32::MIN, |a, &b| a.max(b)).exp() > d.max_world_scale * extent;
            !(transparent || big_screen || big_world)
        })
        .map(|i| (i, true))
        .collect();
    let pruned = out.scene.len() - keep.len();
    let mut out = out.gather(&keep);
    out.grad2d_accum.fill(0.0);
    out.grad2d_count.fill(0);
    out.max_radii.fill(0);
    (out, DensifyStats { cloned: clones.len(), split: splits.len(), pruned })
}

/// Inria's reset_opacity: opacities capped at 0.01, their Adam moments zeroed.
pub fn reset_opacity(st: &mut TrainState) {
    let cap = logit(0.01);
    for o in &mut st.scene.opacities {
        *o = o.min(cap);
    }
    st.exp_avg[3].fill(0.0);
    st.exp_avg_sq[3].fill(0.0);
}

/// log of the root mean squared distance to the 3 nearest other points (Inria's distCUDA2,
/// clamped at 1e-7 squared distance).
pub fn knn_log_scales(points: &[[f32; 3]]) -> Vec<f32> {
    let points: Vec<[f64; 3]> = points.iter().map(|p| p.map(|c| c as f64)).collect();
    let tree = crate::math::tree(&points);
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let nn = tree.nearest_n::<kiddo::SquaredEuclidean>(p, 4);
            let d: Vec<f64> = nn
                .iter()
                .filter(|n| n.item as usize != i)
                .take(3)
                .map(|n| (0..3).map(|a| (points[n.item as usize][a] - p[a]).powi(2)).sum::<f64>())
                .collect();
            let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
            (mean.max(1e-7) as f32).sqrt().ln()
        })
        .collect()
}

/// The initial scene: the dataset's points (or random ones in the cameras' bounding box), one
/// isotropic Gaussian each with the kNN scale, opacity `init.opacity`, sh0 from the colour.
pub fn initial_scene(ds: &Dataset, cfg: &Config) -> Scene {
    let pc = match &ds.points {
        Some(pc) if !pc.positions.is_empty() => pc.clone(),
        _ => {
            let centres: Vec<Vec3> = ds.train.iter().map(|v| v.camera.position()).collect();
            let lo = centres.iter().copied().fold(Vec3::splat(f32::MAX), Vec3::min);
            let hi = centres.iter().copied().fold(Vec3::splat(f32::MIN), Vec3::max);
            let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed);
            let mut pc = crate::dataset::PointCloud::default();
            for _ in 0..cfg.init.random_points {
                let u = Vec3::new(rng.random(), rng.random(), rng.random());
                pc.positions.push((lo + (hi - lo) * u).to_array());
                pc.colors.push([rng.random(), rng.random(), rng.random()]);
            }
            pc
        }
    };
    let coeffs = ((cfg.sh_degree + 1) * (cfg.sh_degree + 1)) as usize;
    let scales = knn_log_scales(&pc.positions);
    let mut s = Scene { sh_degree: cfg.sh_degree, ..Default::default() };
    for (i, p) in pc.positions.iter().enumerate() {
        s.means.push(*p);
        s.scales.push([scales[i]; 3]);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacities.push(logit(cfg.init.opacity));
        for k in 0..coeffs {
            for c in 0..3 {
                s.sh.push(if k == 0 { (pc.colors[i][c] - 0.5) / SH_C0_F32 } else { 0.0 });
            }
        }
    }
    s
}

/// Losses and PSNR of one training iteration.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    pub psnr: f64,
}

/// The GPU side of training: scene, gradients, Adam moments, rasterizer and loss buffers.
pub struct Trainer {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    pub scene: GpuScene,
    /// The instanced run's groups (None: plain).
    layout: Option<Layout>,
    /// Instance-transform parameters and Adam moments (host side; refined when `refine`).
    xforms: [Vec<[f32; 8]>; 3],
    refine: bool,
    grads: Grads,
    adam: AdamState,
    pub raster: Rasterizer,
    losses: Vec<LossBufs>,
    cmd: CommandBuffer,
    timer: Option<crate::gpu::Timer>,
    /// GPU milliseconds per pass of the last iteration (forward passes, loss, backward, Adam).
    pub passes: Vec<(String, f64)>,
}

impl Trainer {
    /// `refine`: optimise the instance transforms of an instanced state too.
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, st: &TrainState, refine: bool) -> Result<Trainer> {
        let (scene, grads, adam) = Trainer::upload_state(gpu, st, refine)?;
        Ok(Trainer {
            gpu: gpu.clone(),
            k: k.clone(),
            scene,
            layout: st.layout.clone(),
            xforms: [st.xform_params.clone(), st.xform_exp_avg.clone(), st.xform_exp_avg_sq.clone()],
            refine,
            grads,
            adam,
            raster: Rasterizer::new(gpu, k)?,
            losses: Vec::new(),
            cmd: CommandBuffer::new(gpu)?,
            timer: crate::gpu::Timer::new(gpu, 16)?,
            passes: Vec::new(),
        })
    }

    fn upload_state(gpu: &Arc<Gpu>, st: &TrainState, refine: bool) -> Result<(GpuScene, Grads, AdamState)> {
        let mut scene = match st.to_instanced()? {
            Some(inst) => {
                let mut s = GpuScene::instanced(gpu, &inst)?;
                s.inst.xform_grads = refine;
                if refine {
                    s.write_transforms(gpu, &st.xform_params.iter().map(xform_from_params).collect::<Vec<_>>())?;
                }
                s
            }
            None => GpuScene::new(gpu, &st.scene)?,
        };
        scene.active_sh_degree = st.active_sh_degree;
        let grads = Grads::new(gpu, &scene)?;
        let adam = AdamState::new(gpu, &scene)?;
        for k in 0..5 {
            gpu.write(&adam.exp_avg[k], &st.exp_avg[k])?;
            gpu.write(&adam.exp_avg_sq[k], &st.exp_avg_sq[k])?;
        }
        for k in 0..3 {
            gpu.write(&adam.offset_exp_avg[k], &st.offset_exp_avg[k])?;
            gpu.write(&adam.offset_exp_avg_sq[k], &st.offset_exp_avg_sq[k])?;
        }
        if st.layout.is_some() {
            gpu.submit_and_wait(|rec| {
                grads.record_reset_stats(rec);
                Ok(())
            })?;
        } else {
            gpu.write(&grads.grad2d_accum, &st.grad2d_accum)?;
            gpu.write(&grads.grad2d_count, &st.grad2d_count)?;
            gpu.write(&grads.max_radii, &st.max_radii)?;
        }
        Ok((scene, grads, adam))
    }

    /// Replaces the device state (after densification or on resume).
    pub fn load(&mut self, st: &TrainState) -> Result<()> {
        let (scene, grads, adam) = Trainer::upload_state(&self.gpu, st, self.refine)?;
        self.scene = scene;
        self.layout = st.layout.clone();
        self.xforms = [st.xform_params.clone(), st.xform_exp_avg.clone(), st.xform_exp_avg_sq.clone()];
        self.grads = grads;
        self.adam = adam;
        Ok(())
    }

    /// Reads the whole device state back.
    pub fn download(&self, iteration: u64) -> Result<TrainState> {
        let g = &self.gpu;
        let n = self.scene.rows;
        let st = strides(self.scene.sh_degree);
        let read = |b: &crate::gpu::Buffer, len: usize| g.read::<f32>(b, len);
        let p = param_buffers(&self.scene);
        let params: Vec<Vec<f32>> = (0..5).map(|k| read(p[k], n * st[k])).collect::<Result<_>>()?;
        let m: Vec<Vec<f32>> = (0..5).map(|k| read(&self.adam.exp_avg[k], n * st[k])).collect::<Result<_>>()?;
        let v: Vec<Vec<f32>> = (0..5).map(|k| read(&self.adam.exp_avg_sq[k], n * st[k])).collect::<Result<_>>()?;
        let to5 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 5] { v.try_into().unwrap() };
        let plain = self.layout.is_none();
        let stats = if plain { n } else { 0 };
        let pairs = self.scene.inst.pairs;
        let ow = [3, 3, 1];
        let ob = offset_buffers(&self.scene);
        let off: Vec<Vec<f32>> = (0..3).map(|k| read(ob[k], pairs * ow[k])).collect::<Result<_>>()?;
        let om: Vec<Vec<f32>> =
            (0..3).map(|k| read(&self.adam.offset_exp_avg[k], pairs * ow[k])).collect::<Result<_>>()?;
        let ov: Vec<Vec<f32>> =
            (0..3).map(|k| read(&self.adam.offset_exp_avg_sq[k], pairs * ow[k])).collect::<Result<_>>()?;
        let to3 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 3] { v.try_into().unwrap() };
        let [dm, dc, dop] = to3(off);
        Ok(TrainState {
            iteration,
            active_sh_degree: self.scene.active_sh_degree,
            scene: scene_from_params(to5(params), self.scene.sh_degree),
            exp_avg: to5(m),
            exp_avg_sq: to5(v),
            grad2d_accum: read(&self.grads.grad2d_accum, stats)?,
            grad2d_count: g.read(&self.grads.grad2d_count, stats)?,
            max_radii: g.read(&self.grads.max_radii, stats)?,
            layout: self.layout.as_ref().map(|l| {
                // Refined transforms: the layout's matrices follow the parameters.
                let mut l = l.clone();
                if self.refine {
                    let mut it = self.xforms[0].iter();
                    for g in &mut l.groups {
                        for inst in &mut g.instances {
                            let x = xform_from_params(it.next().expect("one parameter set per instance"));
                            inst.1 = crate::model::instanced::mat4_to_rows(x.to_mat4());
                        }
                    }
                }
                l
            }),
            xform_params: self.xforms[0].clone(),
            xform_exp_avg: self.xforms[1].clone(),
            xform_exp_avg_sq: self.xforms[2].clone(),
            offsets: Offsets {
                d_means: bytemuck::pod_collect_to_vec(&dm),
                d_sh0: bytemuck::pod_collect_to_vec(&dc),
                d_opacities: dop,
            },
            offset_exp_avg: to3(om),
            offset_exp_avg_sq: to3(ov),
        })
    }

    /// One iteration on `view`: forward, loss, backward and the Adam step (`step` from 1).
    pub fn step(&mut self, view: &View, cfg: &Config, lr: &LearningRates, step: u64) -> Result<StepStats> {
        let cam = &view.camera;
        let frame = self.raster.render(&self.scene, cam, cfg.background)?;
        let li = match self.losses.iter().position(|l| l.width == cam.width && l.height == cam.height) {
            Some(i) => i,
            None => {
                self.losses.push(LossBufs::new(&self.gpu, cam.width, cam.height)?);
                self.losses.len() - 1
            }
        };
        // One submission: target upload, loss, backward, Adam, loss sums back.
        self.losses[li].target_upload.write_mapped(&view.image)?;
        let lb = &self.losses[li];
        let image = self.raster.image_buffer().unwrap();
        let (k, scene, grads, adam, raster) = (&self.k, &self.scene, &self.grads, &self.adam, &self.raster);
        self.cmd.record_timed(self.timer.as_mut(), |rec| {
            lb.record_target_upload(rec)?;
            record_loss(rec, k, image, lb, cfg.ssim_weight)?;
            raster.record_backward(rec, scene, &lb.v_image, grads)?;
            record_adam(rec, k, scene, grads, adam, lr, step)?;
            lb.record_sums_readback(rec)
        })?;
        self.cmd.submit_and_wait()?;
        let sums: Vec<f32> = lb.sums_readback.read_mapped(crate::shared::LOSS_SLOTS as usize)?;
        let (l1, ssim) = lb.means(&sums);
        if self.refine && self.layout.is_some() {
            self.step_transforms(&cfg.lr, step)?;
        }
        self.passes = frame.passes.clone();
        if let Some(t) = &self.timer {
            self.passes.extend(t.results()?);
        }
        let w = cfg.ssim_weight as f64;
        Ok(StepStats {
            loss: (1.0 - w) * l1 + w * (1.0 - ssim),
            l1,
            ssim,
            psnr: crate::util::psnr(&frame.image, &view.image),
        })
    }
}

impl Trainer {
    /// Adam on the instance transforms (host side, f64, the twin of `adam.comp`) at the
    /// `lr.transform_*` rates; then the new transforms go to the device.
    fn step_transforms(&mut self, cfg: &crate::train::config::LrConfig, step: u64) -> Result<()> {
        use crate::shared::XFORM_GRAD_TERMS;
        let n = self.xforms[0].len();
        let terms: Vec<f32> = self.gpu.read(&self.grads.xforms, n * XFORM_GRAD_TERMS as usize)?;
        for (i, chunk) in terms.chunks_exact(XFORM_GRAD_TERMS as usize).enumerate() {
            let g = xform_param_grads(&self.xforms[0][i], chunk);
            let f = |a: &[f32; 8]| a.map(f64::from);
            let (mut p, mut m, mut v) = (f(&self.xforms[0][i]), f(&self.xforms[1][i]), f(&self.xforms[2][i]));
            for (range, rate) in
                [(0..4, cfg.transform_rotation), (4..7, cfg.transform_translation), (7..8, cfg.transform_scale)]
            {
                let a = crate::render::reference::backward::AdamStep {
                    lr: rate as f64,
                    beta1: crate::train::optim::BETA1,
                    beta2: crate::train::optim::BETA2,
                    eps: crate::train::optim::EPS as f64,
                    step,
                };
                crate::render::reference::backward::adam(
                    &mut p[range.clone()],
                    &g[range.clone()],
                    &mut m[range.clone()],
                    &mut v[range],
                    a,
                );
            }
            self.xforms[0][i] = p.map(|x| x as f32);
            self.xforms[1][i] = m.map(|x| x as f32);
            self.xforms[2][i] = v.map(|x| x as f32);
        }
        let transforms: Vec<Similarity> = self.xforms[0].iter().map(xform_from_params).collect();
        self.scene.write_transforms(&self.gpu, &transforms)
    }
}

/// PSNR and SSIM of one view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewScore {
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
}

/// Mean PSNR and SSIM over views, and each view's.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub psnr: f64,
    pub ssim: f64,
    pub views: Vec<ViewScore>,
}

/// Renders `views` from `scene` and scores them against their images; `each` sees every
/// rendered frame (for writing pictures).
pub fn evaluate(
    raster: &mut Rasterizer,
    scene: &GpuScene,
    views: &[View],
    background: [f32; 3],
    mut each: impl FnMut(&View, &crate::render::raster::Frame) -> Result<()>,
) -> Result<Evaluation> {
    let mut per = Vec::new();
    for v in views {
        let f = raster.render(scene, &v.camera, background)?;
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let a: Vec<[f64; 3]> = f.image.iter().map(|p| [0, 1, 2].map(|c| p[c].clamp(0.0, 1.0) as f64)).collect();
        let b: Vec<[f64; 3]> = v.image.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        per.push(ViewScore {
            name: v.camera.name.clone(),
            psnr: crate::util::psnr(&f.image, &v.image),
            ssim: crate::render::reference::backward::ssim(&a, &b, w, h),
        });
        each(v, &f)?;
    }
    let n = per.len().max(1) as f64;
    let psnr = per.iter().map(|p| p.psnr).sum::<f64>() / n;
    let ssim = per.iter().map(|p| p.ssim).sum::<f64>() / n;
    Ok(Evaluation { psnr, ssim, views: per })
}

/// The training view of iteration `it` (from 1): every epoch visits each view once, in an order
/// drawn from (seed, epoch) — stateless, so a resumed run draws the same views.
pub fn view_index(seed: u64, it: u64, n: usize) -> usize {
    let epoch = (it - 1) / n as u64;
    let mut order: Vec<usize> = (0..n).collect();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed ^ epoch.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    for i in (1..n).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    order[((it - 1) % n as u64) as usize]
}

// ---------------------------------------------------------------------------------------------
// Checkpoints

const MAGIC: &[u8; 8] = b"INSTGSCK";
const VERSION: u32 = 1;

#[derive(serde::Serialize, serde::Deserialize)]
struct CheckpointHeader {
    iteration: u64,
    active_sh_degree: u32,
    sh_degree: u32,
    gaussians: usize,
    /// The run's configuration; keys an older checkpoint lacks take today's defaults.
    config: serde_json::Value,
    /// Instanced runs; then the offsets and their moments follow the statistics.
    #[serde(default)]
    layout: Option<Layout>,
}

/// Writes `st` atomically (temporary file + rename) after checking it is finite, so a bad state
/// never replaces the last good checkpoint.
pub fn write_checkpoint(path: &Path, st: &TrainState, cfg: &Config) -> Result<()> {
    st.check_finite().context("checkpoint not written; the last good one is kept")?;
    let header = serde_json::to_vec(&CheckpointHeader {
        iteration: st.iteration,
        active_sh_degree: st.active_sh_degree,
        sh_degree: st.scene.sh_degree,
        gaussians: st.scene.len(),
        config: serde_json::to_value(cfg)?,
        layout: st.layout.clone(),
    })?;
    crate::util::write_atomic(path, |f| {
        let mut w = std::io::BufWriter::new(f);
        w.write_all(MAGIC)?;
        w.write_all(&VERSION.to_le_bytes())?;
        w.write_all(&(header.len() as u64).to_le_bytes())?;
        w.write_all(&header)?;
        let moments = st.exp_avg.iter().chain(&st.exp_avg_sq).map(|v| &v[..]);
        for arr in st.params().into_iter().chain(moments) {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        w.write_all(bytemuck::cast_slice(&st.grad2d_accum))?;
        w.write_all(bytemuck::cast_slice(&st.grad2d_count))?;
        w.write_all(bytemuck::cast_slice(&st.max_radii))?;
        let moments = st.offset_exp_avg.iter().chain(&st.offset_exp_avg_sq).map(|v| &v[..]);
        for arr in st.offset_arrays().into_iter().chain(moments) {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        for arr in [&st.xform_params, &st.xform_exp_avg, &st.xform_exp_avg_sq] {
            w.write_all(bytemuck::cast_slice(arr))?;
        }
        w.flush()
    })
}

/// Reads a checkpoint; returns the state and the configuration it was written with.
pub fn read_checkpoint(path: &Path) -> Result<(TrainState, Config)> {
    let what = path.display();
    let data = std::fs::read(path).with_context(|| format!("{what}: cannot read checkpoint"))?;
    if data.len() < 20 || &data[..8] != MAGIC {
        bail!("{what}: not an instgs-vk checkpoint");
    }
    let version = u32::from_le_bytes(data[8..12].try_into().unwrap());
    if version != VERSION {
        bail!("{what}: checkpoint version {version}, this build reads {VERSION}");
    }
    let hlen = u64::from_le_bytes(data[12..20].try_into().unwrap()) as usize;
    let header: CheckpointHeader = data
        .get(20..20 + hlen)
        .and_then(|h| serde_json::from_slice(h).ok())
        .ok_or_else(|| anyhow!("{what}: damaged checkpoint header"))?;
    if header.sh_degree > 3 {
        bail!("{what}: damaged checkpoint header");
    }
    let n = header.gaussians;
    let st = strides(header.sh_degree);
    let mut pos = 20 + hlen;
    let mut take = |count: usize| -> Result<&[u8]> {
        let bytes = count.checked_mul(4).ok_or_else(|| anyhow!("{what}: damaged checkpoint"))?;
        let s = data.get(pos..pos + bytes).ok_or_else(|| anyhow!("{what}: truncated checkpoint"))?;
        pos += bytes;
        Ok(s)
    };
    let mut f32s = |count: usize| -> Result<Vec<f32>> { Ok(bytemuck::pod_collect_to_vec(take(count)?)) };
    let params: Vec<Vec<f32>> = (0..5).map(|k| f32s(n * st[k])).collect::<Result<_>>()?;
    let m: Vec<Vec<f32>> = (0..5).map(|k| f32s(n * st[k])).collect::<Result<_>>()?;
    let v: Vec<Vec<f32>> = (0..5).map(|k| f32s(n * st[k])).collect::<Result<_>>()?;
    let stats = if header.layout.is_some() { 0 } else { n };
    let accum = f32s(stats)?;
    let count: Vec<u32> = bytemuck::pod_collect_to_vec(&f32s(stats)?);
    let radii: Vec<u32> = bytemuck::pod_collect_to_vec(&f32s(stats)?);
    let pairs = header.layout.as_ref().map_or(0, |l| l.pairs());
    let ow = [3, 3, 1];
    let off: Vec<Vec<f32>> = (0..9).map(|k| f32s(pairs * ow[k % 3])).collect::<Result<_>>()?;
    let instances = header.layout.as_ref().map_or(0, |l| l.groups.iter().map(|g| g.instances.len()).sum());
    let xf: Vec<Vec<[f32; 8]>> =
        (0..3).map(|_| Ok(bytemuck::pod_collect_to_vec(&f32s(instances * 8)?))).collect::<Result<_>>()?;
    if pos != data.len() {
        bail!("{what}: checkpoint has {} trailing bytes", data.len() - pos);
    }
    let to5 = |v: Vec<Vec<f32>>| -> [Vec<f32>; 5] { v.try_into().unwrap() };
    let state = TrainState {
        iteration: header.iteration,
        active_sh_degree: header.active_sh_degree,
        scene: scene_from_params(to5(params), header.sh_degree),
        exp_avg: to5(m),
        exp_avg_sq: to5(v),
        grad2d_accum: accum,
        grad2d_count: count,
        max_radii: radii,
        layout: header.layout,
        offsets: Offsets {
            d_means: bytemuck::pod_collect_to_vec(&off[0]),
            d_sh0: bytemuck::pod_collect_to_vec(&off[1]),
            d_opacities: off[2].clone(),
        },
        offset_exp_avg: [off[3].clone(), off[4].clone(), off[5].clone()],
        offset_exp_avg_sq: [off[6].clone(), off[7].clone(), off[8].clone()],
        xform_params: xf[0].clone(),
        xform_exp_avg: xf[1].clone(),
        xform_exp_avg_sq: xf[2].clone(),
    };
    state.to_instanced().with_context(|| format!("{what}: damaged instanced checkpoint"))?;
    let config =
        Config::from_saved(header.config).with_context(|| format!("{what}: damaged checkpoint configuration"))?;
    Ok((state, config))
}

// ---------------------------------------------------------------------------------------------
// The training run

/// Set by Ctrl-C: the loop writes a checkpoint and stops.
pub static INTERRUPTED: AtomicBool = AtomicBool::new(false);

pub struct RunOptions {
    pub out: PathBuf,
    pub resume: bool,
    /// Joint optimisation of this instanced scene (else plain training from the dataset).
    pub init: Option<InstancedScene>,
    /// Show progress: a bar on a terminal, else a line every 10 % or [`crate::util::LINE_SECONDS`] (false:
    /// a line every 10 % only).
    pub progress: bool,
    /// Written before the progress bar and the progress lines (the pipeline's stage).
    pub label: String,
    /// Stop as Ctrl-C would once this many iterations of this session are done (tests of
    /// interrupting and resuming).
    pub stop_after: Option<u64>,
}

impl RunOptions {
    /// Plain training into `out` (no init, no label, no forced stop).
    pub fn new(out: PathBuf, resume: bool, progress: bool) -> RunOptions {
        RunOptions { out, resume, init: None, progress, label: String::new(), stop_after: None }
    }
}

/// Whether iteration `it` densifies the scene (plain runs; never the last iteration).
fn densifies(d: &crate::train::config::DensifyConfig, it: u64) -> bool {
    it < d.until_iter && it > d.from_iter && it % d.interval == 0
}

/// Whether iteration `it` resets the opacities (plain runs; never the last iteration).
fn resets_opacities(d: &crate::train::config::DensifyConfig, it: u64) -> bool {
    d.opacity_reset_interval > 0 && it % d.opacity_reset_interval == 0 && it < d.until_iter
}

/// The figure of a run's metrics with its schedule's events (`curves.png`).
pub fn curves(rows: &[MetricsRow], cfg: &Config, plain: bool, ds: &Dataset) -> crate::train::plot::Curves {
    let d = &cfg.densify;
    let kind = if plain { "Plain 3DGS training" } else { "Joint optimisation of the instanced scene" };
    crate::train::plot::Curves {
        title: format!(
            "{kind}: {} iterations, {} training views, {} held-out views",
            cfg.iterations,
            ds.train.len(),
            ds.test.len()
        ),
        loss: rows.iter().map(|r| (r.iteration, r.loss)).collect(),
        train_psnr: rows.iter().map(|r| (r.iteration, r.train_psnr)).collect(),
        test_psnr: rows.iter().filter_map(|r| r.test_psnr.map(|p| (r.iteration, p))).collect(),
        densify: (plain && d.until_iter > d.from_iter).then_some((d.from_iter, d.until_iter.min(cfg.iterations))),
        opacity_resets: if plain {
            (1..cfg.iterations).filter(|&it| resets_opacities(d, it)).collect()
        } else {
            Vec::new()
        },
        iterations: cfg.iterations,
    }
}

/// One row of `metrics.csv`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MetricsRow {
    pub iteration: u64,
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    pub train_psnr: f64,
    pub splats: usize,
    pub elapsed_s: f64,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
}

const CSV_HEADER: &str = "iteration,loss,l1,ssim,train_psnr,splats,elapsed_s,test_psnr,test_ssim";

impl MetricsRow {
    fn csv(&self) -> String {
        let opt = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_default();
        format!(
            "{},{:.6},{:.6},{:.6},{:.4},{},{:.3},{},{}",
            self.iteration,
            self.loss,
            self.l1,
            self.ssim,
            self.train_psnr,
            self.splats,
            self.elapsed_s,
            opt(self.test_psnr),
            opt(self.test_ssim)
        )
    }

    fn parse(line: &str) -> Option<MetricsRow> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 9 {
            return None;
        }
        let opt = |s: &str| if s.is_empty() { Some(None) } else { s.parse().ok().map(Some) };
        Some(MetricsRow {
            iteration: f[0].parse().ok()?,
            loss: f[1].parse().ok()?,
            l1: f[2].parse().ok()?,
            ssim: f[3].parse().ok()?,
            train_psnr: f[4].parse().ok()?,
            splats: f[5].parse().ok()?,
            elapsed_s: f[6].parse().ok()?,
            test_psnr: opt(f[7])?,
            test_ssim: opt(f[8])?,
        })
    }
}

/// The outcome of a run.
pub struct RunSummary {
    pub iterations: u64,
    pub splats: usize,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    /// Wall time of the run, resumed parts and the final writes included.
    pub seconds: f64,
    /// This invocation's iterations over their own wall time (held-out evaluations,
    /// densification and checkpoints included; startup and the final writes not).
    pub iterations_per_second: f64,
    pub interrupted: bool,
    /// Median GPU milliseconds per pass over this session's iterations.
    pub pass_medians: Vec<(String, f64)>,
}

/// `INSTGS_FAULT_NAN_AT=N`: put a NaN into a parameter before iteration N (tests of the
/// divergence handling).
fn fault_nan_at() -> Option<u64> {
    std::env::var("INSTGS_FAULT_NAN_AT").ok()?.parse().ok()
}

pub fn checkpoint_path(out: &Path) -> PathBuf {
    out.join("checkpoint.bin")
}

/// Trains `cfg.iterations` iterations on `ds`, writing into `opts.out`: `checkpoint.bin`,
/// `metrics.csv`, `point_cloud.ply` and `curves.png`. With `opts.resume` it continues from the
/// checkpoint (the configuration must match the one it was written with, iterations aside).
pub fn run(gpu: &Arc<Gpu>, k: &Arc<Kernels>, ds: &Dataset, cfg: &Config, opts: &RunOptions) -> Result<RunSummary> {
    std::fs::create_dir_all(&opts.out).with_context(|| format!("{}: cannot create", opts.out.display()))?;
    if ds.train.is_empty() {
        bail!("the dataset has no training views");
    }
    let extent = ds.camera_extent();
    let ckpt = checkpoint_path(&opts.out);
    let metrics_path = opts.out.join("metrics.csv");
    let (mut state, mut rows) = if opts.resume {
        let (st, saved) =
            read_checkpoint(&ckpt).with_context(|| "cannot resume (run without --resume to start afresh)")?;
        let same = Config { iterations: cfg.iterations, ..saved.clone() };
        if &same != cfg {
            bail!(
                "{}: the checkpoint was written with another configuration; resume with the same --config",
                ckpt.display()
            );
        }
        let text = std::fs::read_to_string(&metrics_path).unwrap_or_default();
        let rows: Vec<MetricsRow> =
            text.lines().skip(1).filter_map(MetricsRow::parse).filter(|r| r.iteration <= st.iteration).collect();
        (st, rows)
    } else {
        if ckpt.exists() {
            bail!("{} exists: continue it with --resume, or choose another --out", ckpt.display());
        }
        match &opts.init {
            Some(scene) => (TrainState::instanced(scene), Vec::new()),
            None => (TrainState::new(initial_scene(ds, cfg)), Vec::new()),
        }
    };
    let mut trainer = Trainer::new(gpu, k, &state, cfg.refine_transforms)?;
    let write_metrics = |rows: &[MetricsRow]| -> Result<()> {
        let mut text = String::from(CSV_HEADER);
        text.push('\n');
        for r in rows {
            text.push_str(&r.csv());
            text.push('\n');
        }
        crate::util::write_atomic(&metrics_path, |f| f.write_all(text.as_bytes()))
    };
    let start_it = state.iteration;
    let elapsed0 = rows.last().map_or(0.0, |r| r.elapsed_s);
    let t0 = Instant::now();
    let mode = if opts.progress { ProgressMode::Auto } else { ProgressMode::Tenths };
    let mut progress = Progress::new(&opts.label, "iteration", "it/s", cfg.iterations, start_it, mode);
    let mut test = rows.iter().rev().find_map(|r| r.test_psnr.zip(r.test_ssim));
    let mut interrupted = false;
    let mut pass_times: Vec<(String, Vec<f64>)> = Vec::new();
    for it in start_it + 1..=cfg.iterations {
        if INTERRUPTED.load(Ordering::SeqCst) || opts.stop_after.is_some_and(|n| it > start_it + n) {
            interrupted = true;
            break;
        }
        if it % cfg.sh_increase_interval == 0 && trainer.scene.active_sh_degree < trainer.scene.sh_degree {
            trainer.scene.active_sh_degree += 1;
        }
        let lr = LearningRates {
            means: cfg.position_lr(it, extent),
            scales: cfg.lr.scaling,
            quats: cfg.lr.rotation,
            opacities: cfg.lr.opacity,
            sh0: cfg.lr.sh0,
            sh_rest: cfg.lr.sh_rest,
        };
        if fault_nan_at() == Some(it) {
            // Fault injection for the tests: a NaN in the first Gaussian's colour.
            let mut st = trainer.download(it - 1)?;
            st.scene.sh[0] = f32::NAN;
            trainer.load(&st)?;
        }
        let view = &ds.train[view_index(cfg.seed, it, ds.train.len())];
        let last = trainer.step(view, cfg, &lr, it)?;
        for (name, ms) in &trainer.passes {
            match pass_times.iter_mut().find(|(n, _)| n == name) {
                Some(e) => e.1.push(*ms),
                None => pass_times.push((name.clone(), vec![*ms])),
            }
        }
        if !last.loss.is_finite() {
            bail!(
                "the loss became {} at iteration {it} (view {}); stopped without writing a checkpoint — the last good one is {}",
                last.loss,
                view.camera.name,
                ckpt.display()
            );
        }
        // Held-out views after this step's update and before densification and the opacity reset
        // (Inria's training_report order: a reset iteration reports the trained scene).
        let final_it = it == cfg.iterations;
        let mut tested = None;
        if !ds.test.is_empty() && ((cfg.test_interval > 0 && it % cfg.test_interval == 0) || final_it) {
            let e = evaluate(&mut trainer.raster, &trainer.scene, &ds.test, cfg.background, |_, _| Ok(()))?;
            tested = Some((e.psnr, e.ssim));
        }
        let d = &cfg.densify;
        let plain = state.layout.is_none();
        // Neither on the last iteration: nothing would train after it, it would only alter the output.
        let densify_now = plain && !final_it && densifies(d, it);
        let reset_now = plain && !final_it && resets_opacities(d, it);
        if densify_now || reset_now {
            state = trainer.download(it)?;
            if densify_now {
                let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed.wrapping_add(it.wrapping_mul(0x2545_f491)));
                state = densify(&state, cfg, extent, &mut rng).0;
            }
            if reset_now {
                reset_opacity(&mut state);
            }
            state.check_finite().context("training diverged; the last good checkpoint is kept")?;
            if state.scene.is_empty() {
                bail!("densification pruned every splat at iteration {it}");
            }
            trainer.load(&state)?;
        }
        let mut row = MetricsRow {
            iteration: it,
            loss: last.loss,
            l1: last.l1,
            ssim: last.ssim,
            train_psnr: last.psnr,
            splats: trainer.scene.len,
            elapsed_s: elapsed0 + t0.elapsed().as_secs_f64(),
            ..Default::default()
        };
        if let Some((p, q)) = tested {
            row.test_psnr = Some(p);
            row.test_ssim = Some(q);
            test = tested;
        }
        rows.push(row);
        if (cfg.checkpoint_interval > 0 && it % cfg.checkpoint_interval == 0) || final_it {
            state = trainer.download(it)?;
            write_checkpoint(&ckpt, &state, cfg)?;
            write_metrics(&rows)?;
        }
        let msg = format!(
            "loss {:.4} PSNR {:.2}{} splats {}",
            last.loss,
            last.psnr,
            test.map(|(p, _)| format!(" test {p:.2}")).unwrap_or_default(),
            trainer.scene.len
        );
        progress.set(it, &msg);
    }
    // The iterations' own time (held-out evaluations included), not the run's end below.
    let loop_secs = t0.elapsed().as_secs_f64();
    progress.finish();
    let done = rows.last().map_or(start_it, |r| r.iteration);
    state = trainer.download(done)?;
    if interrupted || done > start_it {
        write_checkpoint(&ckpt, &state, cfg)?;
        write_metrics(&rows)?;
    }
    match state.to_instanced()? {
        Some(inst) => {
            crate::formats::instgs::write(&inst, &opts.out.join("scene.instgs"), crate::formats::instgs::Dtype::F32)?
        }
        None => crate::formats::ply::write_ply(&state.scene, &opts.out.join("point_cloud.ply"))?,
    }
    crate::train::plot::write(&curves(&rows, cfg, state.layout.is_none(), ds), &opts.out.join("curves.png"))?;
    let secs = t0.elapsed().as_secs_f64();
    Ok(RunSummary {
        iterations: done,
        splats: trainer.scene.len,
        test_psnr: test.map(|t| t.0),
        test_ssim: test.map(|t| t.1),
        seconds: elapsed0 + secs,
        iterations_per_second: (done - start_it) as f64 / loop_secs.max(1e-9),
        interrupted,
        pass_medians: pass_times
            .into_iter()
            .filter(|(n, _)| n != "setup" && n != "readback")
            .map(|(n, mut v)| {
                v.sort_by(f64::total_cmp);
                (n, v[v.len() / 2])
            })
            .collect(),
    })
}
