//! Building an instanced scene: from a segmented plain scene (`instgs-vk instance`: optional
//! background pruning, templates, verified transforms, the report) or from templates and a scene
//! graph (`instgs-vk compose`).
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::formats::instgs::{self, Dtype};
use crate::formats::ply::read_ply;
use crate::gpu::kernels::open_device;
use crate::instancing::options::InstanceOptions;
use crate::instancing::pose::RenderCheck;
use crate::instancing::verify::ImageCheck;
use crate::util::write_json;

/// Chooses the kept background fraction: (scene, labels, significance) → (fraction, ranking
/// per Gaussian, what was decided as JSON).
pub type KeepRule<'a> =
    dyn FnMut(&crate::model::scene::Scene, &[u32], &[f32]) -> Result<(f64, Vec<f32>, serde_json::Value)> + 'a;

/// Spends the instanced scene's memory again between its templates and its background
/// ([`crate::instancing::compact::rebalance`]): (instanced scene, the background Gaussians the
/// keep rule dropped) → (the scene to write, what was decided as JSON).
pub type RebalanceRule<'a> = dyn FnMut(
        &crate::model::instanced::InstancedScene,
        &crate::model::scene::Scene,
    ) -> Result<(crate::model::instanced::InstancedScene, serde_json::Value)>
    + 'a;

#[allow(clippy::too_many_arguments)]
/// Builds `out` from a segmented plain scene: optional background pruning (`prune`: the
/// significance file, the keep rule and optionally the rebalance of templates and background), templates and verified transforms
/// ([`template::instantiate`](crate::instancing::template::instantiate)), pose errors against ground truth; prints a line per instance
/// and returns (and writes to `report`) the JSON report. `whole` receives the instanced scene
/// before any compaction (templates whole, every background Gaussian): what a memory budget
/// other than the stage's spends from (`instgs-vk curve`).
pub fn instance(
    scene_path: &Path,
    labels: &Path,
    groups_path: &Path,
    truth_path: Option<(&Path, TruthIds)>,
    opts: &crate::instancing::options::InstanceOptions,
    dtype: instgs::Dtype,
    prune: Option<(&Path, &mut KeepRule, Option<&mut RebalanceRule>)>,
    check: Option<&mut dyn crate::instancing::pose::RenderCheck>,
    report: Option<&Path>,
    whole: Option<&Path>,
    out: &Path,
) -> Result<serde_json::Value> {
    use crate::instancing::template;
    let scene = crate::formats::read_scene(scene_path)?;
    let labels_path = labels;
    let labels = crate::instancing::labels::read_labels(labels_path, scene.len())?;
    let groups = crate::dataset::masks::read_groups(groups_path)?;
    let mut opts = opts.clone();
    opts.starts = read_starting_poses(groups_path)?;
    let opts = &opts;
    let known: std::collections::BTreeSet<u32> = groups.iter().flat_map(|g| g.ids.iter().copied()).collect();
    if let Some(l) = labels.iter().find(|&&l| l != 0 && !known.contains(&l)) {
        bail!("{}: label {l} is not an instance of {}", labels_path.display(), groups_path.display());
    }
    // Background pruning (the pipeline's `instance.background_keep`): the background Gaussians
    // ranked by `rule` from significance.bin (f32 per Gaussian, written by `segment`) stay.
    let mut pruned = serde_json::Value::Null;
    let mut dropped = None;
    let compaction = std::time::Instant::now();
    let (scene, labels, rebalance) = match prune {
        Some((sig_path, rule, rebalance)) => {
            let bytes = std::fs::read(sig_path).with_context(|| format!("{}: cannot read", sig_path.display()))?;
            if bytes.len() != 4 * scene.len() {
                bail!("{}: {} bytes, expected 4 per Gaussian ({})", sig_path.display(), bytes.len(), scene.len());
            }
            let sig: Vec<f32> = bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            let before = labels.iter().filter(|&&l| l == 0).count();
            let (keep, ranking, how) = rule(&scene, &labels, &sig)?;
            let (s, l, n_dropped) = template::prune_background(&scene, &labels, &ranking, keep)?;
            eprintln!("background: kept {} of {before} Gaussians ({:.1} %)", before - n_dropped, 100.0 * keep);
            pruned = serde_json::json!({"keep": keep, "before": before, "dropped": n_dropped, "rule": how});
            let (order, n_keep) = template::ranked_background(&labels, &ranking, keep);
            let mut gone = order[n_keep..].to_vec();
            gone.sort_unstable();
            dropped = Some(scene.select(&gone));
            (s, l, rebalance)
        }
        None => (scene, labels, None),
    };
    let mut compaction_s = compaction.elapsed().as_secs_f64();
    let check_ran = check.is_some();
    let made = template::instantiate(&scene, &labels, &groups, opts, check, |line| eprintln!("{line}"))?;
    let (mut inst, reports, mut timing) = (made.scene, made.reports, made.timing);
    if let Some(path) = whole {
        let mut all = inst.clone();
        if let Some(d) = &dropped {
            all.background = all.background.concat(d);
        }
        instgs::write(&all, path, dtype)?;
    }
    let mut rebalanced = serde_json::Value::Null;
    if let (Some(rule), Some(dropped)) = (rebalance, &dropped) {
        // Nothing dropped, nothing to bring back: the scene stays as instanced.
        if !inst.groups.is_empty() && !dropped.is_empty() {
            let t = std::time::Instant::now();
            (inst, rebalanced) = rule(&inst, dropped)?;
            compaction_s += t.elapsed().as_secs_f64();
        }
    }
    timing.compaction_s = compaction_s;
    if crate::train::INTERRUPTED.load(std::sync::atomic::Ordering::SeqCst) {
        bail!("interrupted before {} was written", out.display());
    }
    instgs::write(&inst, out, dtype)?;
    let truth = match truth_path {
        Some((p, ids)) => crate::instancing::pose_error::read_ground_truth(p)?.map(|t| match ids {
            TruthIds::Same => t,
            TruthIds::ByCentre => {
                let centres = instance_centres(&scene, &labels);
                crate::instancing::pose_error::match_by_centre(&t, &centres)
            }
        }),
        None => None,
    };
    let rows = report_rows(&reports, truth.as_ref(), truth_path);
    println!(
        "{}: {} groups, {} template Gaussians, {} background, {} splats ({:?} templates)",
        out.display(),
        inst.groups.len(),
        inst.groups.iter().map(|g| g.template.len()).sum::<usize>(),
        inst.background.len(),
        inst.splats(),
        opts.init
    );
    println!("{}", timing.line());
    let v = serde_json::json!({
        "init": format!("{:?}", opts.init).to_lowercase(),
        "colour": opts.use_colour,
        "acceptance": serde_json::to_value(&opts.accept)?,
        "render_check": check_ran,
        "synchronise": check_ran && opts.synchronise,
        "template_gaussians": inst.groups.iter().map(|g| g.template.len()).sum::<usize>(),
        "background_gaussians": inst.background.len(),
        "splats": inst.splats(),
        "background_pruning": pruned,
        "rebalance": rebalanced,
        "graphs": serde_json::to_value(&made.graphs)?,
        "timing": serde_json::to_value(&timing)?,
        "instances": rows,
    });
    if let Some(path) = report {
        write_json(path, &v, true)?;
    }
    Ok(v)
}

