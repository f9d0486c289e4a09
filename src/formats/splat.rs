//! antimatter15's `.splat`: 32-byte rows, no SH.
use std::path::Path;

use anyhow::{bail, Result};

use crate::formats::quant::{opacity_logit, unorm8};
use crate::math::sigmoid;
use crate::math::SH_C0_F32;
use crate::model::scene::Scene;

/// Reads antimatter15's `.splat`: per Gaussian 32 bytes — position f32×3, linear scale f32×3,
/// colour and opacity u8×4 (colour = 0.5 + SH_C0·sh0), rotation u8×4 (w, x, y, z; v/255·2 − 1).
pub fn read_splat(what: &str, bytes: &[u8]) -> Result<Scene> {
    if bytes.is_empty() || !bytes.len().is_multiple_of(32) {
        bail!("{what}: a .splat file holds 32-byte rows, but it is {} bytes long", bytes.len());
    }
    let mut s = Scene::default();
    for (i, row) in bytes.chunks_exact(32).enumerate() {
        let f = |k: usize| f32::from_le_bytes(row[k * 4..k * 4 + 4].try_into().expect("4 bytes"));
        s.means.push([f(0), f(1), f(2)]);
        let scale = [f(3), f(4), f(5)];
        if scale.iter().any(|&v| v.is_nan() || v < 0.0) {
            bail!("{what}: Gaussian {i} has a negative or NaN scale {scale:?}");
        }
        s.scales.push(scale.map(|v| v.max(1e-30).ln()));
        s.sh.extend(row[24..27].iter().map(|&b| (b as f32 / 255.0 - 0.5) / SH_C0_F32));
        s.opacities.push(opacity_logit(row[27] as f32 / 255.0));
        s.quats.push(std::array::from_fn(|k| row[28 + k] as f32 / 255.0 * 2.0 - 1.0));
    }
    Ok(s)
}

/// `scene` as `.splat` (SH bands beyond sh0 are dropped; rotations normalised).
pub fn write_splat(scene: &Scene, path: &Path) -> Result<()> {
    scene.validate(&format!("{}: not written", path.display()))?;
    let coeffs = scene.sh_coeffs();
    let mut out = Vec::with_capacity(scene.len() * 32);
    for i in 0..scene.len() {
        for v in scene.means[i] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in scene.scales[i] {
            out.extend_from_slice(&v.exp().to_le_bytes());
        }
        for c in 0..3 {
            out.push(unorm8(0.5 + SH_C0_F32 * scene.sh[i * coeffs * 3 + c]));
        }
        out.push(unorm8(sigmoid(scene.opacities[i])));
        let q = scene.quats[i];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        for v in q {
            out.push(unorm8((v / norm + 1.0) * 0.5));
        }
    }
    crate::util::write_atomic(path, |f| std::io::Write::write_all(f, &out))
}
