//! What a run learns of its photos, on disk: `RUN/appearance.json`, each training photo's colour
//! transform and the lens's vignetting (crate::render::appearance), beside the run's scene.
use anyhow::{bail, Context, Result};

use crate::dataset::Dataset;

/// The file a run that learns colour transforms writes them to, beside its scene.
pub const APPEARANCE_FILE: &str = "appearance.json";

/// Writes what a run learned of its photos: `{"views": [{"name", "transform": [[M00, M01, M02,
/// b0], [..], [..]]}], "vignetting": {"k1", "k2"}}`, the views in the dataset's training order.
pub fn write_appearance(
    path: &std::path::Path,
    ds: &Dataset,
    learned: &crate::render::appearance::PhotoAppearance,
) -> Result<()> {
    let views: Vec<serde_json::Value> = ds
        .train
        .iter()
        .zip(&learned.colours)
        .map(|(v, t)| serde_json::json!({"name": v.camera.name, "transform": [&t[0..4], &t[4..8], &t[8..12]]}))
        .collect();
    let [k1, k2] = learned.vignetting;
    crate::util::write_json(path, &serde_json::json!({"views": views, "vignetting": {"k1": k1, "k2": k2}}), true)
}

/// The lens's vignetting of [`write_appearance`]'s file (none when the file predates it).
fn parse_vignetting(v: Option<VignettingEntry>, what: &str) -> Result<crate::render::appearance::Vignetting> {
    let Some(v) = v else { return Ok(crate::render::appearance::NO_VIGNETTING) };
    let k = [v.k1, v.k2];
    // Finite and of a lens's size (a strong one loses ~0.5 at r² ≈ 0.5): a damaged file otherwise.
    if !k.iter().all(|x| x.is_finite() && x.abs() <= 4.0) {
        bail!("{what}: vignetting k1 = {}, k2 = {} is not a lens's falloff (|k| ≤ 4)", v.k1, v.k2);
    }
    Ok(k)
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct VignettingEntry {
    k1: f32,
    k2: f32,
}

/// The file as written: the views' transforms by name and the lens, if any.
#[derive(serde::Deserialize)]
struct File {
    views: Vec<Entry>,
    vignetting: Option<VignettingEntry>,
}

#[derive(serde::Deserialize)]
struct Entry {
    name: String,
    transform: [[f32; 4]; 3],
}

/// Reads and parses `path` (its name and what is wrong in every error).
fn read_file(path: &std::path::Path) -> Result<File> {
    let what = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    serde_json::from_str(&text).with_context(|| format!("{what}: not a colour-transform file"))
}

/// The lens's vignetting a run learned (RUN/appearance.json beside `scene`, a scene file of
/// the run), or none when there is no such file: the held-out metrics of `eval` render
/// through it.
pub fn vignetting_beside(scene: &std::path::Path) -> Result<crate::render::appearance::Vignetting> {
    let path = scene.parent().unwrap_or(std::path::Path::new(".")).join(APPEARANCE_FILE);
    if !path.is_file() {
        return Ok(crate::render::appearance::NO_VIGNETTING);
    }
    parse_vignetting(read_file(&path)?.vignetting, &path.display().to_string())
}

/// Reads [`write_appearance`]'s file for `ds`: one transform per training view, by name, and the
/// vignetting (none in files written before it was learned).
pub fn read_appearance(path: &std::path::Path, ds: &Dataset) -> Result<crate::render::appearance::PhotoAppearance> {
    let f = read_file(path)?;
    let what = path.display();
    let by_name: std::collections::BTreeMap<&str, &[[f32; 4]; 3]> =
        f.views.iter().map(|e| (e.name.as_str(), &e.transform)).collect();
    let colours = ds
        .train
        .iter()
        .map(|v| {
            let t = by_name
                .get(v.camera.name.as_str())
                .ok_or_else(|| anyhow::anyhow!("{what}: no colour transform for training view {}", v.camera.name))?;
            let flat: Vec<f32> = t.iter().flatten().copied().collect();
            if !flat.iter().all(|x| x.is_finite()) {
                bail!("{what}: the colour transform of {} is not finite", v.camera.name);
            }
            Ok(flat.try_into().expect("12 values"))
        })
        .collect::<Result<_>>()?;
    Ok(crate::render::appearance::PhotoAppearance {
        colours,
        vignetting: parse_vignetting(f.vignetting, &what.to_string())?,
    })
}
