//! Inria's adaptive density control (clone, split, prune, opacity reset) and the initial
//! scene (points with k-nearest-neighbour scales).

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

use crate::dataset::Dataset;
use crate::math::SH_C0_F32;
use crate::math::{logit, sigmoid};
use crate::model::scene::Scene;
use crate::train::config::Config;

use crate::train::state::*;

/// What one densification step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensifyStats {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
}

/// Inria's densify_and_prune on the host: clone small splats and split large ones whose mean
/// view-space gradient passes the threshold (at most `max_splats` in all, highest gradients
/// first), then prune transparent and oversized ones; statistics are reset. `rng` draws the
/// split positions (normal with the splat's scales, rotated).
pub fn densify(st: &TrainState, cfg: &Config, extent: f32, rng: &mut rand_pcg::Pcg64) -> (TrainState, DensifyStats) {
    let d = &cfg.densify;
    let n = st.scene.len();
    let grads: Vec<f32> = (0..n)
        .map(|i| if st.grad2d_count[i] > 0 { st.grad2d_accum[i] / st.grad2d_count[i] as f32 } else { 0.0 })
        .collect();
    let max_scale = |i: usize| st.scene.scales[i].iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
    let small = d.percent_dense * extent;
    let mut candidates: Vec<usize> = (0..n).filter(|&i| grads[i] >= d.grad_threshold).collect();
    // A clone adds one splat, a split net one: cap the growth.
    let budget = d.max_splats.saturating_sub(n);
    if candidates.len() > budget {
        candidates.sort_by(|&a, &b| grads[b].total_cmp(&grads[a]).then(a.cmp(&b)));
        candidates.truncate(budget);
        candidates.sort_unstable();
    }
    let mut is_split = vec![false; n];
    let mut rows: Vec<(usize, bool)> = Vec::new();
    let mut clones = Vec::new();
    let mut splits = Vec::new();
    for &i in &candidates {
        if max_scale(i) <= small {
            clones.push(i);
        } else {
            splits.push(i);
            is_split[i] = true;
        }
    }
    rows.extend((0..n).filter(|&i| !is_split[i]).map(|i| (i, true)));
    rows.extend(clones.iter().map(|&i| (i, false)));
    let n_kept = rows.len();
    for &i in &splits {
        rows.push((i, false));
        rows.push((i, false));
    }
    let mut out = st.gather(&rows);
    // Split children: positions sampled from the parent, scales / (0.8 · 2).
    for (j, &i) in splits.iter().enumerate() {
        let s = Vec3::from(st.scene.scales[i]).exp();
        let r = crate::math::quat_to_mat(st.scene.quats[i]);
        for c in 0..2 {
            let z: [f32; 3] = [0, 1, 2].map(|_| StandardNormal.sample(rng));
            let p = r * (Vec3::from(z) * s) + Vec3::from(st.scene.means[i]);
            let row = n_kept + 2 * j + c;
            out.scene.means[row] = p.to_array();
            out.scene.scales[row] = st.scene.scales[i].map(|v| v - (0.8f32 * 2.0).ln());
        }
    }
    // Prune.
    let after_reset = st.iteration > d.opacity_reset_interval;
    let keep: Vec<(usize, bool)> = (0..out.scene.len())
        .filter(|&i| {
            let transparent = sigmoid(out.scene.opacities[i]) < d.min_opacity;
            let big_screen = after_reset && d.max_screen_size > 0 && out.max_radii[i] > d.max_screen_size;
            let big_world = after_reset
                && out.scene.scales[i].iter().fold(f32::MIN, |a, &b| a.max(b)).exp() > d.max_world_scale * extent;
            !(transparent || big_screen || big_world)
        })
        .map(|i| (i, true))
        .collect();
    let pruned = out.scene.len() - keep.len();
    let mut out = out.gather(&keep);
    out.grad2d_accum.fill(0.0);
    out.grad2d_count.fill(0);
    out.max_radii.fill(0);
    (out, DensifyStats { cloned: clones.len(), split: splits.len(), pruned })
}

/// Inria's reset_opacity: opacities capped at 0.01, their Adam moments zeroed.
pub fn reset_opacity(st: &mut TrainState) {
    let cap = logit(0.01);
    for o in &mut st.scene.opacities {
        *o = o.min(cap);
    }
    st.exp_avg[3].fill(0.0);
    st.exp_avg_sq[3].fill(0.0);
}

/// log of the root mean squared distance to the 3 nearest other points (Inria's distCUDA2,
/// clamped at 1e-7 squared distance).
pub fn knn_log_scales(points: &[[f32; 3]]) -> Vec<f32> {
    let points: Vec<[f64; 3]> = points.iter().map(|p| p.map(|c| c as f64)).collect();
    let tree = crate::math::tree(&points);
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let nn = tree.nearest_n::<kiddo::SquaredEuclidean>(p, crate::math::neighbours(4));
            let d: Vec<f64> = nn
                .iter()
                .filter(|n| n.item as usize != i)
                .take(3)
                .map(|n| (0..3).map(|a| (points[n.item as usize][a] - p[a]).powi(2)).sum::<f64>())
                .collect();
            let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
            (mean.max(1e-7) as f32).sqrt().ln()
        })
        .collect()
}

/// The initial scene: the dataset's points (or random ones in the cameras' bounding box), one
/// isotropic Gaussian each with the kNN scale, opacity `init.opacity`, sh0 from the colour.
pub fn initial_scene(ds: &Dataset, cfg: &Config) -> Scene {
    let pc = match &ds.points {
        Some(pc) if !pc.positions.is_empty() => pc.clone(),
        _ => {
            let centres: Vec<Vec3> = ds.train.iter().map(|v| v.camera.position()).collect();
            let lo = centres.iter().copied().fold(Vec3::splat(f32::MAX), Vec3::min);
            let hi = centres.iter().copied().fold(Vec3::splat(f32::MIN), Vec3::max);
            let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed);
            let mut pc = crate::dataset::PointCloud::default();
            for _ in 0..cfg.init.random_points {
                let u = Vec3::new(rng.random(), rng.random(), rng.random());
                pc.positions.push((lo + (hi - lo) * u).to_array());
                pc.colours.push([rng.random(), rng.random(), rng.random()]);
            }
            pc
        }
    };
    let coeffs = ((cfg.sh_degree + 1) * (cfg.sh_degree + 1)) as usize;
    let scales = knn_log_scales(&pc.positions);
    let mut s = Scene { sh_degree: cfg.sh_degree, ..Default::default() };
    for (i, p) in pc.positions.iter().enumerate() {
        s.means.push(*p);
        s.scales.push([scales[i]; 3]);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacities.push(logit(cfg.init.opacity));
        for k in 0..coeffs {
            for c in 0..3 {
                s.sh.push(if k == 0 { (pc.colours[i][c] - 0.5) / SH_C0_F32 } else { 0.0 });
            }
        }
    }
    s
}