/// One row per instance of the JSON report (and a line printed for each): its verdict, checks,
/// render check, synchronisation and, against `truth` (read from `truth_path`), its pose errors.
fn report_rows(
    reports: &[crate::instancing::pose::InstanceReport],
    truth: Option<&std::collections::BTreeMap<u32, crate::instancing::pose_error::GroundTruthPose>>,
    truth_path: Option<(&Path, TruthIds)>,
) -> Vec<serde_json::Value> {
    let truth_name = truth_path.map(|t| t.0.display().to_string()).unwrap_or_default();
    let mut rows = Vec::new();
    for r in reports {
        let mut row = serde_json::json!({
            "group": r.group, "id": r.id, "reference": r.reference, "gaussians": r.gaussians,
            "status": r.status.name(), "reason": r.status.reason(),
            "fitness": r.check.fitness, "fitness_reverse": r.check.fitness_reverse,
            "scale": r.relative.scale, "scale_ratio": r.check.scale_ratio,
            "poses_tried": r.tried, "poses_refined": r.refined, "shape_ambiguous": r.shape_ambiguous,
            "registrations": r.registrations,
        });
        let mut line = format!(
            "{} {} ({}): {} Gaussians, fitness {:.2} / {:.2}, scale {:.4}",
            r.group,
            r.id,
            r.status.name(),
            r.gaussians,
            r.check.fitness,
            r.check.fitness_reverse,
            r.relative.scale
        );
        if let Some(s) = &r.render {
            row["render_iou"] = s.iou.into();
            row["render_own_iou"] = s.own_iou.into();
            row["render_relative_iou"] = s.relative_iou.into();
            row["render_psnr"] = s.psnr.into();
            row["render_views"] = s.views.into();
            line += &format!(
                ", render IoU {:.2} ({:.2} of its own {:.2}) PSNR {:.1} dB ({} views)",
                s.iou, s.relative_iou, s.own_iou, s.psnr, s.views
            );
        }
        if let Some(s) = &r.synchronised {
            row["synchronised_moved_deg"] = s.moved_deg.into();
            row["synchronised_spread_deg"] = s.spread_deg.into();
            row["synchronised_estimates"] = s.estimates.into();
            line += &format!(", synchronised (moved {:.2}°, estimates within {:.2}°)", s.moved_deg, s.spread_deg);
        }
        if let Some(t) = &truth {
            if let (Some(a), Some(b)) = (t.get(&r.reference), t.get(&r.id)) {
                let (rot, trans, scale) = crate::instancing::pose_error::pose_error(&r.relative, a, b);
                line += &format!(
                    "; against {truth_name}: rotation {rot:.3}°, translation {:.3} % of the size, scale {:+.3} %",
                    100.0 * trans,
                    100.0 * scale
                );
                row["rotation_error_deg"] = rot.into();
                row["translation_error_fraction"] = trans.into();
                row["scale_error_fraction"] = scale.into();
            }
        }
        if let Some(why) = r.status.reason() {
            line += &format!("\n    {}: {why}", r.status.name());
        }
        println!("{line}");
        rows.push(row);
    }
    rows
}

