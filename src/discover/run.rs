//! `instgs-vk discover`: the example resolved to Gaussians, the search run with the render check
//! over the dataset's training views, and the labels and groups files written for the instance
//! stage (`instgs-vk instance --labels L --groups G`). Where the dataset's `instances.json`
//! carries ground-truth poses, what was found is compared with them (printed and in the groups
//! file); the search itself never reads it, nor any mask but the example's.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::Vec3;

use crate::discover::{auto, from_example, DiscoverOptions, Discovery};
use crate::instancing::pose::RenderCheck;
use crate::instancing::pose_error::{pose_error, read_ground_truth, GroundTruthPose};
use crate::instancing::verify::ImageCheck;
use crate::model::scene::Scene;
use crate::register::{object_size, Sim3};

/// Lifts one view's binary mask into the scene: per-Gaussian labels, 1 = the mask's.
pub type Lift<'a> = dyn FnMut(&crate::dataset::View, &[u16]) -> Result<Vec<u32>> + 'a;

/// What the search starts from.
#[derive(Clone, Debug)]
pub enum ExampleSpec {
    /// No example: find the groups ([`auto`]).
    Auto,
    /// The Gaussians whose means lie in [xmin, ymin, zmin, xmax, ymax, zmax] (world units).
    Box([f64; 6]),
    /// The Gaussians of label `id` in a labels file (`segment`'s or a previous `discover`'s).
    Label { labels: PathBuf, id: u32 },
    /// One instance's mask in one training view (8/16-bit grey PNG, non-zero = the instance, or
    /// only `id` where given); the view is `view` or the training image of the mask's file name.
    Mask { path: PathBuf, view: Option<String>, id: Option<u16> },
}

pub struct DiscoverRequest {
    pub scene: PathBuf,
    /// The dataset: its training views drive the render check and the mask example.
    pub data: PathBuf,
    pub example: ExampleSpec,
    pub opts: DiscoverOptions,
    pub render_check: bool,
    pub downscale: u32,
    /// labels.json ({ids, labels}).
    pub out: PathBuf,
    /// The groups file ({groups: [{name, instances: [{id, to_reference, ...}]}]}).
    pub groups: PathBuf,
}

/// Summary of a run against ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    /// Ground-truth instances found (each matched by at most one found instance).
    pub found: usize,
    pub truth: usize,
    /// Found instances that match no ground-truth instance, one already matched, or one of
    /// another group than most of their group's members.
    pub false_instances: usize,
    /// Largest rotation (degrees), translation (fraction of size) and |scale| error of the found
    /// instances' poses onto their group's reference.
    pub worst: (f64, f64, f64),
}

/// Resolves `spec` to scene indices (empty for [`ExampleSpec::Auto`]).
pub fn example_gaussians(
    scene: &Scene,
    spec: &ExampleSpec,
    views: &[crate::dataset::View],
    lift: &mut Lift,
) -> Result<Vec<usize>> {
    let idx: Vec<usize> = match spec {
        ExampleSpec::Auto => return Ok(Vec::new()),
        ExampleSpec::Box(b) => (0..scene.len())
            .filter(|&i| (0..3).all(|a| (b[a]..=b[a + 3]).contains(&(scene.means[i][a] as f64))))
            .collect(),
        ExampleSpec::Label { labels, id } => {
            let l = crate::instancing::labels::read_labels(labels, scene.len())?;
            let idx: Vec<usize> = (0..l.len()).filter(|&i| l[i] == *id).collect();
            if idx.is_empty() {
                bail!("{}: no Gaussian has label {id}", labels.display());
            }
            idx
        }
        ExampleSpec::Mask { path, view, id } => {
            let name = match view {
                Some(v) => v.clone(),
                None => path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
            };
            let stem = |s: &str| Path::new(s).file_stem().map(|x| x.to_string_lossy().into_owned()).unwrap_or_default();
            let Some(v) = views.iter().find(|v| {
                let file = v.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                file == name || stem(&file) == stem(&name) || v.camera.name == name
            }) else {
                bail!("{}: no training view named {name:?} (pass --view)", path.display());
            };
            let mask = crate::dataset::masks::read_mask(path, v.camera.width, v.camera.height)?;
            let ids = crate::dataset::masks::mask_ids(&mask);
            let want = match (id, ids.as_slice()) {
                (Some(i), _) if ids.contains(i) => *i,
                (Some(i), _) => bail!("{}: no pixel has id {i} (ids {ids:?})", path.display()),
                (None, [one]) => *one,
                (None, []) => bail!("{}: the mask is empty", path.display()),
                (None, _) => bail!("{}: the mask shows ids {ids:?}; pick one with --mask-id", path.display()),
            };
            let binary: Vec<u16> = mask.iter().map(|&x| u16::from(x == want)).collect();
            lift_mask(scene, v, &binary, lift)?
        }
    };
    if idx.is_empty() {
        bail!("the example holds no Gaussian");
    }
    Ok(idx)
}

