//! The training state on the host: parameters, Adam moments and densification statistics of
//! every Gaussian row, and the instanced layout (groups, offsets, transforms).

use anyhow::{bail, Result};

use crate::model::instanced::{xform_params, Group, Instance, InstancedScene, Offsets, Similarity};
use crate::model::scene::Scene;
use crate::render::appearance::{ColourTransform, Vignetting, IDENTITY, NO_VIGNETTING};
use crate::render::reference::backward::AdamStep;

/// Parameters per Gaussian of the five parameter groups (means, scales, quats, opacities, sh).
pub(crate) fn strides(sh_degree: u32) -> [usize; 5] {
    [3, 3, 4, 1, 3 * ((sh_degree + 1) * (sh_degree + 1)) as usize]
}

/// A scene from its five flat parameter arrays (means, scales, quats, opacities, sh).
pub(crate) fn scene_from_params(p: [Vec<f32>; 5], sh_degree: u32) -> Scene {
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
    /// (template Gaussian, instance) pairs, the rows of the offsets; `None` on overflow (a
    /// damaged checkpoint header).
    pub(crate) fn pairs(&self) -> Option<usize> {
        self.groups
            .iter()
            .try_fold(0usize, |a, g| g.template_gaussians.checked_mul(g.instances.len()).and_then(|p| a.checked_add(p)))
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
    /// The training photos' colour transforms (empty when the run learns none).
    pub appearance: AppearanceState,
    /// The training cameras' corrections (empty when the run refines none).
    pub cameras: crate::train::cameras::CameraState,
}

/// The per-photo colour transforms of a run (crate::render::appearance), one per training view
/// in the dataset's order, with their Adam moments and how many steps each has taken (a photo's
/// transform only steps when its photo is drawn).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AppearanceState {
    pub params: Vec<ColourTransform>,
    pub exp_avg: Vec<ColourTransform>,
    pub exp_avg_sq: Vec<ColourTransform>,
    pub steps: Vec<u32>,
    /// Which parameters learn (the model's: `AppearanceConfig::free_params`; set by the run
    /// from its configuration, not stored in checkpoints).
    pub free: [bool; 12],
    /// The lens's vignetting (crate::render::appearance::Vignetting), shared by every photo, with
    /// its Adam moments and step count (it steps with every photo).
    pub vignetting: Vignetting,
    pub vignetting_exp_avg: Vignetting,
    pub vignetting_exp_avg_sq: Vignetting,
    pub vignetting_steps: u32,
    /// Whether the vignetting learns (`appearance.vignetting`; set by the run, not stored).
    pub vignetting_free: bool,
}

impl AppearanceState {
    /// `n` identity transforms with zero moments.
    pub fn identity(n: usize) -> AppearanceState {
        AppearanceState::from_params(vec![IDENTITY; n], NO_VIGNETTING)
    }

