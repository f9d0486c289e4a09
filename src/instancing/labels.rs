//! Per-Gaussian instance labels as `instgs-vk segment` writes them (`labels.json`, `labels.bin`).
use std::path::Path;

use anyhow::{bail, Context, Result};

/// Per-Gaussian labels (0 = background) from `labels.json` ({ids, labels}) or `labels.bin`
/// (u32 little-endian), as `instgs-vk segment` writes them; `n` Gaussians expected.
pub fn read_labels(path: &Path, n: usize) -> Result<Vec<u32>> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).with_context(|| format!("{what}: cannot read labels"))?;
    labels_from_bytes(&bytes, path.extension().and_then(|e| e.to_str()).unwrap_or_default(), &what, n)
}

/// [`read_labels`] on a labels file's bytes; `ext` is `json` or `bin`, `what` names the file.
pub fn labels_from_bytes(bytes: &[u8], ext: &str, what: &str, n: usize) -> Result<Vec<u32>> {
    let labels: Vec<u32> = match ext {
        "json" => {
            #[derive(serde::Deserialize)]
            struct Labels {
                labels: Vec<u32>,
            }
            let l: Labels = serde_json::from_slice(bytes)
                .with_context(|| format!("{what}: not a labels file ({{\"ids\": [..], \"labels\": [..]}})"))?;
            l.labels
        }
        "bin" => {
            if !bytes.len().is_multiple_of(4) {
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
