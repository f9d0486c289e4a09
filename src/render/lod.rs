//! Rendering an instanced scene: whole-instance frustum culling and template level of detail
//! (LOD). Settings live in `configs/render.toml` (embedded defaults, overridable by a file).
//!
//! Levels: besides the template itself (level 0), each template keeps coarser levels of about
//! `fractions` of its Gaussians. A level is built by merging neighbours: the template's means
//! are clustered on a voxel grid whose cell size is bisected until the cluster count matches the
//! target, and each cluster becomes one Gaussian that keeps the cluster's appearance:
//! - weights w_i = opacity_i · s_a s_b (opacity times the area of the two largest axes, the
//!   footprint a Gaussian covers, as hierarchical 3DGS weighs its merges);
//! - mean and covariance by moment matching, Σ = Σ_i w_i (Σ_i + (μ_i − μ)(μ_i − μ)ᵀ) / Σ_i w_i,
//!   whose eigen decomposition gives scales and rotation;
//! - opacity conserving covered area, α = min(0.99, Σ_i α_i A_i / A) with A = s_a s_b;
//! - SH coefficients (every degree) and the per-instance offsets (Δp, Δ SH DC, Δ opacity
//!   logit) as w-weighted means, so offsets follow the level.
//!
//! Selection (per frame, on the GPU: `instance_select.comp`, CPU twin [`select_instance`]): see
//! the kernel's header. Training never uses either: it renders every pair.
use crate::math::{quat_to_mat, sigmoid};
use std::collections::HashMap;

use anyhow::{bail, Context, Result};
use glam::{Mat3, Quat, Vec3};
use nalgebra::{Matrix3, SymmetricEigen};
use serde::{Deserialize, Serialize};

use crate::model::instanced::Offsets;
use crate::model::scene::Scene;
use crate::shared::*;

pub const RENDER_TOML: &str = include_str!("../../configs/render.toml");

/// `configs/render.toml`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RenderConfig {
    /// Skip instances whose bounding sphere is outside the view frustum (lossless).
    pub cull: bool,
    /// Frustum margin in pixels.
    pub cull_margin_px: f32,
    pub lod: LodConfig,
}

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LodConfig {
    /// Off: exact rendering (every visible instance at level 0).
    pub enabled: bool,
    /// Coarser levels as fractions of the template's Gaussians, decreasing, at most
    /// LOD_LEVELS − 1 of them.
    pub fractions: Vec<f32>,
    /// The quality knob: an instance uses the coarsest level that keeps at least this many
    /// Gaussians per pixel of its projected bounding disc.
    pub splats_per_pixel: f32,
}

impl RenderConfig {
    /// The embedded defaults, with the keys of `path` (a TOML file) over them.
    pub fn load(path: Option<&std::path::Path>) -> Result<RenderConfig> {
        match path {
            Some(p) => {
                let text = std::fs::read_to_string(p).with_context(|| format!("{}: cannot read", p.display()))?;
                RenderConfig::from_toml(&text, &p.display().to_string())
            }
            None => RenderConfig::from_toml("", "configs/render.toml"),
        }
    }

    /// The embedded defaults with the keys of `text` (TOML; `what` names it in errors) over them.
    pub fn from_toml(text: &str, what: &str) -> Result<RenderConfig> {
        let mut base: toml::Table = toml::from_str(RENDER_TOML).context("configs/render.toml (embedded)")?;
        let user: toml::Table = toml::from_str(text).with_context(|| format!("{what}: not valid TOML"))?;
        merge(&mut base, user);
        let cfg: RenderConfig = toml::Value::Table(base).try_into().with_context(|| what.to_string())?;
        cfg.validate().with_context(|| what.to_string())?;
        Ok(cfg)
    }

    /// Exact rendering: culling only (lossless), no level of detail.
    pub fn exact(mut self) -> RenderConfig {
        self.lod.enabled = false;
        self
    }

    fn validate(&self) -> Result<()> {
        let f = &self.lod.fractions;
        if f.len() + 1 > LOD_LEVELS as usize {
            bail!("lod.fractions: at most {} coarser levels", LOD_LEVELS - 1);
        }
        if f.iter().any(|&x| !(x > 0.0 && x < 1.0)) || f.windows(2).any(|w| w[1] >= w[0]) {
            bail!("lod.fractions must decrease within (0, 1), got {f:?}");
        }
        if !(self.lod.splats_per_pixel > 0.0 && self.lod.splats_per_pixel.is_finite()) {
            bail!("lod.splats_per_pixel must be positive, got {}", self.lod.splats_per_pixel);
        }
        if self.cull_margin_px.is_nan() || self.cull_margin_px < 0.0 {
            bail!("cull_margin_px must be >= 0, got {}", self.cull_margin_px);
        }
        Ok(())
    }
}

