//! What a dataset's files hold, as a run records it: a SHA-256 over every image's bytes and one
//! over every mask file's (`masks/`, categories included), so a dataset edited in place (same
//! names, same cameras) is not taken for the one a run was trained on. Each file's digest is
//! cached by its size and modification time (`RUN/dataset-files.json`), so a re-run reads only
//! the files that changed.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::dataset::Dataset;

/// The digests of a dataset's images and of its masks (empty string: no masks).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ContentIdentity {
    pub images: String,
    pub masks: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Cached {
    size: u64,
    modified_ns: u128,
    sha256: String,
}

/// The name of the cache in a run folder.
pub const CACHE_FILE: &str = "dataset-files.json";

/// A scan of a dataset's files: their identity, and the per-file cache to keep
/// ([`ContentScan::save`], once the run has passed its checks: a refused run writes nothing).
pub struct ContentScan {
    pub id: ContentIdentity,
    cache: BTreeMap<String, Cached>,
    path: PathBuf,
    changed: bool,
}

impl ContentScan {
    /// Writes the per-file cache into the run folder, where it changed.
    pub fn save(&self) -> Result<()> {
        if self.changed {
            crate::util::write_json(&self.path, &serde_json::to_value(&self.cache)?, false)?;
        }
        Ok(())
    }
}

/// The content identity of `ds` (loaded from `data`), with the per-file cache of `run`.
pub fn content_identity(ds: &Dataset, data: &Path, run: &Path) -> Result<ContentScan> {
    let cache_path = run.join(CACHE_FILE);
    let mut cache: BTreeMap<String, Cached> =
        std::fs::read_to_string(&cache_path).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_default();
    let before = cache.clone();
    let views: Vec<&crate::dataset::View> = ds.train.iter().chain(&ds.test).collect();
    let mut masks = Vec::new();
    collect_files(&data.join("masks"), &mut masks);
    masks.sort();
    // Each file counts with its name inside the dataset and its contents; a view made in memory
    // (no file behind it) by its pixels.
    let mut digest = |files: &[(Option<&Path>, &[[f32; 4]])]| -> Result<String> {
        if files.is_empty() {
            return Ok(String::new());
        }
        let mut h = Sha256::new();
        for (f, pixels) in files {
            match f {
                Some(f) => {
                    h.update(f.strip_prefix(data).unwrap_or(f).to_string_lossy().as_bytes());
                    h.update(file_digest(f, &mut cache)?.as_bytes());
                }
                None => h.update(bytemuck::cast_slice::<[f32; 4], u8>(pixels)),
            }
        }
        Ok(hex(&h.finalize()))
    };
    let masks = digest(&masks.iter().map(|m| (Some(m.as_path()), &[][..])).collect::<Vec<_>>())?;
    let images = digest(
        &views
            .iter()
            .map(|v| ((!v.path.as_os_str().is_empty()).then_some(v.path.as_path()), &v.image[..]))
            .collect::<Vec<_>>(),
    )?;
    let id = ContentIdentity { images, masks };
    let changed = cache != before;
    Ok(ContentScan { id, cache, path: cache_path, changed })
}

fn collect_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            collect_files(&p, out);
        } else {
            out.push(p);
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// One file's SHA-256, from the cache when its size and modification time are unchanged.
fn file_digest(path: &Path, cache: &mut BTreeMap<String, Cached>) -> Result<String> {
    let meta = std::fs::metadata(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let modified_ns =
        meta.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map_or(0, |d| d.as_nanos());
    let key = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf()).display().to_string();
    if let Some(c) = cache.get(&key).filter(|c| c.size == meta.len() && c.modified_ns == modified_ns) {
        return Ok(c.sha256.clone());
    }
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let sha256 = hex(&Sha256::digest(&bytes));
    cache.insert(key, Cached { size: meta.len(), modified_ns, sha256: sha256.clone() });
    Ok(sha256)
}
