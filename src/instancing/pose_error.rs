//! Pose errors against ground truth: a dataset's `instances.json` may carry each instance's true
//! object → world pose; the error of a registered relative pose is reported as rotation (degrees),
//! translation (fraction of the object's size) and scale.
use anyhow::bail;
use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};

use crate::register::Sim3;

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

/// The dataset file with ground-truth poses for masks whose ids are not the truth's (per-frame
/// ids from a 2D segmenter, or instances found without masks): `instances.json`'s layout, ids
/// matched to the run's instances by [`match_by_centre`] (`tools/make_capture.py` writes one).
pub const GROUND_TRUTH_FILE: &str = "ground_truth.json";

/// Ground-truth poses keyed by the run's instance ids (see [`match_ids_by_centre`]).
pub fn match_by_centre(
    truth: &BTreeMap<u32, GroundTruthPose>,
    centres: &BTreeMap<u32, [f64; 3]>,
) -> BTreeMap<u32, GroundTruthPose> {
    match_ids_by_centre(truth, centres).into_iter().map(|(id, t)| (id, truth[&t].clone())).collect()
}

/// The true instance id of each of the run's instances: each instance (its Gaussians' centre,
/// `centres`) takes the true instance whose centre is nearest, closest pairs first, one each,
/// and only within half the true object's size (else it has none).
pub fn match_ids_by_centre(
    truth: &BTreeMap<u32, GroundTruthPose>,
    centres: &BTreeMap<u32, [f64; 3]>,
) -> BTreeMap<u32, u32> {
    let mut pairs: Vec<(f64, u32, u32)> = centres
        .iter()
        .flat_map(|(&id, c)| {
            truth.iter().map(move |(&t, g)| {
                let d = (0..3).map(|a| (c[a] - g.center[a]).powi(2)).sum::<f64>().sqrt();
                (d, id, t)
            })
        })
        .filter(|&(d, _, t)| d < 0.5 * truth[&t].size)
        .collect();
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut out, mut used) = (BTreeMap::new(), std::collections::BTreeSet::new());
    for (_, id, t) in pairs {
        if !out.contains_key(&id) && used.insert(t) {
            out.insert(id, t);
        }
    }
    out
}
