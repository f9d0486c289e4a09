//! Instanced scenes (InstGS, paper §4.3 Eq. 6): groups of one shared *template* (full
//! Gaussians) placed by K *instances*, each a template→world similarity transform with
//! per-instance, per-Gaussian *offsets* (Δp in world space added after the transform, Δ SH DC,
//! Δ opacity logit), plus plain *background* Gaussians.
//!
//! Expanded Gaussian (template Gaussian j, instance k with transform p ↦ s·R·p + t):
//! mean s·R·μ_j + t + Δp_jk; log-scales log σ_j + ln s; rotation q_T·q_j (Hamilton product,
//! (w, x, y, z)); opacity logit o_j + Δo_jk; SH DC c_j,0 + Δc_jk; higher SH bands evaluated at
//! the template-space direction Rᵀ·d, which [`expand`](InstancedScene::expand) bakes into plain
//! SH coefficients by rotating every band. Splat order everywhere (GPU and CPU): background
//! first, then each group's splats instance-major (k · T + j).
use anyhow::{bail, Context, Result};
use glam::{DVec3, Mat3, Mat4, Quat, Vec3, Vec4};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use crate::model::scene::Scene;

/// A template→world similarity: p_world = scale · rotation · p + translation. Rendering uses the
/// parts; files store `matrix`, the 4×4 as it was given (so a file round trip is exact).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    pub rotation: Quat,
    pub scale: f32,
    pub translation: Vec3,
    matrix: Mat4,
}

impl Similarity {
    /// The similarity of the given parts (its parts then come from its matrix, as a file read
    /// would give them).
    pub fn from_parts(rotation: Quat, scale: f32, translation: Vec3) -> Similarity {
        Self::decompose(Mat4::from_scale_rotation_translation(Vec3::splat(scale), rotation.normalize(), translation))
    }

    /// Decomposes a 4×4 matrix [s·R | t; 0 0 0 1]; refuses shears, non-uniform scales,
    /// reflections and projective rows (tolerance 1e-3 relative). `what` names it in errors.
    pub fn from_mat4(m: Mat4, what: &str) -> Result<Similarity> {
        if !m.to_cols_array().iter().all(|v| v.is_finite()) {
            bail!("{what}: the transform has non-finite entries");
        }
        let row3 = m.row(3);
        if (row3 - Vec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-6 {
            bail!("{what}: the transform's last row is {row3}, not (0, 0, 0, 1)");
        }
        let a = Mat3::from_mat4(m);
        // In f64: a uniform scale of 1e30 has a determinant of 1e90, past f32.
        let det = glam::DMat3::from_cols_array(&a.to_cols_array().map(f64::from)).determinant();
        if det <= 0.0 {
            bail!("{what}: the transform's determinant is {det}; reflections and degenerate transforms are not similarities");
        }
        let scale = det.cbrt();
        if !(1e-6..=1e6).contains(&scale) {
            bail!("{what}: the transform's scale {scale:e} is out of range (a similarity's uniform scale must lie in 1e-6..1e6)");
        }
        let r = a * (1.0 / scale as f32);
        let err = (r.transpose() * r - Mat3::IDENTITY).to_cols_array().iter().fold(0.0f32, |e, v| e.max(v.abs()));
        if err > 1e-3 {
            bail!("{what}: the transform is not a rotation times a uniform scale (|RᵀR − I| = {err:.2e})");
        }
        Ok(Self::decompose(m))
    }

    /// s = det^(1/3), R the nearest rotation's unit quaternion (w ≥ 0), t; `m` kept as given.
    fn decompose(m: Mat4) -> Similarity {
        let a = Mat3::from_mat4(m);
        let scale = a.determinant().cbrt();
        let mut rotation = Quat::from_mat3(&(a * (1.0 / scale))).normalize();
        if rotation.w < 0.0 {
            rotation = -rotation;
        }
        Similarity { rotation, scale, translation: m.w_axis.truncate(), matrix: m }
    }

    /// The matrix as given (files store it).
    pub fn to_mat4(&self) -> Mat4 {
        self.matrix
    }

    /// The matrix of the parts (rendering uses it; equals `to_mat4` up to rounding).
    pub fn render_mat4(&self) -> Mat4 {
        Mat4::from_scale_rotation_translation(Vec3::splat(self.scale), self.rotation, self.translation)
    }

    /// The rotation as a (w, x, y, z) quaternion, the layout of Gaussian rotations.
    pub fn quat_wxyz(&self) -> [f32; 4] {
        let q = self.rotation;
        [q.w, q.x, q.y, q.z]
    }

    /// self∘b: `b` first, then `self`.
    pub fn compose(&self, b: &Similarity) -> Similarity {
        Similarity::from_parts(
            (self.rotation * b.rotation).normalize(),
            self.scale * b.scale,
            self.rotation * (b.translation * self.scale) + self.translation,
        )
    }

    pub fn inverse(&self) -> Similarity {
        let rotation = self.rotation.inverse();
        let scale = 1.0 / self.scale;
        Similarity::from_parts(rotation, scale, -(rotation * self.translation) * scale)
    }
}

/// Hamilton product a·b of (w, x, y, z) quaternions.
pub fn quat_mul(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

/// Per-instance, per-template-Gaussian offsets of one group, instance-major (index k·T + j).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Offsets {
    /// Δp, world space, added after the transform.
    pub d_means: Vec<[f32; 3]>,
    /// Δ SH DC (the Inria `f_dc`), RGB.
    pub d_sh0: Vec<[f32; 3]>,
    /// Δ opacity logit.
    pub d_opacities: Vec<f32>,
}

impl Offsets {
    pub fn zeros(n: usize) -> Offsets {
        Offsets { d_means: vec![[0.0; 3]; n], d_sh0: vec![[0.0; 3]; n], d_opacities: vec![0.0; n] }
    }

