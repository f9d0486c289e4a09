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

use anyhow::{bail, Context, Result};
use glam::Vec3;
use kiddo::SquaredEuclidean;

use crate::dataset::masks::InstanceGroup;
use crate::instancing::options::{InstanceOptions, Status, TemplateInit};
use crate::instancing::pose::{
    register_and_check, registration_cloud, sim3_to_similarity, synchronise_group, to_f64, up_axis, GraphReport,
    InstanceReport, RenderCheck,
};
use crate::instancing::timing::{Clock, Step, StepTimes, Timed};
use crate::math::{logit, sigmoid};
use crate::model::instanced::{transform_gaussians, Group, Instance, InstancedScene, Offsets, Similarity};
use crate::model::scene::Scene;
use crate::register::{centroid, farthest_point_sample, object_size, Sim3};
use crate::train::knn_log_scales;

/// The background Gaussians (label 0), most significant first (ties: scene order), and how many
/// of them a kept fraction `keep` keeps (⌈keep × background⌉): [`prune_background`]'s choice.
pub fn ranked_background(labels: &[u32], significance: &[f32], keep: f64) -> (Vec<usize>, usize) {
    let mut bg: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] == 0).collect();
    let n_keep = ((keep * bg.len() as f64).ceil() as usize).min(bg.len());
    bg.sort_by(|&a, &b| significance[b].total_cmp(&significance[a]).then(a.cmp(&b)));
    (bg, n_keep)
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
    let (bg, n_keep) = ranked_background(labels, significance, keep);
    let mut kept = vec![false; scene.len()];
    for &i in &bg[..n_keep] {
        kept[i] = true;
    }
    let idx: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] != 0 || kept[i]).collect();
    Ok((scene.select(&idx), idx.iter().map(|&i| labels[i]).collect(), bg.len() - n_keep))
}

/// What [`instantiate`] made and decided.
#[derive(Debug)]
pub struct Instantiated {
    pub scene: InstancedScene,
    /// One per instance, group by group.
    pub reports: Vec<InstanceReport>,
    /// One per group whose poses were synchronised over a pose graph.
    pub graphs: Vec<GraphReport>,
    /// The time per step and the work done.
    pub timing: StepTimes,
}