fn merge(base: &mut toml::Table, user: toml::Table) {
    for (k, v) in user {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(u)) => merge(b, u),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// Template-space bounding sphere (centre, radius) of the Gaussians' 3σ extents.
pub fn bound(t: &Scene) -> [f32; 4] {
    if t.is_empty() {
        return [0.0; 4];
    }
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for m in &t.means {
        lo = lo.min(Vec3::from(*m));
        hi = hi.max(Vec3::from(*m));
    }
    let c = 0.5 * (lo + hi);
    let r = t
        .means
        .iter()
        .zip(&t.scales)
        .map(|(m, s)| (Vec3::from(*m) - c).length() + 3.0 * s[0].max(s[1]).max(s[2]).exp())
        .fold(0.0f32, f32::max);
    [c.x, c.y, c.z, r]
}

/// Largest |Δp| per instance (offsets instance-major, `rows` per instance).
pub fn max_offsets(offsets: &Offsets, rows: usize) -> Vec<f32> {
    if rows == 0 {
        return Vec::new();
    }
    offsets.d_means.chunks(rows).map(|c| c.iter().map(|d| Vec3::from(*d).length()).fold(0.0, f32::max)).collect()
}

/// Clusters of the template's Gaussians on a voxel grid with about `target` occupied cells
/// (each cluster's members in index order; clusters ordered by their first member).
pub fn cluster(means: &[[f32; 3]], target: usize) -> Vec<Vec<usize>> {
    let n = means.len();
    let target = target.clamp(1, n.max(1));
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for m in means {
        lo = lo.min(Vec3::from(*m));
        hi = hi.max(Vec3::from(*m));
    }
    let diag = (hi - lo).length().max(1e-6) as f64;
    let cells = |h: f64| -> Vec<Vec<usize>> {
        let mut map: HashMap<[i64; 3], usize> = HashMap::new();
        let mut out: Vec<Vec<usize>> = Vec::new();
        for (i, m) in means.iter().enumerate() {
            let key = [0, 1, 2].map(|a| ((m[a] - lo[a]) as f64 / h).floor() as i64);
            let c = *map.entry(key).or_insert_with(|| {
                out.push(Vec::new());
                out.len() - 1
            });
            out[c].push(i);
        }
        out
    };
    // Cell count falls as the cell size grows: bisect the size in log space.
    let (mut small, mut large) = (diag * 1e-7, diag * 2.0);
    let mut best = cells(large);
    for _ in 0..40 {
        let h = (small * large).sqrt();
        let c = cells(h);
        if c.len() == target {
            return c;
        }
        if (c.len() as i64 - target as i64).abs() < (best.len() as i64 - target as i64).abs() {
            best = c.clone();
        }
        if c.len() > target {
            small = h;
        } else {
            large = h;
        }
    }
    best
}

/// One Gaussian per cluster (see the module docs), with the offsets of `instances` instances
/// (instance-major, `t.len()` per instance) merged alike.
pub fn merge_clusters(t: &Scene, offsets: &Offsets, instances: usize, clusters: &[Vec<usize>]) -> (Scene, Offsets) {
    let coeffs = ((t.sh_degree + 1) * (t.sh_degree + 1) * 3) as usize;
    let rows = t.len();
    let mut out = Scene { sh_degree: t.sh_degree, ..Default::default() };
    let m = clusters.len();
    let mut weights_all: Vec<Vec<f64>> = Vec::with_capacity(m);
    for members in clusters {
        let scale = |i: usize| t.scales[i].map(f32::exp);
        let area = |s: [f32; 3]| {
            let mut s = s;
            s.sort_by(|a, b| b.total_cmp(a));
            (s[0] * s[1]) as f64
        };
        let mut w: Vec<f64> = members.iter().map(|&i| sigmoid(t.opacities[i]) as f64 * area(scale(i))).collect();
        let total: f64 = w.iter().sum();
        if total <= 0.0 || !total.is_finite() {
            w = vec![1.0; members.len()];
        }
        let total: f64 = w.iter().sum();
        w.iter_mut().for_each(|x| *x /= total);
        if members.len() == 1 {
            let i = members[0];
            out.means.push(t.means[i]);
            out.scales.push(t.scales[i]);
            out.quats.push(t.quats[i]);
            out.opacities.push(t.opacities[i]);
            out.sh.extend_from_slice(&t.sh[i * coeffs..(i + 1) * coeffs]);
            weights_all.push(w);
            continue;
        }
        let mut mu = [0.0f64; 3];
        for (&i, &wi) in members.iter().zip(&w) {
            for (m, &v) in mu.iter_mut().zip(&t.means[i]) {
                *m += wi * v as f64;
            }
        }
        let mut cov = Matrix3::<f64>::zeros();
        let mut covered = 0.0f64;
        for (&i, &wi) in members.iter().zip(&w) {
            let r = quat_to_mat(t.quats[i]);
            let s = scale(i);
            let rm = Matrix3::from_fn(|a, b| r.col(b)[a] as f64);
            let s2 = Matrix3::from_diagonal(&nalgebra::Vector3::new(
                (s[0] as f64).powi(2),
                (s[1] as f64).powi(2),
                (s[2] as f64).powi(2),
            ));
            let d = nalgebra::Vector3::from_fn(|a, _| t.means[i][a] as f64 - mu[a]);
            cov += wi * (rm * s2 * rm.transpose() + d * d.transpose());
            covered += sigmoid(t.opacities[i]) as f64 * area(s);
        }
        let eig = SymmetricEigen::new(cov);
        let mut axes = eig.eigenvectors;
        if axes.determinant() < 0.0 {
            axes.set_column(2, &(-axes.column(2)));
        }
        let sd = eig.eigenvalues.map(|v| v.max(1e-14).sqrt());
        let rot = Mat3::from_cols_array(&[
            axes[(0, 0)] as f32,
            axes[(1, 0)] as f32,
            axes[(2, 0)] as f32,
            axes[(0, 1)] as f32,
            axes[(1, 1)] as f32,
            axes[(2, 1)] as f32,
            axes[(0, 2)] as f32,
            axes[(1, 2)] as f32,
            axes[(2, 2)] as f32,
        ]);
        let q = Quat::from_mat3(&rot).normalize();
        let merged_area = area([sd[0] as f32, sd[1] as f32, sd[2] as f32]);
        let alpha = (covered / merged_area.max(1e-30)).clamp(1e-3, 0.99) as f32;
        out.means.push(mu.map(|v| v as f32));
        out.scales.push([sd[0], sd[1], sd[2]].map(|v| v.ln() as f32));
        out.quats.push([q.w, q.x, q.y, q.z]);
        out.opacities.push((alpha / (1.0 - alpha)).ln());
        let mut sh = vec![0.0f64; coeffs];
        for (&i, &wi) in members.iter().zip(&w) {
            for (c, v) in sh.iter_mut().enumerate() {
                *v += wi * t.sh[i * coeffs + c] as f64;
            }
        }
        out.sh.extend(sh.iter().map(|&v| v as f32));
        weights_all.push(w);
    }
    let mut off = Offsets::zeros(instances * m);
    for k in 0..instances {
        for (c, (members, w)) in clusters.iter().zip(&weights_all).enumerate() {
            let o = k * m + c;
            for (&i, &wi) in members.iter().zip(w) {
                let src = k * rows + i;
                for a in 0..3 {
                    off.d_means[o][a] += (wi * offsets.d_means[src][a] as f64) as f32;
                    off.d_sh0[o][a] += (wi * offsets.d_sh0[src][a] as f64) as f32;
                }
                off.d_opacities[o] += (wi * offsets.d_opacities[src] as f64) as f32;
            }
        }
    }
    (out, off)
}

/// The coarser levels of a template (one per fraction), each with its offsets.
pub fn build_levels(t: &Scene, offsets: &Offsets, instances: usize, fractions: &[f32]) -> Vec<(Scene, Offsets)> {
    fractions
        .iter()
        .map(|f| {
            let target = ((t.len() as f32 * f).round() as usize).max(1);
            merge_clusters(t, offsets, instances, &cluster(&t.means, target))
        })
        .collect()
}

/// CPU twin of `instance_select.comp` for one instance: (splats this frame, level).
pub fn select_instance(g: &GroupInfo, x: &InstanceXform, fp: &FrameParams, a: &SelectArgs) -> (u32, u32) {
    let m = glam::Mat4::from_cols_array_2d(&x.transform);
    let v = glam::Mat4::from_cols_array_2d(&fp.viewmat);
    let c = v.transform_point3(m.transform_point3(Vec3::new(g.bound[0], g.bound[1], g.bound[2])));
    let [fx, fy, cx, cy] = fp.intrinsics;
    let r = x.scale[0] * g.bound[3] + x.scale[2] + a.margin_px * c.z.max(0.0) / fx.min(fy);
    let (right, bottom) = (fp.width as f32 - cx, fp.height as f32 - cy);
    let outside = c.z + r <= fp.near_plane
        || Vec3::new(fx, 0.0, -right).dot(c) > r * Vec3::new(fx, 0.0, right).length()
        || Vec3::new(-fx, 0.0, -cx).dot(c) > r * Vec3::new(fx, 0.0, cx).length()
        || Vec3::new(0.0, fy, -bottom).dot(c) > r * Vec3::new(0.0, fy, bottom).length()
        || Vec3::new(0.0, -fy, -cy).dot(c) > r * Vec3::new(0.0, fy, cy).length();
    let mut level = 0;
    if !outside && c.z - r > fp.near_plane {
        let rp = fx.min(fy) * r / c.z;
        let area = (std::f32::consts::PI * rp * rp).min(fp.width as f32 * fp.height as f32);
        let top = a.max_level.min(g.levels - 1);
        for l in (1..=top).rev() {
            if g.level_rows[l as usize] as f32 >= a.splats_per_pixel * area {
                level = l;
                break;
            }
        }
    }
    (if outside { 0 } else { g.level_rows[level as usize] }, level)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_load_and_bad_values_are_refused() {
        let c = RenderConfig::load(None).unwrap();
        assert!(c.cull && c.lod.enabled && c.lod.fractions.len() == 2);
        assert!(!c.clone().exact().lod.enabled);
        let dir = std::env::temp_dir().join(format!("instgs-render-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("r.toml");
        std::fs::write(&p, "[lod]\nfractions = [0.1, 0.5]\n").unwrap();
        let e = format!("{:#}", RenderConfig::load(Some(&p)).unwrap_err());
        assert!(e.contains("r.toml") && e.contains("decrease"), "{e}");
        std::fs::write(&p, "[lod]\nsplats_per_pixel = 2.5\n").unwrap();
        assert_eq!(RenderConfig::load(Some(&p)).unwrap().lod.splats_per_pixel, 2.5);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn clusters_reach_the_target_and_cover_every_gaussian() {
        let means: Vec<[f32; 3]> =
            (0..5000).map(|i| [(i % 17) as f32 * 0.1, (i / 17 % 19) as f32 * 0.07, (i % 23) as f32 * 0.05]).collect();
        for target in [1, 50, 1250] {
            let c = cluster(&means, target);
            let n: usize = c.iter().map(|m| m.len()).sum();
            assert_eq!(n, means.len());
            let got = c.len() as f64;
            assert!((got - target as f64).abs() <= 0.2 * target as f64 + 1.0, "{target}: {got}");
        }
    }

    #[test]
    fn merging_two_gaussians_matches_their_moments() {
        let t = Scene {
            means: vec![[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            scales: vec![[0.1f32.ln(), 0.2f32.ln(), 0.3f32.ln()]; 2],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacities: vec![0.0; 2],
            sh: vec![0.1, 0.2, 0.3, 0.5, 0.6, 0.7],
            sh_degree: 0,
        };
        let mut off = Offsets::zeros(4);
        off.d_means[0] = [1.0, 0.0, 0.0];
        off.d_means[1] = [3.0, 0.0, 0.0];
        off.d_opacities[2] = 1.0;
        let (m, o) = merge_clusters(&t, &off, 2, &[vec![0, 1]]);
        assert_eq!(m.len(), 1);
        assert!(Vec3::from(m.means[0]).length() < 1e-6);
        // Variance along x: 0.1² + 1² ; y, z unchanged.
        let mut s: Vec<f32> = m.scales[0].iter().map(|v| v.exp()).collect();
        s.sort_by(f32::total_cmp);
        let want = [0.2f32, 0.3, (0.01f32 + 1.0).sqrt()];
        for (a, b) in s.iter().zip(want) {
            assert!((a - b).abs() < 1e-4, "{s:?}");
        }
        assert!((m.sh[0] - 0.3).abs() < 1e-6 && (m.sh[2] - 0.5).abs() < 1e-6);
        assert!((o.d_means[0][0] - 2.0).abs() < 1e-6 && (o.d_opacities[1] - 0.5).abs() < 1e-6);
        assert!(o.d_opacities[0].abs() < 1e-6);
    }
}