    pub fn len(&self) -> usize {
        self.d_opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.d_opacities.is_empty()
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    /// The instance's name (the scene graph's `instance_id`).
    pub id: String,
    /// Template → world.
    pub transform: Similarity,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Group {
    /// The group's name (the scene graph's `template_id`).
    pub name: String,
    /// Template-space Gaussians, T of them, at the scene's SH degree.
    pub template: Scene,
    pub instances: Vec<Instance>,
    /// K·T offsets.
    pub offsets: Offsets,
}

/// An instanced scene. `background` may hold no Gaussians.
#[derive(Clone, Debug, PartialEq)]
pub struct InstancedScene {
    pub sh_degree: u32,
    pub background: Scene,
    pub groups: Vec<Group>,
}

impl InstancedScene {
    /// Splats once expanded: background + Σ T·K.
    pub fn splats(&self) -> usize {
        self.background.len() + self.groups.iter().map(|g| g.template.len() * g.instances.len()).sum::<usize>()
    }

    /// Parameter rows: background + Σ T.
    pub fn rows(&self) -> usize {
        self.background.len() + self.groups.iter().map(|g| g.template.len()).sum::<usize>()
    }

    /// Checks counts, SH degrees and finiteness; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        if self.sh_degree > 3 {
            bail!("{what}: SH degree {} is not supported (0..3)", self.sh_degree);
        }
        if self.background.sh_degree != self.sh_degree {
            bail!("{what}: the background has SH degree {}, the scene {}", self.background.sh_degree, self.sh_degree);
        }
        if !self.background.is_empty() {
            self.background.validate(&format!("{what}: background"))?;
        }
        if self.splats() == 0 {
            bail!("{what}: the scene has no Gaussians");
        }
        for g in &self.groups {
            let w = format!("{what}: group {:?}", g.name);
            if g.template.sh_degree != self.sh_degree {
                bail!("{w}: template SH degree {} differs from the scene's {}", g.template.sh_degree, self.sh_degree);
            }
            g.template.validate(&format!("{w}: template"))?;
            if g.instances.is_empty() {
                bail!("{w}: no instances");
            }
            let n = g.template.len() * g.instances.len();
            let o = &g.offsets;
            if o.d_means.len() != n || o.d_sh0.len() != n || o.d_opacities.len() != n {
                bail!(
                    "{w}: {} offsets for {} instances of {} template Gaussians",
                    o.len(),
                    g.instances.len(),
                    g.template.len()
                );
            }
            let finite = o.d_means.iter().chain(&o.d_sh0).flatten().chain(&o.d_opacities).all(|v| v.is_finite());
            if !finite {
                bail!("{w}: non-finite offsets");
            }
            for inst in &g.instances {
                let t = &inst.transform;
                if !(t.scale.is_finite() && t.scale > 0.0 && t.translation.is_finite() && t.rotation.is_finite()) {
                    bail!("{w}: instance {:?} has an invalid transform", inst.id);
                }
            }
        }
        Ok(())
    }

