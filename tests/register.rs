//! Registration and template initialisation on point clouds with known transforms: FPFH
//! invariance under similarities, Umeyama, RANSAC + ICP with noise, outliers, partial overlap
//! and scale, the farthest-point sampler, and `instantiate` on a scene built from a known
//! template. CPU only.
mod common;

use common::*;
use glam::Vec3;
use instgs_vk::dataset::masks::InstanceGroup;
use instgs_vk::instancing::options::{InstanceOptions, TemplateInit};
use instgs_vk::instancing::template::instantiate;
use instgs_vk::register::{
    farthest_point_sample, fpfh, normals, register, support_plane, umeyama, voxel_downsample, RegisterOptions, Sim3,
};
use nalgebra::{Rotation3, Vector3};

/// Surface samples of an asymmetric object about 0.8 units across: an ellipsoid body, a head
/// sphere and a cylindrical handle on one side.
fn object(rng: &mut Rng, n: usize) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    while out.len() < n {
        let d = Vector3::new(rng.normal() as f64, rng.normal() as f64, rng.normal() as f64).normalize();
        let p = match out.len() % 4 {
            0 | 1 => Vector3::new(0.3 * d.x, 0.2 * d.y, 0.15 * d.z),
            2 => Vector3::new(0.25, 0.0, 0.2) + d * 0.1,
            _ => {
                let a = rng.range(0.0, std::f32::consts::TAU) as f64;
                Vector3::new(-0.3 - rng.range(0.0, 0.2) as f64, 0.04 * a.cos() + 0.05, 0.04 * a.sin())
            }
        };
        out.push([p.x, p.y, p.z]);
    }
    out
}

fn random_sim3(rng: &mut Rng, scale: f64) -> Sim3 {
    let axis = Vector3::new(rng.normal() as f64, rng.normal() as f64, rng.normal() as f64).normalize();
    let angle = rng.range(0.3, 3.1) as f64;
    Sim3 {
        rotation: *Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle).matrix(),
        scale,
        translation: Vector3::new(
            rng.range(-2.0, 2.0) as f64,
            rng.range(-2.0, 2.0) as f64,
            rng.range(-1.0, 1.0) as f64,
        ),
    }
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
}

#[test]
fn fpfh_is_invariant_under_similarities() {
    let mut rng = Rng::new(1);
    let pts = voxel_downsample(&object(&mut rng, 6000), 0.03);
    let r = 0.03;
    let n = normals(&pts, 2.0 * r, 30);
    let f = fpfh(&pts, &n, 5.0 * r, 100);
    for s in [1.0, 1.7] {
        let x = random_sim3(&mut rng, s);
        let moved: Vec<[f64; 3]> = pts.iter().map(|p| x.apply(p)).collect();
        let nm = normals(&moved, 2.0 * r * s, 30);
        let fm = fpfh(&moved, &nm, 5.0 * r * s, 100);
        // Normals turn with the cloud (orientation included) ...
        let turned =
            n.iter().zip(&nm).filter(|(a, b)| (x.rotation * Vector3::from(**a) - Vector3::from(**b)).norm() < 1e-6);
        assert!(turned.count() as f64 >= 0.99 * pts.len() as f64);
        // ... and descriptors stay put (a pair on a bin edge or at the radius may move).
        let same = f.iter().zip(&fm).filter(|(a, b)| a.iter().zip(b.iter()).all(|(u, v)| (u - v).abs() < 1e-6)).count();
        assert!(same as f64 >= 0.97 * pts.len() as f64, "scale {s}: {same} of {} descriptors equal", pts.len());
        // Descriptors are informative: most points' nearest descriptor in the moved cloud is its own.
        let matches = instgs_vk::register::mutual_matches(&f, &fm);
        let right = matches.iter().filter(|(i, j)| i == j).count();
        assert!(right as f64 >= 0.8 * matches.len() as f64, "{right} of {} mutual matches right", matches.len());
    }
}

