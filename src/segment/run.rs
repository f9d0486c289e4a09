//! The segmentation stage as `instgs-vk segment` and the pipeline run it: masks (or per-frame
//! ids and their association), the scores, the labels, the held-out IoU and the files.
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Result};

use crate::gpu::kernels::{open_device, Kernels};
use crate::gpu::Gpu;
use crate::util::{write_json, Progress, ProgressMode};

#[allow(clippy::too_many_arguments)]
/// `instgs-vk segment`: labels per Gaussian (`out` .json or raw u32 .bin); `export_dir` receives
/// one PLY per instance and the background.
pub fn segment(
    device: Option<String>,
    scene_path: &Path,
    data: &Path,
    split: &str,
    alpha: f32,
    out: &Path,
    export_dir: Option<&Path>,
    per_frame_ids: bool,
) -> Result<()> {
    let is_json = out.extension().and_then(|e| e.to_str()) == Some("json");
    if per_frame_ids && !is_json {
        bail!("{}: with --per-frame-ids the output must be .json (it carries the associated groups)", out.display());
    }
    if !is_json && out.extension().and_then(|e| e.to_str()) != Some("bin") {
        bail!("{}: the output must end in .json or .bin", out.display());
    }
    let scene = crate::formats::read_scene(scene_path)?;
    let opts = crate::dataset::LoadOptions { downscale: 1, background: [0.0; 3] };
    let ds = crate::dataset::load(data, &opts)?;
    let (gpu, k) = open_device(device)?;
    let seg = segment_scene(
        &gpu,
        &k,
        &scene,
        data,
        &ds,
        split,
        alpha,
        per_frame_ids,
        ("segmentation: ", ProgressMode::Auto),
    )?;
    if is_json {
        write_json(out, &seg.doc, false)?;
    } else {
        crate::util::write_atomic(out, |f| {
            use std::io::Write;
            f.write_all(bytemuck::cast_slice(&seg.labels))
        })?;
    }
    if let Some(dir) = export_dir {
        crate::util::write_dir_atomic(dir, None, |tmp| {
            for id in seg.ids.iter().copied().chain([0]) {
                let part = crate::segment::subset(&scene, &seg.labels, id);
                let name = if id == 0 { "background.ply".to_string() } else { format!("instance_{id}.ply") };
                if !part.is_empty() {
                    crate::formats::ply::write_ply(&part, &tmp.join(name))?;
                }
            }
            Ok(())
        })?;
    }
    Ok(())
}

/// A segmentation and what `segment` reports of it.
pub struct SegmentOutcome {
    /// Instance ids in group order.
    pub ids: Vec<u32>,
    pub labels: Vec<u32>,
    /// labels.json: {ids, labels} (and, with per-frame ids, the associated groups).
    pub doc: serde_json::Value,
    /// {instances: [{group, id, gaussians, test_iou, test_views}], background}.
    pub summary: serde_json::Value,
    /// Per Gaussian: blending weight summed over the views (`Segmentation::weight`).
    pub significance: Vec<f32>,
}

