//! `instgs_vk::discover` on a synthetic scene: four copies of a shared trained splat
//! (`playbot_lod6`, a toy robot on a base plate, 1 873 Gaussians) standing on a ground plane at
//! known transforms (turned about the up axis, one scaled by 1.1), and two distractors that
//! resemble nothing (a loose cloud of random Gaussians, a flat slab). From none (`auto`) and from
//! one example (the Gaussians in a box around one copy): every copy found, nothing invented,
//! every pose within 1° of the truth; the render check runs on a ring of cameras. Validation on.
mod common;

use common::*;
use glam::Vec3;
use instgs_vk::discover::{auto, from_example, DiscoverOptions, Discovery};
use instgs_vk::instancing::pose::{sim3_to_similarity, RenderCheck};
use instgs_vk::instancing::verify::ImageCheck;
use instgs_vk::model::camera::Camera;
use instgs_vk::model::instanced::transform_gaussians;
use instgs_vk::model::scene::Scene;
use instgs_vk::register::{object_size, Sim3};
use nalgebra::{Rotation3, Vector3};

/// The robot, +Z up (the capture's −Y), its base centred on the origin and standing on z = 0.
fn robot() -> Scene {
    let s = instgs_vk::formats::read_scene(&shared_data("splats/playbot_lod6.ply")).unwrap();
    let up = Rotation3::from_axis_angle(&Vector3::x_axis(), -std::f64::consts::FRAC_PI_2);
    let s = transform_gaussians(&s, &sim3_to_similarity(&Sim3 { rotation: *up.matrix(), ..Sim3::identity() }));
    let (lo, hi) = s.robust_bounds(0.01);
    let shift = Vec3::new(-(lo.x + hi.x) / 2.0, -(lo.y + hi.y) / 2.0, -lo.z);
    let mut s = s;
    for m in &mut s.means {
        *m = (Vec3::from(*m) + shift).to_array();
    }
    s
}

fn append(a: &mut Scene, b: &Scene) {
    a.means.extend_from_slice(&b.means);
    a.scales.extend_from_slice(&b.scales);
    a.quats.extend_from_slice(&b.quats);
    a.opacities.extend_from_slice(&b.opacities);
    a.sh.extend_from_slice(&b.sh);
}

/// Gaussians at `points` (log scales `scale`, opaque), coloured `rgb` ± noise, SH rest zero.
fn blobs(rng: &mut Rng, points: &[[f32; 3]], scale: [f32; 3], rgb: [f32; 3], deg: u32) -> Scene {
    let coeffs = ((deg + 1) * (deg + 1)) as usize;
    let mut s = Scene { sh_degree: deg, ..Default::default() };
    for p in points {
        s.means.push(*p);
        s.scales.push(scale);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacities.push(4.0);
        for k in 0..coeffs {
            for c in rgb {
                s.sh.push(if k == 0 { (c - 0.5) / 0.282_094_8 + 0.3 * rng.normal() } else { 0.0 });
            }
        }
    }
    s
}

struct World {
    scene: Scene,
    /// Object → world of each copy; the copies' Gaussians, in order, after the ground.
    poses: Vec<Sim3>,
    first: Vec<usize>,
    size: f64,
}

