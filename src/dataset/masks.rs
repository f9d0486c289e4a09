//! Instance masks and groups of a dataset: `instances.json` (groups of instance ids), one 8- or
//! 16-bit id mask per view under `masks/<split>/` (0 = background), and, for masks whose ids mean
//! nothing across frames, per-frame categories `masks/<split>/<image stem>.json`.
use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::dataset::View;

/// A dataset's groups file (`instances.json`): groups of instance ids. Extra fields ignored.
#[derive(Clone, Debug, PartialEq)]
pub struct InstanceGroup {
    pub name: String,
    pub ids: Vec<u32>,
}

#[derive(serde::Deserialize)]
struct GroupsFile {
    groups: Vec<GroupEntry>,
}

#[derive(serde::Deserialize)]
struct GroupEntry {
    name: String,
    instances: Vec<InstanceEntry>,
}

#[derive(serde::Deserialize)]
struct InstanceEntry {
    id: u32,
}

/// Reads `instances.json`; ids must be positive (0 is the background) and unique.
pub fn read_groups(path: &Path) -> Result<Vec<InstanceGroup>> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    groups_from_str(&text, &what)
}

/// [`read_groups`] on the text of a groups file; `what` names it in errors.
pub fn groups_from_str(text: &str, what: &str) -> Result<Vec<InstanceGroup>> {
    let f: GroupsFile = serde_json::from_str(text)
        .with_context(|| format!("{what}: not a groups file ({{groups: [{{name, instances: [{{id}}]}}]}})"))?;
    let mut seen = std::collections::BTreeSet::new();
    let groups: Vec<InstanceGroup> = f
        .groups
        .into_iter()
        .map(|g| InstanceGroup { name: g.name, ids: g.instances.iter().map(|i| i.id).collect() })
        .collect();
    for g in &groups {
        for &id in &g.ids {
            if id == 0 {
                bail!("{what}: group {:?} uses id 0, the background's", g.name);
            }
            if !seen.insert(id) {
                bail!("{what}: instance id {id} appears twice");
            }
        }
    }
    Ok(groups)
}

/// Reads one mask (8- or 16-bit grey PNG of instance ids, 0 = background) of `width`×`height`.
/// A mask an integer factor f larger in both dimensions (the image was loaded with
/// `--downscale f`) is subsampled at each f×f block's centre pixel, so ids stay ids.
pub fn read_mask(path: &Path, width: u32, height: u32) -> Result<Vec<u16>> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read mask"))?;
    mask_from_bytes(&bytes, &what, width, height)
}

/// [`read_mask`] on a PNG's bytes; `what` names it in errors.
pub fn mask_from_bytes(bytes: &[u8], what: &str, width: u32, height: u32) -> Result<Vec<u16>> {
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| anyhow::anyhow!("{what}: cannot read mask: {e}"))?;
    let (w, h) = (img.width(), img.height());
    let img: Vec<u16> = match img {
        image::DynamicImage::ImageLuma8(m) => m.pixels().map(|p| p.0[0] as u16).collect(),
        image::DynamicImage::ImageLuma16(m) => m.pixels().map(|p| p.0[0]).collect(),
        other => bail!("{what}: a mask must be 8- or 16-bit greyscale, not {:?}", other.color()),
    };
    fit_ids(img, (w, h), (width, height), what)
}

/// A mask of `w`×`h` for a view of `width`×`height`: as it is, or subsampled at each f×f block's
/// centre pixel where it is an integer factor f larger (`--downscale f`).
fn fit_ids(img: Vec<u16>, (w, h): (u32, u32), (width, height): (u32, u32), what: &str) -> Result<Vec<u16>> {
    if (w, h) == (width, height) {
        return Ok(img);
    }
    let f = w / width.max(1);
    if f > 1 && (w, h) == (f * width, f * height) {
        let c = f / 2;
        return Ok((0..height)
            .flat_map(|y| (0..width).map(move |x| ((y * f + c) * w + x * f + c) as usize))
            .map(|i| img[i])
            .collect());
    }
    bail!("{what}: mask is {w}x{h}, its image {width}x{height}");
}

/// The mask file of the image `image` under `data/masks/<split>/`: the image's own name
/// (`r_000.png`, or `img_001.jpg` holding PNG bytes) or its stem with `.png` (`img_001.png`, as
/// SAM-style tools, Gaussian Grouping and SAGA write them), the first that exists.
pub fn mask_path(data: &Path, split: &str, image: &Path) -> Result<std::path::PathBuf> {
    let dir = data.join("masks").join(split);
    let name = image.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stem = image.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let candidates = [dir.join(&name), dir.join(format!("{stem}.png"))];
    match candidates.iter().find(|p| p.is_file()) {
        Some(p) => Ok(p.clone()),
        None if name.ends_with(".png") => {
            bail!("{}: the mask of image {} is missing", candidates[0].display(), image.display())
        }
        None => bail!(
            "{}: the mask of image {} is missing (looked for {name} and {stem}.png)",
            dir.display(),
            image.display()
        ),
    }
}

/// The masks of `views` (see [`mask_path`] for their names), resized views refused. A view whose
/// photo was undistorted has its mask (of the photo's size) remapped the same way.
pub fn load_masks(data: &Path, split: &str, views: &[View]) -> Result<Vec<Vec<u16>>> {
    views
        .iter()
        .map(|v| {
            let path = mask_path(data, split, &v.path)?;
            match &v.undistort {
                None => read_mask(&path, v.camera.width, v.camera.height),
                Some(u) => {
                    let (w, h) = (u.source.width, u.source.height);
                    let remapped = u.ids(&read_mask(&path, w, h)?);
                    fit_ids(remapped, (w, h), (v.camera.width, v.camera.height), &path.display().to_string())
                }
            }
        })
        .collect()
}

/// The distinct non-zero ids of a mask, ascending.
pub fn mask_ids(m: &[u16]) -> Vec<u16> {
    let mut ids: Vec<u16> = m.iter().copied().filter(|&x| x != 0).collect();
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// Per-frame mask categories for masks whose ids mean nothing across frames (e.g. from SAM):
/// `masks/<split>/<image stem>.json` = `{"<mask id>": "<category>", ...}`; every id in the mask
/// needs a category.
pub fn load_frame_categories(
    data: &Path,
    split: &str,
    views: &[View],
    masks: &[Vec<u16>],
) -> Result<Vec<BTreeMap<u16, String>>> {
    views
        .iter()
        .zip(masks)
        .map(|(v, m)| {
            let stem = v.path.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let path = data.join("masks").join(split).join(format!("{stem}.json"));
            let what = path.display();
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("{what}: cannot read the frame's mask categories"))?;
            let raw: BTreeMap<String, String> = serde_json::from_str(&text)
                .with_context(|| format!("{what}: not a {{\"<mask id>\": \"<category>\"}} object"))?;
            let mut cats = BTreeMap::new();
            for (id, cat) in raw {
                let n: u16 = id.parse().with_context(|| format!("{what}: {id:?} is not a mask id (1..65535)"))?;
                if n == 0 {
                    bail!("{what}: id 0 is the background and takes no category");
                }
                cats.insert(n, cat);
            }
            if let Some(id) = mask_ids(m).iter().find(|id| !cats.contains_key(id)) {
                bail!("{what}: mask id {id} of {} has no category", v.path.display());
            }
            Ok(cats)
        })
        .collect()
}