/// Segments `scene` with the masks of `ds`'s `split` views (`DIR/masks/<split>/`); prints one
/// line per instance (with the held-out IoU where test masks with global ids exist).
#[allow(clippy::too_many_arguments)]
pub fn segment_scene(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &crate::model::scene::Scene,
    data: &Path,
    ds: &crate::dataset::Dataset,
    split: &str,
    alpha: f32,
    per_frame_ids: bool,
    progress: (&str, ProgressMode),
) -> Result<SegmentOutcome> {
    let views = ds.split(split)?;
    let mut masks = crate::dataset::masks::load_masks(data, split, views)?;
    let mut members_json = serde_json::Map::new();
    let groups = if per_frame_ids {
        let cats = crate::dataset::masks::load_frame_categories(data, split, views, &masks)?;
        let o = crate::segment::AssociateOptions { alpha, ..Default::default() };
        let a = crate::segment::associate(gpu, k, scene, views, &masks, &cats, &o, progress)?;
        let total: usize = a.members.values().map(Vec::len).sum::<usize>() + a.dropped.len();
        println!(
            "association: {} masks of {} views → {} instances in {} groups ({} masks in no instance of ≥ {} views)",
            total,
            views.len(),
            a.members.len(),
            a.groups.len(),
            a.dropped.len(),
            o.min_views
        );
        for (id, ms) in &a.members {
            let list: Vec<serde_json::Value> = ms
                .iter()
                .map(|(v, m)| {
                    let name = views[*v].path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                    serde_json::json!([name, m])
                })
                .collect();
            members_json.insert(id.to_string(), list.into());
        }
        masks = a.masks;
        a.groups
    } else {
        crate::dataset::masks::read_groups(&data.join("instances.json"))?
    };
    let ids: Vec<u32> = groups.iter().flat_map(|g| g.ids.iter().copied()).collect();
    let mut bar = Progress::new(progress.0, "view", "views/s", views.len() as u64, 0, progress.1);
    let seg =
        crate::segment::segment_with_progress(gpu, k, scene, views, &masks, &ids, alpha, |i, _| bar.set(i as u64, ""))?;
    bar.finish();
    if !seg.unknown_ids.is_empty() {
        eprintln!(
            "warning: mask ids {:?} are not in {}; their pixels count as background",
            seg.unknown_ids,
            data.join("instances.json").display()
        );
    }
    let mut doc = serde_json::json!({"ids": seg.ids, "labels": seg.labels});
    if per_frame_ids {
        // A groups file too (`instance --groups`): groups → instances with their masks.
        doc["groups"] = groups
            .iter()
            .map(|g| {
                let inst: Vec<serde_json::Value> = g
                    .ids
                    .iter()
                    .map(|id| serde_json::json!({"id": id, "masks": members_json[&id.to_string()]}))
                    .collect();
                serde_json::json!({"name": g.name, "instances": inst})
            })
            .collect();
    }
    // Held-out views with masks: the IoU of every instance's rendered visible region against
    // its mask (per-frame ids: the overlapping mask of its category).
    let test_masks = if ds.test.is_empty() {
        None
    } else {
        crate::dataset::masks::load_masks(data, "test", &ds.test).ok().and_then(|m| {
            let cats = if per_frame_ids {
                Some(crate::dataset::masks::load_frame_categories(data, "test", &ds.test, &m).ok()?)
            } else {
                None
            };
            Some((m, cats))
        })
    };
    let mut rows = Vec::new();
    // The held-out regions three instances at a time (one render each; a region per instance,
    // view and pixel is held only for those three).
    let mut regions = Vec::new();
    for (j, (g, &id)) in groups.iter().flat_map(|g| g.ids.iter().map(move |id| (g, id))).enumerate() {
        if j % 3 == 0 {
            regions = match &test_masks {
                Some((m, _)) if !m.is_empty() => {
                    let three = &ids[j..(j + 3).min(ids.len())];
                    crate::segment::instance_regions(gpu, k, scene, &seg.labels, &ds.test, three)?
                }
                _ => Vec::new(),
            };
        }
        let n = seg.labels.iter().filter(|&&l| l == id).count();
        let mut row = serde_json::json!({"group": g.name, "id": id, "gaussians": n});
        let iou = match (&test_masks, regions.get(j % 3)) {
            (Some((m, cats)), Some(r)) => {
                let v = match cats {
                    None => crate::segment::instance_iou(r, m, id),
                    Some(c) => crate::segment::instance_iou_per_frame(r, m, c, &g.name),
                };
                let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
                row["test_iou"] = mean.into();
                row["test_views"] = v.len().into();
                format!("  test IoU {mean:.3} ({} views)", v.len())
            }
            _ => String::new(),
        };
        println!("{} {id}: {n} Gaussians{iou}", g.name);
        rows.push(row);
    }
    let background = seg.labels.iter().filter(|&&l| l == 0).count();
    println!("background: {background} Gaussians");
    let summary = serde_json::json!({"instances": rows, "background": background, "alpha": alpha});
    Ok(SegmentOutcome { ids, labels: seg.labels, doc, summary, significance: seg.weight })
}