fn world() -> World {
    let mut rng = Rng::new(7);
    let robot = robot();
    let pts: Vec<[f64; 3]> = robot.means.iter().map(|m| m.map(|c| c as f64)).collect();
    let size = object_size(&pts);
    let d = 1.6 * size as f32;
    // The ground: a jittered grid, flat Gaussians in z.
    let n = 70;
    let ground_pts: Vec<[f32; 3]> = (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32 / (n - 1) as f32, (i / n) as f32 / (n - 1) as f32);
            [(x - 0.5) * 4.0 * d + 0.01 * d * rng.normal(), (y - 0.5) * 4.0 * d + 0.01 * d * rng.normal(), 0.0]
        })
        .collect();
    let ln = (0.6 * 4.0 * d / n as f32).ln();
    let mut scene = blobs(&mut rng, &ground_pts, [ln, ln, ln - 3.0], [0.55, 0.45, 0.35], robot.sh_degree);
    let place = |yaw: f64, x: f32, y: f32, scale: f64| Sim3 {
        rotation: *Rotation3::from_axis_angle(&Vector3::z_axis(), yaw.to_radians()).matrix(),
        scale,
        translation: Vector3::new(x as f64, y as f64, 0.0),
    };
    let poses =
        vec![place(0.0, -d, -d, 1.0), place(70.0, d, -d, 1.0), place(160.0, -d, d, 1.1), place(-110.0, d, d, 1.0)];
    let mut first = Vec::new();
    for p in &poses {
        first.push(scene.len());
        append(&mut scene, &transform_gaussians(&robot, &sim3_to_similarity(p)));
    }
    // Distractors: a loose cloud of random Gaussians, and a flat slab, between the copies.
    let s = size as f32;
    let cloud: Vec<[f32; 3]> = (0..400)
        .map(|_| [0.25 * s * rng.normal(), 0.25 * s * rng.normal(), 0.3 * s + 0.12 * s * rng.normal().abs()])
        .collect();
    let cloud_scene = blobs(&mut rng, &cloud, [(0.02 * s).ln(); 3], [0.3, 0.6, 0.8], robot.sh_degree);
    append(&mut scene, &cloud_scene);
    let slab: Vec<[f32; 3]> = (0..600)
        .map(|_| [rng.range(-0.45, 0.45) * s, 1.8 * d + rng.range(-0.1, 0.1) * s, rng.range(0.0, 0.1) * s])
        .collect();
    let slab_scene = blobs(&mut rng, &slab, [(0.03 * s).ln(); 3], [0.8, 0.2, 0.2], robot.sh_degree);
    append(&mut scene, &slab_scene);
    first.push(scene.len() - cloud.len() - slab.len());
    World { scene, poses, first, size }
}

/// A ring of cameras looking down at the scene from 30°, +Z up.
fn cameras(w: &World) -> Vec<Camera> {
    let r = 5.5 * w.size as f32;
    (0..16)
        .map(|i| {
            let a = i as f32 * std::f32::consts::TAU / 16.0;
            let eye = Vec3::new(r * a.cos(), r * a.sin(), 0.6 * r);
            look_at(eye, Vec3::ZERO, Vec3::Z, 160, 120, 150.0)
        })
        .collect()
}

/// Which copy (index) a found instance is: the one holding most of its Gaussians.
fn copy_of(w: &World, gaussians: &[usize]) -> Option<usize> {
    let mut count = vec![0usize; w.poses.len()];
    for &i in gaussians {
        if let Some(k) = (0..w.poses.len()).find(|&k| (w.first[k]..w.first[k + 1]).contains(&i)) {
            count[k] += 1;
        }
    }
    let (k, &c) = count.iter().enumerate().max_by_key(|(_, c)| **c)?;
    (2 * c > gaussians.len()).then_some(k)
}

/// Every copy found once, in one group, no other group of two or more, poses within 1° and
/// `tol` in scale and translation (a fraction of the size).
fn assert_found(w: &World, d: &Discovery, tol: f64) {
    let groups: Vec<_> = d.groups.iter().filter(|g| g.members.len() > 1).collect();
    assert_eq!(groups.len(), 1, "groups {:?}; refused {:#?}", summary(d), d.refused);
    let g = groups[0];
    let copies: Vec<Option<usize>> = g.members.iter().map(|m| copy_of(w, &m.gaussians)).collect();
    let mut sorted: Vec<usize> = copies.iter().map(|c| c.expect("every member is a copy")).collect();
    sorted.sort_unstable();
    assert_eq!(sorted, [0, 1, 2, 3], "members are copies {copies:?}; refused {:#?}", d.refused);
    let r = copies[0].unwrap();
    for (m, c) in g.members.iter().zip(&copies) {
        let truth = w.poses[r].compose(&w.poses[c.unwrap()].inverse());
        let err = m.relative.rotation_error_deg(&truth);
        assert!(err < 1.0, "copy {c:?}: rotation {err:.2}° off");
        assert!(
            (m.relative.scale / truth.scale - 1.0).abs() < tol,
            "copy {c:?}: scale {} vs {}",
            m.relative.scale,
            truth.scale
        );
        let centre = w.poses[c.unwrap()].translation + Vector3::new(0.0, 0.0, 0.3 * w.size);
        let moved = Vector3::from(m.relative.apply(&centre.into()));
        let want = Vector3::from(truth.apply(&centre.into()));
        assert!(
            (moved - want).norm() < tol * w.size,
            "copy {c:?}: {:.4} of its size off",
            (moved - want).norm() / w.size
        );
    }
}

fn summary(d: &Discovery) -> Vec<(String, usize)> {
    d.groups.iter().map(|g| (g.name.clone(), g.members.len())).collect()
}