/// One view's mask lifted into the scene: the Gaussians the segmentation's score gives to the
/// mask (`lift`: per-Gaussian labels, 1 = the mask's), then every Gaussian whose mean projects
/// into the mask and lies no deeper behind the nearest lifted one than the lifted ones' size
/// (one view sees only the object's front; an object is about as deep as it is wide).
fn lift_mask(scene: &Scene, view: &crate::dataset::View, mask: &[u16], lift: &mut Lift) -> Result<Vec<usize>> {
    let labels = lift(view, mask)?;
    let seed: Vec<usize> = (0..scene.len()).filter(|&i| labels[i] == 1).collect();
    if seed.is_empty() {
        bail!("view {}: no Gaussian shows through the mask", view.camera.name);
    }
    let cam = &view.camera;
    let pts: Vec<[f64; 3]> = seed.iter().map(|&i| scene.means[i].map(|c| c as f64)).collect();
    let depth = |i: usize| cam.project(Vec3::from(scene.means[i])).map(|p| p[2]);
    let near = seed.iter().filter_map(|&i| depth(i)).fold(f32::INFINITY, f32::min);
    let reach = near + object_size(&pts) as f32;
    let (w, h) = (cam.width as i64, cam.height as i64);
    Ok((0..scene.len())
        .filter(|&i| {
            labels[i] == 1
                || cam.project(Vec3::from(scene.means[i])).is_some_and(|[u, v, z]| {
                    let (x, y) = (u.floor() as i64, v.floor() as i64);
                    (0..w).contains(&x) && (0..h).contains(&y) && mask[(y * w + x) as usize] != 0 && z <= reach
                })
        })
        .collect())
}

/// Matches what was found with ground truth (by the nearest true centre within half its size)
/// and measures the poses.
/// `group_of`: each true id's group (instances.json).
pub fn evaluate(
    scene: &Scene,
    d: &Discovery,
    truth: &BTreeMap<u32, GroundTruthPose>,
    group_of: &BTreeMap<u32, String>,
) -> (Evaluation, Vec<serde_json::Value>) {
    let mut used = std::collections::BTreeSet::new();
    let mut rows = Vec::new();
    let mut ev = Evaluation { found: 0, truth: truth.len(), false_instances: 0, worst: (0.0, 0.0, 0.0) };
    for g in d.groups.iter().filter(|g| g.members.len() > 1) {
        let matched: Vec<Option<u32>> = g
            .members
            .iter()
            .map(|m| {
                let pts: Vec<[f64; 3]> = m.gaussians.iter().map(|&i| scene.means[i].map(|c| c as f64)).collect();
                let c = crate::register::centroid(&pts);
                truth
                    .iter()
                    .map(|(id, t)| (((0..3).map(|a| (t.center[a] - c[a]).powi(2)).sum::<f64>()).sqrt() / t.size, *id))
                    .filter(|(r, _)| *r < 0.5)
                    .min_by(|a, b| a.0.total_cmp(&b.0))
                    .map(|(_, id)| id)
            })
            .collect();
        let reference = matched[0];
        for (m, t) in g.members.iter().zip(&matched) {
            let mut row = serde_json::json!({"group": g.name, "id": m.id, "truth": t});
            let same_group = matches!((reference, t), (Some(r), Some(t)) if group_of.get(&r) == group_of.get(t));
            match t {
                Some(t) if used.insert(*t) && (Some(*t) == reference || same_group) => {
                    ev.found += 1;
                    if let Some(r) = reference {
                        let (rot, tr, sc) = pose_error(&m.relative, &truth[&r], &truth[t]);
                        row["rotation_error_deg"] = rot.into();
                        row["translation_error_fraction"] = tr.into();
                        row["scale_error_fraction"] = sc.into();
                        ev.worst = (ev.worst.0.max(rot), ev.worst.1.max(tr), ev.worst.2.max(sc.abs()));
                    }
                }
                _ => {
                    ev.false_instances += 1;
                    row["false"] = true.into();
                }
            }
            rows.push(row);
        }
    }
    (ev, rows)
}

/// 4×4 row-major matrix of a similarity.
fn matrix(x: &Sim3) -> Vec<Vec<f64>> {
    let m = x.rotation * x.scale;
    (0..4)
        .map(|r| if r < 3 { vec![m[(r, 0)], m[(r, 1)], m[(r, 2)], x.translation[r]] } else { vec![0.0, 0.0, 0.0, 1.0] })
        .collect()
}

/// Runs the search `spec` asks for on `scene`, the render check (unless `render_check` is
/// false) over `views`' cameras; `progress` gets one line per step.
#[allow(clippy::too_many_arguments)]
pub fn search(
    gpu: &std::sync::Arc<crate::gpu::Gpu>,
    k: &std::sync::Arc<crate::gpu::kernels::Kernels>,
    scene: &Scene,
    spec: &ExampleSpec,
    views: &[crate::dataset::View],
    opts: &DiscoverOptions,
    render_check: bool,
    mut progress: impl FnMut(&str),
) -> Result<Discovery> {
    let mut lift = |v: &crate::dataset::View, m: &[u16]| -> Result<Vec<u32>> {
        let s = crate::segment::segment(gpu, k, scene, std::slice::from_ref(v), &[m.to_vec()], &[1], 0.8)?;
        Ok(s.labels)
    };
    let example = example_gaussians(scene, spec, views, &mut lift)?;
    let mut check = if render_check {
        let cams = views.iter().map(|v| v.camera.clone()).collect();
        Some(ImageCheck::new(gpu, k, cams, None)?)
    } else {
        None
    };
    let rc = check.as_mut().map(|c| c as &mut dyn RenderCheck);
    match spec {
        ExampleSpec::Auto => auto(scene, opts, rc, progress),
        _ => {
            progress(&format!("example: {} Gaussians", example.len()));
            from_example(scene, &example, opts, rc, progress)
        }
    }
}