    /// World-space means of every splat (splat order), without expanding the rest.
    pub fn expanded_means(&self) -> Vec<[f32; 3]> {
        let mut out = self.background.means.clone();
        for g in &self.groups {
            for (k, inst) in g.instances.iter().enumerate() {
                let x = inst.transform;
                for (j, m) in g.template.means.iter().enumerate() {
                    let p = x.rotation * (Vec3::from(*m) * x.scale) + x.translation;
                    out.push((p + Vec3::from(g.offsets.d_means[k * g.template.len() + j])).to_array());
                }
            }
        }
        out
    }

    /// Instance `k` of group `g` in its template's frame: the template with the instance's
    /// offsets (Δposition taken back through its transform: R⁻¹·Δp / s; Δopacity; Δ base colour),
    /// so that `transform_gaussians(&own, &transform)` is its part of [`Self::expand`].
    pub fn instance_in_template_frame(&self, g: usize, k: usize) -> Scene {
        let (group, mut own) = (&self.groups[g], self.groups[g].template.clone());
        let (x, n, c) = (group.instances[k].transform, own.len(), own.sh_coeffs());
        for j in 0..n {
            let p = k * n + j;
            let d = x.rotation.inverse() * Vec3::from(group.offsets.d_means[p]) / x.scale;
            own.means[j] = (Vec3::from(own.means[j]) + d).to_array();
            own.opacities[j] += group.offsets.d_opacities[p];
            for ch in 0..3 {
                own.sh[j * c * 3 + ch] += group.offsets.d_sh0[p][ch];
            }
        }
        own
    }

    /// The fully expanded plain scene (splat order as the GPU's), higher SH bands rotated so the
    /// plain scene renders the same colours.
    pub fn expand(&self) -> Scene {
        let c = self.background.sh_coeffs();
        let mut out = self.background.clone();
        out.sh_degree = self.sh_degree;
        for g in &self.groups {
            let t = &g.template;
            for (k, inst) in g.instances.iter().enumerate() {
                let x = inst.transform;
                let q_t = x.quat_wxyz();
                let ln_s = x.scale.ln();
                let sh_rot = ShRotation::new(x.rotation, self.sh_degree);
                for j in 0..t.len() {
                    let p = k * t.len() + j;
                    let m = x.rotation * (Vec3::from(t.means[j]) * x.scale) + x.translation;
                    out.means.push((m + Vec3::from(g.offsets.d_means[p])).to_array());
                    let s = t.scales[j];
                    out.scales.push([s[0] + ln_s, s[1] + ln_s, s[2] + ln_s]);
                    out.quats.push(quat_mul(q_t, t.quats[j]));
                    out.opacities.push(t.opacities[j] + g.offsets.d_opacities[p]);
                    let mut sh = t.sh[j * c * 3..(j + 1) * c * 3].to_vec();
                    for (v, d) in sh.iter_mut().zip(g.offsets.d_sh0[p]) {
                        *v += d;
                    }
                    sh_rot.apply(&mut sh);
                    out.sh.extend_from_slice(&sh);
                }
            }
        }
        out
    }
}

/// Gradients of an instanced scene's parameters (layouts as the scene's): parameter rows
/// (background, then every template) and per-group offsets.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct InstancedGrads {
    /// Parameter-row gradients as a plain scene (means, log-scales, raw quats, logits, SH).
    pub rows: Scene,
    pub offsets: Vec<Offsets>,
}

