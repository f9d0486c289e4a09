//! The registration robustness study (BENCHMARKS.md "Registration robustness"): the segmented
//! instances of a pipeline run (RUN/point_cloud.ply + RUN/labels.json of a dataset with
//! ground-truth poses in DIR/instances.json) are perturbed, seeded, and registered again with
//! the acceptance checks and the render check of the `instance` stage; every instance but the
//! reference is classed against the ground truth: correct (< 2°, < 2 % translation and scale),
//! refused, wrong (accepted with > 5° or > 5 %, and a different picture), in between
//! (accepted, 2–5°/2–5 %), or another pose the images prefer or cannot tell apart (> 5° off, but
//! see [`equivalent`]: an object symmetry, or the instance's own render matches it at least as
//! well as the true pose, both refined).
//!
//! With `--meshes DIR` (pybullet's `pybullet_data` folder, the meshes `instances.json` names:
//! `tools/pybullet-meshes.sh` fetches it) the errors are also taken up to a symmetry of the
//! object ([`symmetry`], as pose benchmarks judge symmetric objects): a pose off the ground
//! truth by a symmetry of the textured mesh — a soccer ball's fifth of a turn, a square brick's
//! quarter turn — is measured against the ground truth turned by that symmetry. Such poses are
//! counted apart ("correct up to a symmetry"), never in the strict "correct".
//!
//! Cases: as segmented; Gaussians subsampled to 50 % and 25 % (the kept ones enlarged to cover
//! the same surface), then either left so or re-fit: the whole perturbed scene fine-tuned on the
//! training photos for `--refit N` iterations (default 500, no densification, the plain
//! schedule's final learning rates), as a reconstruction with that many Gaussians would be fit
//! to the same photos (enlarged alone, an instance's silhouette and colours no longer match its
//! photos, which no trained scene shows); partial (the 30 % of each instance's Gaussians
//! farthest along a random horizontal direction cut away); scaled (each instance by a uniform
//! factor in 0.85–1.15 about its centroid; the truth scaled alike); outliers (10 % more
//! Gaussians scattered in each instance's box, 20 % larger).
//!
//! ```sh
//! cargo run --release --example robustness -- RUN DIR [--judge] [--downscale K] [--seeds N] [--up z|y]
//!     [--only CASE[,CASE]] [--refit N] [--no-synchronise] [--meshes DIR]
//! ```
//!
//! `--only A,B`: the cases whose names contain A or B. `--no-synchronise`: each pose registered
//! onto the reference alone (the stage's `synchronise = false`).
//!
//! `--judge`: no case is run; the run's own instance stage is judged instead — every instance of
//! RUN/instance.json, its pose read from RUN/init.instgs, against the ground truth (up to a
//! symmetry of the object with `--meshes`): shared (accepted, within 5° and 5 %), shared
//! wrongly (another group's, or farther off), left plain with its reason. Exits with 1 when one
//! is shared wrongly or left plain without a reason. DIR may be a capture of
//! `tools/make-capture.sh` (its `ground_truth.json`, poses in COLMAP's frame, in place of
//! `instances.json`): the run's instance ids, which a segmenter's masks leave unrelated to the
//! truth's, are then matched to the true instances by their centres, as the `instance` stage
//! itself does (`pose_error::match_ids_by_centre`).
use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use instgs_vk::gpu::kernels::Kernels;
use instgs_vk::gpu::{Gpu, GpuOptions};
use instgs_vk::instancing::options::InstanceOptions;
use instgs_vk::instancing::pose::{self, RenderCheck};
use instgs_vk::instancing::pose_error::GroundTruthPose;
use instgs_vk::instancing::template;
use instgs_vk::model::scene::Scene;
use instgs_vk::register::{centroid, Sim3};
use rand::{Rng, SeedableRng};

mod symmetry;

#[derive(Clone, Copy, Debug)]
enum Case {
    AsSegmented,
    /// Kept fraction; re-fit on the photos afterwards.
    Subsample(f64, bool),
    Partial(f64),
    Scaled,
    Outliers(f64),
}

