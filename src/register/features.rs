//! Point-cloud features for registration: voxel downsampling, normals, FPFH (Rusu et al., ICRA
//! 2009) and mutual nearest matches between feature sets.
use crate::math::tree;
use std::collections::HashMap;

use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

/// FPFH bins per angle feature; a descriptor holds three such histograms.
pub const FPFH_BINS: usize = 11;
pub const FPFH_DIM: usize = 3 * FPFH_BINS;

/// Centroids of the occupied cells of a `voxel`-sized grid, in first-seen cell order.
pub fn voxel_downsample(points: &[[f64; 3]], voxel: f64) -> Vec<[f64; 3]> {
    voxel_downsample_with(points, None, voxel).0
}

/// [`voxel_downsample`] that also averages per-point `values` (e.g. colours) per cell.
pub(crate) fn voxel_downsample_with(
    points: &[[f64; 3]],
    values: Option<&[[f64; 3]]>,
    voxel: f64,
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let mut cells: HashMap<[i64; 3], usize> = HashMap::new();
    let mut sums: Vec<([f64; 3], [f64; 3], usize)> = Vec::new();
    for (j, p) in points.iter().enumerate() {
        let key = p.map(|c| (c / voxel).floor() as i64);
        let i = *cells.entry(key).or_insert_with(|| {
            sums.push(([0.0; 3], [0.0; 3], 0));
            sums.len() - 1
        });
        let v = values.map_or([0.0; 3], |v| v[j]);
        for a in 0..3 {
            sums[i].0[a] += p[a];
            sums[i].1[a] += v[a];
        }
        sums[i].2 += 1;
    }
    sums.into_iter().map(|(s, v, n)| (s.map(|c| c / n as f64), v.map(|c| c / n as f64))).unzip()
}

/// Unit normals from the covariance of the neighbours within `radius` (at most `max_nn`,
/// nearest first): the eigenvector of the smallest eigenvalue, oriented away from the cloud's
/// centroid so that the orientation moves with the cloud under any similarity.
pub fn normals(points: &[[f64; 3]], radius: f64, max_nn: usize) -> Vec<[f64; 3]> {
    let t = tree(points);
    let c = centroid(points);
    points
        .iter()
        .map(|p| {
            let nn = t.nearest_n_within::<SquaredEuclidean>(p, radius * radius, crate::math::neighbours(max_nn), true);
            let n = if nn.len() < 3 {
                Vector3::from(*p) - c
            } else {
                let pts: Vec<Vector3<f64>> = nn.iter().map(|x| Vector3::from(points[x.item as usize])).collect();
                let m = pts.iter().fold(Vector3::zeros(), |a, x| a + x) / pts.len() as f64;
                let cov = pts.iter().fold(Matrix3::zeros(), |a, x| a + (x - m) * (x - m).transpose());
                let e = SymmetricEigen::new(cov);
                let i = e.eigenvalues.imin();
                e.eigenvectors.column(i).into_owned()
            };
            let n = if n.dot(&(Vector3::from(*p) - c)) < 0.0 { -n } else { n };
            let len = n.norm();
            if len > 0.0 {
                (n / len).into()
            } else {
                [0.0, 0.0, 1.0]
            }
        })
        .collect()
}

/// The mean of `points` (origin when empty).
pub fn centroid(points: &[[f64; 3]]) -> Vector3<f64> {
    points.iter().fold(Vector3::zeros(), |a, x| a + Vector3::from(*x)) / points.len().max(1) as f64
}

/// The Darboux-frame angles (α, φ, θ) of a point pair (Rusu et al. 2009; PCL's
/// `computePairFeatures` convention: the source is the point whose normal makes the smaller
/// angle with the connecting line). None for coincident points or parallel geometry.
fn pair_features(p1: Vector3<f64>, n1: Vector3<f64>, p2: Vector3<f64>, n2: Vector3<f64>) -> Option<[f64; 3]> {
    let mut d = p2 - p1;
    let len = d.norm();
    if len <= 0.0 {
        return None;
    }
    let (a1, a2) = (n1.dot(&d) / len, n2.dot(&d) / len);
    let (u, other, f3) = if a1.abs().acos() > a2.abs().acos() {
        d = -d;
        (n2, n1, -a2)
    } else {
        (n1, n2, a1)
    };
    let v = d.cross(&u);
    let vn = v.norm();
    if vn <= 0.0 {
        return None;
    }
    let v = v / vn;
    let w = u.cross(&v);
    let f2 = v.dot(&other);
    let f1 = w.dot(&other).atan2(u.dot(&other));
    Some([f1, f2, f3])
}

