//! Registration of one instance's Gaussian means onto another's (InstGS paper §4.2): FPFH
//! features (Rusu et al., ICRA 2009) on a voxel-downsampled cloud, RANSAC global alignment over
//! mutual feature correspondences with edge-length and distance checks (the scheme of Open3D's
//! `registration_ransac_based_on_feature_matching`), candidate poses spun about the principal
//! axes, then point-to-point ICP, and colour-aware ICP where the shape is ambiguous; similarity
//! transforms (rotation, uniform scale, translation) by Umeyama's closed form when scale is
//! estimated. All in f64, deterministic for a seed.
//!
//! Crates looked at first (2026-11): `threecrate-algorithms` (young, pulls kdtree, rstar, ndarray
//! and rayon, no similarity ICP), `fast-gicp` (C++ GICP bindings, no FPFH) and `fricp` (ICP only).
//! None does FPFH + RANSAC + scaled ICP well, so that logic lives here on top of `kiddo` (k-d
//! trees) and `nalgebra` (SVD, symmetric eigen).
use crate::math::tree;

use anyhow::{bail, Result};
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

pub mod features;
pub mod sim3;

pub use features::*;
pub use sim3::*;

pub type Tree3 = ImmutableKdTree<f64, u32, 3, 32>;

/// Parameters of [`register`]; lengths in the clouds' units.
#[derive(Clone, Debug)]
pub struct RegisterOptions {
    /// Voxel size of the downsampled clouds (features, RANSAC); ICP runs at half of it.
    pub voxel: f64,
    /// Also estimate a uniform scale.
    pub with_scale: bool,
    /// With scale: the estimate stays within this relative distance of the two clouds' size
    /// ratio ([`object_size`]): s ∈ [s₀/(1+tol), s₀·(1+tol)].
    pub scale_tolerance: f64,
    pub ransac_iterations: usize,
    /// Edge-length check: pairwise source and target distances of a sample agree to this ratio.
    pub edge_ratio: f64,
    pub icp_iterations: usize,
    /// Rotations of a uniform grid on SO(3) ([`rotation_grid`]) tried as starts besides
    /// RANSAC's hypotheses, each about the clouds' centroids (0: RANSAC alone).
    pub grid_rotations: usize,
    /// Weight of colour in [`register_coloured`]'s ICP (0: geometry only).
    pub colour_weight: f64,
    pub seed: u64,
}

impl RegisterOptions {
    /// Defaults for an object whose bounding-box diagonal is `size`: voxel size/25.
    pub fn for_size(size: f64) -> RegisterOptions {
        RegisterOptions {
            voxel: size / 25.0,
            with_scale: true,
            scale_tolerance: 0.25,
            ransac_iterations: 100_000,
            edge_ratio: 0.9,
            icp_iterations: 60,
            grid_rotations: 300,
            colour_weight: 1.0,
            seed: 0,
        }
    }
}

/// A registration of `source` onto `target`: `transform` maps source points to target points.
#[derive(Clone, Debug)]
pub struct Registration {
    pub transform: Sim3,
    /// Fraction of (ICP-resolution) source points with a target point within one voxel.
    pub fitness: f64,
    /// Fraction of target points with a (moved) source point within one voxel: low when the
    /// source covers only part of the target (a collapsed or misplaced pose).
    pub fitness_reverse: f64,
    /// RMS distance of the source → target pairs (within one voxel).
    pub rmse: f64,
    /// Mean L1 difference of their normalised colours ([`register_coloured`]; 0 without).
    pub colour_error: f64,
    /// Another pose fitted the shape nearly as well (colour decided, when given).
    pub shape_ambiguous: bool,
    /// Mutual feature correspondences RANSAC drew from.
    pub correspondences: usize,
    /// The size ratio the scale was held near (1 for rigid registration).
    pub expected_scale: f64,
}

impl Registration {
    /// The smaller of the two fitnesses: both clouds must be covered.
    pub fn overlap(&self) -> f64 {
        self.fitness.min(self.fitness_reverse)
    }
}

