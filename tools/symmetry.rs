//! Symmetries of the ground truth's objects, for the robustness study's symmetry-aware pose
//! error (as pose benchmarks judge symmetric objects: BOP's MSSD takes the least error over the
//! object's symmetries, Hodaň et al. 2020). A soccer ball turned a fifth of a turn about a
//! pentagon, or a square brick a quarter turn, is the same object: a registration that lands
//! there is right, and no picture can tell it from the ground truth's pose but by the lighting.
//!
//! The symmetries come from the meshes the scenes were rendered from (`instances.json`'s
//! `mesh`, `parts` and materials, in pybullet's `pybullet_data` folder), not from anything the
//! pipeline made: the textured surface is sampled (albedo from the texture, nearest texel, as
//! the renderer filtered it; or the part's constant albedo), and a rotation is a symmetry when
//! it maps the samples onto the surface, colours included, as closely as the samples lie on it.
use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use instgs_vk::math::tree;
use instgs_vk::register::{umeyama, Sim3};
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};

/// Surface samples of one object in its mesh's own frame (the frame `object_to_world` maps),
/// with what every symmetry test of it shares: the k-d trees of the samples (all, and per colour
/// class) and how closely the probes lie on the surface unmoved.
pub struct Surface {
    /// Where the candidate symmetries are judged against.
    points: Vec<[f64; 3]>,
    colours: Vec<[f64; 3]>,
    /// Other samples (another seed), moved by a candidate and looked up in `points`.
    probes: Vec<[f64; 3]>,
    probe_colours: Vec<[f64; 3]>,
    /// The samples' bounding-box diagonal.
    diameter: f64,
    tree: Tree3,
    /// Per colour class ([`colour_class`]): its samples' tree and their indices in `points`.
    classes: HashMap<usize, (Tree3, Vec<usize>)>,
    /// Twice the 99th-percentile distance from an unmoved probe to the nearest sample.
    far: f64,
    /// [`Surface::misfit`] of the identity.
    identity_misfit: (f64, f64),
}

type Tree3 = ImmutableKdTree<f64, u32, 3, 32>;

/// A colour's class for the colour-aware ICP: each channel in 8 levels.
fn colour_class(c: &[f64; 3]) -> usize {
    (0..3).map(|a| ((c[a] * 8.0) as usize).min(7) << (3 * a)).sum()
}

/// Two colours agree when no channel differs by more than this (0–1).
const COLOUR_AGREES: f64 = 0.15;
/// Samples of the surface (probes: a third of this).
const SAMPLES: usize = 60_000;

/// A triangle of a part: corners in the object's frame and the colour at a barycentric point.
struct Triangle {
    corners: [Vector3<f64>; 3],
    uv: Option<[[f64; 2]; 3]>,
    texture: Option<usize>,
    albedo: [f64; 3],
}