#[test]
fn umeyama_recovers_exact_similarities() {
    let mut rng = Rng::new(2);
    let src = object(&mut rng, 50);
    for scale in [1.0, 0.6, 2.5] {
        let x = random_sim3(&mut rng, scale);
        let dst: Vec<[f64; 3]> = src.iter().map(|p| x.apply(p)).collect();
        let y = umeyama(&src, &dst, true).unwrap();
        assert!(y.rotation_error_deg(&x) < 1e-6);
        assert!((y.scale - scale).abs() < 1e-9 && (y.translation - x.translation).norm() < 1e-9);
        assert!((y.rotation.determinant() - 1.0).abs() < 1e-9);
        let rigid = umeyama(&src, &dst, false).unwrap();
        assert_eq!(rigid.scale, 1.0);
        if scale == 1.0 {
            assert!(rigid.rotation_error_deg(&x) < 1e-6);
        }
    }
    assert!(umeyama(&src[..2], &src[..2], true).is_none());
    let line: Vec<[f64; 3]> = (0..5).map(|_| [1.0, 1.0, 1.0]).collect();
    assert!(umeyama(&line, &line, true).is_none(), "degenerate source");
}

#[test]
fn ransac_and_icp_recover_known_transforms_under_noise_outliers_and_scale() {
    let mut rng = Rng::new(3);
    for case in 0..4 {
        let target = object(&mut rng, 8000);
        let scale = [1.0, 1.04, 0.95, 1.0][case];
        let truth = random_sim3(&mut rng, scale);
        // source = truth⁻¹(target-shaped object), resampled, with noise (0.5 % of the size),
        // 10 % outliers, and (cases 2–3) a quarter of the object missing.
        let inv = truth.inverse();
        let mut source: Vec<[f64; 3]> = object(&mut rng, 8000)
            .into_iter()
            .filter(|p| case < 2 || p[1] > -0.12)
            .map(|p| {
                let q = inv.apply(&p);
                q.map(|c| c + 0.004 * rng.normal() as f64)
            })
            .collect();
        let centre = inv.apply(&[0.0; 3]);
        for _ in 0..source.len() / 10 {
            let o = [0; 3].map(|_| rng.range(-0.5, 0.5) as f64 / scale);
            source.push([centre[0] + o[0], centre[1] + o[1], centre[2] + o[2]]);
        }
        let o = RegisterOptions { seed: case as u64, ..RegisterOptions::for_size(0.8) };
        let r = register(&source, &target, &o).unwrap();
        let rot = r.transform.rotation_error_deg(&truth);
        let t = dist(r.transform.apply(&centre), truth.apply(&centre));
        assert!(rot < 1.0, "case {case}: rotation error {rot}°");
        assert!(t < 0.008, "case {case}: centre displaced by {t} (1 % of the size)");
        assert!((r.transform.scale / scale - 1.0).abs() < 0.01, "case {case}: scale {} vs {scale}", r.transform.scale);
        assert!(r.fitness > 0.6, "case {case}: fitness {}", r.fitness);
        // Deterministic for a seed.
        let again = register(&source, &target, &o).unwrap();
        assert_eq!(again.transform, r.transform);
    }
}

#[test]
fn register_refuses_clouds_too_small() {
    let pts = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
    let e = register(&pts, &pts, &RegisterOptions::for_size(1.0)).unwrap_err();
    assert!(format!("{e:#}").contains("too few points"), "{e:#}");
}