/// Fitness, RMSE and mean colour difference (L1 over channels; 0 without colours) of `x` over
/// `src` against `dst_tree` with pairs closer than `dist`.
fn evaluate(
    x: &Sim3,
    src: &[[f64; 3]],
    src_c: &[[f64; 3]],
    dst_tree: &Tree3,
    dst_c: &[[f64; 3]],
    dist: f64,
) -> (f64, f64, f64) {
    let mut n = 0;
    let (mut sq, mut col) = (0.0, 0.0);
    for (p, c) in src.iter().zip(src_c) {
        let nn = dst_tree.nearest_one::<SquaredEuclidean>(&x.apply(p));
        if nn.distance <= dist * dist {
            n += 1;
            sq += nn.distance;
            col += (0..3).map(|a| (c[a] - dst_c[nn.item as usize][a]).abs()).sum::<f64>();
        }
    }
    let rms = if n > 0 { (sq / n as f64).sqrt() } else { f64::INFINITY };
    let col = if n > 0 { col / n as f64 } else { f64::INFINITY };
    (n as f64 / src.len().max(1) as f64, rms, col)
}

/// Fraction of `dst` points with a point of `src` moved by `x` within `dist`.
pub fn reverse_fitness(x: &Sim3, src: &[[f64; 3]], dst: &[[f64; 3]], dist: f64) -> f64 {
    if src.is_empty() {
        return 0.0;
    }
    let moved: Vec<[f64; 3]> = src.iter().map(|p| x.apply(p)).collect();
    let t = tree(&moved);
    let n = dst.iter().filter(|q| t.nearest_one::<SquaredEuclidean>(q).distance <= dist * dist).count();
    n as f64 / dst.len().max(1) as f64
}

/// The median distance of a point of `points` to its nearest other point (0 for fewer than 2).
pub fn median_spacing(points: &[[f64; 3]]) -> f64 {
    if points.len() < 2 {
        return 0.0;
    }
    let t = tree(points);
    let mut d: Vec<f64> = points
        .iter()
        .map(|p| {
            t.nearest_n::<SquaredEuclidean>(p, crate::math::neighbours(2)).last().map_or(0.0, |n| n.distance.sqrt())
        })
        .collect();
    d.sort_by(f64::total_cmp);
    d[d.len() / 2]
}

/// An object's size, rotation-invariant: twice the 98th percentile of the points' distances to
/// their centroid, after statistical outlier removal ([`inliers`]: stray Gaussians and floaters
/// do not count).
pub fn object_size(points: &[[f64; 3]]) -> f64 {
    let kept: Vec<[f64; 3]> = inliers(points).into_iter().map(|i| points[i]).collect();
    let c = centroid(&kept);
    let mut d: Vec<f64> = kept.iter().map(|p| (Vector3::from(*p) - c).norm()).collect();
    d.sort_by(f64::total_cmp);
    2.0 * d.get(((d.len() as f64 - 1.0) * 0.98) as usize).copied().unwrap_or(0.0)
}

/// Statistical outlier removal (as PCL's and Open3D's): the indices of the points whose mean
/// distance to their 16 nearest neighbours is at most the mean of that over all points plus two
/// standard deviations. Every index for fewer than 32 points.
pub fn inliers(points: &[[f64; 3]]) -> Vec<usize> {
    const K: usize = 16;
    if points.len() < 2 * K {
        return (0..points.len()).collect();
    }
    let t = tree(points);
    let mean_dist: Vec<f64> = points
        .iter()
        .map(|p| {
            let nn = t.nearest_n::<SquaredEuclidean>(p, crate::math::neighbours(K + 1));
            nn.iter().skip(1).map(|n| n.distance.sqrt()).sum::<f64>() / K as f64
        })
        .collect();
    let n = mean_dist.len() as f64;
    let mu = mean_dist.iter().sum::<f64>() / n;
    let sigma = (mean_dist.iter().map(|d| (d - mu).powi(2)).sum::<f64>() / n).sqrt();
    (0..points.len()).filter(|&i| mean_dist[i] <= mu + 2.0 * sigma).collect()
}