/// Registers every group's instances onto the group's reference (the instance with the most
/// opaque Gaussians), checks each pose ([`PoseCheck`](crate::instancing::pose::PoseCheck), and
/// [`RenderCheck`] when given), synchronises each group's poses over its sparse pose graph
/// (`pose::graph::synchronise_group`), builds templates and offsets from the accepted instances. A
/// refused instance's Gaussians stay background, as do a whole group's when fewer than two of
/// its instances are left; Gaussians of no group's instance stay background. `progress`
/// receives one line per step.
pub fn instantiate(
    scene: &Scene,
    labels: &[u32],
    groups: &[InstanceGroup],
    o: &InstanceOptions,
    render_check: Option<&mut dyn RenderCheck>,
    mut progress: impl FnMut(&str),
) -> Result<Instantiated> {
    if labels.len() != scene.len() {
        bail!("{} labels for {} Gaussians", labels.len(), scene.len());
    }
    let (labels, groups) = subset(labels, groups, o.only.as_ref())?;
    let (labels, groups) = (labels.as_slice(), groups.as_slice());
    let clock = Clock::default();
    let mut timed = render_check.map(|rc| Timed::new(rc, &clock));
    let mut render_check: Option<&mut dyn RenderCheck> = timed.as_mut().map(|t| t as &mut dyn RenderCheck);
    let mut timing = StepTimes::default();
    let step = Step::start(&clock);
    let members = members_of(labels, groups)?;
    let mut background_idx = members.get(&0).cloned().unwrap_or_default();
    let with_up;
    let o = match o.up {
        Some(_) => o,
        None => {
            let up = up_axis(scene, &background_idx, o.min_opacity, o.seed);
            progress(&match up {
                Some(n) => format!(
                    "up axis (the normal of the background's floor; shape-ambiguous instances try turns about it): [{:.3}, {:.3}, {:.3}]",
                    n.x, n.y, n.z
                ),
                None => "no floor in the background: no turns about an up axis".into(),
            });
            with_up = InstanceOptions { up, ..o.clone() };
            &with_up
        }
    };
    timing.candidates_s += step.own(&clock);
    let mut reports = Vec::new();
    let mut graphs = Vec::new();
    let mut out_groups = Vec::new();
    for g in groups {
        let step = Step::start(&clock);
        let parts: Vec<Scene> = g.ids.iter().map(|id| scene.select(&members[id])).collect();
        type Clouds = Vec<Vec<[f64; 3]>>;
        let (opaque, colours): (Clouds, Clouds) = parts.iter().map(|p| registration_cloud(p, o.min_opacity)).unzip();
        // The reference: the most complete cloud (most opaque Gaussians; ties: the first).
        let r = (0..parts.len()).max_by_key(|&k| (opaque[k].len(), usize::MAX - k)).expect("instances");
        let reg = o.register_options(object_size(&opaque[r]));
        timing.candidates_s += step.own(&clock);
        // relative[k]: instance k's world → the reference's world; None: not instanced.
        let mut relative: Vec<Option<Sim3>> = vec![None; parts.len()];
        relative[r] = Some(Sim3::identity());
        let mut group_reports: Vec<InstanceReport> = Vec::new();
        if g.ids.len() == 1 {
            progress(&format!(
                "group {:?} has one instance ({}): its Gaussians become the template unchanged",
                g.name, g.ids[0]
            ));
        }
        let step = Step::start(&clock);
        for k in 0..parts.len() {
            let mut report = InstanceReport::new(&g.name, g.ids[k], g.ids[r], parts[k].len());
            if k != r {
                let (x, status) = register_and_check(
                    &parts,
                    &opaque,
                    &colours,
                    k,
                    r,
                    &reg,
                    o,
                    &mut render_check,
                    &mut report,
                    &g.name,
                    &g.ids,
                )?;
                report.relative = x;
                report.status = status;
                if report.status.instanced() {
                    relative[k] = Some(x);
                }
                timing.registrations += report.registrations;
                progress(&pose_line(&report, x.scale));
            }
            group_reports.push(report);
        }
        timing.registration_s += step.own(&clock);
        if o.synchronise {
            if let Some(rc) = render_check.as_deref_mut() {
                let step = Step::start(&clock);
                let graph = synchronise_group(
                    rc,
                    &parts,
                    &opaque,
                    &g.ids,
                    r,
                    &mut relative,
                    &reg,
                    o,
                    &mut group_reports,
                    &mut progress,
                )
                .with_context(|| format!("group {:?}: pose synchronisation", g.name))?;
                timing.edges += graph.edges;
                if graph.edges > 0 {
                    graphs.push(graph);
                }
                timing.synchronisation_s += step.own(&clock);
            }
        }
        let step = Step::start(&clock);
        let kept: Vec<usize> = (0..parts.len()).filter(|&k| relative[k].is_some()).collect();
        if kept.len() < 2 && g.ids.len() > 1 {
            let why = format!(
                "no instance of group {:?} but its reference {} passed the checks: the group stays plain",
                g.name, g.ids[r]
            );
            progress(&why);
            for rep in &mut group_reports {
                if rep.status.instanced() {
                    rep.status = Status::Plain(why.clone());
                }
            }
            for id in &g.ids {
                background_idx.extend_from_slice(&members[id]);
            }
            reports.extend(group_reports);
            continue;
        }
        for &k in (0..parts.len()).filter(|k| !kept.contains(k)).collect::<Vec<_>>().iter() {
            background_idx.extend_from_slice(&members[&g.ids[k]]);
        }
        reports.extend(group_reports);
        let group = build_group(&g.name, &parts, &kept, &g.ids, &relative, centroid(&opaque[r]), reg.voxel as f32, o);
        progress(&format!("{}: template of {} Gaussians ({:?})", g.name, group.template.len(), o.init));
        out_groups.push(group);
        timing.templates_s += step.own(&clock);
    }
    background_idx.sort_unstable();
    let background = scene.select(&background_idx);
    let out = InstancedScene { sh_degree: scene.sh_degree, background, groups: out_groups };
    out.validate("instanced scene")?;
    timing.render_checks_s = clock.seconds();
    timing.render_checks = clock.calls();
    Ok(Instantiated { scene: out, reports, graphs, timing })
}

/// The labels and groups of only the instances `only` names (None: all): the others' labels
/// become background and their groups lose them (a group left empty goes).
fn subset(
    labels: &[u32],
    groups: &[InstanceGroup],
    only: Option<&std::collections::BTreeSet<u32>>,
) -> Result<(Vec<u32>, Vec<InstanceGroup>)> {
    let Some(keep) = only else { return Ok((labels.to_vec(), groups.to_vec())) };
    if let Some(id) = keep.iter().find(|id| !groups.iter().any(|g| g.ids.contains(id))) {
        bail!("instance {id} (named to register) is not an instance of the groups file");
    }
    let labels = labels.iter().map(|&l| if keep.contains(&l) { l } else { 0 }).collect();
    let groups = groups
        .iter()
        .filter_map(|g| {
            let ids: Vec<u32> = g.ids.iter().copied().filter(|i| keep.contains(i)).collect();
            (!ids.is_empty()).then(|| InstanceGroup { name: g.name.clone(), ids })
        })
        .collect();
    Ok((labels, groups))
}