impl Case {
    fn name(self) -> String {
        match self {
            Case::AsSegmented => "as segmented".into(),
            Case::Subsample(f, false) => format!("subsampled to {:.0} %, enlarged", 100.0 * f),
            Case::Subsample(f, true) => format!("subsampled to {:.0} %, enlarged and re-fit", 100.0 * f),
            Case::Partial(f) => format!("partial ({:.0} % cut away)", 100.0 * f),
            Case::Scaled => "scaled 0.85–1.15".into(),
            Case::Outliers(f) => format!("{:.0} % outliers", 100.0 * f),
        }
    }
}

/// The perturbed scene and labels, and the ground truth moved with the instances.
fn perturb(
    scene: &Scene,
    labels: &[u32],
    truth: &BTreeMap<u32, GroundTruthPose>,
    case: Case,
    up: usize,
    seed: u64,
) -> (Scene, Vec<u32>, BTreeMap<u32, GroundTruthPose>) {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let ids: Vec<u32> = truth.keys().copied().collect();
    let mut keep: Vec<usize> = (0..scene.len()).collect();
    let mut out_truth = truth.clone();
    let mut extra = Scene { sh_degree: scene.sh_degree, ..Default::default() };
    let mut extra_labels = Vec::new();
    let mut s = scene.clone();
    for &id in &ids {
        let members: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] == id).collect();
        if members.is_empty() {
            continue;
        }
        let pts: Vec<[f64; 3]> = members.iter().map(|&i| scene.means[i].map(|c| c as f64)).collect();
        let c = centroid(&pts);
        match case {
            Case::AsSegmented => {}
            Case::Subsample(f, _) => {
                // A coarser reconstruction: fewer Gaussians, each larger (the kept ones cover
                // the surface area of those dropped: scale × f^(-1/2)).
                let drop: std::collections::HashSet<usize> =
                    members.iter().copied().filter(|_| rng.random::<f64>() >= f).collect();
                keep.retain(|i| !drop.contains(i));
                for &i in &members {
                    s.scales[i] = scene.scales[i].map(|v| v - 0.5 * f.ln() as f32);
                }
            }
            Case::Partial(f) => {
                // A horizontal direction (perpendicular to the up axis).
                let a = rng.random::<f64>() * std::f64::consts::TAU;
                let mut d = [0.0; 3];
                d[(up + 1) % 3] = a.cos();
                d[(up + 2) % 3] = a.sin();
                let mut along: Vec<(f64, usize)> =
                    members.iter().map(|&i| ((0..3).map(|k| scene.means[i][k] as f64 * d[k]).sum(), i)).collect();
                along.sort_by(|x, y| y.0.total_cmp(&x.0));
                let cut: std::collections::HashSet<usize> =
                    along[..(f * along.len() as f64) as usize].iter().map(|x| x.1).collect();
                keep.retain(|i| !cut.contains(i));
            }
            Case::Scaled => {
                let k = 0.85 + 0.3 * rng.random::<f64>();
                for &i in &members {
                    for a in 0..3 {
                        s.means[i][a] = (c[a] + k * (scene.means[i][a] as f64 - c[a])) as f32;
                    }
                    s.scales[i] = scene.scales[i].map(|v| v + k.ln() as f32);
                }
                let about = Sim3 { scale: k, translation: c * (1.0 - k), ..Sim3::identity() };
                let t = out_truth.get_mut(&id).expect("truth");
                t.object_to_world = about.compose(&t.object_to_world);
                t.center = about.apply(&t.center);
                t.size *= k;
            }
            Case::Outliers(f) => {
                let (lo, hi) = pts.iter().fold(([f64::MAX; 3], [f64::MIN; 3]), |(lo, hi), p| {
                    (std::array::from_fn(|a| lo[a].min(p[a])), std::array::from_fn(|a| hi[a].max(p[a])))
                });
                let n = (f * members.len() as f64).round() as usize;
                let coeffs = scene.sh_coeffs() * 3;
                for j in 0..n {
                    let src = members[j % members.len()];
                    let p: [f32; 3] = std::array::from_fn(|a| {
                        let (m, h) = (0.5 * (lo[a] + hi[a]), 0.6 * (hi[a] - lo[a]));
                        (m + h * (2.0 * rng.random::<f64>() - 1.0)) as f32
                    });
                    extra.means.push(p);
                    extra.scales.push(scene.scales[src]);
                    extra.quats.push(scene.quats[src]);
                    extra.opacities.push(scene.opacities[src]);
                    extra.sh.extend_from_slice(&scene.sh[src * coeffs..(src + 1) * coeffs]);
                    extra_labels.push(id);
                }
            }
        }
    }
    let mut out = s.select(&keep);
    let mut out_labels: Vec<u32> = keep.iter().map(|&i| labels[i]).collect();
    out.means.extend(extra.means);
    out.scales.extend(extra.scales);
    out.quats.extend(extra.quats);
    out.opacities.extend(extra.opacities);
    out.sh.extend(extra.sh);
    out_labels.extend(extra_labels);
    (out, out_labels, out_truth)
}