#[test]
fn farthest_point_sampling_spreads_and_is_deterministic() {
    let mut rng = Rng::new(5);
    // A dense cluster plus a sparse shell: FPS must reach the shell, a random pick would not.
    let mut pts: Vec<[f64; 3]> = (0..5000).map(|_| [0; 3].map(|_| 0.05 * rng.normal() as f64)).collect();
    for _ in 0..50 {
        let d = Vector3::new(rng.normal() as f64, rng.normal() as f64, rng.normal() as f64).normalize();
        pts.push([d.x, d.y, d.z]);
    }
    let pick = farthest_point_sample(&pts, 200);
    assert_eq!(pick.len(), 200);
    let mut sorted = pick.clone();
    sorted.sort();
    sorted.dedup();
    assert_eq!(sorted.len(), 200, "indices unique");
    assert_eq!(pick, farthest_point_sample(&pts, 200));
    assert!(pick.iter().filter(|&&i| i >= 5000).count() == 50, "every shell point is sampled");
    // Covering radius: every point within the smallest distance between samples' spacing.
    let cover = |idx: &[usize]| {
        pts.iter().map(|p| idx.iter().map(|&i| dist(*p, pts[i])).fold(f64::INFINITY, f64::min)).fold(0.0, f64::max)
    };
    let stride: Vec<usize> = (0..200).map(|i| i * pts.len() / 200).collect();
    assert!(cover(&pick) < 0.5 * cover(&stride));
    assert_eq!(farthest_point_sample(&pts[..10], 20).len(), 10);
    assert!(farthest_point_sample(&pts, 0).is_empty());
}

/// A plain scene made of a known object's Gaussians placed as instances (each its own
/// resampling with a little noise), plus background Gaussians; labels known.
fn plain_scene(rng: &mut Rng, truths: &[Sim3]) -> (instgs_vk::model::scene::Scene, Vec<u32>) {
    let mut s = instgs_vk::model::scene::Scene { sh_degree: 1, ..Default::default() };
    let mut labels = Vec::new();
    let mut push = |s: &mut instgs_vk::model::scene::Scene, p: [f64; 3], dc: [f32; 3], label: u32| {
        s.means.push(p.map(|c| c as f32));
        s.scales.push([-4.0; 3]);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacities.push(2.0);
        s.sh.extend_from_slice(&dc);
        s.sh.extend_from_slice(&[0.1; 9]);
        labels.push(label);
    };
    for (k, x) in truths.iter().enumerate() {
        for p in object(rng, 4000 + 500 * k) {
            let dc = [p[0] as f32, p[1] as f32 + 0.1 * k as f32, p[2] as f32];
            let q = x.apply(&p).map(|c| c + 0.002 * rng.normal() as f64);
            push(&mut s, q, dc, k as u32 + 1);
        }
    }
    for _ in 0..3000 {
        push(&mut s, [rng.range(-4.0, 4.0) as f64, rng.range(-4.0, 4.0) as f64, -1.0], [0.0; 3], 0);
    }
    (s, labels)
}