    /// These transforms and this vignetting with zero moments (a new run that starts from
    /// another's).
    pub fn from_params(params: Vec<ColourTransform>, vignetting: Vignetting) -> AppearanceState {
        let n = params.len();
        AppearanceState {
            params,
            exp_avg: vec![[0.0; 12]; n],
            exp_avg_sq: vec![[0.0; 12]; n],
            steps: vec![0; n],
            free: [true; 12],
            vignetting,
            vignetting_exp_avg: NO_VIGNETTING,
            vignetting_exp_avg_sq: NO_VIGNETTING,
            vignetting_steps: 0,
            vignetting_free: true,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    /// What the run has learned of its photos (what RUN/appearance.json holds).
    pub fn learned(&self) -> crate::render::appearance::PhotoAppearance {
        crate::render::appearance::PhotoAppearance { colours: self.params.clone(), vignetting: self.vignetting }
    }

    /// One Adam step of photo `i`'s transform on its gradient `grad` at rate `lr` (the twin of
    /// `adam.comp`, in f64). The change is then spread back over all transforms so that their
    /// mean stays the identity: the scene keeps the photos' average appearance (without it,
    /// every transform could drift one way and the scene the other, and renders without a
    /// transform — held-out views — would drift too). `grad`'s last two entries are the
    /// vignetting's, which steps too when it learns.
    pub fn step(&mut self, i: usize, grad: &[f32; crate::shared::APPEARANCE_GRADS as usize], lr: f64) {
        if lr <= 0.0 {
            return;
        }
        self.steps[i] += 1;
        let f = |a: &[f32; 12]| a.map(f64::from);
        let (mut p, mut m, mut v) = (f(&self.params[i]), f(&self.exp_avg[i]), f(&self.exp_avg_sq[i]));
        let before = p;
        let a = AdamStep {
            lr,
            beta1: crate::train::optim::BETA1,
            beta2: crate::train::optim::BETA2,
            eps: crate::train::optim::EPS as f64,
            step: self.steps[i] as u64,
        };
        let g: [f64; 12] = std::array::from_fn(|k| if self.free[k] { grad[k] as f64 } else { 0.0 });
        crate::render::reference::backward::adam(&mut p, &g, &mut m, &mut v, a);
        self.params[i] = p.map(|x| x as f32);
        self.exp_avg[i] = m.map(|x| x as f32);
        self.exp_avg_sq[i] = v.map(|x| x as f32);
        let n = self.params.len() as f64;
        for t in &mut self.params {
            for k in 0..12 {
                t[k] -= ((p[k] - before[k]) / n) as f32;
            }
        }
        if self.vignetting_free {
            self.vignetting_steps += 1;
            let f = |a: &Vignetting| a.map(f64::from);
            let (mut p, mut m, mut v) =
                (f(&self.vignetting), f(&self.vignetting_exp_avg), f(&self.vignetting_exp_avg_sq));
            let g = [grad[12] as f64, grad[13] as f64];
            crate::render::reference::backward::adam(
                &mut p,
                &g,
                &mut m,
                &mut v,
                AdamStep { step: self.vignetting_steps as u64, ..a },
            );
            self.vignetting = p.map(|x| x as f32);
            self.vignetting_exp_avg = m.map(|x| x as f32);
            self.vignetting_exp_avg_sq = v.map(|x| x as f32);
        }
    }
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
            appearance: AppearanceState::default(),
            cameras: Default::default(),
        }
    }

    /// A fresh state for joint optimisation of an instanced scene.
    pub fn instanced(scene: &InstancedScene) -> TrainState {
        let rows = crate::render::upload::scene_rows(scene);
        let offsets = crate::render::upload::all_offsets(scene);
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
            appearance: AppearanceState::default(),
            cameras: Default::default(),
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

    pub(crate) fn offset_arrays(&self) -> [&[f32]; 3] {
        let o = &self.offsets;
        [bytemuck::cast_slice(&o.d_means), bytemuck::cast_slice(&o.d_sh0), &o.d_opacities]
    }

    pub(crate) fn params(&self) -> [&[f32]; 5] {
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
        let a = &self.appearance;
        for arr in [&a.params, &a.exp_avg, &a.exp_avg_sq] {
            if let Some(k) = arr.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
                bail!("non-finite colour transform of training view {k} at iteration {}", self.iteration);
            }
        }
        if ![a.vignetting, a.vignetting_exp_avg, a.vignetting_exp_avg_sq].iter().flatten().all(|v| v.is_finite()) {
            bail!("non-finite vignetting at iteration {}", self.iteration);
        }
        let c = &self.cameras;
        if let Some(k) = [&c.deltas, &c.exp_avg, &c.exp_avg_sq]
            .iter()
            .find_map(|arr| arr.iter().position(|d| !d.iter().all(|v| v.is_finite())))
        {
            bail!("non-finite camera correction of training view {k} at iteration {}", self.iteration);
        }
        Ok(())
    }

    /// The state restricted to the rows `rows` (source index, kept Adam moments?).
    pub(crate) fn gather(&self, rows: &[(usize, bool)]) -> TrainState {
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
            appearance: self.appearance.clone(),
            cameras: self.cameras.clone(),
            // Densification is for plain runs only: no instancing parts.
            ..TrainState::new(Scene::default())
        }
    }
}