/// Point-to-point ICP from `init`: pairs each source point with its nearest target point
/// within `dist` and, when `symmetric`, each target point with its nearest (moved) source point
/// within `dist`; refits (Umeyama, the scale held in `scale_range`; `None`: rigid) until the transform
/// changes by less than 1e-9 or `iterations` end. The target → source pairs keep a scaled fit
/// from shrinking the source onto part of the target (one-sided pairs reward that: every
/// shrunken source point still finds a near target point).
pub fn icp(
    src: &[[f64; 3]],
    dst: &[[f64; 3]],
    init: Sim3,
    dist: f64,
    iterations: usize,
    scale_range: Option<(f64, f64)>,
    symmetric: bool,
) -> Sim3 {
    let t = tree(dst);
    let mut x = init;
    for _ in 0..iterations {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let moved: Vec<[f64; 3]> = src.iter().map(|p| x.apply(p)).collect();
        for (p, q) in src.iter().zip(&moved) {
            let nn = t.nearest_one::<SquaredEuclidean>(q);
            if nn.distance <= dist * dist {
                a.push(*p);
                b.push(dst[nn.item as usize]);
            }
        }
        if symmetric {
            let back = tree(&moved);
            for q in dst {
                let nn = back.nearest_one::<SquaredEuclidean>(q);
                if dist2(&moved[nn.item as usize], q) <= dist * dist {
                    a.push(src[nn.item as usize]);
                    b.push(*q);
                }
            }
        }
        let Some(next) = umeyama_bounded(&a, &b, scale_range) else { break };
        let change = (next.rotation - x.rotation).norm()
            + (next.translation - x.translation).norm() / dist
            + (next.scale - x.scale).abs();
        x = next;
        if change < 1e-9 {
            break;
        }
    }
    x
}

/// Registers `source` onto `target` (both clouds of one object, any similarity apart); the
/// first of [`candidates`].
pub fn register(source: &[[f64; 3]], target: &[[f64; 3]], o: &RegisterOptions) -> Result<Registration> {
    Ok(candidates(source, None, target, None, o)?.remove(0))
}

/// [`register`] with per-point colours (e.g. the RGB of the SH DC), for objects whose shape is
/// (nearly) symmetric. Colours are normalised per cloud by their per-channel mean, so a
/// per-instance tint (a per-channel factor, also after a gamma curve) cancels. Colour is used
/// only where the shape leaves the pose open (see `shape_ambiguous`): then every candidate is
/// refined by ICP in (position, λ·colour) space (λ = 2 voxels × `colour_weight`), and polished
/// by shape ICP.
pub fn register_coloured(
    source: &[[f64; 3]],
    source_rgb: &[[f64; 3]],
    target: &[[f64; 3]],
    target_rgb: &[[f64; 3]],
    o: &RegisterOptions,
) -> Result<Registration> {
    Ok(candidates(source, Some(source_rgb), target, Some(target_rgb), o)?.remove(0))
}

/// Colours divided by their per-channel mean.
fn normalise_colours(c: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let n = c.len().max(1) as f64;
    let mean = c.iter().fold([0.0; 3], |m, x| [m[0] + x[0] / n, m[1] + x[1] / n, m[2] + x[2] / n]);
    c.iter().map(|x| std::array::from_fn(|a| x[a] / mean[a].max(1e-6))).collect()
}