#[test]
fn instantiate_recovers_instances_and_builds_templates() {
    let mut rng = Rng::new(6);
    let truths: Vec<Sim3> = (0..3)
        .map(|k| Sim3 { translation: Vector3::new(2.0 * k as f64 - 2.0, 0.5, 0.0), ..random_sim3(&mut rng, 1.0) })
        .collect();
    let (scene, labels) = plain_scene(&mut rng, &truths);
    let groups = vec![InstanceGroup { name: "blob".into(), ids: vec![1, 2, 3] }];
    for init in [TemplateInit::Merge, TemplateInit::Max, TemplateInit::First] {
        let o = InstanceOptions { init, ..Default::default() };
        let (inst, reports) =
            instantiate(&scene, &labels, &groups, &o, None, |_| {}).map(|m| (m.scene, m.reports)).unwrap();
        assert_eq!(inst.background.len(), 3000);
        let g = &inst.groups[0];
        assert_eq!(g.instances.iter().map(|i| i.id.as_str()).collect::<Vec<_>>(), ["1", "2", "3"]);
        let expect = match init {
            TemplateInit::Merge => 4500,
            TemplateInit::Max => 5000,
            TemplateInit::First => 4000,
        };
        assert_eq!(g.template.len(), expect, "{init:?}");
        for (k, r) in reports.iter().enumerate() {
            // The reference is the largest instance (3, 5000 Gaussians); relative = instance k
            // world → the reference's world = truth₂ ∘ truthₖ⁻¹.
            assert_eq!(r.reference, 3);
            assert_eq!(r.status.name(), if k == 2 { "reference" } else { "accepted" }, "{init:?} {k}");
            let truth = truths[2].compose(&truths[k].inverse());
            let c = truths[k].apply(&[0.0; 3]);
            assert!(r.relative.rotation_error_deg(&truth) < 1.0, "{init:?} {k}");
            assert!(dist(r.relative.apply(&c), truth.apply(&c)) < 0.008, "{init:?} {k}");
        }
        // Template → world lands every instance on its own Gaussians: offsets are small (≤ one
        // registration voxel) and the expanded instances sit on the original surfaces.
        assert!(g.offsets.d_means.iter().all(|d| Vec3::from(*d).length() <= 0.05));
        let expanded = inst.expand();
        let orig: Vec<[f64; 3]> = scene.means.iter().map(|m| m.map(|c| c as f64)).collect();
        let tree = instgs_vk::math::tree(&orig);
        let mean_err = expanded.means[3000..]
            .iter()
            .map(|m| tree.nearest_one::<kiddo::SquaredEuclidean>(&m.map(|c| c as f64)).distance.sqrt() as f32)
            .sum::<f32>()
            / (expanded.len() - 3000) as f32;
        assert!(mean_err < 0.002, "{init:?}: expanded means {mean_err} from the originals");
        match init {
            TemplateInit::Merge => {
                assert!(g.template.opacities.iter().all(|&o| (o - (0.1f32 / 0.9).ln()).abs() < 1e-6));
                assert!(g.template.quats.iter().all(|q| *q == [1.0, 0.0, 0.0, 0.0]));
                assert!(g.template.sh.chunks(12).all(|c| c[3..].iter().all(|&v| v == 0.0)), "shN reset");
            }
            _ => assert!(g.template.opacities.iter().all(|&o| o == 2.0), "parameters kept"),
        }
    }
}

#[test]
fn instantiate_reports_bad_labels() {
    let mut rng = Rng::new(7);
    let truths = vec![Sim3::identity(), Sim3 { translation: Vector3::new(2.0, 0.0, 0.0), ..Sim3::identity() }];
    let (scene, labels) = plain_scene(&mut rng, &truths);
    let o = InstanceOptions::default();
    let groups = vec![InstanceGroup { name: "blob".into(), ids: vec![1, 2, 5] }];
    let e = instantiate(&scene, &labels, &groups, &o, None, |_| {}).unwrap_err();
    assert!(format!("{e:#}").contains("instance 5 claims no Gaussian"), "{e:#}");
    let groups = vec![InstanceGroup { name: "blob".into(), ids: vec![1] }];
    let e = instantiate(&scene, &labels, &groups, &o, None, |_| {}).unwrap_err();
    assert!(format!("{e:#}").contains("labels [2] are not instances"), "{e:#}");
    let e = instantiate(&scene, &labels[1..], &groups, &o, None, |_| {}).unwrap_err();
    assert!(format!("{e:#}").contains("labels for"), "{e:#}");
    // A group of one instance keeps its Gaussians as the template.
    let groups =
        vec![InstanceGroup { name: "a".into(), ids: vec![1] }, InstanceGroup { name: "b".into(), ids: vec![2] }];
    let mut lines = Vec::new();
    let (inst, _) = instantiate(&scene, &labels, &groups, &o, None, |l| lines.push(l.to_string()))
        .map(|m| (m.scene, m.reports))
        .unwrap();
    assert_eq!(inst.groups[0].template.len(), 4000);
    assert!(lines.iter().any(|l| l.contains("has one instance")));
}

#[test]
fn point_trees_take_clouds_with_many_equal_coordinates() {
    // A flat floor (z = 0 exactly) on a quantised grid (kiddo 4 refused it).
    let pts: Vec<[f64; 3]> = (0..4000).map(|i| [(i % 50) as f64 * 0.01, (i / 50) as f64 * 0.01, 0.0]).collect();
    let t = instgs_vk::math::tree(&pts);
    let mut rng = Rng::new(8);
    for _ in 0..200 {
        let q = [rng.range(0.0, 0.5) as f64, rng.range(0.0, 0.8) as f64, rng.range(-0.1, 0.1) as f64];
        let got = t.nearest_one::<kiddo::SquaredEuclidean>(&q).item as usize;
        let best = pts.iter().map(|p| dist(*p, q)).fold(f64::INFINITY, f64::min);
        assert!((dist(pts[got], q) - best).abs() < 1e-8);
    }
}