impl InstancedScene {
    /// The CPU twin of the instancing backward (paper Eq. 7–9): maps gradients of the expanded
    /// plain scene (splat order, as a [`Scene`] of gradients) to the instanced parameters.
    /// Offsets take them 1:1; a template Gaussian sums Jₖᵀ·g over its instances: means s·Rᵀ,
    /// log-scales 1, raw quaternions q_T⁻¹·g (left multiplication by a unit quaternion is
    /// orthogonal), logit 1, SH DC 1, higher SH bands D (the transpose of the expansion's Dᵀ).
    pub fn map_expanded_grads(&self, g: &Scene) -> InstancedGrads {
        let c = self.background.sh_coeffs();
        let nb = self.background.len();
        let mut rows = Scene {
            means: g.means[..nb].to_vec(),
            scales: g.scales[..nb].to_vec(),
            quats: g.quats[..nb].to_vec(),
            opacities: g.opacities[..nb].to_vec(),
            sh: g.sh[..nb * c * 3].to_vec(),
            sh_degree: self.sh_degree,
        };
        let mut offsets = Vec::new();
        let mut splat = nb;
        for grp in &self.groups {
            let t = grp.template.len();
            let first = rows.len();
            rows.means.extend(std::iter::repeat_n([0.0; 3], t));
            rows.scales.extend(std::iter::repeat_n([0.0; 3], t));
            rows.quats.extend(std::iter::repeat_n([0.0; 4], t));
            rows.opacities.extend(std::iter::repeat_n(0.0, t));
            rows.sh.extend(std::iter::repeat_n(0.0, t * c * 3));
            let mut off = Offsets::zeros(t * grp.instances.len());
            for (k, inst) in grp.instances.iter().enumerate() {
                let x = inst.transform;
                let qc = x.quat_wxyz();
                let q_inv = [qc[0], -qc[1], -qc[2], -qc[3]];
                let sh_rot = ShRotation::new(x.rotation, self.sh_degree);
                for j in 0..t {
                    let (i, p, r) = (splat + k * t + j, k * t + j, first + j);
                    off.d_means[p] = g.means[i];
                    off.d_opacities[p] = g.opacities[i];
                    off.d_sh0[p] = [g.sh[i * c * 3], g.sh[i * c * 3 + 1], g.sh[i * c * 3 + 2]];
                    let m = (x.rotation.inverse() * Vec3::from(g.means[i])) * x.scale;
                    rows.means[r] = (Vec3::from(rows.means[r]) + m).to_array();
                    for a in 0..3 {
                        rows.scales[r][a] += g.scales[i][a];
                    }
                    let q = quat_mul(q_inv, g.quats[i]);
                    for (v, d) in rows.quats[r].iter_mut().zip(q) {
                        *v += d;
                    }
                    rows.opacities[r] += g.opacities[i];
                    let mut sh = g.sh[i * c * 3..(i + 1) * c * 3].to_vec();
                    sh_rot.apply_transpose(&mut sh);
                    for (dst, v) in rows.sh[r * c * 3..(r + 1) * c * 3].iter_mut().zip(sh) {
                        *dst += v;
                    }
                }
            }
            splat += t * grp.instances.len();
            offsets.push(off);
        }
        InstancedGrads { rows, offsets }
    }
}

/// Rotates SH coefficients of degree 1–3 so that Σ c′ₘ Yₘ(d) = Σ cₘ Yₘ(Rᵀd) for every unit
/// direction d (Inria's real SH basis and signs). Each band l maps to itself through a
/// (2l+1)² matrix, found by least squares from the basis at fixed directions (Fibonacci
/// sphere), in f64.
pub struct ShRotation {
    /// Per band 1..=degree: Dᵀ, so that c′ = Dᵀ·c (row-major, (2l+1)²).
    bands: Vec<Vec<f64>>,
}

impl ShRotation {
    pub fn new(rotation: Quat, degree: u32) -> ShRotation {
        let r = Mat3::from_quat(rotation.normalize()).as_dmat3();
        const N: usize = 32;
        let dirs: Vec<DVec3> = (0..N)
            .map(|i| {
                let z = 1.0 - (2.0 * i as f64 + 1.0) / N as f64;
                let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
                let rho = (1.0 - z * z).sqrt();
                DVec3::new(rho * phi.cos(), rho * phi.sin(), z)
            })
            .collect();
        let bands = (1..=degree as usize)
            .map(|l| {
                let (lo, n) = (l * l, 2 * l + 1);
                // With Y(Rᵀd) = D·Y(d) (band l): A[i][m] = Y_m(d_i), B[i][m] = Y_m(Rᵀd_i), so
                // B = A·Dᵀ, and cᵀY(Rᵀd) = (Dᵀc)ᵀY(d): c′ = Dᵀ·c.
                let a = DMatrix::from_fn(N, n, |i, m| crate::math::sh_basis_grad(dirs[i], degree).0[lo + m]);
                let b = DMatrix::from_fn(N, n, |i, m| {
                    crate::math::sh_basis_grad(r.transpose() * dirs[i], degree).0[lo + m]
                });
                let dt = a.svd(true, true).solve(&b, 1e-12).expect("SVD of the SH basis at fixed directions");
                (0..n * n).map(|e| dt[(e / n, e % n)]).collect()
            })
            .collect();
        ShRotation { bands }
    }

    /// Rotates one Gaussian's coefficients in place (`sh[k * 3 + channel]`): c′ = Dᵀ·c.
    pub fn apply(&self, sh: &mut [f32]) {
        self.apply_impl(sh, false)
    }

