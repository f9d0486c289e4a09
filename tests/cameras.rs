//! Camera refinement (train::cameras): the gauge that keeps the corrections' mean world motion at
//! zero, RUN/cameras.json read back with every value checked, and training that recovers cameras
//! moved off their true poses. The gradients are in tests/grad.rs (finite differences, and the
//! GPU's camera terms against the CPU twin).
mod common;
use common::*;
use glam::{DMat3, DVec3, Vec3};
use instgs_vk::model::camera::Camera;
use instgs_vk::train::cameras::{apply_cameras, corrected, CameraState};

fn random_cameras(rng: &mut Rng, n: usize) -> Vec<Camera> {
    (0..n)
        .map(|_| {
            let eye = Vec3::new(rng.range(-4.0, 4.0), rng.range(-4.0, 4.0), rng.range(2.0, 4.0));
            look_at(eye, Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 64, 48, 60.0)
        })
        .collect()
}

fn rt(c: &Camera) -> (DMat3, DVec3) {
    let v = c.viewmat.as_dmat4();
    (DMat3::from_mat4(v), v.w_axis.truncate())
}

/// The corrections' mean world motion (ω_w, v_w) (the module's first-order reading).
fn mean_world_motion(st: &CameraState) -> (DVec3, DVec3) {
    let n = st.deltas.len() as f64;
    let (mut mw, mut mv) = (DVec3::ZERO, DVec3::ZERO);
    for (c, d) in st.original.iter().zip(&st.deltas) {
        let (r, t) = rt(c);
        let w = DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64);
        let tau = DVec3::new(d[3] as f64, d[4] as f64, d[5] as f64);
        mw += r.transpose() * w / n;
        mv += r.transpose() * (w.cross(t) + tau) / n;
    }
    (mw, mv)
}

#[test]
fn the_gauge_keeps_the_mean_world_motion_at_zero() {
    let mut rng = Rng::new(3);
    let cams = random_cameras(&mut rng, 9);
    // Corrections that all move the world the same way (the scene could follow them): removed.
    let (xi_w, xi_v) = (DVec3::new(0.01, -0.02, 0.005), DVec3::new(0.03, 0.01, -0.02));
    let mut st = CameraState::identity(cams.clone());
    for (c, d) in cams.iter().zip(&mut st.deltas) {
        let (r, t) = rt(c);
        let w = r * xi_w;
        let tau = r * xi_v - w.cross(t);
        *d = [w.x, w.y, w.z, tau.x, tau.y, tau.z].map(|x| x as f32);
    }
    // A step on a zero gradient moves nothing; the gauge then takes the common motion out.
    st.step(0, &[0.0; 15], [1e-3, 1e-3]);
    for d in &st.deltas {
        assert!(d.iter().all(|x| x.abs() < 1e-6), "common motion left: {d:?}");
    }
    // Corrections of their own keep what is not common, and no mean motion.
    let mut st = CameraState::identity(cams);
    for d in &mut st.deltas {
        *d = std::array::from_fn(|_| rng.range(-0.01, 0.01));
    }
    let before = st.deltas.clone();
    st.step(4, &[0.0; 15], [1e-3, 1e-3]);
    let (mw, mv) = mean_world_motion(&st);
    assert!(mw.length() < 1e-7 && mv.length() < 1e-7, "mean world motion {mw} {mv}");
    let changed: f32 = st.deltas.iter().zip(&before).flat_map(|(a, b)| (0..6).map(move |k| (a[k] - b[k]).abs())).sum();
    let size: f32 = before.iter().flatten().map(|x| x.abs()).sum();
    assert!(changed < 0.7 * size, "the gauge changed {changed} of {size}");
}