#[test]
fn a_ball_is_flagged_shape_ambiguous_and_colours_are_checked() {
    // A ball fits in any orientation: registration says so (and then lets colour decide).
    let mut rng = Rng::new(9);
    let ball = |rng: &mut Rng| -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        (0..4000)
            .map(|_| {
                let d = Vector3::new(rng.normal() as f64, rng.normal() as f64, rng.normal() as f64).normalize();
                ([0.3 * d.x, 0.3 * d.y, 0.3 * d.z], [0.5 + 0.4 * d.x, 0.5, 0.5])
            })
            .unzip()
    };
    let (target, target_rgb) = ball(&mut rng);
    let (source, source_rgb) = ball(&mut rng);
    let o = RegisterOptions::for_size(0.6);
    let r = instgs_vk::register::register_coloured(&source, &source_rgb, &target, &target_rgb, &o).unwrap();
    assert!(r.shape_ambiguous);
    assert!((r.transform.scale - 1.0).abs() < 0.02 && r.transform.translation.norm() < 0.01, "{:?}", r.transform);
    let shaped = register(&object(&mut rng, 6000), &object(&mut rng, 6000), &o).unwrap();
    assert!(!shaped.shape_ambiguous, "the asymmetric object is not");
    let e = instgs_vk::register::register_coloured(&source, &source_rgb[1..], &target, &target_rgb, &o).unwrap_err();
    assert!(format!("{e:#}").contains("colours for"), "{e:#}");
}

#[test]
fn background_pruning_keeps_instances_and_the_most_significant_background() {
    let mut rng = Rng::new(8);
    let scene = random_scene(&mut rng, 40, 1);
    let labels: Vec<u32> = (0..40).map(|i| if i % 4 == 0 { 1 + (i % 3) as u32 } else { 0 }).collect();
    let significance: Vec<f32> = (0..40).map(|i| ((i * 17) % 40) as f32).collect();
    let (pruned, kept_labels, dropped) =
        instgs_vk::instancing::template::prune_background(&scene, &labels, &significance, 0.25).unwrap();
    let bg: Vec<usize> = (0..40).filter(|&i| labels[i] == 0).collect();
    assert_eq!(bg.len(), 30);
    assert_eq!(dropped, 30 - 8, "⌈0.25 × 30⌉ = 8 background Gaussians stay");
    let mut by_sig = bg.clone();
    by_sig.sort_by(|&a, &b| significance[b].total_cmp(&significance[a]));
    let mut want: Vec<usize> = (0..40).filter(|&i| labels[i] != 0).chain(by_sig[..8].iter().copied()).collect();
    want.sort();
    assert_eq!(pruned.len(), want.len());
    for (j, &i) in want.iter().enumerate() {
        assert_eq!(pruned.means[j], scene.means[i], "order kept");
        assert_eq!(kept_labels[j], labels[i]);
    }
    let (all, _, none) =
        instgs_vk::instancing::template::prune_background(&scene, &labels, &significance, 1.0).unwrap();
    assert_eq!((all.len(), none), (40, 0));
    assert!(instgs_vk::instancing::template::prune_background(&scene, &labels, &significance, 0.0).is_err());
}

/// `d` applied about the point `c`, after `x`.
fn about(c: [f64; 3], d: Sim3, x: Sim3) -> Sim3 {
    d.about(&Vector3::from(c)).compose(&x)
}