    /// The transpose, c = D·c′: maps gradients of rotated coefficients back (its vector-Jacobian
    /// product).
    pub fn apply_transpose(&self, sh: &mut [f32]) {
        self.apply_impl(sh, true)
    }

    fn apply_impl(&self, sh: &mut [f32], transpose: bool) {
        for (b, d) in self.bands.iter().enumerate() {
            let l = b + 1;
            let (lo, n) = (l * l, 2 * l + 1);
            for ch in 0..3 {
                let c: Vec<f64> = (0..n).map(|m| sh[(lo + m) * 3 + ch] as f64).collect();
                for m in 0..n {
                    let at = |q: usize| if transpose { d[q * n + m] } else { d[m * n + q] };
                    sh[(lo + m) * 3 + ch] = (0..n).map(|q| at(q) * c[q]).sum::<f64>() as f32;
                }
            }
        }
    }
}

/// The prototype's `scene_graph.json`: groups with instances whose `transform` (4×4, row-major,
/// column vectors) maps the instance's world points onto instance 1's frame, which serves as
/// template space — the inverse of our template→world transform.
#[derive(serde::Serialize, serde::Deserialize)]
pub struct SceneGraphGroup {
    pub template_id: String,
    pub instances: Vec<SceneGraphInstance>,
}

#[derive(serde::Serialize, serde::Deserialize)]
pub struct SceneGraphInstance {
    pub instance_id: String,
    pub transform: [[f32; 4]; 4],
}

/// Row-major 4×4 rows → glam matrix.
pub fn mat4_from_rows(rows: &[[f32; 4]; 4]) -> Mat4 {
    Mat4::from_cols_array_2d(rows).transpose()
}

pub fn mat4_to_rows(m: Mat4) -> [[f32; 4]; 4] {
    m.transpose().to_cols_array_2d()
}

/// Reads a scene graph: (template_id, [(instance_id, template→world)]) per group.
pub fn read_scene_graph(path: &std::path::Path) -> Result<Vec<(String, Vec<Instance>)>> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    scene_graph_from_str(&text, &what)
}

/// [`read_scene_graph`] on a scene graph's text; `what` names it in errors.
pub fn scene_graph_from_str(text: &str, what: &str) -> Result<Vec<(String, Vec<Instance>)>> {
    let groups: Vec<SceneGraphGroup> = serde_json::from_str(text)
        .with_context(|| format!("{what}: not a scene graph (a list of {{template_id, instances}})"))?;
    if groups.is_empty() {
        bail!("{what}: no groups");
    }
    groups
        .into_iter()
        .map(|g| {
            if g.instances.is_empty() {
                bail!("{what}: group {:?} has no instances", g.template_id);
            }
            let instances = g
                .instances
                .iter()
                .map(|i| {
                    let w = format!("{what}: group {:?} instance {:?}", g.template_id, i.instance_id);
                    let world_to_template = Similarity::from_mat4(mat4_from_rows(&i.transform), &w)?;
                    Ok(Instance { id: i.instance_id.clone(), transform: world_to_template.inverse() })
                })
                .collect::<Result<Vec<_>>>()?;
            Ok((g.template_id, instances))
        })
        .collect()
}

/// The scene graph of `scene` (inverse transforms, the prototype's convention).
pub fn scene_graph(scene: &InstancedScene) -> Vec<SceneGraphGroup> {
    scene
        .groups
        .iter()
        .map(|g| SceneGraphGroup {
            template_id: g.name.clone(),
            instances: g
                .instances
                .iter()
                .map(|i| SceneGraphInstance {
                    instance_id: i.id.clone(),
                    transform: mat4_to_rows(i.transform.inverse().to_mat4()),
                })
                .collect(),
        })
        .collect()
}

