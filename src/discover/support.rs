//! The scene's support plane (the floor or table the objects stand on) and its footprints.

use anyhow::Result;
use nalgebra::Vector3;

use crate::math::quat_to_mat;
use crate::model::scene::Scene;
use crate::register::{median_spacing, support_plane};

use super::copies::{f64s, opaque, voxel_cells};
use super::DiscoverOptions;

/// The scene's support plane: points p with normal·p − offset ≤ `thickness` lie on it; the
/// normal points to the side where more of the scene stands.
#[derive(Clone, Copy, Debug)]
pub struct Support {
    pub normal: Vector3<f64>,
    pub offset: f64,
    pub thickness: f64,
    /// Fraction of the scene's occupied cells (of `thickness`) on the plane.
    pub share: f64,
    /// An orthonormal basis of the plane (planar coordinates, footprints).
    basis: [Vector3<f64>; 2],
}

impl Support {
    /// The plane n·p = offset (n a unit normal pointing up), `thickness` thick.
    pub fn new(normal: Vector3<f64>, offset: f64, thickness: f64, share: f64) -> Support {
        let a = if normal[0].abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let u = normal.cross(&a).normalize();
        Support { normal, offset, thickness, share, basis: [u, normal.cross(&u)] }
    }

    /// Height of `p` above the plane.
    pub fn height(&self, p: [f32; 3]) -> f64 {
        self.normal.dot(&Vector3::from(f64s(p))) - self.offset
    }

    /// Coordinates of `p` in the plane.
    fn planar(&self, p: [f32; 3]) -> [f64; 2] {
        let q = Vector3::from(f64s(p));
        self.basis.map(|b| b.dot(&q))
    }

    /// Whether Gaussian `i` of `scene` lies in the footprint `hull` with its extent: its centre
    /// plus two standard deviations towards each edge's outside within half a plane thickness
    /// of the edge. An object's bottom passes (thin across its wall, which is an edge); a
    /// floor Gaussian whose centre falls just inside but which spreads out over the floor
    /// around does not.
    pub(crate) fn fits_inside(&self, hull: &[[f64; 2]], scene: &Scene, i: usize) -> bool {
        let [u, v] = self.basis;
        let q = self.planar(scene.means[i]);
        // Each edge: how far the centre lies beyond it (outward unit normal of a
        // counter-clockwise edge), and the outward normal in the world.
        let edges: Vec<(f64, Vector3<f64>)> = (0..hull.len())
            .filter_map(|k| {
                let (a, b) = (hull[k], hull[(k + 1) % hull.len()]);
                let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
                let out = [(b[1] - a[1]) / len, -(b[0] - a[0]) / len];
                (len > 0.0).then(|| ((q[0] - a[0]) * out[0] + (q[1] - a[1]) * out[1], u * out[0] + v * out[1]))
            })
            .collect();
        let tolerance = 0.5 * self.thickness;
        if edges.iter().any(|e| e.0 > tolerance) {
            return false;
        }
        let r = quat_to_mat(scene.quats[i]);
        let s = scene.scales[i].map(|x| x.exp() as f64);
        edges.iter().all(|(beyond, d)| {
            let var: f64 = (0..3)
                .map(|c| {
                    let col = r.col(c);
                    (s[c] * (col.x as f64 * d.x + col.y as f64 * d.y + col.z as f64 * d.z)).powi(2)
                })
                .sum();
            beyond + 2.0 * var.sqrt() <= tolerance
        })
    }

    /// Whether `p` lies in the plane's slab: from half a thickness below the plane to 1.5
    /// thicknesses above it (what stands higher is clustered into objects).
    pub(crate) fn in_slab(&self, p: [f32; 3]) -> bool {
        let h = self.height(p);
        h > -0.5 * self.thickness && h <= 1.5 * self.thickness
    }