/// Each label's Gaussians (0: background), checked against the groups file: every label names
/// one of its instances and every instance claims a Gaussian.
fn members_of(labels: &[u32], groups: &[InstanceGroup]) -> Result<BTreeMap<u32, Vec<usize>>> {
    let mut members: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for (i, &l) in labels.iter().enumerate() {
        members.entry(l).or_default().push(i);
    }
    let known: std::collections::BTreeSet<u32> = groups.iter().flat_map(|g| g.ids.iter().copied()).collect();
    let unknown: Vec<u32> = members.keys().copied().filter(|&l| l != 0 && !known.contains(&l)).collect();
    if !unknown.is_empty() {
        bail!("labels {unknown:?} are not instances of the groups file");
    }
    for g in groups {
        for &id in &g.ids {
            if members.get(&id).is_none_or(|m| m.is_empty()) {
                bail!("group {:?}: instance {id} claims no Gaussian (its labels are empty)", g.name);
            }
        }
    }
    Ok(members)
}

/// The progress line of one instance's registration onto its reference.
fn pose_line(report: &InstanceReport, scale: f64) -> String {
    let line = match &report.status {
        Status::Refused(why) => format!("refused, stays plain: {why}"),
        _ => "accepted".into(),
    };
    format!(
        "{} {}: onto {} {line} (fitness {:.2} / {:.2}, scale {:.4}{}; {} poses tried{}{})",
        report.group,
        report.id,
        report.reference,
        report.check.fitness,
        report.check.fitness_reverse,
        scale,
        report
            .render
            .map(|s| format!(", render IoU {:.2} ({:.2} of its own) PSNR {:.1} dB", s.iou, s.relative_iou, s.psnr))
            .unwrap_or_default(),
        report.tried,
        if report.refined > 1 { format!(", {} distinct ones refined", report.refined) } else { String::new() },
        if report.shape_ambiguous { "; shape ambiguous" } else { "" }
    )
}

/// One group's template and offsets from its instances (`kept`: those with a pose; `relative`:
/// each one's world → the reference's world). Template space is the reference's world shifted so
/// that `centre` (its opaque centroid) is the origin; the template is `o.init`'s choice.
#[allow(clippy::too_many_arguments)]
fn build_group(
    name: &str,
    parts: &[Scene],
    kept: &[usize],
    ids: &[u32],
    relative: &[Option<Sim3>],
    centre: nalgebra::Vector3<f64>,
    voxel: f32,
    o: &InstanceOptions,
) -> Group {
    let parts: Vec<Scene> = kept.iter().map(|&k| parts[k].clone()).collect();
    let ids: Vec<u32> = kept.iter().map(|&k| ids[k]).collect();
    let relative: Vec<Sim3> = kept.iter().map(|&k| relative[k].expect("kept")).collect();
    // Template space: the reference's world shifted so that its centroid is the origin.
    let shift = Sim3 { translation: centre, ..Sim3::identity() };
    // template → world of instance k, and its inverse.
    let to_world: Vec<Sim3> = relative.iter().map(|a| a.inverse().compose(&shift)).collect();
    let to_template: Vec<Similarity> = to_world.iter().map(|x| sim3_to_similarity(&x.inverse())).collect();
    let template = if parts.len() == 1 {
        transform_gaussians(&parts[0], &to_template[0])
    } else {
        match o.init {
            TemplateInit::First => transform_gaussians(&parts[0], &to_template[0]),
            TemplateInit::Max => {
                let k = (0..parts.len()).max_by_key(|&k| (parts[k].len(), usize::MAX - k)).expect("instances");
                transform_gaussians(&parts[k], &to_template[k])
            }
            TemplateInit::Merge => merge_and_sample(&parts, &to_template, o.min_opacity, parts[0].sh_coeffs()),
        }
    };
    let instances: Vec<Instance> = ids
        .iter()
        .zip(&to_world)
        .map(|(id, x)| Instance { id: id.to_string(), transform: sim3_to_similarity(x) })
        .collect();
    let offsets = nearest_offsets(&template, &instances, &parts, voxel);
    Group { name: name.to_string(), template, instances, offsets }
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
        let tree = crate::math::tree(&part.means.iter().map(|m| to_f64(*m)).collect::<Vec<_>>());
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