#[test]
fn camera_files_are_checked_and_applied() {
    let demo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("demo/ducks6-mini");
    let load = || {
        instgs_vk::dataset::load(&demo, &instgs_vk::dataset::LoadOptions { downscale: 1, background: [0.0; 3] })
            .unwrap()
    };
    let ds = load();
    let dir = tempdir("cameras-file");
    let path = dir.join("cameras.json");
    let entry =
        |name: &str, w: [f32; 3], t: [f32; 3]| serde_json::json!({"name": name, "rotation": w, "translation": t});
    let names: Vec<String> = ds.train.iter().map(|v| v.camera.name.clone()).collect();
    let write =
        |views: Vec<serde_json::Value>| std::fs::write(&path, serde_json::json!({"views": views}).to_string()).unwrap();
    let good: Vec<serde_json::Value> =
        names.iter().enumerate().map(|(i, n)| entry(n, [0.001 * i as f32, 0.0, -0.002], [0.0, 0.01, 0.0])).collect();
    let refused = |views: Vec<serde_json::Value>, needle: &str| {
        write(views);
        let e = format!("{:#}", apply_cameras(&path, &mut load()).unwrap_err());
        assert!(e.contains("cameras.json") && e.contains(needle), "{e}");
    };
    refused(good[1..].to_vec(), &format!("no correction for training view {}", names[0]));
    let mut far = good.clone();
    far[2] = entry(&names[2], [0.9, 0.0, 0.0], [0.0; 3]);
    refused(far, "not finite or not small");
    std::fs::write(&path, "{\"views\": [{\"name\": 3}]}").unwrap();
    let e = format!("{:#}", apply_cameras(&path, &mut load()).unwrap_err());
    assert!(e.contains("not a camera-correction file"), "{e}");
    // A good file: each training camera corrected, the held-out ones untouched.
    write(good);
    let mut got = load();
    apply_cameras(&path, &mut got).unwrap();
    for (i, (a, b)) in got.train.iter().zip(&ds.train).enumerate() {
        let want = corrected(&b.camera, &[0.001 * i as f32, 0.0, -0.002, 0.0, 0.01, 0.0]);
        assert_eq!(a.camera.viewmat, want.viewmat);
    }
    for (a, b) in got.test.iter().zip(&ds.test) {
        assert_eq!(a.camera.viewmat, b.camera.viewmat);
    }
}

/// The angle (degrees) between two cameras' rotations and the distance of their centres.
fn pose_error(a: &Camera, b: &Camera) -> (f64, f64) {
    let ((ra, _), (rb, _)) = (rt(a), rt(b));
    // ‖Ra − Rb‖_F = 2√2 sin(θ/2): exact near 0, where acos of the trace is not.
    let d = ra - rb;
    let frob = (d.x_axis.length_squared() + d.y_axis.length_squared() + d.z_axis.length_squared()).sqrt();
    let angle = (2.0 * (frob / (2.0 * 2f64.sqrt())).min(1.0).asin()).to_degrees();
    (angle, (a.position() - b.position()).length() as f64)
}

/// How far `a` images the points from where `b` does: the median distance in pixels over the
/// points well in front of both (what a pose error costs a photo, whatever mix of rotation and
/// translation makes it).
fn reprojection_error(a: &Camera, b: &Camera, points: &[[f32; 3]]) -> f64 {
    let mut d: Vec<f64> = points
        .iter()
        .filter_map(|p| {
            let (pa, pb) = (a.project(Vec3::from(*p))?, b.project(Vec3::from(*p))?);
            (pa[2] > 0.5 && pb[2] > 0.5).then(|| ((pa[0] - pb[0]) as f64).hypot((pa[1] - pb[1]) as f64))
        })
        .collect();
    d.sort_by(f64::total_cmp);
    d.get(d.len() / 2).copied().unwrap_or(0.0)
}

