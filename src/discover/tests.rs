//! Clusters, the support plane and the search on synthetic scenes.
use super::copies::edges_fit;
use super::support::convex_hull;
use super::*;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

#[test]
fn clusters_split_at_gaps_wider_than_the_link() {
    let line = |x0: f64, n: usize| (0..n).map(move |i| [x0 + 0.01 * i as f64, 0.0, 0.0]);
    let pts: Vec<[f64; 3]> = line(0.0, 50).chain(line(1.0, 30)).chain(line(0.6, 20)).collect();
    let c = clusters(&pts, 0.015);
    let sizes: Vec<usize> = c.iter().map(|c| c.len()).collect();
    assert_eq!(sizes, [50, 30, 20]);
    assert_eq!(clusters(&pts, 0.5).len(), 1);
}

#[test]
fn the_convex_hull_holds_every_point_and_nothing_outside() {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
    let pts: Vec<[f64; 2]> = (0..200).map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-0.5..0.5)]).collect();
    let hull = convex_hull(pts.clone());
    assert!(hull.len() >= 4 && hull.len() < 40, "{} corners", hull.len());
    let inside = |q: [f64; 2]| {
        (0..hull.len()).all(|k| {
            let (a, b) = (hull[k], hull[(k + 1) % hull.len()]);
            (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0]) >= 0.0
        })
    };
    assert!(pts.iter().all(|&q| inside(q)), "counter-clockwise, every point inside");
    assert!(!inside([1.01, 0.0]) && !inside([0.0, -0.51]));
    assert!(convex_hull(vec![[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]).len() < 3, "collinear: no area");
}

#[test]
fn an_object_keeps_its_bottom_and_leaves_the_floor_around_it() {
    // A floor at z = 0 (flat Gaussians 5 cm wide within ±4 mm; some centred just inside
    // the box's base, spreading out) and a 0.2 × 0.2 × 0.3 box standing on it, its walls
    // (Gaussians flat across them) down to the floor.
    let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
    let mut scene = Scene::default();
    let mut truth = Vec::new();
    let mut push = |scene: &mut Scene, p: [f64; 3], scales: [f32; 3], object: bool| {
        scene.means.push(p.map(|c| c as f32));
        scene.scales.push(scales);
        scene.quats.push([1.0, 0.0, 0.0, 0.0]);
        scene.opacities.push(3.0);
        scene.sh.extend([0.5; 3]);
        truth.push(object);
    };
    for _ in 0..3000 {
        let p: [f64; 3] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-0.004..0.004)];
        if p[0].abs() > 0.1 || p[1].abs() > 0.1 {
            push(&mut scene, p, [-3.0, -3.0, -8.0], false);
        }
    }
    for k in 0..20 {
        let a = -0.09 + 0.009 * k as f64;
        push(&mut scene, [0.095, a, 0.0], [-3.0, -3.0, -8.0], false);
        push(&mut scene, [a, -0.095, 0.0], [-3.0, -3.0, -8.0], false);
    }
    for _ in 0..2000 {
        let (a, z) = (rng.random_range(-0.1..0.1), rng.random_range(0.0..0.3));
        let (p, scales) = match rng.random_range(0..4) {
            0 => ([0.1, a, z], [-8.0, -5.0, -5.0]),
            1 => ([-0.1, a, z], [-8.0, -5.0, -5.0]),
            2 => ([a, 0.1, z], [-5.0, -8.0, -5.0]),
            _ => ([a, -0.1, z], [-5.0, -8.0, -5.0]),
        };
        push(&mut scene, p, scales, true);
    }
    let support = Support::new(Vector3::z(), 0.0, 0.02, 0.5);
    // The part: the box and the floor within 5 cm of it.
    let part: Vec<usize> =
        (0..scene.len()).filter(|&i| scene.means[i][0].abs() < 0.15 && scene.means[i][1].abs() < 0.15).collect();
    let kept = support.object_gaussians(&scene, &part, 0.5).unwrap();
    let box_all = truth.iter().filter(|&&t| t).count();
    assert!(kept.iter().all(|&i| truth[i]), "no floor Gaussian kept");
    assert!(kept.len() * 100 >= box_all * 98, "{} of {box_all} box Gaussians kept", kept.len());
    assert!(part.iter().any(|&i| !truth[i]), "the part holds floor");
}

#[test]
fn edges_fit_needs_one_scale_in_range() {
    let a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
    let b = a.map(|p| p.map(|c| 1.1 * c + 3.0));
    assert!(edges_fit(&a, &b, 0.9, Some((0.8, 1.25))));
    let far = a.map(|p| p.map(|c| 1.3 * c));
    assert!(!edges_fit(&a, &far, 0.9, None), "rigid: scale 1.3 is refused");
    let mut c = b;
    c[2][1] *= 1.5;
    assert!(!edges_fit(&a, &c, 0.9, Some((0.8, 1.25))), "no common scale");
}

#[test]
fn groups_of_specks_are_dropped_and_reported() {
    // Two groups standing on z = 0: boxes of side 0.3 (two members) and specks of side 0.05
    // (two members), and a lone box; the specks fall below a quarter of the boxes' size.
    let mut scene = Scene::default();
    let cube = |scene: &mut Scene, centre: [f64; 3], side: f64| -> Vec<usize> {
        let first = scene.len();
        for i in 0..216 {
            let (x, y, z) = ((i % 6) as f64 / 5.0, ((i / 6) % 6) as f64 / 5.0, (i / 36) as f64 / 5.0);
            let p = [centre[0] + (x - 0.5) * side, centre[1] + (y - 0.5) * side, 0.05 + z * side];
            scene.means.push(p.map(|c| c as f32));
            scene.scales.push([(0.1 * side as f32).ln(); 3]);
            scene.quats.push([1.0, 0.0, 0.0, 0.0]);
            scene.opacities.push(3.0);
            scene.sh.extend([0.5; 3]);
        }
        (first..scene.len()).collect()
    };
    let member = |id: u32, gaussians: Vec<usize>| Member { id, gaussians, relative: Sim3::identity(), report: None };
    let mut groups = vec![
        FoundGroup { name: "boxes".into(), members: vec![member(1, cube(&mut scene, [0.0, 0.0, 0.0], 0.3))] },
        FoundGroup { name: "specks".into(), members: vec![member(3, cube(&mut scene, [1.0, 0.0, 0.0], 0.05))] },
        FoundGroup { name: "lone".into(), members: vec![member(5, cube(&mut scene, [2.0, 0.0, 0.0], 0.02))] },
    ];
    groups[0].members.push(member(2, cube(&mut scene, [0.0, 1.0, 0.0], 0.3)));
    groups[1].members.push(member(4, cube(&mut scene, [1.0, 1.0, 0.0], 0.05)));
    let support = Support::new(Vector3::z(), 0.0, 0.01, 0.5);
    let mut refused = Vec::new();
    drop_specks(&scene, &support, &mut groups, &DiscoverOptions::default(), &mut refused, &mut |_| {});
    let names: Vec<&str> = groups.iter().map(|g| g.name.as_str()).collect();
    assert_eq!(names, ["boxes", "lone"], "single members are left to the caller: {refused:?}");
    assert_eq!(refused.len(), 1);
    assert!(
        refused[0].starts_with("specks: 2 members") && refused[0].contains("a speck, not an object"),
        "{refused:?}"
    );
}