/// Every distinct pose hypothesis for `source` onto `target`, the most plausible first (at
/// least one): a caller that checks poses against the data ([`crate::instancing::template::instantiate`])
/// takes the first that passes.
///
/// With scale, the source is first scaled by the clouds' size ratio s₀ ([`object_size`]), so
/// that features, RANSAC's edge-length check and the ICP distances see one object size; the
/// scale then stays within [`RegisterOptions::scale_tolerance`] of s₀. FPFH on
/// voxel-downsampled clouds, RANSAC over mutual nearest features (3-point samples passing the
/// edge-length check, scored by correspondence inliers within 1.5 voxels); the 8 best distinct
/// hypotheses, each also spun about the target's three principal axes in 30° steps (a mug's
/// handle, a brick's studs: small asymmetries of symmetric bulk) and screened by a short ICP on
/// the coarse clouds; the 8 fittest refined by symmetric ICP (1.5 voxels, then 0.5 voxel at
/// half the voxel size). Fitness is counted within one voxel (Gaussian means of two instances
/// are different samples of one surface: within half a voxel a right and a flipped pose score
/// alike on a few hundred points). Ranked by the two-sided fitness
/// ([`Registration::overlap`]), then RMSE.
/// When the shape leaves the choice open (a candidate turned more than 10° from the best fits
/// within 95 % as well: a ball, a can) and colours are given, every candidate is refined by
/// colour ICP, then by shape ICP, and ranked the same way.
pub fn candidates(
    source: &[[f64; 3]],
    source_rgb: Option<&[[f64; 3]]>,
    target: &[[f64; 3]],
    target_rgb: Option<&[[f64; 3]]>,
    o: &RegisterOptions,
) -> Result<Vec<Registration>> {
    for (rgb, pts, what) in [(source_rgb, source, "source"), (target_rgb, target, "target")] {
        if rgb.is_some_and(|c| c.len() != pts.len()) {
            bail!("colours for {} {what} points, not {}", rgb.map_or(0, |c| c.len()), pts.len());
        }
    }
    let (sc, tc) = (source_rgb.map(normalise_colours), target_rgb.map(normalise_colours));
    let source_size = object_size(source);
    let expected_scale = if o.with_scale && source_size > 0.0 { object_size(target) / source_size } else { 1.0 };
    if !(expected_scale.is_finite() && expected_scale > 0.0) {
        bail!("cannot register a cloud of size {} onto one of size {}", source_size, object_size(target));
    }
    let pre = Sim3 { scale: expected_scale, ..Sim3::identity() };
    let scaled: Vec<[f64; 3]> = source.iter().map(|p| pre.apply(p)).collect();
    let range = o.with_scale.then(|| (1.0 / (1.0 + o.scale_tolerance), 1.0 + o.scale_tolerance));
    let mut out = register_scaled(&scaled, sc.as_deref(), target, tc.as_deref(), o, range)?;
    for r in &mut out {
        r.transform = r.transform.compose(&pre);
        r.expected_scale = expected_scale;
    }
    Ok(out)
}

/// RANSAC over the feature correspondences `corr` (source index, target index): triples whose
/// edge lengths agree, fitted by Umeyama within the scale `range`; the 8 hypotheses with the
/// most correspondences within 1.5 voxels, at most one per 5° of rotation, most first.
fn ransac(
    s: &[[f64; 3]],
    d: &[[f64; 3]],
    corr: &[(usize, usize)],
    o: &RegisterOptions,
    range: Option<(f64, f64)>,
) -> Vec<(usize, Sim3)> {
    let dist = 1.5 * o.voxel;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(o.seed);
    let mut best: Vec<(usize, Sim3)> = Vec::new();
    const KEEP: usize = 8;
    for _ in 0..o.ransac_iterations {
        let idx = [0; 3].map(|_| rng.random_range(0..corr.len()));
        if idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2] {
            continue;
        }
        let a: Vec<[f64; 3]> = idx.iter().map(|&i| s[corr[i].0]).collect();
        let b: Vec<[f64; 3]> = idx.iter().map(|&i| d[corr[i].1]).collect();
        if !edges_agree(&a, &b, o.edge_ratio) {
            continue;
        }
        let Some(x) = umeyama_bounded(&a, &b, range) else { continue };
        if a.iter().zip(&b).any(|(p, q)| dist2(&x.apply(p), q) > dist * dist) {
            continue;
        }
        let inliers = corr.iter().filter(|&&(i, j)| dist2(&x.apply(&s[i]), &d[j]) <= dist * dist).count();
        if best.len() < KEEP || inliers > best[KEEP - 1].0 {
            // Near-duplicates of a kept hypothesis replace it rather than crowd the list.
            if let Some(k) = best.iter().position(|(_, y)| y.rotation_error_deg(&x) < 5.0) {
                if inliers > best[k].0 {
                    best[k] = (inliers, x);
                }
            } else {
                best.push((inliers, x));
            }
            best.sort_by_key(|b| std::cmp::Reverse(b.0));
            best.truncate(KEEP);
        }
    }
    best
}