/// Samples the surface of a group of `instances.json` (its `parts`, or its `mesh` alone)
/// from the `pybullet_data` folder `meshes`.
pub fn load(group: &serde_json::Value, meshes: &Path) -> Result<Surface> {
    let name = group["name"].as_str().unwrap_or("?");
    let single = serde_json::json!([{ "mesh": group["mesh"], "material": {} }]);
    let parts = group["parts"].as_array().or(single.as_array()).context("no parts")?;
    let mut triangles = Vec::new();
    let mut textures: Vec<image::RgbImage> = Vec::new();
    for part in parts {
        let mesh = part["mesh"].as_str().with_context(|| format!("group {name:?}: a part without a mesh (--meshes needs mesh objects; judge objects made of splats, as tools/other-objects.sh makes, without it)"))?;
        let path = meshes.join(mesh);
        let (models, _) = tobj::load_obj(&path, &tobj::GPU_LOAD_OPTIONS)
            .with_context(|| format!("{}: cannot read the mesh", path.display()))?;
        let to_object = match part["part_to_object"].as_array() {
            Some(rows) => {
                let m: Vec<f64> =
                    rows.iter().flat_map(|r| r.as_array().into_iter().flatten()).filter_map(|v| v.as_f64()).collect();
                if rows.len() != 4 || m.len() != 16 {
                    bail!("group {name:?}: {mesh}: part_to_object is not a 4×4 matrix of numbers");
                }
                (Matrix3::from_fn(|r, c| m[4 * r + c]), Vector3::new(m[3], m[7], m[11]))
            }
            None => (Matrix3::identity(), Vector3::zeros()),
        };
        let material = &part["material"];
        let texture = match material["texture"].as_str() {
            Some(t) => {
                let file = path.parent().unwrap_or(meshes).join(t);
                let img = image::open(&file).with_context(|| format!("{}: cannot read the texture", file.display()))?;
                textures.push(img.to_rgb8());
                Some(textures.len() - 1)
            }
            None => None,
        };
        let albedo = match material["albedo"].as_array() {
            Some(a) => std::array::from_fn(|c| a.get(c).and_then(|v| v.as_f64()).unwrap_or(1.0)),
            None => [1.0; 3],
        };
        for model in &models {
            let m = &model.mesh;
            let vertices = m.positions.len() / 3;
            if !m.texcoords.is_empty() && m.texcoords.len() != 2 * vertices {
                bail!("{}: {} texture coordinates for {vertices} vertices", path.display(), m.texcoords.len() / 2);
            }
            if m.indices.iter().any(|&i| i as usize >= vertices) {
                bail!("{}: a face refers to a vertex past the {vertices} it has", path.display());
            }
            let p = |i: u32| {
                let i = i as usize * 3;
                let v = Vector3::new(m.positions[i] as f64, m.positions[i + 1] as f64, m.positions[i + 2] as f64);
                to_object.0 * v + to_object.1
            };
            let uv = |i: u32| [m.texcoords[i as usize * 2] as f64, m.texcoords[i as usize * 2 + 1] as f64];
            for f in m.indices.chunks_exact(3) {
                triangles.push(Triangle {
                    corners: [p(f[0]), p(f[1]), p(f[2])],
                    uv: (texture.is_some() && !m.texcoords.is_empty()).then(|| [uv(f[0]), uv(f[1]), uv(f[2])]),
                    texture,
                    albedo,
                });
            }
        }
    }
    if triangles.is_empty() {
        bail!("group {name:?}: its meshes hold no triangle");
    }
    let (points, colours) = sample(&triangles, &textures, SAMPLES, 1);
    let (probes, probe_colours) = sample(&triangles, &textures, SAMPLES / 3, 2);
    Ok(Surface::new(points, colours, probes, probe_colours))
}

/// `n` points uniformly on the triangles' area, with their colours.
fn sample(triangles: &[Triangle], textures: &[image::RgbImage], n: usize, seed: u64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut total = 0.0;
    for t in triangles {
        total += 0.5 * (t.corners[1] - t.corners[0]).cross(&(t.corners[2] - t.corners[0])).norm();
        cumulative.push(total);
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let (mut points, mut colours) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        let at = rng.random::<f64>() * total;
        let t = &triangles[cumulative.partition_point(|&c| c < at).min(triangles.len() - 1)];
        let (mut a, mut b) = (rng.random::<f64>(), rng.random::<f64>());
        if a + b > 1.0 {
            (a, b) = (1.0 - a, 1.0 - b);
        }
        let w = [1.0 - a - b, a, b];
        let p = t.corners[0] * w[0] + t.corners[1] * w[1] + t.corners[2] * w[2];
        let colour = match (t.uv, t.texture) {
            (Some(uv), Some(k)) => {
                let img = &textures[k];
                let u = w[0] * uv[0][0] + w[1] * uv[1][0] + w[2] * uv[2][0];
                let v = w[0] * uv[0][1] + w[1] * uv[1][1] + w[2] * uv[2][1];
                // OBJ texture coordinates: v up, wrapping.
                let x = ((u.rem_euclid(1.0) * img.width() as f64) as u32).min(img.width() - 1);
                let y = (((1.0 - v.rem_euclid(1.0)) * img.height() as f64) as u32).min(img.height() - 1);
                let px = img.get_pixel(x, y).0;
                std::array::from_fn(|c| px[c] as f64 / 255.0 * t.albedo[c])
            }
            _ => t.albedo,
        };
        points.push([p.x, p.y, p.z]);
        colours.push(colour);
    }
    (points, colours)
}