    /// The footprint of an object standing on the plane: the convex hull, in the plane, of its
    /// opaque Gaussians (of `part`, indices into `scene`) above the slab and less than 3
    /// thicknesses up — its lowest band, whose outline is its base. None for fewer than 3.
    pub(crate) fn footprint(&self, scene: &Scene, part: &[usize], min_opacity: f32) -> Option<Vec<[f64; 2]>> {
        let band: Vec<[f64; 2]> = part
            .iter()
            .filter(|&&i| opaque(scene, i, min_opacity))
            .filter(|&&i| (1.5 * self.thickness..=3.0 * self.thickness).contains(&self.height(scene.means[i])))
            .map(|&i| self.planar(scene.means[i]))
            .collect();
        let hull = convex_hull(band);
        (hull.len() >= 3).then_some(hull)
    }

    /// The Gaussians of `part` (indices into `scene`) that make up the object(s) standing
    /// there: those above the slab, and those in the slab inside their footprint — the
    /// object's bottom, down to where it meets the plane, where the floor around it lies
    /// outside. None where fewer than 16 stand above the slab.
    pub fn object_gaussians(&self, scene: &Scene, part: &[usize], min_opacity: f32) -> Option<Vec<usize>> {
        let above = |i: usize| self.height(scene.means[i]) > 1.5 * self.thickness;
        let up: Vec<usize> = part.iter().copied().filter(|&i| above(i)).collect();
        if up.len() < 16 {
            return None;
        }
        let Some(hull) = self.footprint(scene, &up, min_opacity) else { return Some(up) };
        Some(
            part.iter()
                .copied()
                .filter(|&i| above(i) || (self.in_slab(scene.means[i]) && self.fits_inside(&hull, scene, i)))
                .collect(),
        )
    }
}

/// Convex hull of 2D points, counter-clockwise (Andrew's monotone chain); collinear points
/// are left out.
pub(crate) fn convex_hull(mut p: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        let points: Box<dyn Iterator<Item = &[f64; 2]>> =
            if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for &q in points {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0 {
                hull.pop();
            }
            hull.push(q);
        }
        hull.pop();
    }
    hull
}

/// [`support_plane`] of the scene's opaque means, `o.plane_spacings` median spacings thick.
pub fn find_support(scene: &Scene, o: &DiscoverOptions, progress: &mut dyn FnMut(&str)) -> Result<Support> {
    let pts: Vec<[f64; 3]> =
        (0..scene.len()).filter(|&i| opaque(scene, i, o.instance.min_opacity)).map(|i| f64s(scene.means[i])).collect();
    if pts.len() < 3 {
        anyhow::bail!("the scene has too few opaque Gaussians ({}) to search", pts.len());
    }
    let thickness = o.plane_spacings * median_spacing(&pts);
    let (coarse, _) = voxel_cells(&pts, thickness);
    let Some((mut n, mut d, on)) = support_plane(&coarse, thickness, o.instance.seed) else {
        anyhow::bail!("no support plane found");
    };
    // Up: the side of the plane with more of the rest.
    let above = pts.iter().filter(|p| n.dot(&Vector3::from(**p)) - d > thickness).count();
    let below = pts.iter().filter(|p| n.dot(&Vector3::from(**p)) - d < -thickness).count();
    if below > above {
        (n, d) = (-n, -d);
    }
    // The plane is as thick as its Gaussians spread about it (4 × their median distance),
    // between a tenth of the search's thickness and all of it: a flat floor cuts off no more
    // of what stands on it than it must.
    let mut h: Vec<f64> =
        pts.iter().map(|p| (n.dot(&Vector3::from(*p)) - d).abs()).filter(|&h| h <= thickness).collect();
    h.sort_by(f64::total_cmp);
    let spread = h.get(h.len() / 2).copied().unwrap_or(thickness);
    let thickness = (4.0 * spread).clamp(0.1 * thickness, thickness);
    progress(&format!(
        "support plane: normal [{:.3}, {:.3}, {:.3}], {} of {} occupied cells on it ({:.4} thick)",
        n[0],
        n[1],
        n[2],
        on,
        coarse.len(),
        thickness
    ));
    Ok(Support::new(n, d, thickness, on as f64 / coarse.len() as f64))
}