fn register_scaled(
    source: &[[f64; 3]],
    source_rgb: Option<&[[f64; 3]]>,
    target: &[[f64; 3]],
    target_rgb: Option<&[[f64; 3]]>,
    o: &RegisterOptions,
    range: Option<(f64, f64)>,
) -> Result<Vec<Registration>> {
    let (s, sc) = voxel_downsample_with(source, source_rgb, o.voxel);
    let (d, dc) = voxel_downsample_with(target, target_rgb, o.voxel);
    if s.len() < 8 || d.len() < 8 {
        bail!(
            "too few points to register ({} and {} voxels of {:.4}; {} and {} points)",
            s.len(),
            d.len(),
            o.voxel,
            source.len(),
            target.len()
        );
    }
    let (ns, nd) = (normals(&s, 2.0 * o.voxel, 30), normals(&d, 2.0 * o.voxel, 30));
    let (fs, fd) = (fpfh(&s, &ns, 5.0 * o.voxel, 100), fpfh(&d, &nd, 5.0 * o.voxel, 100));
    let corr = mutual_matches(&fs, &fd);
    if corr.len() < 3 {
        bail!("only {} mutual feature correspondences", corr.len());
    }
    let dist = 1.5 * o.voxel;
    let best = ransac(&s, &d, &corr, o, range);
    const KEEP: usize = 8;
    if best.is_empty() && o.grid_rotations == 0 {
        bail!(
            "RANSAC found no hypothesis passing the edge-length and distance checks ({} correspondences)",
            corr.len()
        );
    }
    // Candidates: every kept hypothesis, also spun about the target's principal axes in 30°
    // steps, and the rotation grid about the centroids (feature matches on a few hundred noisy
    // Gaussian means can all be wrong); screened by a short ICP on the coarse clouds
    // (two-sided fitness), the 8 fittest refined.
    let d_tree = tree(&d);
    let centre = centroid(&d);
    let axes = principal_axes(&d);
    let mut starts: Vec<Sim3> = Vec::new();
    for (_, x) in &best {
        starts.push(*x);
        for axis in &axes {
            for step in 1..12 {
                let r = *nalgebra::Rotation3::from_axis_angle(axis, step as f64 * std::f64::consts::PI / 6.0).matrix();
                starts.push(Sim3 { rotation: r, ..Sim3::identity() }.about(&centre).compose(x));
            }
        }
    }
    let source_centre = centroid(&s);
    for r in rotation_grid(o.grid_rotations) {
        starts.push(Sim3 { rotation: r, scale: 1.0, translation: centre - r * source_centre });
    }
    let mut screened: Vec<(f64, Sim3)> = starts
        .into_par_iter()
        .map(|x| {
            let x = icp(&s, &d, x, dist, 15, range, false);
            let (fitness, _, _) = evaluate(&x, &s, &sc, &d_tree, &dc, o.voxel);
            (fitness.min(reverse_fitness(&x, &s, &d, o.voxel)), x)
        })
        .collect();
    screened.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut coarse: Vec<Sim3> = Vec::new();
    for (_, x) in screened {
        if coarse.len() < KEEP && coarse.iter().all(|y| y.rotation_error_deg(&x) > 5.0) {
            coarse.push(x);
        }
    }
    let fine = o.voxel / 2.0;
    let (s2, s2c) = voxel_downsample_with(source, source_rgb, fine);
    let (d2, d2c) = voxel_downsample_with(target, target_rgb, fine);
    let d2_tree = tree(&d2);
    let lambda = 2.0 * o.voxel * o.colour_weight;
    let coloured = source_rgb.is_some() && target_rgb.is_some() && lambda > 0.0;
    let score = |x: Sim3| {
        let (fitness, rmse, colour) = evaluate(&x, &s2, &s2c, &d2_tree, &d2c, o.voxel);
        Registration {
            transform: x,
            fitness,
            fitness_reverse: reverse_fitness(&x, &s2, &d2, o.voxel),
            rmse,
            colour_error: colour,
            shape_ambiguous: false,
            correspondences: corr.len(),
            expected_scale: 1.0,
        }
    };
    let rank = |v: &mut Vec<Registration>| {
        v.sort_by(|a, b| {
            (b.overlap(), -b.rmse).partial_cmp(&(a.overlap(), -a.rmse)).unwrap_or(std::cmp::Ordering::Equal)
        });
        let mut kept: Vec<Registration> = Vec::new();
        for r in v.drain(..) {
            if kept.iter().all(|k| k.transform.rotation_error_deg(&r.transform) > 5.0) {
                kept.push(r);
            }
        }
        *v = kept;
    };
    let mut shaped: Vec<Registration> = coarse
        .into_par_iter()
        .map(|x| {
            let x = icp(&s2, &d2, x, dist, o.icp_iterations, range, true);
            score(icp(&s2, &d2, x, fine, o.icp_iterations, range, true))
        })
        .collect();
    rank(&mut shaped);
    let top = shaped[0].overlap();
    let ambiguous = shaped[1..].iter().any(|c| c.overlap() >= 0.95 * top);
    let mut out = if coloured && ambiguous {
        let mut tinted: Vec<Registration> = shaped
            .par_iter()
            .map(|c| {
                let x = colour_icp(&s2, &s2c, &d2, &d2c, c.transform, o.voxel, lambda, o.icp_iterations, range);
                score(icp(&s2, &d2, x, fine, o.icp_iterations, range, true))
            })
            .collect();
        // Colour ICP has moved each candidate to where the colours agree too; ranked by shape
        // as before (ranking by colour agreement alone picked wrong mug poses, BENCHMARKS.md).
        rank(&mut tinted);
        tinted
    } else {
        shaped
    };
    for r in &mut out {
        r.shape_ambiguous = ambiguous;
    }
    Ok(out)
}