impl Surface {
    pub fn new(
        points: Vec<[f64; 3]>,
        colours: Vec<[f64; 3]>,
        probes: Vec<[f64; 3]>,
        probe_colours: Vec<[f64; 3]>,
    ) -> Surface {
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in &points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let diameter = (0..3).map(|a| (hi[a] - lo[a]).powi(2)).sum::<f64>().sqrt();
        let all = tree(&points);
        let mut members: HashMap<usize, Vec<usize>> = HashMap::new();
        for (i, c) in colours.iter().enumerate() {
            members.entry(colour_class(c)).or_default().push(i);
        }
        let classes = members
            .into_iter()
            .map(|(k, idx)| (k, (tree(&idx.iter().map(|&i| points[i]).collect::<Vec<_>>()), idx)))
            .collect();
        let mut d0: Vec<f64> = probes.iter().map(|p| all.nearest_one::<SquaredEuclidean>(p).distance.sqrt()).collect();
        d0.sort_by(f64::total_cmp);
        let far = 2.0 * d0.get((0.99 * d0.len().saturating_sub(1) as f64) as usize).copied().unwrap_or(0.0);
        let mut s = Surface {
            points,
            colours,
            probes,
            probe_colours,
            diameter,
            tree: all,
            classes,
            far,
            identity_misfit: (0.0, 0.0),
        };
        s.identity_misfit = s.misfit(&Sim3::identity());
        s
    }

    /// How far the probes moved by `x` lie off the surface: the share farther from every sample
    /// than `far`, and the share whose colour disagrees with the nearest sample's.
    fn misfit(&self, x: &Sim3) -> (f64, f64) {
        let (mut off, mut disagree) = (0usize, 0usize);
        for (p, c) in self.probes.iter().zip(&self.probe_colours) {
            let nn = self.tree.nearest_one::<SquaredEuclidean>(&x.apply(p));
            off += (nn.distance > self.far * self.far) as usize;
            disagree += (0..3).any(|a| (c[a] - self.colours[nn.item as usize][a]).abs() > COLOUR_AGREES) as usize;
        }
        let n = self.probes.len().max(1) as f64;
        (off as f64 / n, disagree as f64 / n)
    }

    /// The symmetry of the object nearest `d` (a similarity of the object's frame onto itself,
    /// e.g. the ground truth's pose against a registered one), or None: a rigid motion refined
    /// from `d` by ICP in which each probe pairs with the nearest sample of its own colour
    /// class, kept when it maps the probes onto the surface as well as the identity does — no
    /// more than 0.5 % of them farther from every sample than twice the identity's 99th
    /// percentile distance, and no more than 1 % more of them off colour. The test is strict:
    /// a mug turned 2° about its axis (the handle moved) is no symmetry of it.
    pub fn nearest_symmetry(&self, d: &Sim3) -> Option<Sim3> {
        let step = (self.probes.len() / 8000).max(1);
        let probes: Vec<usize> = (0..self.probes.len()).step_by(step).collect();
        // Rigid, moving the probes' centroid where `d` does.
        let n = self.probes.len() as f64;
        let c = self.probes.iter().fold(Vector3::zeros(), |a, p| a + Vector3::from(*p)) / n;
        let at = Vector3::from(d.apply(&[c.x, c.y, c.z]));
        let mut x = Sim3 { rotation: d.rotation, scale: 1.0, translation: at - d.rotation * c };
        for _ in 0..150 {
            let (mut from, mut to) = (Vec::with_capacity(probes.len()), Vec::with_capacity(probes.len()));
            for &i in &probes {
                let q = x.apply(&self.probes[i]);
                let j = match self.classes.get(&colour_class(&self.probe_colours[i])) {
                    Some((t, idx)) => idx[t.nearest_one::<SquaredEuclidean>(&q).item as usize],
                    None => self.tree.nearest_one::<SquaredEuclidean>(&q).item as usize,
                };
                from.push(self.probes[i]);
                to.push(self.points[j]);
            }
            let next = umeyama(&from, &to, false)?;
            let change =
                (next.rotation - x.rotation).norm() + (next.translation - x.translation).norm() / self.diameter;
            x = next;
            if change < 1e-9 {
                break;
            }
        }
        let (off0, colour0) = self.identity_misfit;
        let (off, colour) = self.misfit(&x);
        (off <= off0 + 0.005 && colour <= colour0 + 0.01).then_some(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn turn(axis: Vector3<f64>, deg: f64) -> Sim3 {
        let r = nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), deg.to_radians());
        Sim3 { rotation: *r.matrix(), ..Sim3::identity() }
    }

