//! From a segmented plain scene to an initial instanced scene (InstGS paper §4.2, Fig. 8):
//! every instance of a group is registered onto the group's first instance
//! ([`crate::register`]), then a template is built in the first instance's frame (its centroid
//! at the origin) and per-instance offsets start as nearest-neighbour differences.
//!
//! Template initialisations ([`TemplateInit`]):
//! * `merge` (the paper's): all instances' Gaussians (opacity ≥ `min_opacity`) aligned into
//!   template space and merged, farthest-point sampled down to the mean instance count; kept:
//!   positions and base colours (SH DC); re-initialised: scales (k-NN, as Inria's initial
//!   points), rotations (identity), opacities (0.1), higher SH bands (0).
//! * `max` / `first` (the paper's ablations): the largest / first instance's Gaussians, all
//!   parameters kept, mapped into template space (rotations and SH bands rotated).
//!
//! Offsets: Δp = nearest Gaussian of the instance (world space) − the transformed template
//! mean, Δ SH DC = that Gaussian's DC − the template's; left at 0 where the nearest Gaussian is
//! farther than one registration voxel (parts the instance never showed), Δ opacity = 0.
use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::{Mat3, Quat, Vec3};
use kiddo::SquaredEuclidean;

use crate::instance::{quat_mul, Group, Instance, InstancedScene, Offsets, ShRotation, Similarity};
use crate::register::{centroid, farthest_point_sample, register, register_coloured, RegisterOptions, Sim3};
use crate::scene::{Scene, SH_C0};
use crate::segment::InstanceGroup;
use crate::train::{knn_log_scales, logit, sigmoid};

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TemplateInit {
    /// Merge all aligned instances, farthest-point sample to the mean count, re-initialise all
    /// but positions and SH DC (paper).
    Merge,
    /// The instance with the most Gaussians, kept whole (the default: measured 0.2–0.5 dB better
    /// than `Merge` on the shared scenes, BENCHMARKS.md).
    Max,
    /// The group's first instance.
    First,
}

#[derive(Clone, Debug)]
pub struct InstanceOptions {
    pub init: TemplateInit,
    /// Estimate a uniform scale per instance (registration and ICP).
    pub with_scale: bool,
    /// Register with the Gaussians' base colours too ([`register_coloured`]), for symmetric shapes.
    pub use_colour: bool,
    /// [`RegisterOptions::colour_weight`].
    pub colour_weight: f64,
    /// Gaussians below this opacity take no part in registration and merging.
    pub min_opacity: f32,
    /// Registration voxel = this fraction of the first instance's size ([`object_size`]).
    pub voxel_fraction: f64,
    pub seed: u64,
}

impl Default for InstanceOptions {
    fn default() -> Self {
        InstanceOptions {
            init: TemplateInit::Max,
            with_scale: true,
            use_colour: true,
            colour_weight: 1.0,
            min_opacity: 0.05,
            voxel_fraction: 0.04,
            seed: 0,
        }
    }
}

/// The outcome for one instance.
#[derive(Clone, Debug)]
pub struct InstanceReport {
    pub group: String,
    pub id: u32,
    /// Gaussians labelled with the instance.
    pub gaussians: usize,
    /// Instance world → first instance's world (identity for the first).
    pub relative: Sim3,
    /// Registration fitness and RMSE (see [`crate::register::Registration`]); 1 and 0 for the
    /// first instance.
    pub fitness: f64,
    pub rmse: f64,
    /// Another pose fitted the shape nearly as well; colour decided (when used).
    pub shape_ambiguous: bool,
}

/// Per-Gaussian labels (0 = background) from `labels.json` ({ids, labels}) or `labels.bin`
/// (u32 little-endian), as `instgs-vk segment` writes them; `n` Gaussians expected.
pub fn read_labels(path: &Path, n: usize) -> Result<Vec<u32>> {
    let what = path.display();
    let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read labels"))?;
    let labels: Vec<u32> = match path.extension().and_then(|e| e.to_str()) {
        Some("json") => {
            #[derive(serde::Deserialize)]
            struct Labels {
                labels: Vec<u32>,
            }
            let l: Labels = serde_json::from_slice(&bytes)
                .with_context(|| format!("{what}: not a labels file ({{\"ids\": [..], \"labels\": [..]}})"))?;
            l.labels
        }
        Some("bin") => {
            if bytes.len() % 4 != 0 {
                bail!("{what}: {} bytes is not a whole number of u32 labels", bytes.len());
            }
            bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
        }
        _ => bail!("{what}: labels must be .json or .bin"),
    };
    if labels.len() != n {
        bail!("{what}: {} labels for a scene of {n} Gaussians", labels.len());
    }
    Ok(labels)
}

fn to_f64(p: [f32; 3]) -> [f64; 3] {
    p.map(|c| c as f64)
}

