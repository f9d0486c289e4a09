//! Registration checked against the images (`instgs_vk::instancing::verify`): on a rendered scene of copies
//! of one coloured object and one object that only resembles it, the copies are accepted, the
//! other is refused and stays plain (the instanced scene renders like the plain one over its
//! pixels), a group left with one instance stays plain whole, and a flipped pose of a copy
//! fails the render check. Validation on.
mod common;

use common::*;
use glam::Vec3;
use instgs_vk::dataset::masks::InstanceGroup;
use instgs_vk::instancing::options::InstanceOptions;
use instgs_vk::instancing::pose::RenderCheck;
use instgs_vk::instancing::template::instantiate;
use instgs_vk::instancing::verify::ImageCheck;
use instgs_vk::model::camera::Camera;
use instgs_vk::model::scene::Scene;
use instgs_vk::register::Sim3;
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::render::upload::GpuScene;
use nalgebra::{Rotation3, Vector3};

/// Surface samples of an asymmetric object about 0.8 units across (an ellipsoid body, a head,
/// a handle), or of a ball of the same size (`ball`).
fn surface(rng: &mut Rng, n: usize, ball: bool) -> Vec<[f64; 3]> {
    (0..n)
        .map(|i| {
            let d = Vector3::new(rng.normal() as f64, rng.normal() as f64, rng.normal() as f64).normalize();
            let p = if ball {
                d * 0.33
            } else {
                match i % 4 {
                    0 | 1 => Vector3::new(0.3 * d.x, 0.2 * d.y, 0.15 * d.z),
                    2 => Vector3::new(0.25, 0.0, 0.2) + d * 0.1,
                    _ => Vector3::new(-0.3 - rng.range(0.0, 0.2) as f64, 0.04 * d.y + 0.05, 0.04 * d.z),
                }
            };
            [p.x, p.y, p.z]
        })
        .collect()
}

/// Gaussians on `points` placed by `x`, coloured by their object-space position (so a turned
/// copy shows other colours where the true pose shows these).
fn push(scene: &mut Scene, labels: &mut Vec<u32>, points: &[[f64; 3]], x: &Sim3, label: u32) {
    for p in points {
        let q = x.apply(p);
        scene.means.push(q.map(|c| c as f32));
        scene.scales.push([-3.4; 3]);
        scene.quats.push([1.0, 0.0, 0.0, 0.0]);
        scene.opacities.push(3.0);
        scene.sh.extend([4.0 * p[0] as f32, 4.0 * p[1] as f32, 4.0 * p[2] as f32]);
        labels.push(label);
    }
}

fn pose(yaw_deg: f64, x: f64) -> Sim3 {
    let r = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians());
    Sim3 { rotation: *r.matrix(), scale: 1.0, translation: Vector3::new(x, 0.0, 0.0) }
}

/// Copies 1 and 2 of the object, 3 the ball, on a line; a ground of background Gaussians.
fn scene() -> (Scene, Vec<u32>, [Sim3; 3]) {
    let mut rng = Rng::new(31);
    let mut s = Scene { sh_degree: 0, ..Default::default() };
    let mut labels = Vec::new();
    let poses = [pose(40.0, -1.3), pose(-75.0, 0.0), pose(10.0, 1.3)];
    push(&mut s, &mut labels, &surface(&mut rng, 3000, false), &poses[0], 1);
    push(&mut s, &mut labels, &surface(&mut rng, 3400, false), &poses[1], 2);
    push(&mut s, &mut labels, &surface(&mut rng, 3000, true), &poses[2], 3);
    let ground: Vec<[f64; 3]> =
        (0..2000).map(|_| [rng.range(-2.5, 2.5) as f64, 0.45, rng.range(-1.5, 1.5) as f64]).collect();
    push(&mut s, &mut labels, &ground, &Sim3::identity(), 0);
    (s, labels, poses)
}

/// A ring of cameras looking down at the scene (−Y is up, as OpenCV captures).
fn cameras(n: usize) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let a = i as f32 * std::f32::consts::TAU / n as f32;
            let eye = Vec3::new(4.5 * a.sin(), -2.5, 4.5 * a.cos());
            look_at(eye, Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 128, 96, 110.0)
        })
        .collect()
}

/// PSNR of two renders over the pixels `keep` marks (∞ when equal).
fn psnr_over(a: &[[f32; 4]], b: &[[f32; 4]], keep: &[bool]) -> f64 {
    let (mut sq, mut n) = (0.0f64, 0usize);
    for ((p, q), &k) in a.iter().zip(b).zip(keep) {
        if k {
            sq += (0..3).map(|c| (p[c] as f64 - q[c] as f64).powi(2)).sum::<f64>();
            n += 3;
        }
    }
    assert!(n > 300, "{n} channel values compared");
    if sq == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * (sq / n as f64).log10()
    }
}