fn bin(x: f64, lo: f64, hi: f64) -> usize {
    (((x - lo) / (hi - lo) * FPFH_BINS as f64).floor() as isize).clamp(0, FPFH_BINS as isize - 1) as usize
}

/// Fast point feature histograms: per point, SPFH(p) + (1/k)·Σ SPFH(pₖ)/|p − pₖ| over the
/// neighbours within `radius` (at most `max_nn`); each 11-bin histogram sums to 100.
pub fn fpfh(points: &[[f64; 3]], normals: &[[f64; 3]], radius: f64, max_nn: usize) -> Vec<[f64; FPFH_DIM]> {
    let t = tree(points);
    let neigh: Vec<Vec<(usize, f64)>> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            t.nearest_n_within::<SquaredEuclidean>(p, radius * radius, crate::math::neighbours(max_nn + 1), true)
                .into_iter()
                .filter(|n| n.item as usize != i)
                .take(max_nn)
                .map(|n| (n.item as usize, n.distance.sqrt()))
                .collect()
        })
        .collect();
    let spfh: Vec<[f64; FPFH_DIM]> = (0..points.len())
        .map(|i| {
            let mut h = [0.0; FPFH_DIM];
            let (p, n) = (Vector3::from(points[i]), Vector3::from(normals[i]));
            let feats: Vec<[f64; 3]> = neigh[i]
                .iter()
                .filter_map(|&(j, _)| pair_features(p, n, Vector3::from(points[j]), Vector3::from(normals[j])))
                .collect();
            if feats.is_empty() {
                return h;
            }
            let inc = 100.0 / feats.len() as f64;
            for f in feats {
                h[bin(f[0], -std::f64::consts::PI, std::f64::consts::PI)] += inc;
                h[FPFH_BINS + bin(f[1], -1.0, 1.0)] += inc;
                h[2 * FPFH_BINS + bin(f[2], -1.0, 1.0)] += inc;
            }
            h
        })
        .collect();
    (0..points.len())
        .map(|i| {
            let mut f = spfh[i];
            let mut nb = [0.0; FPFH_DIM];
            for &(j, d) in &neigh[i] {
                if d > 0.0 {
                    for (a, b) in nb.iter_mut().zip(&spfh[j]) {
                        *a += b / d;
                    }
                }
            }
            for part in 0..3 {
                let r = part * FPFH_BINS..(part + 1) * FPFH_BINS;
                let sum: f64 = nb[r.clone()].iter().sum();
                if sum > 0.0 {
                    for (a, b) in f[r.clone()].iter_mut().zip(&nb[r]) {
                        *a = (*a + b * 100.0 / sum) / 2.0;
                    }
                }
            }
            f
        })
        .collect()
}

/// Index pairs (source, target) whose FPFH descriptors are each other's nearest neighbours
/// (Euclidean; ties: lowest index). Exhaustive search: in 33 dimensions, with histograms full
/// of equal zeros, a k-d tree prunes little.
pub fn mutual_matches(fs: &[[f64; FPFH_DIM]], fd: &[[f64; FPFH_DIM]]) -> Vec<(usize, usize)> {
    fn nearest(f: &[f64; FPFH_DIM], set: &[[f64; FPFH_DIM]]) -> usize {
        let mut best = (f64::INFINITY, 0);
        for (j, g) in set.iter().enumerate() {
            let d: f64 = f.iter().zip(g).map(|(a, b)| (a - b) * (a - b)).sum();
            if d < best.0 {
                best = (d, j);
            }
        }
        best.1
    }
    let back: Vec<usize> = fd.iter().map(|g| nearest(g, fs)).collect();
    fs.iter()
        .enumerate()
        .filter_map(|(i, f)| {
            let j = nearest(f, fd);
            (back[j] == i).then_some((i, j))
        })
        .collect()
}