#[test]
fn auto_finds_every_copy_and_no_distractor() {
    let (gpu, k) = gpu();
    let w = world();
    let mut check = ImageCheck::new(&gpu, &k, cameras(&w), None).unwrap();
    let d = auto(&w.scene, &DiscoverOptions::default(), Some(&mut check as &mut dyn RenderCheck), |l| eprintln!("{l}"))
        .unwrap();
    assert_found(&w, &d, 0.01);
    // Labels: the copies' Gaussians labelled, the distractors' and the ground's background.
    let labels = d.labels(w.scene.len());
    assert!(labels[w.first[4]..].iter().all(|&l| l == 0), "a distractor Gaussian was labelled");
    assert!(labels[..w.first[0]].iter().filter(|&&l| l != 0).count() < w.first[0] / 50, "ground labelled");
    assert_clean(&gpu);
}

#[test]
fn one_example_in_a_box_finds_the_other_copies() {
    let (gpu, k) = gpu();
    let w = world();
    let mut check = ImageCheck::new(&gpu, &k, cameras(&w), None).unwrap();
    // The example: every Gaussian in a box around copy 1, from just above the ground.
    let c = w.poses[1].translation;
    let h = 0.6 * w.size;
    let example: Vec<usize> = (0..w.scene.len())
        .filter(|&i| {
            let m = w.scene.means[i];
            (m[0] as f64 - c.x).abs() < h
                && (m[1] as f64 - c.y).abs() < h
                && (0.005 * w.size..1.2 * w.size).contains(&(m[2] as f64))
        })
        .collect();
    let d =
        from_example(&w.scene, &example, &DiscoverOptions::default(), Some(&mut check as &mut dyn RenderCheck), |l| {
            eprintln!("{l}")
        })
        .unwrap();
    assert_found(&w, &d, 0.01);
    assert_clean(&gpu);
}

#[test]
fn one_views_mask_lifts_to_the_copy_it_shows() {
    let (gpu, k) = gpu();
    let w = world();
    let cam = cameras(&w).remove(14); // on the side of copy 1
                                      // The mask: copy 1 rendered white among black Gaussians (so occluders hide it), > ½.
    let mut paint = w.scene.clone();
    let c = paint.sh_coeffs() * 3;
    for i in 0..paint.len() {
        let white = (w.first[1]..w.first[2]).contains(&i);
        for (j, v) in paint.sh[i * c..(i + 1) * c].iter_mut().enumerate() {
            *v = if j < 3 && white {
                0.5 / 0.282_094_8
            } else if j < 3 {
                -0.5 / 0.282_094_8
            } else {
                0.0
            };
        }
    }
    let mut r = instgs_vk::render::raster::Rasterizer::new(&gpu, &k).unwrap();
    let img = r.render(&instgs_vk::render::upload::GpuScene::new(&gpu, &paint).unwrap(), &cam, [0.0; 3]).unwrap().image;
    let mask: Vec<u8> = img.iter().map(|p| if p[0] > 0.5 { 7 } else { 0 }).collect();
    assert!(mask.iter().filter(|&&m| m != 0).count() > 200, "copy 1 shows in the view");
    let dir = tempdir("discover-mask");
    let path = dir.join("view_14.png");
    image::GrayImage::from_raw(cam.width, cam.height, mask).unwrap().save(&path).unwrap();
    let view = instgs_vk::dataset::View {
        camera: cam,
        image: img,
        path: dir.join("images").join("view_14.png"),
        undistort: None,
    };
    let mut lift = |v: &instgs_vk::dataset::View, m: &[u16]| -> anyhow::Result<Vec<u32>> {
        Ok(instgs_vk::segment::segment(&gpu, &k, &w.scene, std::slice::from_ref(v), &[m.to_vec()], &[1], 0.8)?.labels)
    };
    let spec = instgs_vk::discover::run::ExampleSpec::Mask { path, view: None, id: None };
    let got =
        instgs_vk::discover::run::example_gaussians(&w.scene, &spec, std::slice::from_ref(&view), &mut lift).unwrap();
    let copy = w.first[1]..w.first[2];
    let inside = got.iter().filter(|&&i| copy.contains(&i)).count();
    // The view sees the copy's front; the lift reaches its back by depth: most of the copy,
    // little else (the ground under its base plate).
    assert!(inside as f64 >= 0.8 * copy.len() as f64, "{inside} of the copy's {} Gaussians", copy.len());
    assert!(inside as f64 >= 0.8 * got.len() as f64, "{} Gaussians lifted, {inside} of them the copy's", got.len());
    assert_clean(&gpu);
}