    /// A box 2 × 2 × 1 (square about z) whose four side faces are coloured red, white, red,
    /// white: its symmetries are the half turns about z (the quarter turns swap the colours)
    /// and the half turns about x and y.
    fn striped_box(n: usize, seed: u64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let (mut p, mut c) = (Vec::new(), Vec::new());
        while p.len() < n {
            let (u, v) = (rng.random::<f64>() * 2.0 - 1.0, rng.random::<f64>() * 2.0 - 1.0);
            // Faces by area: top and bottom 4 each, each side 2.
            let face = rng.random_range(0..16);
            let (q, col) = match face {
                0..4 => ([u, v, 0.5], [0.5, 0.5, 0.5]),
                4..8 => ([u, v, -0.5], [0.5, 0.5, 0.5]),
                8..10 => ([1.0, u, 0.5 * v], [1.0, 0.0, 0.0]),
                10..12 => ([-1.0, u, 0.5 * v], [1.0, 0.0, 0.0]),
                12..14 => ([u, 1.0, 0.5 * v], [1.0, 1.0, 1.0]),
                _ => ([u, -1.0, 0.5 * v], [1.0, 1.0, 1.0]),
            };
            p.push(q);
            c.push(col);
        }
        (p, c)
    }

    #[test]
    fn a_turn_near_a_symmetry_of_shape_and_colour_refines_onto_it_and_others_are_none() {
        let (p, c) = striped_box(20_000, 1);
        let (q, qc) = striped_box(5_000, 2);
        let s = Surface::new(p, c, q, qc);
        let z = Vector3::z();
        // 3° off the half turn about z, shifted a little: refined onto the half turn.
        let near = Sim3 { translation: Vector3::new(0.03, -0.02, 0.01), ..turn(Vector3::new(0.1, 0.0, 1.0), 183.0) };
        let found = s.nearest_symmetry(&near).expect("the half turn about z");
        assert!(found.rotation_error_deg(&turn(z, 180.0)) < 0.3, "{found:?}");
        assert!(found.translation.norm() < 0.01, "{found:?}");
        let flip = s.nearest_symmetry(&turn(Vector3::x(), 178.0)).expect("the half turn about x");
        assert!(flip.rotation_error_deg(&turn(Vector3::x(), 180.0)) < 0.3);
        // The shape's quarter turn swaps red and white, and 45° is none of the shape's: no
        // symmetry near either (ICP may slide on to one further away).
        for deg in [90.0, 45.0] {
            let start = turn(z, deg);
            assert!(s.nearest_symmetry(&start).is_none_or(|x| x.rotation_error_deg(&start) > 40.0), "{deg}°");
        }
        // The identity is one.
        assert!(s.nearest_symmetry(&turn(z, 1.0)).is_some_and(|x| x.rotation_error_deg(&Sim3::identity()) < 0.3));
    }
}