/// `n` rotations spread evenly over SO(3): a super-Fibonacci spiral of unit quaternions (Alexa,
/// "Super-Fibonacci Spirals", CVPR 2022); 300 leave no rotation farther than ~25° from one.
pub fn rotation_grid(n: usize) -> Vec<Matrix3<f64>> {
    let phi = std::f64::consts::SQRT_2;
    let psi = 1.533_751_168_755_204_3;
    (0..n)
        .map(|i| {
            let s = i as f64 + 0.5;
            let (r, big_r) = ((s / n as f64).sqrt(), (1.0 - s / n as f64).sqrt());
            let (a, b) = (std::f64::consts::TAU * s / phi, std::f64::consts::TAU * s / psi);
            let q = nalgebra::Quaternion::new(big_r * b.cos(), r * a.sin(), r * a.cos(), big_r * b.sin());
            *nalgebra::UnitQuaternion::from_quaternion(q).to_rotation_matrix().matrix()
        })
        .collect()
}

/// The principal axes (unit eigenvectors of the covariance) of `points`.
pub fn principal_axes(points: &[[f64; 3]]) -> Vec<nalgebra::Unit<Vector3<f64>>> {
    let c = centroid(points);
    let cov = points.iter().fold(Matrix3::zeros(), |a, p| {
        let d = Vector3::from(*p) - c;
        a + d * d.transpose()
    });
    let e = SymmetricEigen::new(cov);
    (0..3).map(|i| nalgebra::Unit::new_normalize(e.eigenvectors.column(i).into_owned())).collect()
}

/// Point-to-point ICP whose pairs are nearest neighbours in (position, λ·colour) space within
/// `dist`; the fit uses positions only.
#[allow(clippy::too_many_arguments)]
fn colour_icp(
    src: &[[f64; 3]],
    src_c: &[[f64; 3]],
    dst: &[[f64; 3]],
    dst_c: &[[f64; 3]],
    init: Sim3,
    dist: f64,
    lambda: f64,
    iterations: usize,
    scale_range: Option<(f64, f64)>,
) -> Sim3 {
    let lift =
        |p: &[f64; 3], c: &[f64; 3]| -> [f64; 6] { [p[0], p[1], p[2], lambda * c[0], lambda * c[1], lambda * c[2]] };
    let d6: Vec<[f64; 6]> = dst.iter().zip(dst_c).map(|(p, c)| lift(p, c)).collect();
    let t = tree(&d6);
    let mut x = init;
    for _ in 0..iterations {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for (p, c) in src.iter().zip(src_c) {
            let nn = t.nearest_one::<SquaredEuclidean>(&lift(&x.apply(p), c));
            if nn.distance <= dist * dist {
                a.push(*p);
                b.push(dst[nn.item as usize]);
            }
        }
        let Some(next) = umeyama_bounded(&a, &b, scale_range) else { break };
        let change = (next.rotation - x.rotation).norm() + (next.translation - x.translation).norm() / dist;
        x = next;
        if change < 1e-9 {
            break;
        }
    }
    x
}