/// The perturbed scene fine-tuned on the training photos for `iterations` (a random view each,
/// L1 + D-SSIM, Adam at the plain schedule's final rates, every SH band active), without
/// densification: the rows, and so the labels, stay as they are.
fn refit(
    gpu: &std::sync::Arc<Gpu>,
    k: &std::sync::Arc<Kernels>,
    ds: &instgs_vk::dataset::Dataset,
    scene: Scene,
    iterations: u64,
    seed: u64,
) -> Result<Scene> {
    use instgs_vk::train::{config::Config, TrainState, Trainer};
    let cfg = Config { seed, ..Config::load(None)? };
    let mut state = TrainState::new(scene);
    state.active_sh_degree = state.scene.sh_degree;
    let mut trainer = Trainer::new(gpu, k, &state, false)?;
    let lr = cfg.learning_rates(cfg.lr.position_max_steps, ds.camera_extent());
    let mut psnr = Vec::new();
    for it in 1..=iterations {
        let index = instgs_vk::train::view_index(seed, it, ds.train.len());
        psnr.push(trainer.step(&ds.train[index], index, &cfg, &lr, it)?.psnr);
    }
    let last = &psnr[psnr.len().saturating_sub(ds.train.len())..];
    eprintln!(
        "  re-fit {iterations} iterations: training PSNR {:.2} dB over the last {} views",
        last.iter().sum::<f64>() / last.len().max(1) as f64,
        last.len()
    );
    Ok(trainer.download(iterations)?.scene)
}

#[derive(Default)]
struct Tally {
    instances: usize,
    correct: usize,
    correct_by_symmetry: usize,
    between: usize,
    symmetric: usize,
    refused: usize,
    wrong: usize,
    worst_accepted: (f64, f64),
}