#[test]
fn copies_are_accepted_and_a_look_alike_stays_plain() {
    let (gpu, k) = gpu();
    let (plain, labels, poses) = scene();
    let mut check = ImageCheck::new(&gpu, &k, cameras(12), None).unwrap();
    let groups = vec![InstanceGroup { name: "thing".into(), ids: vec![1, 2, 3] }];
    let o = InstanceOptions::default();
    let (inst, reports) = instantiate(&plain, &labels, &groups, &o, Some(&mut check as &mut dyn RenderCheck), |_| {})
        .map(|m| (m.scene, m.reports))
        .unwrap();
    let status: Vec<&str> = reports.iter().map(|r| r.status.name()).collect();
    assert_eq!(status, ["accepted", "reference", "refused"], "{reports:#?}");
    assert!(reports.iter().all(|r| r.reference == 2));
    // The copy's pose is right: instance 1 → the reference = pose₂ ∘ pose₁⁻¹.
    let truth = poses[1].compose(&poses[0].inverse());
    assert!(reports[0].relative.rotation_error_deg(&truth) < 1.0, "{:?}", reports[0].relative);
    let render = reports[0].render.expect("render check ran");
    assert!(render.iou > 0.9 && render.psnr > 25.0, "{render:?}");
    // The ball stays background: 3000 ground-truth-plain Gaussians more than the ground.
    assert_eq!(inst.groups.len(), 1);
    assert_eq!(inst.groups[0].instances.len(), 2);
    assert_eq!(inst.background.len(), 2000 + 3000);
    // The instanced scene renders like the plain one over the ball's pixels.
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let top = look_at(Vec3::new(0.0, -6.0, 0.3), Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0), 160, 120, 150.0);
    let a = r.render(&GpuScene::new(&gpu, &plain).unwrap(), &top, [0.0; 3]).unwrap().image;
    let b = r.render(&GpuScene::instanced(&gpu, &inst).unwrap(), &top, [0.0; 3]).unwrap().image;
    let ball = instgs_vk::segment::subset(&plain, &labels, 3);
    let alone = r.render(&GpuScene::new(&gpu, &ball).unwrap(), &top, [0.0; 3]).unwrap().image;
    let keep: Vec<bool> = alone.iter().map(|p| p[3] < 0.99).collect();
    let db = psnr_over(&a, &b, &keep);
    assert!(db >= 50.0, "refused instance's pixels: {db} dB against the plain render");
    assert_clean(&gpu);
}

#[test]
fn a_group_left_with_one_instance_stays_plain() {
    let (gpu, k) = gpu();
    let (plain, labels, _) = scene();
    let mut check = ImageCheck::new(&gpu, &k, cameras(12), None).unwrap();
    let groups = vec![
        InstanceGroup { name: "thing".into(), ids: vec![1, 3] },
        InstanceGroup { name: "other".into(), ids: vec![2] },
    ];
    let mut lines = Vec::new();
    let (inst, reports) = instantiate(
        &plain,
        &labels,
        &groups,
        &InstanceOptions::default(),
        Some(&mut check as &mut dyn RenderCheck),
        |l| lines.push(l.to_string()),
    )
    .map(|m| (m.scene, m.reports))
    .unwrap();
    let status: Vec<&str> = reports.iter().map(|r| r.status.name()).collect();
    assert_eq!(status, ["plain", "refused", "reference"], "{reports:#?}");
    assert!(lines.iter().any(|l| l.contains("stays plain")), "{lines:?}");
    assert_eq!(inst.groups.len(), 1, "only the one-instance group is instanced");
    assert_eq!(inst.background.len(), 2000 + 3000 + 3000);
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    for cam in cameras(4) {
        let a = r.render(&GpuScene::new(&gpu, &plain).unwrap(), &cam, [0.0; 3]).unwrap().image;
        let b = r.render(&GpuScene::instanced(&gpu, &inst).unwrap(), &cam, [0.0; 3]).unwrap().image;
        let db = psnr_over(&a, &b, &vec![true; a.len()]);
        assert!(db >= 50.0, "{db} dB against the plain render");
    }
    assert_clean(&gpu);
}