/// `instgs-vk discover`.
pub fn discover_command(device: Option<String>, req: &DiscoverRequest) -> Result<Evaluation> {
    let scene = crate::formats::read_scene(&req.scene)?;
    let load = crate::dataset::LoadOptions { downscale: req.downscale, background: [0.0; 3] };
    let ds = crate::dataset::load(&req.data, &load)?;
    let (gpu, k) = crate::gpu::kernels::open_device(device)?;
    let started = std::time::Instant::now();
    let found = search(&gpu, &k, &scene, &req.example, &ds.train, &req.opts, req.render_check, |l| eprintln!("{l}"))?;
    if crate::train::INTERRUPTED.load(std::sync::atomic::Ordering::SeqCst) {
        bail!("interrupted before {} was written", req.out.display());
    }
    let ev = write_outputs(&scene, &found, &req.data, &req.out, &req.groups, started.elapsed().as_secs_f64())?;
    eprintln!("wrote {} and {}", req.out.display(), req.groups.display());
    Ok(ev)
}

/// Writes the labels file (`out`) and the groups file (`groups_path`) of `found`; where
/// `data/instances.json` carries ground-truth poses, compares (printed, and in the groups file).
pub fn write_outputs(
    scene: &Scene,
    found: &Discovery,
    data: &Path,
    out: &Path,
    groups_path: &Path,
    seconds: f64,
) -> Result<Evaluation> {
    let labels = found.labels(scene.len());
    let kept: Vec<&crate::discover::FoundGroup> = found.groups.iter().filter(|g| g.members.len() > 1).collect();
    let ids: Vec<u32> = kept.iter().flat_map(|g| g.members.iter().map(|m| m.id)).collect();
    let truth_path = data.join("instances.json");
    let truth = match truth_path.exists() {
        true => read_ground_truth(&truth_path).ok().flatten(),
        false => None,
    };
    let group_of: BTreeMap<u32, String> = match truth {
        Some(_) => crate::dataset::masks::read_groups(&truth_path)?
            .into_iter()
            .flat_map(|g| g.ids.into_iter().map(move |id| (id, g.name.clone())))
            .collect(),
        None => BTreeMap::new(),
    };
    let mut groups_json = serde_json::json!({
        "groups": kept.iter().map(|g| serde_json::json!({
            "name": g.name,
            "instances": g.members.iter().map(|m| {
                let mut row = serde_json::json!({"id": m.id, "gaussians": m.gaussians.len(), "to_reference": matrix(&m.relative)});
                if let Some(r) = &m.report {
                    row["fitness"] = r.check.fitness.into();
                    row["fitness_reverse"] = r.check.fitness_reverse.into();
                    if let Some(s) = r.render {
                        row["render_iou"] = s.iou.into();
                        row["render_psnr"] = s.psnr.into();
                    }
                }
                row
            }).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "refused": found.refused,
        "seconds": seconds,
    });
    let mut ev = Evaluation { found: 0, truth: 0, false_instances: 0, worst: (0.0, 0.0, 0.0) };
    if let Some(t) = &truth {
        let (e, rows) = evaluate(scene, found, t, &group_of);
        groups_json["ground_truth"] = serde_json::json!({
            "found": e.found, "instances": e.truth, "false_instances": e.false_instances,
            "worst_rotation_deg": e.worst.0, "worst_translation_fraction": e.worst.1, "worst_scale_fraction": e.worst.2,
            "members": rows,
        });
        ev = e;
    }
    for p in [&out, &groups_path] {
        if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        }
    }
    crate::util::write_json(out, &serde_json::json!({"ids": ids, "labels": labels}), false)
        .with_context(|| format!("{}: cannot write labels", out.display()))?;
    crate::util::write_json(groups_path, &groups_json, true)?;
    for g in &found.groups {
        let ids: Vec<String> = g.members.iter().map(|m| m.id.to_string()).collect();
        eprintln!("{}: {} member(s): {}", g.name, g.members.len(), ids.join(", "));
    }
    if truth.is_some() {
        eprintln!(
            "against {}: {} of {} instances found, {} false; poses within {:.2}°, {:.2} % translation, {:.2} % scale",
            data.join("instances.json").display(),
            ev.found,
            ev.truth,
            ev.false_instances,
            ev.worst.0,
            100.0 * ev.worst.1,
            100.0 * ev.worst.2
        );
    }
    Ok(ev)
}