/// Whether an accepted pose off the ground truth is one the images cannot tell from it: the
/// reference's Gaussians placed by the true pose and by the accepted one render alike from the
/// training cameras (silhouette IoU ≥ 0.95, PSNR ≥ 30 dB: an object symmetry, a brick turned half
/// a turn), or the accepted pose matches the instance's own render at least as well as the true
/// pose does, both refined alike (`check`, the stage's render check and its refinement: the
/// pictures themselves prefer it).
#[allow(clippy::too_many_arguments)]
fn equivalent(
    gpu: &std::sync::Arc<Gpu>,
    k: &std::sync::Arc<Kernels>,
    cams: &[instgs_vk::model::camera::Camera],
    check: &mut dyn RenderCheck,
    scene: &Scene,
    labels: &[u32],
    r: &pose::InstanceReport,
    gt: &BTreeMap<u32, GroundTruthPose>,
) -> Result<bool> {
    let reference = instgs_vk::segment::subset(scene, labels, r.reference);
    let own = instgs_vk::segment::subset(scene, labels, r.id);
    let truth = gt[&r.reference].object_to_world.compose(&gt[&r.id].object_to_world.inverse());
    let by_truth =
        instgs_vk::model::instanced::transform_gaussians(&reference, &pose::sim3_to_similarity(&truth.inverse()));
    let mut alike = instgs_vk::instancing::verify::ImageCheck::new(gpu, k, cams.to_vec(), None)?;
    if alike.score(&reference, &by_truth, r.id, &r.relative)?.is_some_and(|s| s.iou >= 0.95 && s.psnr >= 30.0) {
        return Ok(true);
    }
    let (Some(at_truth), Some(accepted)) = (check.score(&reference, &own, r.id, &truth)?, r.render) else {
        return Ok(false);
    };
    let opaque = pose::registration_cloud(&reference, InstanceOptions::default().min_opacity).0;
    let (centre, size) = (centroid(&opaque), instgs_vk::register::object_size(&opaque));
    let (refined, at_refined, _) = pose::refine_pose(
        check,
        &reference,
        &own,
        r.id,
        (truth, at_truth, pose::Detail::Full),
        centre,
        size,
        false,
        (0..4, 120),
    )?;
    eprintln!(
        "  {} {}: the instance's own render against the reference placed by the accepted pose {:.2} dB, by the true pose {:.2} dB, refined ({:.2}° away) {:.2} dB",
        r.group,
        r.id,
        accepted.pose_psnr,
        at_truth.pose_psnr,
        refined.rotation_error_deg(&truth),
        at_refined.pose_psnr
    );
    Ok(accepted.pose_psnr >= at_refined.pose_psnr)
}

/// A rotation's axis in the object's frame, for the study's lines.
fn axis_of(x: &Sim3) -> String {
    let r = nalgebra::Rotation3::from_matrix_unchecked(x.rotation);
    r.axis().map_or("none".into(), |a| format!("{:.2}, {:.2}, {:.2}", a.x, a.y, a.z))
}

/// `--judge`: the run's own instance stage against the ground truth (module docs).
fn judge(
    run: &std::path::Path,
    groups: &[instgs_vk::dataset::masks::InstanceGroup],
    truth: &BTreeMap<u32, GroundTruthPose>,
    surfaces: &BTreeMap<u32, std::rc::Rc<symmetry::Surface>>,
) -> Result<()> {
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("instance.json")).context("RUN/instance.json")?)?;
    let scene = instgs_vk::formats::instgs::read(&run.join("init.instgs"))?;
    // Instance id → (its group, template → world).
    let mut placed: BTreeMap<u32, (String, Sim3)> = BTreeMap::new();
    for g in &scene.groups {
        for i in &g.instances {
            let x = i.transform;
            let r = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                x.rotation.w as f64,
                x.rotation.x as f64,
                x.rotation.y as f64,
                x.rotation.z as f64,
            ));
            let t = nalgebra::Vector3::new(x.translation.x as f64, x.translation.y as f64, x.translation.z as f64);
            let sim = Sim3 { rotation: *r.to_rotation_matrix().matrix(), scale: x.scale as f64, translation: t };
            placed.insert(i.id.parse()?, (g.name.clone(), sim));
        }
    }
    let group_of = |id: u32| groups.iter().find(|g| g.ids.contains(&id)).map(|g| g.name.clone());
    let (mut shared, mut by_symmetry, mut wrong, mut plain, mut silent) = (0, 0, 0, 0, 0);
    let mut worst = (0.0f64, 0.0f64);
    for r in report["instances"].as_array().context("instance.json: no instances")? {
        let id = r["id"].as_u64().context("an instance without an id")? as u32;
        let status = r["status"].as_str().unwrap_or("?");
        let Some((group, x)) = placed.get(&id) else {
            match r["reason"].as_str() {
                Some(why) => {
                    plain += 1;
                    println!("{id}: {status}, left plain: {why}");
                }
                None => {
                    silent += 1;
                    println!("{id}: {status}, left plain WITHOUT A REASON");
                }
            }
            continue;
        };
        if group_of(id).as_deref() != Some(group.as_str()) {
            wrong += 1;
            println!("{id}: WRONG: shared in group {group}, its truth's group is {:?}", group_of(id));
            continue;
        }
        let reference = r["reference"].as_u64().context("no reference")? as u32;
        if reference == id {
            shared += 1;
            continue;
        }
        // The instance's world → the reference's world.
        let relative = placed[&reference].1.compose(&x.inverse());
        let pose_error = instgs_vk::instancing::pose_error::pose_error;
        let (mut rot, mut trans, mut scale) = pose_error(&relative, &truth[&reference], &truth[&id]);
        let mut turned = false;
        if let (true, Some(surface)) = (rot > 5.0, surfaces.get(&id)) {
            let (a, b) = (&truth[&reference].object_to_world, &truth[&id].object_to_world);
            let d = a.inverse().compose(&relative).compose(b);
            if let Some(sym) = surface.nearest_symmetry(&d).filter(|x| x.rotation_error_deg(&Sim3::identity()) > 10.0) {
                let t = GroundTruthPose { object_to_world: b.compose(&sym.inverse()), ..truth[&id].clone() };
                let e = pose_error(&relative, &truth[&reference], &t);
                if e.0 < rot {
                    ((rot, trans, scale), turned) = (e, true);
                }
            }
        }
        let err = trans.max(scale.abs());
        if rot <= 5.0 && err <= 0.05 {
            shared += 1;
            by_symmetry += turned as usize;
            worst = (worst.0.max(rot), worst.1.max(100.0 * err));
            println!(
                "{id}: shared onto {reference}, {rot:.2}°, {:.2} %{}",
                100.0 * err,
                if turned { " (up to a symmetry of the object)" } else { "" }
            );
        } else {
            wrong += 1;
            println!("{id}: WRONG: shared onto {reference} at {rot:.2}°, {:.2} %", 100.0 * err);
        }
    }
    println!(
        "{}: {shared} shared ({by_symmetry} of them up to a symmetry of the object; worst {:.2}°, {:.2} %), {wrong} shared wrongly, {plain} left plain with a reason, {silent} without",
        run.display(),
        worst.0,
        worst.1
    );
    if wrong > 0 || silent > 0 {
        bail!("{wrong} instance(s) shared wrongly, {silent} left plain without a reason");
    }
    Ok(())
}

