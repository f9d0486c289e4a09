//! `q8` offsets: every offset value of a group's (instance, template Gaussian) pairs as a signed
//! 8-bit multiple of its kind's step (Δmeans, Δsh0, Δopacities: three steps a group), the codes
//! in seven planes (Δmeans x y z, Δsh0 r g b, Δopacity; pair `p = instance · T + gaussian`)
//! compressed as one zstd frame. Uniform steps entropy-code better than a codebook of the same
//! error (most offsets are small): on cafe40 5.7 bits a value at 0.1 of each kind's rms.
//! Lossy once: a decoded offset is its code times its step, and decoded offsets (on that grid)
//! are coded again to the same values (to a float's last bit).
use anyhow::{anyhow, bail, Result};

use crate::model::instanced::Offsets;

/// A step is this fraction of its kind's root-mean-square offset (or larger, so the largest
/// offset fits ±127 steps). 0.1 cost cafe40's held-out views 0.02 dB (0.05: under 0.01 dB,
/// 18 % more bytes; 0.2: 0.04 dB, 18 % fewer).
pub const STEP_OF_RMS: f32 = 0.1;
/// Values a pair: Δmeans (3), Δsh0 (3), Δopacity.
pub const PLANES: usize = 7;
/// zstd's level for the codes.
const LEVEL: i32 = 19;

/// A group's offsets as steps and compressed codes.
pub struct OffsetCodes {
    /// Steps of Δmeans, Δsh0 and Δopacities.
    pub steps: [f32; 3],
    /// One zstd frame of the [`PLANES`] planes of codes (i8 as u8), each a plane of all pairs.
    pub codes: Vec<u8>,
}

impl OffsetCodes {
    /// Codes `o` (any number of pairs).
    pub fn encode(o: &Offsets) -> Result<OffsetCodes> {
        let kinds = [o.d_means.concat(), o.d_sh0.concat(), o.d_opacities.clone()];
        let steps = kinds.each_ref().map(|v| grid_step(v).unwrap_or_else(|| step_for(v)));
        // A code decodes as code × step in f32: at ±127 steps it must stay finite.
        if let Some(s) = steps.iter().find(|s| !(127.0 * **s).is_finite()) {
            bail!("offsets near ±f32::MAX: their step {s:e} decodes past f32 at ±127 (q8 offsets)");
        }
        let n = o.d_opacities.len();
        let code = |x: f32, step: f32| (x / step).round().clamp(-127.0, 127.0) as i8 as u8;
        let mut planes = vec![0u8; PLANES * n];
        for p in 0..n {
            for a in 0..3 {
                planes[a * n + p] = code(o.d_means[p][a], steps[0]);
                planes[(3 + a) * n + p] = code(o.d_sh0[p][a], steps[1]);
            }
            planes[6 * n + p] = code(o.d_opacities[p], steps[2]);
        }
        let codes = zstd::bulk::compress(&planes, LEVEL).map_err(|e| anyhow!("zstd: {e}"))?;
        Ok(OffsetCodes { steps, codes })
    }

    /// The `n` pairs' offsets; `what` names the group in errors.
    pub fn decode(&self, n: usize, what: &str) -> Result<Offsets> {
        if let Some(s) = self.steps.iter().find(|s| !(s.is_finite() && **s > 0.0)) {
            bail!("{what}: a step of {s} (steps must be finite and positive)");
        }
        let size = n.checked_mul(PLANES).ok_or_else(|| anyhow!("{what}: too many pairs"))?;
        crate::limits::check_bytes(what, &format!("its {n} pairs' codes"), size as u64)?;
        let planes = zstd::bulk::decompress(&self.codes, size)
            .map_err(|e| anyhow!("{what}: the codes are not a zstd frame of {size} bytes: {e}"))?;
        if planes.len() != size {
            bail!("{what}: the codes hold {} bytes; {n} pairs need {size}", planes.len());
        }
        let value = |plane: usize, p: usize, step: f32| planes[plane * n + p] as i8 as f32 * step;
        let [sm, sc, so] = self.steps;
        Ok(Offsets {
            d_means: (0..n).map(|p| [0, 1, 2].map(|a| value(a, p, sm))).collect(),
            d_sh0: (0..n).map(|p| [0, 1, 2].map(|a| value(3 + a, p, sc))).collect(),
            d_opacities: (0..n).map(|p| value(6, p, so)).collect(),
        })
    }
}

/// The step of a kind's values `v`: [`STEP_OF_RMS`] of their root mean square, or more where
/// the largest would not fit ±127 steps (1 for values all zero).
fn step_for(v: &[f32]) -> f32 {
    let rms = (v.iter().map(|x| (*x as f64) * (*x as f64)).sum::<f64>() / v.len().max(1) as f64).sqrt() as f32;
    let largest = v.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    let step = (STEP_OF_RMS * rms).max(largest / 127.0);
    if step > 0.0 {
        step
    } else {
        1.0
    }
}

/// The step of values already on a grid — each a multiple of the smallest nonzero magnitude
/// over some whole number d ≤ 127, within ±127 steps, as decoded q8 offsets are — so that a
/// decoded scene is coded again exactly (the player saves a file as it was stored). None for
/// values off every such grid (any set of measured offsets but the smallest).
fn grid_step(v: &[f32]) -> Option<f32> {
    let smallest = v.iter().map(|x| x.abs()).filter(|x| *x > 0.0).min_by(f32::total_cmp)?;
    (1..=127).map(|d| smallest / d as f32).find(|&step| {
        v.iter().all(|x| {
            let c = x / step;
            c.abs() <= 127.5 && (c - c.round()).abs() < 1e-3
        })
    })
}