fn sim3_to_similarity(x: &Sim3) -> Similarity {
    let r = Mat3::from_cols_array(&std::array::from_fn(|i| x.rotation[(i % 3, i / 3)] as f32));
    Similarity::from_parts(
        Quat::from_mat3(&r).normalize(),
        x.scale as f32,
        Vec3::new(x.translation.x as f32, x.translation.y as f32, x.translation.z as f32),
    )
}

/// `part` (world Gaussians) mapped by `x`, every parameter: means, rotations, log scales, SH.
fn transform_gaussians(part: &Scene, x: &Similarity) -> Scene {
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

/// Drops background Gaussians (label 0) of little significance: keeps every instance Gaussian
/// and the ⌈keep × background⌉ background Gaussians of the largest `significance` (e.g.
/// [`crate::segment::Segmentation::weight`]), in their order. Returns the scene, its labels and
/// how many background Gaussians were dropped.
pub fn prune_background(
    scene: &Scene,
    labels: &[u32],
    significance: &[f32],
    keep: f64,
) -> Result<(Scene, Vec<u32>, usize)> {
    if labels.len() != scene.len() || significance.len() != scene.len() {
        bail!("{} labels and {} significances for {} Gaussians", labels.len(), significance.len(), scene.len());
    }
    if !(keep > 0.0 && keep <= 1.0) {
        bail!("the kept background fraction must be in (0, 1], not {keep}");
    }
    let mut bg: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] == 0).collect();
    let n_keep = ((keep * bg.len() as f64).ceil() as usize).min(bg.len());
    bg.sort_by(|&a, &b| significance[b].total_cmp(&significance[a]).then(a.cmp(&b)));
    let mut kept = vec![false; scene.len()];
    for &i in &bg[..n_keep] {
        kept[i] = true;
    }
    let idx: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] != 0 || kept[i]).collect();
    Ok((scene.select(&idx), idx.iter().map(|&i| labels[i]).collect(), bg.len() - n_keep))
}