fn main() -> Result<()> {
    let mut it = std::env::args().skip(1);
    let (Some(run), Some(data)) = (it.next().map(PathBuf::from), it.next().map(PathBuf::from)) else {
        bail!(
            "usage: robustness RUN DIR [--judge] [--downscale K] [--seeds N] [--up z|y] [--only CASE] [--refit N] [--no-synchronise] [--meshes DIR]"
        );
    };
    let (mut downscale, mut seeds, mut up, mut only, mut synchronise, mut refit_its) =
        (1u32, 2u64, 2usize, String::new(), true, 500u64);
    let mut meshes: Option<PathBuf> = None;
    let mut judging = false;
    while let Some(k) = it.next() {
        if k == "--no-synchronise" {
            synchronise = false;
            continue;
        }
        if k == "--judge" {
            judging = true;
            continue;
        }
        let v = it.next().with_context(|| format!("{k} needs a value"))?;
        match k.as_str() {
            "--downscale" => downscale = v.parse()?,
            "--seeds" => seeds = v.parse()?,
            "--up" => up = if v == "y" { 1 } else { 2 },
            "--only" => only = v,
            "--refit" => refit_its = v.parse()?,
            "--meshes" => meshes = Some(PathBuf::from(v)),
            _ => bail!("unknown option {k}"),
        }
    }
    let scene = instgs_vk::formats::ply::read_ply(&run.join("point_cloud.ply"))?;
    let labels = instgs_vk::instancing::labels::read_labels(&run.join("labels.json"), scene.len())?;
    use instgs_vk::instancing::pose_error::{match_ids_by_centre, read_ground_truth, GROUND_TRUTH_FILE};
    let capture = !data.join("instances.json").exists() && data.join(GROUND_TRUTH_FILE).exists();
    let groups_path = data.join(if capture { GROUND_TRUTH_FILE } else { "instances.json" });
    let mut groups = instgs_vk::dataset::masks::read_groups(&groups_path)?;
    let mut truth = read_ground_truth(&groups_path)?
        .with_context(|| format!("{}: no ground-truth poses", groups_path.display()))?;
    // The run's instance id → the true one (the same ids, but for a capture).
    let mut true_id: BTreeMap<u32, u32> = truth.keys().map(|&t| (t, t)).collect();
    if capture {
        let centres = instgs_vk::instancing::build::instance_centres(&scene, &labels);
        true_id = match_ids_by_centre(&truth, &centres);
        truth = true_id.iter().map(|(&id, t)| (id, truth[t].clone())).collect();
        for g in &mut groups {
            g.ids = true_id.iter().filter(|(_, t)| g.ids.contains(t)).map(|(&id, _)| id).collect();
        }
        println!("{}: {} of the run's instances matched to true ones by their centres", data.display(), true_id.len());
    }
    // Per instance id, the surface of its object (with --meshes).
    let mut surfaces: BTreeMap<u32, std::rc::Rc<symmetry::Surface>> = BTreeMap::new();
    if let Some(dir) = &meshes {
        let text = std::fs::read_to_string(&groups_path).with_context(|| groups_path.display().to_string())?;
        let file: serde_json::Value = serde_json::from_str(&text).with_context(|| groups_path.display().to_string())?;
        for g in file["groups"].as_array().with_context(|| format!("{}: no groups", groups_path.display()))? {
            let surface = std::rc::Rc::new(symmetry::load(g, dir)?);
            for i in g["instances"].as_array().into_iter().flatten() {
                let t = i["id"].as_u64().context("an instance without an id")? as u32;
                for (&id, _) in true_id.iter().filter(|(_, &x)| x == t) {
                    surfaces.insert(id, surface.clone());
                }
            }
        }
    }
    if judging {
        return judge(&run, &groups, &truth, &surfaces);
    }
    let ds = instgs_vk::dataset::load(&data, &instgs_vk::dataset::LoadOptions { downscale, background: [0.0; 3] })?;
    let masks = instgs_vk::dataset::masks::load_masks(&data, "train", &ds.train)?;
    let gpu = Gpu::new(&GpuOptions::from_env(None))?;
    let k = Kernels::new(&gpu)?;
    let cams: Vec<_> = ds.train.iter().map(|v| v.camera.clone()).collect();
    let cases = [
        Case::AsSegmented,
        Case::Subsample(0.5, false),
        Case::Subsample(0.5, true),
        Case::Subsample(0.25, false),
        Case::Subsample(0.25, true),
        Case::Partial(0.3),
        Case::Scaled,
        Case::Outliers(0.1),
    ];
    println!("{} ({} instances), {}", data.display(), truth.len(), gpu.describe());
    println!(
        "| case | registrations | correct | correct up to a symmetry of the object | 2–5° / 2–5 % | other pose the images prefer or cannot tell apart | refused | **wrong** | worst accepted (°, %) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut rows = Vec::new();
    for case in cases.into_iter().filter(|c| only.split(',').any(|o| c.name().contains(o))) {
        let mut t = Tally::default();
        let n_seeds = if matches!(case, Case::AsSegmented) { 1 } else { seeds };
        for seed in 0..n_seeds {
            let (mut s, l, gt) = perturb(&scene, &labels, &truth, case, up, seed);
            if let Case::Subsample(_, true) = case {
                s = refit(&gpu, &k, &ds, s, refit_its, seed)?;
            }
            let mut check =
                instgs_vk::instancing::verify::ImageCheck::new(&gpu, &k, cams.clone(), Some(masks.clone()))?;
            let o = InstanceOptions { synchronise, ..Default::default() };
            let reports = template::instantiate(&s, &l, &groups, &o, Some(&mut check as &mut dyn RenderCheck), |m| {
                eprintln!("  {m}")
            })?
            .reports;
            for r in reports.iter().filter(|r| r.id != r.reference) {
                t.instances += 1;
                let pose_error = instgs_vk::instancing::pose_error::pose_error;
                let (mut rot, mut trans, mut scale) = pose_error(&r.relative, &gt[&r.reference], &gt[&r.id]);
                let mut by_symmetry = false;
                if let (false, Some(surface)) = (rot < 2.0 && trans.max(scale.abs()) < 0.02, surfaces.get(&r.id)) {
                    // The accepted pose in the object's frame against the true one: a symmetry
                    // of the object near it turns the ground truth.
                    let (a, b) = (&gt[&r.reference].object_to_world, &gt[&r.id].object_to_world);
                    let d = a.inverse().compose(&r.relative).compose(b);
                    // The identity's neighbourhood is the strict count's: a symmetry other than
                    // it, more than 10° away.
                    let other = surface.nearest_symmetry(&d).filter(|x| x.rotation_error_deg(&Sim3::identity()) > 10.0);
                    if let Some(sym) = other {
                        let turned =
                            GroundTruthPose { object_to_world: b.compose(&sym.inverse()), ..gt[&r.id].clone() };
                        let e = pose_error(&r.relative, &gt[&r.reference], &turned);
                        if e.0 < rot {
                            eprintln!(
                                "  {} {}: {rot:.2}° off the ground truth, {:.2}° off it turned by a symmetry of the object ({:.2}° about [{}])",
                                r.group,
                                r.id,
                                e.0,
                                sym.rotation_error_deg(&Sim3::identity()),
                                axis_of(&sym)
                            );
                            ((rot, trans, scale), by_symmetry) = (e, true);
                        }
                    }
                }
                let err = trans.max(scale.abs());
                eprintln!(
                    "{} seed {seed}: {} {} onto {}: {} at {rot:.2}°, translation {:.2} %, scale {:+.2} %",
                    case.name(),
                    r.group,
                    r.id,
                    r.reference,
                    r.status.name(),
                    100.0 * trans,
                    100.0 * scale
                );
                match r.status.name() {
                    "accepted" => {
                        t.worst_accepted = (t.worst_accepted.0.max(rot), t.worst_accepted.1.max(100.0 * err));
                        if rot < 2.0 && err < 0.02 && by_symmetry {
                            t.correct_by_symmetry += 1;
                        } else if rot < 2.0 && err < 0.02 {
                            t.correct += 1;
                        } else if (rot > 5.0 || err > 0.05) && equivalent(&gpu, &k, &cams, &mut check, &s, &l, r, &gt)?
                        {
                            t.symmetric += 1;
                            eprintln!(
                                "symmetric {} seed {seed}: {} {}: {rot:.2}°, {:.2} % matches the images at least as the true pose",
                                case.name(),
                                r.group,
                                r.id,
                                100.0 * err
                            );
                        } else if rot > 5.0 || err > 0.05 {
                            t.wrong += 1;
                            eprintln!(
                                "WRONG {} seed {seed}: {} {}: {rot:.2}°, {:.2} % ({:?}, {:?})",
                                case.name(),
                                r.group,
                                r.id,
                                100.0 * err,
                                r.check,
                                r.render
                            );
                        } else {
                            t.between += 1;
                        }
                    }
                    _ => {
                        t.refused += 1;
                        eprintln!(
                            "refused {} seed {seed}: {} {} ({rot:.2}°, {:.2} %): {}",
                            case.name(),
                            r.group,
                            r.id,
                            100.0 * err,
                            r.status.reason().unwrap_or("")
                        );
                    }
                }
            }
        }
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | **{}** | {:.2}°, {:.2} % |",
            case.name(),
            t.instances,
            t.correct,
            t.correct_by_symmetry,
            t.between,
            t.symmetric,
            t.refused,
            t.wrong,
            t.worst_accepted.0,
            t.worst_accepted.1
        );
        rows.push(serde_json::json!({
            "case": case.name(), "registrations": t.instances, "correct": t.correct,
            "correct_by_symmetry": t.correct_by_symmetry, "between": t.between, "symmetric": t.symmetric,
            "refused": t.refused, "wrong": t.wrong,
        }));
    }
    let out = run.join("robustness.json");
    std::fs::write(&out, serde_json::to_string_pretty(&rows)?).with_context(|| out.display().to_string())?;
    eprintln!("{}", out.display());
    Ok(())
}