fn dist2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]) * (a[i] - b[i])).sum()
}

/// Every pairwise distance of `a` and of `b` agree within `ratio` (shorter ≥ ratio·longer).
fn edges_agree(a: &[[f64; 3]], b: &[[f64; 3]], ratio: f64) -> bool {
    for i in 0..a.len() {
        for j in i + 1..a.len() {
            let (x, y) = (dist2(&a[i], &a[j]).sqrt(), dist2(&b[i], &b[j]).sqrt());
            if x < ratio * y || y < ratio * x {
                return false;
            }
        }
    }
    true
}

/// The dominant plane of `points`: unit normal n and offset d (n·p = d for points on it), and
/// the number of points within `thickness`. RANSAC over 3-point samples (seeded), refined by
/// least squares on its inliers. None for fewer than 3 points.
pub fn support_plane(points: &[[f64; 3]], thickness: f64, seed: u64) -> Option<(Vector3<f64>, f64, usize)> {
    if points.len() < 3 {
        return None;
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let count = |n: &Vector3<f64>, d: f64| {
        points.iter().filter(|p| (n.dot(&Vector3::from(**p)) - d).abs() <= thickness).count()
    };
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..1000 {
        let [a, b, c] = [0; 3].map(|_| Vector3::from(points[rng.random_range(0..points.len())]));
        let n = (b - a).cross(&(c - a));
        if n.norm() < 1e-12 {
            continue;
        }
        let n = n.normalize();
        let d = n.dot(&a);
        let k = count(&n, d);
        if best.as_ref().is_none_or(|b| k > b.0) {
            best = Some((k, n, d));
        }
    }
    let (_, n, d) = best?;
    let inl: Vec<Vector3<f64>> =
        points.iter().map(|p| Vector3::from(*p)).filter(|p| (n.dot(p) - d).abs() <= thickness).collect();
    let m = inl.iter().fold(Vector3::zeros(), |a, p| a + p) / inl.len() as f64;
    let cov = inl.iter().fold(Matrix3::zeros(), |a, p| a + (p - m) * (p - m).transpose());
    let e = SymmetricEigen::new(cov);
    let mut n2: Vector3<f64> = e.eigenvectors.column(e.eigenvalues.imin()).into_owned();
    if n2.dot(&n) < 0.0 {
        n2 = -n2;
    }
    let d2 = n2.dot(&m);
    Some((n2, d2, count(&n2, d2)))
}

/// Farthest-point sampling: `n` indices of `points`, starting from the point nearest the
/// centroid, each next one the farthest from those already taken (ties: lowest index).
/// Deterministic; returns every index when `n ≥ points.len()`.
pub fn farthest_point_sample(points: &[[f64; 3]], n: usize) -> Vec<usize> {
    if n >= points.len() {
        return (0..points.len()).collect();
    }
    if n == 0 {
        return Vec::new();
    }
    let c = centroid(points);
    let c = [c.x, c.y, c.z];
    let first =
        (0..points.len()).min_by(|&a, &b| dist2(&points[a], &c).total_cmp(&dist2(&points[b], &c))).expect("non-empty");
    let mut d: Vec<f64> = points.iter().map(|p| dist2(p, &points[first])).collect();
    let mut out = vec![first];
    while out.len() < n {
        let mut next = 0;
        for i in 1..points.len() {
            if d[i] > d[next] {
                next = i;
            }
        }
        out.push(next);
        let q = points[next];
        for (di, p) in d.iter_mut().zip(points) {
            *di = di.min(dist2(p, &q));
        }
    }
    out
}