#[test]
fn a_flipped_or_shrunk_pose_fails_the_render_check() {
    let (gpu, k) = gpu();
    let (plain, labels, poses) = scene();
    let mut check = ImageCheck::new(&gpu, &k, cameras(12), None).unwrap();
    let (one, two) = (instgs_vk::segment::subset(&plain, &labels, 1), instgs_vk::segment::subset(&plain, &labels, 2));
    let truth = poses[1].compose(&poses[0].inverse());
    let a = instgs_vk::instancing::options::Acceptance::default();
    let good = check.score(&two, &one, 1, &truth).unwrap().expect("visible");
    assert_eq!(good.failure(&a), None, "{good:?}");
    let centre = poses[1].translation;
    let around = |d: Sim3| d.about(&centre).compose(&truth);
    for (name, d) in [
        (
            "flipped",
            Sim3 {
                rotation: *Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI).matrix(),
                ..Sim3::identity()
            },
        ),
        (
            "turned",
            Sim3 {
                rotation: *Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2).matrix(),
                ..Sim3::identity()
            },
        ),
        ("shrunk", Sim3 { scale: 0.3, ..Sim3::identity() }),
    ] {
        let s = check.score(&two, &one, 1, &around(d)).unwrap().expect("visible");
        assert!(s.failure(&a).is_some(), "{name}: {s:?} passes");
    }
    assert_clean(&gpu);
}

#[test]
fn a_cropped_render_check_scores_as_the_whole_images_do() {
    // The check renders only each view's window around the instance; the same comparison
    // over the whole images (every view where the instance's silhouette has 64 pixels, the
    // placed reference's silhouette whole) must give the same score, with masks and without.
    use instgs_vk::instancing::verify::{compare, window, Compared};
    let (gpu, k) = gpu();
    let (plain, labels, poses) = scene();
    let (one, two) = (instgs_vk::segment::subset(&plain, &labels, 1), instgs_vk::segment::subset(&plain, &labels, 2));
    let cams = cameras(12);
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let mut whole = |s: &Scene| -> Vec<Vec<[f32; 4]>> {
        let gs = GpuScene::new(&gpu, s).unwrap();
        cams.iter().map(|c| r.render(&gs, c, [0.0; 3]).unwrap().image).collect()
    };
    let own = whole(&one);
    // A mask per view: the instance's own silhouette, and id 9 (another object) over a band.
    let masks: Vec<Vec<u16>> = own
        .iter()
        .map(|img| {
            img.iter()
                .enumerate()
                .map(|(i, p)| {
                    if p[3] < 0.5 {
                        1
                    } else if i % 128 < 20 {
                        9
                    } else {
                        0
                    }
                })
                .collect()
        })
        .collect();
    let truth = poses[1].compose(&poses[0].inverse());
    let turned = Sim3 { rotation: *Rotation3::from_axis_angle(&Vector3::y_axis(), 0.3).matrix(), ..Sim3::identity() }
        .about(&poses[1].translation)
        .compose(&truth);
    for x in [truth, turned] {
        let placed = whole(&instgs_vk::model::instanced::transform_gaussians(
            &two,
            &instgs_vk::instancing::pose::sim3_to_similarity(&x.inverse()),
        ));
        for with_masks in [false, true] {
            let views: Vec<Compared> = (0..cams.len())
                .filter(|&v| own[v].iter().filter(|p| p[3] < 0.5).count() >= 64)
                .map(|v| Compared {
                    own: &own[v],
                    placed: &placed[v],
                    mask: with_masks.then(|| masks[v].as_slice()),
                    truth_outside: 0,
                })
                .collect();
            assert!(views.len() >= 8, "{} views", views.len());
            let expected = compare(&views, 1);
            let mut check = ImageCheck::new(&gpu, &k, cams.clone(), with_masks.then(|| masks.clone())).unwrap();
            let got = check.score(&two, &one, 1, &x).unwrap().expect("visible");
            // Without a render, the same as the instance checked against itself.
            let own_iou = check.own_iou(&one, 1).unwrap().expect("visible");
            assert_eq!(own_iou, got.own_iou);
            assert_eq!(own_iou, check.score(&one, &one, 1, &Sim3::identity()).unwrap().unwrap().own_iou);
            assert_eq!(got.views, expected.views);
            assert!((got.iou - expected.iou).abs() < 1e-3, "IoU {} cropped, {} whole", got.iou, expected.iou);
            assert!((got.own_iou - expected.own_iou).abs() < 1e-3, "{got:?} {expected:?}");
            assert!((got.relative_iou - expected.relative_iou).abs() < 1e-3, "{got:?} {expected:?}");
            assert!((got.psnr - expected.psnr).abs() < 0.01, "PSNR {} cropped, {} whole", got.psnr, expected.psnr);
            assert!((got.pose_psnr - expected.pose_psnr).abs() < 0.01, "{got:?} {expected:?}");
        }
    }
    // The windows are crops: far smaller than the 128 × 96 views.
    let areas: Vec<u32> = cams.iter().filter_map(|c| window(&one, c)).map(|w| (w[2] - w[0]) * (w[3] - w[1])).collect();
    assert!(areas.iter().all(|&a| a < 128 * 96), "{areas:?}");
    assert_clean(&gpu);
}