/// Registers every group's instances, builds templates and offsets; Gaussians of no group's
/// instance stay background. `progress` receives one line per step.
pub fn instantiate(
    scene: &Scene,
    labels: &[u32],
    groups: &[InstanceGroup],
    o: &InstanceOptions,
    mut progress: impl FnMut(&str),
) -> Result<(InstancedScene, Vec<InstanceReport>)> {
    if labels.len() != scene.len() {
        bail!("{} labels for {} Gaussians", labels.len(), scene.len());
    }
    let mut members: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for (i, &l) in labels.iter().enumerate() {
        members.entry(l).or_default().push(i);
    }
    let known: std::collections::BTreeSet<u32> = groups.iter().flat_map(|g| g.ids.iter().copied()).collect();
    let unknown: Vec<u32> = members.keys().copied().filter(|&l| l != 0 && !known.contains(&l)).collect();
    if !unknown.is_empty() {
        bail!("labels {unknown:?} are not instances of the groups file");
    }
    let background_idx = members.get(&0).cloned().unwrap_or_default();
    let mut reports = Vec::new();
    let mut out_groups = Vec::new();
    let c = scene.sh_coeffs() * 3;
    for g in groups {
        for &id in &g.ids {
            if members.get(&id).is_none_or(|m| m.is_empty()) {
                bail!("group {:?}: instance {id} claims no Gaussian (its labels are empty)", g.name);
            }
        }
        let parts: Vec<Scene> = g.ids.iter().map(|id| scene.select(&members[id])).collect();
        // Registration clouds: the opaque Gaussians' means and base colours (RGB of the SH DC).
        type Clouds = Vec<Vec<[f64; 3]>>;
        let (opaque, colours): (Clouds, Clouds) = parts
            .iter()
            .map(|p| {
                let mut idx: Vec<usize> = (0..p.len()).filter(|&i| sigmoid(p.opacities[i]) >= o.min_opacity).collect();
                if idx.len() < 16 {
                    idx = (0..p.len()).collect();
                }
                let c = p.sh_coeffs() * 3;
                let rgb = |i: usize| std::array::from_fn(|a| (0.5 + SH_C0 * p.sh[i * c + a]).max(0.01) as f64);
                (idx.iter().map(|&i| to_f64(p.means[i])).collect(), idx.iter().map(|&i| rgb(i)).collect())
            })
            .unzip();
        let size = object_size(&opaque[0]);
        let reg = RegisterOptions {
            voxel: size * o.voxel_fraction,
            with_scale: o.with_scale,
            colour_weight: o.colour_weight,
            seed: o.seed,
            ..RegisterOptions::for_size(size)
        };
        // relative[k]: instance k's world → instance 1's world.
        let mut relative = vec![Sim3::identity()];
        reports.push(InstanceReport {
            group: g.name.clone(),
            id: g.ids[0],
            gaussians: parts[0].len(),
            relative: Sim3::identity(),
            fitness: 1.0,
            rmse: 0.0,
            shape_ambiguous: false,
        });
        if g.ids.len() == 1 {
            progress(&format!(
                "group {:?} has one instance ({}): its Gaussians become the template unchanged",
                g.name, g.ids[0]
            ));
        }
        for k in 1..g.ids.len() {
            let ro = RegisterOptions { seed: o.seed + k as u64, ..reg.clone() };
            let r = if o.use_colour {
                register_coloured(&opaque[k], &colours[k], &opaque[0], &colours[0], &ro)
            } else {
                register(&opaque[k], &opaque[0], &ro)
            }
            .with_context(|| format!("group {:?}: registering instance {} onto {}", g.name, g.ids[k], g.ids[0]))?;
            progress(&format!(
                "{} {}: registered onto {} (fitness {:.3}, RMSE {:.4}, scale {:.4}, {} correspondences{})",
                g.name,
                g.ids[k],
                g.ids[0],
                r.fitness,
                r.rmse,
                r.transform.scale,
                r.correspondences,
                if r.shape_ambiguous { "; shape ambiguous" } else { "" }
            ));
            relative.push(r.transform);
            reports.push(InstanceReport {
                group: g.name.clone(),
                id: g.ids[k],
                gaussians: parts[k].len(),
                relative: r.transform,
                fitness: r.fitness,
                rmse: r.rmse,
                shape_ambiguous: r.shape_ambiguous,
            });
        }
        // Template space: instance 1's world shifted so that its centroid is the origin.
        let shift = Sim3 { translation: centroid(&opaque[0]), ..Sim3::identity() };
        // template → world of instance k, and its inverse.
        let to_world: Vec<Sim3> = relative.iter().map(|a| a.inverse().compose(&shift)).collect();
        let to_template: Vec<Similarity> = to_world.iter().map(|x| sim3_to_similarity(&x.inverse())).collect();
        let template = if g.ids.len() == 1 {
            transform_gaussians(&parts[0], &to_template[0])
        } else {
            match o.init {
                TemplateInit::First => transform_gaussians(&parts[0], &to_template[0]),
                TemplateInit::Max => {
                    let k = (0..parts.len()).max_by_key(|&k| (parts[k].len(), usize::MAX - k)).expect("instances");
                    transform_gaussians(&parts[k], &to_template[k])
                }
                TemplateInit::Merge => merge_and_sample(&parts, &to_template, o.min_opacity, c / 3),
            }
        };
        progress(&format!("{}: template of {} Gaussians ({:?})", g.name, template.len(), o.init));
        let instances: Vec<Instance> = g
            .ids
            .iter()
            .zip(&to_world)
            .map(|(id, x)| Instance { id: id.to_string(), transform: sim3_to_similarity(x) })
            .collect();
        let offsets = nearest_offsets(&template, &instances, &parts, reg.voxel as f32);
        out_groups.push(Group { name: g.name.clone(), template, instances, offsets });
    }
    let background = scene.select(&background_idx);
    let out = InstancedScene { sh_degree: scene.sh_degree, background, groups: out_groups };
    out.validate("instanced scene")?;
    Ok((out, reports))
}

/// An object's size, rotation-invariant: twice the 98th percentile of the points' distances to
/// their centroid (a stray Gaussian does not count).
pub fn object_size(points: &[[f64; 3]]) -> f64 {
    let c = centroid(points);
    let mut d: Vec<f64> = points.iter().map(|p| (nalgebra::Vector3::from(*p) - c).norm()).collect();
    d.sort_by(f64::total_cmp);
    2.0 * d.get(((d.len() as f64 - 1.0) * 0.98) as usize).copied().unwrap_or(0.0)
}

/// The paper's merge-and-sample template: every instance's opaque Gaussians in template space,
/// farthest-point sampled to the mean opaque count; positions and DC kept, the rest
/// re-initialised.
fn merge_and_sample(parts: &[Scene], to_template: &[Similarity], min_opacity: f32, coeffs: usize) -> Scene {
    let mut points = Vec::new();
    let mut dc = Vec::new();
    let mut total = 0;
    for (p, x) in parts.iter().zip(to_template) {
        let mut n = 0;
        for i in 0..p.len() {
            if sigmoid(p.opacities[i]) >= min_opacity {
                let m = x.rotation * (Vec3::from(p.means[i]) * x.scale) + x.translation;
                points.push(to_f64(m.to_array()));
                dc.push([p.sh[i * coeffs * 3], p.sh[i * coeffs * 3 + 1], p.sh[i * coeffs * 3 + 2]]);
                n += 1;
            }
        }
        total += n;
    }
    let count = (total as f64 / parts.len() as f64).round().max(1.0) as usize;
    let pick = farthest_point_sample(&points, count);
    let means: Vec<[f32; 3]> = pick.iter().map(|&i| points[i].map(|v| v as f32)).collect();
    let scales = knn_log_scales(&means).into_iter().map(|s| [s; 3]).collect();
    let mut sh = vec![0.0; pick.len() * coeffs * 3];
    for (j, &i) in pick.iter().enumerate() {
        sh[j * coeffs * 3..j * coeffs * 3 + 3].copy_from_slice(&dc[i]);
    }
    Scene {
        means,
        scales,
        quats: vec![[1.0, 0.0, 0.0, 0.0]; pick.len()],
        opacities: vec![logit(0.1); pick.len()],
        sh,
        sh_degree: parts[0].sh_degree,
    }
}