/// Builds an instanced scene from templates (template space = the scene graph's instance-1
/// frame), a scene graph and an optional background. With `random_offsets = Some((σ, seed))`
/// every offset is drawn from N(0, σ²) (Δp in scene units, Δ SH DC, Δ logit alike).
pub fn compose(
    templates: Vec<(String, Scene)>,
    graph: Vec<(String, Vec<Instance>)>,
    background: Option<Scene>,
    random_offsets: Option<(f32, u64)>,
) -> Result<InstancedScene> {
    let sh_degree = templates.first().map(|t| t.1.sh_degree).unwrap_or(0);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(random_offsets.map_or(0, |r| r.1));
    let normal = Normal::new(0.0f32, random_offsets.map_or(0.0, |r| r.0))
        .map_err(|e| anyhow::anyhow!("--random-offsets: {e}"))?;
    let mut groups = Vec::new();
    for (name, instances) in graph {
        let Some((_, template)) = templates.iter().find(|t| t.0 == name) else {
            bail!(
                "the scene graph's template_id {name:?} has no --template {name}=FILE.ply (given: {})",
                templates.iter().map(|t| t.0.as_str()).collect::<Vec<_>>().join(", ")
            );
        };
        let n = template.len() * instances.len();
        let mut offsets = Offsets::zeros(n);
        if random_offsets.is_some() {
            let mut draw = || normal.sample(&mut rng);
            for p in 0..n {
                offsets.d_means[p] = [draw(), draw(), draw()];
                offsets.d_sh0[p] = [draw(), draw(), draw()];
                offsets.d_opacities[p] = draw();
            }
        }
        groups.push(Group { name, template: template.clone(), instances, offsets });
    }
    let mut background = background.unwrap_or_default();
    if background.is_empty() {
        background = Scene { sh_degree, ..Scene::default() };
    }
    let scene = InstancedScene { sh_degree, background, groups };
    if let Some(g) = scene.groups.iter().find(|g| g.template.sh_degree != sh_degree) {
        bail!(
            "template {:?} has SH degree {} and the first template degree {sh_degree}: templates and background must share one SH degree (convert them to one degree first)",
            g.name,
            g.template.sh_degree
        );
    }
    if scene.background.sh_degree != sh_degree {
        bail!(
            "the background has SH degree {} and the templates {sh_degree}: templates and background must share one SH degree (convert them to one degree first)",
            scene.background.sh_degree
        );
    }
    scene.validate("composed scene")?;
    Ok(scene)
}

/// An instance transform as optimisation parameters: a raw (w, x, y, z) rotation quaternion
/// (normalised in use), the translation and ln s — 8 values, `[q, t, ln s]`.
pub fn xform_params(x: &Similarity) -> [f32; 8] {
    let q = x.quat_wxyz();
    let t = x.translation;
    [q[0], q[1], q[2], q[3], t.x, t.y, t.z, x.scale.ln()]
}

/// The similarity of transform parameters ([`xform_params`]).
pub fn xform_from_params(p: &[f32; 8]) -> Similarity {
    Similarity::from_parts(Quat::from_xyzw(p[1], p[2], p[3], p[0]), p[7].exp(), Vec3::new(p[4], p[5], p[6]))
}

/// dL/d([`xform_params`]) from an instance's summed gradient terms (`XFORM_GRAD_TERMS`:
/// dL/dt, dL/d ln s, dL/dR column-major, dL/dq̂ through the rotation composition): the rotation
/// matrix's VJP and the normalisation's, in f64.
pub fn xform_param_grads(params: &[f32; 8], terms: &[f32]) -> [f64; 8] {
    let q = glam::DVec4::new(params[0] as f64, params[1] as f64, params[2] as f64, params[3] as f64);
    let len = q.length();
    let qn = q / len;
    let t: Vec<f64> = terms.iter().map(|&v| v as f64).collect();
    let v_r = glam::DMat3::from_cols_slice(&t[4..13]);
    let v_qn = crate::math::rotation_vjp(qn, v_r) + glam::DVec4::new(t[13], t[14], t[15], t[16]);
    let v_q = (v_qn - qn * qn.dot(v_qn)) / len;
    [v_q.x, v_q.y, v_q.z, v_q.w, t[0], t[1], t[2], t[3]]
}

/// `part` (world Gaussians) mapped by `x`, every parameter: means, rotations, log scales, SH.
pub fn transform_gaussians(part: &Scene, x: &Similarity) -> Scene {
    let mut out = part.clone();
    let q = x.quat_wxyz();
    let ln_s = x.scale.ln();
    let rot = ShRotation::new(x.rotation, part.sh_degree);
    let c = part.sh_coeffs() * 3;
    for i in 0..part.len() {
        out.means[i] = (x.rotation * (Vec3::from(part.means[i]) * x.scale) + x.translation).to_array();
        out.quats[i] = quat_mul(q, part.quats[i]);
        out.scales[i] = part.scales[i].map(|s| s + ln_s);
        rot.apply(&mut out.sh[i * c..(i + 1) * c]);
    }
    out
}