/// ducks6's exact training cameras, half of them moved off their poses (0.8° and 2 % of the
/// camera distance, about 2 px at this size, directions alternating so the errors have no common
/// motion): training
/// with camera refinement brings them back towards the truth, and writes the corrections beside
/// the scene.
#[test]
fn training_recovers_cameras_moved_off_their_poses() {
    let src = shared_data("scenes/ducks6");
    let dir = tempdir("cameras-recover");
    let n_train = 12;
    let mut moved = Vec::new();
    for split in ["train", "test"] {
        let text = std::fs::read_to_string(src.join(format!("transforms_{split}.json"))).unwrap();
        let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
        let frames = v["frames"].as_array_mut().unwrap();
        frames.truncate(if split == "train" { n_train } else { 3 });
        std::fs::create_dir_all(dir.join(split)).unwrap();
        for (i, f) in frames.iter_mut().enumerate() {
            let rel = format!("{}.png", f["file_path"].as_str().unwrap());
            std::fs::copy(src.join(&rel), dir.join(&rel)).unwrap();
            if split != "train" || i % 2 == 1 {
                continue;
            }
            // Rotate the camera about its centre and shift it: c2w' = [Rδ R | c + δc].
            let m: Vec<Vec<f64>> = serde_json::from_value(f["transform_matrix"].clone()).unwrap();
            let sign = if i % 4 == 0 { 1.0 } else { -1.0 };
            let axis = DVec3::new(0.3, 1.0, -0.5).normalize() * sign;
            let rd = DMat3::from_axis_angle(axis, 0.8f64.to_radians());
            let r = DMat3::from_cols(
                DVec3::new(m[0][0], m[1][0], m[2][0]),
                DVec3::new(m[0][1], m[1][1], m[2][1]),
                DVec3::new(m[0][2], m[1][2], m[2][2]),
            );
            let c = DVec3::new(m[0][3], m[1][3], m[2][3]);
            let (r2, c2) = (rd * r, c + DVec3::new(0.6, -0.3, 0.4).normalize() * (0.02 * c.length() * sign));
            let mut out = m.clone();
            for (row, line) in out.iter_mut().enumerate().take(3) {
                *line = vec![r2.x_axis[row], r2.y_axis[row], r2.z_axis[row], c2[row]];
            }
            f["transform_matrix"] = serde_json::to_value(out).unwrap();
            moved.push(i);
        }
        std::fs::write(dir.join(format!("transforms_{split}.json")), v.to_string()).unwrap();
    }
    std::fs::copy(src.join("points3d.ply"), dir.join("points3d.ply")).unwrap();
    let cfg = dir.join("cfg.toml");
    std::fs::write(
        &cfg,
        "iterations = 600\ntest_interval = 0\ncheckpoint_interval = 0\n[densify]\nfrom_iter = 40\ninterval = 50\nopacity_reset_interval = 0\n[cameras]\nrefine = true\nfrom_iter = 100\nlr_rotation_init = 0.001\nlr_rotation_final = 0.0001\nlr_translation_init = 0.001\nlr_translation_final = 0.0001\n[lr]\nposition_max_steps = 600\n",
    )
    .unwrap();
    let out = dir.join("run");
    let o = run_bin(
        &["train", "--data", dir.to_str().unwrap(), "--downscale", "2", "--out", out.to_str().unwrap()]
            .into_iter()
            .chain(["--config", cfg.to_str().unwrap(), "--quiet"])
            .collect::<Vec<_>>(),
        &[],
    );
    assert!(o.ok, "{}", o.stderr);
    let opts = instgs_vk::dataset::LoadOptions { downscale: 2, background: [0.0; 3] };
    let truth = instgs_vk::dataset::load(&src, &opts).unwrap();
    let mut got = instgs_vk::dataset::load(&dir, &opts).unwrap();
    let before: Vec<(f64, f64)> =
        (0..n_train).map(|i| pose_error(&got.train[i].camera, &truth.train[i].camera)).collect();
    apply_cameras(&out.join("cameras.json"), &mut got).unwrap();
    let after: Vec<(f64, f64)> =
        (0..n_train).map(|i| pose_error(&got.train[i].camera, &truth.train[i].camera)).collect();
    let points = &truth.points.as_ref().expect("ducks6 has points").positions;
    let moved_cams = instgs_vk::dataset::load(&dir, &opts).unwrap();
    let px = |cams: &instgs_vk::dataset::Dataset, i: usize| {
        reprojection_error(&cams.train[i].camera, &truth.train[i].camera, points)
    };
    let mean =
        |f: &dyn Fn(usize) -> f64, which: &[usize]| which.iter().map(|&i| f(i)).sum::<f64>() / which.len() as f64;
    let kept: Vec<usize> = (0..n_train).filter(|i| !moved.contains(i)).collect();
    let (was, now) = (mean(&|i| px(&moved_cams, i), &moved), mean(&|i| px(&got, i), &moved));
    let kept_now = mean(&|i| px(&got, i), &kept);
    eprintln!(
        "moved cameras: reprojection {was:.2} → {now:.2} px (rotation {:?}° → {:?}°); true cameras: {kept_now:.2} px",
        moved.iter().map(|&i| before[i].0).collect::<Vec<_>>(),
        moved.iter().map(|&i| after[i].0).collect::<Vec<_>>()
    );
    assert!(now < 0.5 * was, "moved cameras: reprojection {was} → {now} px; poses {before:?} → {after:?}");
    // The cameras that were right stay close to right.
    assert!(kept_now < 0.35 * was, "true cameras moved by {kept_now} px: {after:?}");
}
