//! A plain 3DGS scene in memory: per-Gaussian means, log scales, (w, x, y, z) quaternions,
//! opacity logits and SH coefficients, as the Inria PLY stores them (`formats::ply` reads and
//! writes it; `docs/conventions.md` gives the conventions).
use anyhow::{anyhow, bail, Result};
use glam::Vec3;

/// Bounds of `means` between the `q` and `1 − q` quantiles per axis.
pub fn robust_bounds(means: &[[f32; 3]], q: f32) -> (Vec3, Vec3) {
    let mut lo = [0.0f32; 3];
    let mut hi = [0.0f32; 3];
    for a in 0..3 {
        let mut v: Vec<f32> = means.iter().map(|m| m[a]).collect();
        v.sort_by(f32::total_cmp);
        let n = v.len();
        if n == 0 {
            continue;
        }
        let at = |f: f32| v[((f * (n - 1) as f32).round() as usize).min(n - 1)];
        lo[a] = at(q);
        hi[a] = at(1.0 - q);
    }
    (Vec3::from(lo), Vec3::from(hi))
}

/// The largest log-scale a scene may hold: e^20 ≈ 4.9e8 scene units, far past any real
/// Gaussian; above about 44 the covariance (scale²) overflows f32.
pub const MAX_LOG_SCALE: f32 = 20.0;

/// A plain 3DGS scene, structure of arrays, N Gaussians.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    /// World-space centres, N.
    pub means: Vec<[f32; 3]>,
    /// Natural-log scales, N.
    pub scales: Vec<[f32; 3]>,
    /// Rotations as (w, x, y, z) quaternions, N; need not be normalised.
    pub quats: Vec<[f32; 4]>,
    /// Opacity logits, N.
    pub opacities: Vec<f32>,
    /// SH coefficients, N × (degree+1)² × 3, coefficient-major then RGB:
    /// `sh[(i * coeffs + k) * 3 + c]`; k = 0 is sh0 (the Inria `f_dc`), k ≥ 1 shN (`f_rest`).
    pub sh: Vec<f32>,
    /// SH degree, 0..=3.
    pub sh_degree: u32,
}

impl Scene {
    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// `self`'s Gaussians followed by `other`'s (the same SH degree).
    pub fn concat(&self, other: &Scene) -> Scene {
        let mut out = self.clone();
        out.append(other);
        out
    }

    /// The scene at SH `degree` (at least its own): zero coefficients for the bands it lacks.
    pub fn with_sh_degree(mut self, degree: u32) -> Scene {
        if self.sh_degree >= degree {
            return self;
        }
        let (from, to) = (self.sh_coeffs(), ((degree + 1) * (degree + 1)) as usize);
        let mut sh = vec![0.0; self.len() * to * 3];
        for i in 0..self.len() {
            sh[i * to * 3..i * to * 3 + from * 3].copy_from_slice(&self.sh[i * from * 3..(i + 1) * from * 3]);
        }
        self.sh = sh;
        self.sh_degree = degree;
        self
    }

    /// Adds `other`'s Gaussians after `self`'s (the same SH degree).
    pub fn append(&mut self, other: &Scene) {
        self.means.extend_from_slice(&other.means);
        self.scales.extend_from_slice(&other.scales);
        self.quats.extend_from_slice(&other.quats);
        self.opacities.extend_from_slice(&other.opacities);
        self.sh.extend_from_slice(&other.sh);
    }

    /// The Gaussians at `idx`, in that order.
    pub fn select(&self, idx: &[usize]) -> Scene {
        let c = self.sh_coeffs() * 3;
        Scene {
            means: idx.iter().map(|&i| self.means[i]).collect(),
            scales: idx.iter().map(|&i| self.scales[i]).collect(),
            quats: idx.iter().map(|&i| self.quats[i]).collect(),
            opacities: idx.iter().map(|&i| self.opacities[i]).collect(),
            sh: idx.iter().flat_map(|&i| self.sh[i * c..(i + 1) * c].iter().copied()).collect(),
            sh_degree: self.sh_degree,
        }
    }

    /// SH coefficients per channel: (degree + 1)².
    pub fn sh_coeffs(&self) -> usize {
        ((self.sh_degree + 1) * (self.sh_degree + 1)) as usize
    }

    /// Axis-aligned bounds of the means.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for m in &self.means {
            lo = lo.min(Vec3::from(*m));
            hi = hi.max(Vec3::from(*m));
        }
        (lo, hi)
    }

    /// Bounds of the means between the `q` and `1 − q` quantiles per axis: the object without
    /// its floaters (trained scenes have far-away Gaussians).
    pub fn robust_bounds(&self, q: f32) -> (Vec3, Vec3) {
        robust_bounds(&self.means, q)
    }

    /// Checks the arrays agree in length and every value is usable: finite, quaternions that
    /// normalise in f32, log-scales at most [`MAX_LOG_SCALE`]; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let n = self.len();
        if n == 0 {
            bail!("{what}: the scene has no Gaussians");
        }
        if self.sh_degree > 3 {
            bail!("{what}: SH degree {} is not supported (0..3)", self.sh_degree);
        }
        if self.scales.len() != n
            || self.quats.len() != n
            || self.opacities.len() != n
            || self.sh.len() != n * self.sh_coeffs() * 3
        {
            bail!("{what}: attribute arrays disagree in length");
        }
        let bad = |name: &str, i: usize| anyhow!("{what}: Gaussian {i} has a non-finite {name}");
        for i in 0..n {
            if !self.means[i].iter().all(|v| v.is_finite()) {
                return Err(bad("position", i));
            }
            if !self.scales[i].iter().all(|v| v.is_finite()) {
                return Err(bad("scale", i));
            }
            if let Some(s) = self.scales[i].iter().find(|&&s| s > MAX_LOG_SCALE) {
                bail!(
                    "{what}: Gaussian {i}'s log-scale {s} exceeds {MAX_LOG_SCALE} (its covariance would overflow f32)"
                );
            }
            let q = self.quats[i];
            if !q.iter().all(|v| v.is_finite()) {
                return Err(bad("rotation", i));
            }
            if q.iter().all(|&v| v == 0.0) {
                bail!("{what}: Gaussian {i} has a zero rotation quaternion");
            }
            // Normalised as the kernels do it, in f32: the squared norm must be a normal number
            // (subnormal or overflowing norms give no rotation).
            let norm2: f32 = q.iter().map(|v| v * v).sum();
            if !norm2.is_normal() {
                bail!(
                    "{what}: Gaussian {i}'s rotation quaternion {q:?} cannot be normalised in f32 (norm² = {norm2:e})"
                );
            }
            if !self.opacities[i].is_finite() {
                return Err(bad("opacity", i));
            }
        }
        if let Some(k) = self.sh.iter().position(|v| !v.is_finite()) {
            return Err(bad("SH coefficient", k / (self.sh_coeffs() * 3)));
        }
        Ok(())
    }
}