/// Δp and Δ SH DC towards each instance's nearest own Gaussian (within `cap`), Δ opacity 0.
fn nearest_offsets(template: &Scene, instances: &[Instance], parts: &[Scene], cap: f32) -> Offsets {
    let t = template.len();
    let mut o = Offsets::zeros(t * instances.len());
    let c = template.sh_coeffs() * 3;
    for (k, (inst, part)) in instances.iter().zip(parts).enumerate() {
        let tree = crate::register::tree(&part.means.iter().map(|m| to_f64(*m)).collect::<Vec<_>>());
        let x = inst.transform;
        for j in 0..t {
            let w = x.rotation * (Vec3::from(template.means[j]) * x.scale) + x.translation;
            let i = tree.nearest_one::<SquaredEuclidean>(&to_f64(w.to_array())).item as usize;
            if (Vec3::from(part.means[i]) - w).length() <= cap {
                o.d_means[k * t + j] = (Vec3::from(part.means[i]) - w).to_array();
                for ch in 0..3 {
                    o.d_sh0[k * t + j][ch] = part.sh[i * c + ch] - template.sh[j * c + ch];
                }
            }
        }
    }
    o
}

/// One instance's ground-truth pose from a groups file that carries them (the shared scenes'
/// `instances.json`): `object_to_world` (4×4 row-major), `center_world`, and the object's size
/// (the diagonal of `canonical_bbox` × `scale`).
#[derive(Clone, Debug)]
pub struct GroundTruthPose {
    pub object_to_world: Sim3,
    pub center: [f64; 3],
    pub size: f64,
}

/// Ground-truth poses by instance id, or None when the file has none.
pub fn read_ground_truth(path: &Path) -> Result<Option<BTreeMap<u32, GroundTruthPose>>> {
    #[derive(serde::Deserialize)]
    struct File {
        groups: Vec<G>,
    }
    #[derive(serde::Deserialize)]
    struct G {
        canonical_bbox: Option<[[f64; 3]; 2]>,
        instances: Vec<I>,
    }
    #[derive(serde::Deserialize)]
    struct I {
        id: u32,
        object_to_world: Option<[[f64; 4]; 4]>,
        center_world: Option<[f64; 3]>,
        scale: Option<f64>,
    }
    let what = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    let f: File = serde_json::from_str(&text).with_context(|| format!("{what}: not a groups file"))?;
    let mut out = BTreeMap::new();
    for g in f.groups {
        let Some(bbox) = g.canonical_bbox else { return Ok(None) };
        let diag = (0..3).map(|a| (bbox[1][a] - bbox[0][a]).powi(2)).sum::<f64>().sqrt();
        for i in g.instances {
            let (Some(m), Some(center)) = (i.object_to_world, i.center_world) else { return Ok(None) };
            let a = nalgebra::Matrix3::from_fn(|r, c| m[r][c]);
            let det = a.determinant();
            if det <= 0.0 {
                bail!("{what}: instance {}: object_to_world is not a similarity", i.id);
            }
            let s = det.cbrt();
            let pose =
                Sim3 { rotation: a / s, scale: s, translation: nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]) };
            out.insert(i.id, GroundTruthPose { object_to_world: pose, center, size: diag * i.scale.unwrap_or(1.0) });
        }
    }
    Ok(Some(out))
}

/// Errors of a recovered relative transform (instance world → first instance's world) against
/// ground truth: rotation (degrees), the displacement of the instance's centre as a fraction of
/// the first instance's size, and the relative scale error.
pub fn pose_error(relative: &Sim3, first: &GroundTruthPose, this: &GroundTruthPose) -> (f64, f64, f64) {
    let truth = first.object_to_world.compose(&this.object_to_world.inverse());
    let rot = relative.rotation_error_deg(&truth);
    let (a, b) = (relative.apply(&this.center), truth.apply(&this.center));
    let d = (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt();
    (rot, d / first.size, relative.scale / truth.scale - 1.0)
}