#[test]
fn degenerate_poses_are_refused_by_the_geometric_checks() {
    use instgs_vk::instancing::options::Acceptance;
    use instgs_vk::instancing::pose::PoseCheck;
    let mut rng = Rng::new(11);
    let reference = object(&mut rng, 4000);
    let truth = random_sim3(&mut rng, 1.0);
    let instance: Vec<[f64; 3]> = object(&mut rng, 4000).iter().map(|p| truth.apply(p)).collect();
    let x = truth.inverse();
    let voxel = 0.8 * 0.04;
    let a = Acceptance::default();
    let check = |y: &Sim3| PoseCheck::measure(&instance, &reference, y, voxel).failure(y, &a, false);
    assert_eq!(check(&x), None, "the true pose passes: {:?}", PoseCheck::measure(&instance, &reference, &x, voxel));
    let c = instgs_vk::register::centroid(&reference);
    let c = [c.x, c.y, c.z];
    // Collapsed onto the reference's centre (one-sided fitness would read ~1).
    let collapsed = about(c, Sim3 { scale: 0.02, ..Sim3::identity() }, x);
    assert!(check(&collapsed).is_some_and(|w| w.contains("scale")), "{:?}", check(&collapsed));
    // Shrunk by half: still inside the reference, fitness one way only.
    let shrunk = about(c, Sim3 { scale: 0.5, ..Sim3::identity() }, x);
    assert!(check(&shrunk).is_some_and(|w| w.contains("scale")), "{:?}", check(&shrunk));
    // Mirrored through a plane (det −1).
    let mut m = Sim3::identity();
    m.rotation[(2, 2)] = -1.0;
    let mirrored = about(c, m, x);
    assert!(check(&mirrored).is_some_and(|w| w.contains("mirror")), "{:?}", check(&mirrored));
    // Turned a quarter about each axis, and flipped upside down: the clouds no longer cover
    // each other.
    for (axis, angle) in [(0, 90.0), (1, 90.0), (2, 90.0), (0, 180.0)] {
        let r = Rotation3::from_axis_angle(&Vector3::ith_axis(axis), f64::to_radians(angle));
        let turned = about(c, Sim3 { rotation: *r.matrix(), ..Sim3::identity() }, x);
        assert!(check(&turned).is_some_and(|w| w.contains("fitness")), "axis {axis} {angle}°: {:?}", check(&turned));
    }
    // A rigid run refuses any scale but 1; not a similarity at all is refused.
    let rigid_check = PoseCheck::measure(&instance, &reference, &x, voxel);
    assert!(rigid_check.failure(&Sim3 { scale: 1.1, ..x }, &a, true).is_some());
    let mut sheared = x;
    sheared.rotation[(0, 1)] += 0.3;
    assert!(check(&sheared).is_some_and(|w| w.contains("not a similarity")), "{:?}", check(&sheared));
}

#[test]
fn the_support_plane_is_found_tilted_and_thin() {
    let mut rng = Rng::new(3);
    let n = Vector3::new(0.1, -0.2, 1.0).normalize();
    let (u, v) = (n.cross(&Vector3::x()).normalize(), n.cross(&n.cross(&Vector3::x())).normalize());
    let mut r = |lo: f64, hi: f64| rng.range(lo as f32, hi as f32) as f64;
    let mut pts: Vec<[f64; 3]> = (0..3000)
        .map(|_| {
            let p = u * r(-2.0, 2.0) + v * r(-2.0, 2.0) + n * (0.5 + r(-0.002, 0.002));
            [p.x, p.y, p.z]
        })
        .collect();
    // Two blobs above it.
    for c in [u * 0.5 + n * 0.8, -u * 0.7 + n * 0.9] {
        for _ in 0..500 {
            let p = c + Vector3::new(r(-0.1, 0.1), r(-0.1, 0.1), r(-0.1, 0.1));
            pts.push([p.x, p.y, p.z]);
        }
    }
    let (m, d, on) = support_plane(&pts, 0.01, 0).unwrap();
    assert!(m.dot(&n).abs() > 0.9999, "normal {m:?}");
    assert!((d * m.dot(&n).signum() - 0.5).abs() < 1e-3, "offset {d}");
    assert!((2990..=3000).contains(&on), "{on} on the plane");
}