/// How a ground-truth file's instance ids relate to the run's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TruthIds {
    /// The same ids (masks with ids shared by all views, grouped by the truth's own file).
    Same,
    /// Unrelated ids: matched by the instances' centres (`pose_error::match_by_centre`).
    ByCentre,
}

/// Every labelled instance's centre: the opacity-weighted mean of its Gaussians' means.
pub fn instance_centres(
    scene: &crate::model::scene::Scene,
    labels: &[u32],
) -> std::collections::BTreeMap<u32, [f64; 3]> {
    let mut sums: std::collections::BTreeMap<u32, ([f64; 3], f64)> = Default::default();
    for (i, &l) in labels.iter().enumerate().filter(|(_, &l)| l != 0) {
        let w = crate::math::sigmoid(scene.opacities[i]) as f64;
        let e = sums.entry(l).or_default();
        for a in 0..3 {
            e.0[a] += w * scene.means[i][a] as f64;
        }
        e.1 += w;
    }
    sums.into_iter().map(|(l, (s, w))| (l, s.map(|v| v / w.max(1e-12)))).collect()
}

/// `instgs-vk compose`: an instanced scene from named template PLYs (`NAME=FILE`), a scene graph
/// and an optional background; `random_offsets` (amplitude, seed) adds test offsets.
pub fn compose(
    templates: &[String],
    graph: &Path,
    background: Option<&Path>,
    random_offsets: Option<(f32, u64)>,
    dtype: Dtype,
    out: &Path,
) -> Result<()> {
    let mut loaded = Vec::new();
    let mut seen = std::collections::BTreeMap::new();
    for t in templates {
        let Some((name, file)) = t.split_once('=') else {
            bail!("--template {t:?}: expected NAME=FILE.ply");
        };
        if let Some(first) = seen.insert(name, file) {
            bail!("--template {name}= is given twice ({first} and {file}); give each template name once");
        }
        loaded.push((name.to_string(), crate::formats::read_scene(Path::new(file))?));
    }
    let graph = crate::model::instanced::read_scene_graph(graph)?;
    let background_path = background;
    let background = background.map(read_ply).transpose()?;
    let names: Vec<String> = templates.to_vec();
    let scene = crate::model::instanced::compose(loaded, graph, background, random_offsets).with_context(|| {
        let bg = background_path.map(|p| format!(", --background {}", p.display())).unwrap_or_default();
        format!("--template {}{bg}", names.join(" --template "))
    })?;
    instgs::write(&scene, out, dtype)?;
    eprintln!(
        "wrote {}: {} groups, {} splats from {} parameter rows",
        out.display(),
        scene.groups.len(),
        scene.splats(),
        scene.rows()
    );
    Ok(())
}

/// The `to_reference` poses (4×4 row-major similarities, instance world → a common frame) a
/// groups file carries (`discover` writes them); none where it has none.
pub fn read_starting_poses(path: &Path) -> Result<std::collections::BTreeMap<u32, crate::register::Sim3>> {
    #[derive(serde::Deserialize)]
    struct File {
        groups: Vec<G>,
    }
    #[derive(serde::Deserialize)]
    struct G {
        instances: Vec<I>,
    }
    #[derive(serde::Deserialize)]
    struct I {
        id: u32,
        to_reference: Option<[[f64; 4]; 4]>,
    }
    let what = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    let f: File = serde_json::from_str(&text).with_context(|| format!("{what}: not a groups file"))?;
    let mut out = std::collections::BTreeMap::new();
    for i in f.groups.into_iter().flat_map(|g| g.instances) {
        let Some(m) = i.to_reference else { continue };
        let a = nalgebra::Matrix3::from_fn(|r, c| m[r][c]);
        let det = a.determinant();
        if !(det > 0.0 && det.is_finite()) {
            bail!("{what}: instance {}: to_reference is not a similarity", i.id);
        }
        let s = det.cbrt();
        let x = crate::register::Sim3 {
            rotation: a / s,
            scale: s,
            translation: nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]),
        };
        if (x.rotation * x.rotation.transpose() - nalgebra::Matrix3::identity()).norm() > 1e-4 {
            bail!("{what}: instance {}: to_reference is not a similarity", i.id);
        }
        out.insert(i.id, x);
    }
    Ok(out)
}

/// What `instgs-vk instance` was asked.
pub struct InstanceRequest {
    /// The trained plain scene.
    pub scene: PathBuf,
    /// labels.json (or .bin) from `segment`.
    pub labels: PathBuf,
    /// The dataset: its `instances.json` names the groups unless `groups` is given; its training
    /// views (and masks) drive the render check.
    pub data: PathBuf,
    /// A groups file (from `segment --per-frame-ids`) instead of `data/instances.json`; then no
    /// ground-truth pose errors are printed.
    pub groups: Option<PathBuf>,
    pub opts: InstanceOptions,
    pub offset_dtype: Dtype,
    /// The JSON report.
    pub report: Option<PathBuf>,
    /// Image downscale factor of the render check.
    pub downscale: u32,
    /// Check every registered pose by rendering against the training views (where there are any).
    pub render_check: bool,
    pub out: PathBuf,
}

/// `instgs-vk instance`: [`instance`] with the render check built from the dataset's training
/// views (and global-id masks, where `data/masks/train/` exists).
pub fn instance_command(device: Option<String>, req: &InstanceRequest) -> Result<()> {
    let data = &req.data;
    let groups_file = req.groups.clone().unwrap_or_else(|| data.join("instances.json"));
    let gt_file = data.join(crate::instancing::pose_error::GROUND_TRUTH_FILE);
    let truth = match &req.groups {
        None => Some((groups_file.as_path(), TruthIds::Same)),
        Some(_) if gt_file.exists() => Some((gt_file.as_path(), TruthIds::ByCentre)),
        Some(_) => None,
    };
    let has_views = data.join("transforms_train.json").exists() || data.join("sparse").is_dir();
    let mut check = if !req.render_check || !has_views {
        None
    } else {
        let load = crate::dataset::LoadOptions { downscale: req.downscale, background: [0.0; 3] };
        let ds = crate::dataset::load(data, &load)?;
        let masks = match req.groups {
            None if data.join("masks").join("train").is_dir() => {
                Some(crate::dataset::masks::load_masks(data, "train", &ds.train)?)
            }
            _ => None,
        };
        let (gpu, k) = open_device(device)?;
        let cams = ds.train.iter().map(|v| v.camera.clone()).collect();
        Some(ImageCheck::new(&gpu, &k, cams, masks)?)
    };
    let check = check.as_mut().map(|c| c as &mut dyn RenderCheck);
    instance(
        &req.scene,
        &req.labels,
        &groups_file,
        truth,
        &req.opts,
        req.offset_dtype,
        None,
        check,
        req.report.as_deref(),
        None,
        &req.out,
    )?;
    if req.render_check && !has_views {
        eprintln!(
            "note: {} holds no training views (transforms_train.json or sparse/): the poses were checked by geometry alone",
            data.display()
        );
    }
    Ok(())
}
