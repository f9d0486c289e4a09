//! The per-photo colour transform and the lens's vignetting (render::appearance): the CPU
//! twin's gradient against finite differences, the GPU kernels against the twin (poisoned
//! outputs, float atomics and the compare-and-swap fallback), the least-squares fit behind the
//! compensated metrics, and training that learns the exposure of photos that differ and the
//! falloff of a lens. Validation layers on.
mod common;
use common::*;
use instgs_vk::gpu::kernels::{KernelPolicy, Kernels};
use instgs_vk::model::camera::Camera;
use instgs_vk::render::appearance::{
    apply, apply_photo, backward, compensated_scores, falloff, fit, radius2, AppearanceBufs, ColourTransform,
    Vignetting,
};

fn random_transform(rng: &mut Rng) -> ColourTransform {
    let mut t = instgs_vk::render::appearance::IDENTITY;
    for v in t.iter_mut() {
        *v += 0.15 * rng.range(-1.0, 1.0);
    }
    t
}

fn random_image(rng: &mut Rng, n: usize) -> Vec<[f32; 4]> {
    (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32(), rng.f32()]).collect()
}

/// A w×h pinhole with its principal point off centre and fx ≠ fy, as a photo's.
fn camera(w: u32, h: u32) -> Camera {
    let (fx, fy) = (0.8 * w as f32, 0.75 * w as f32);
    Camera::from_c2w_opengl("cam", glam::Mat4::IDENTITY, w, h, [fx, fy, 0.47 * w as f32, 0.53 * h as f32])
}

fn random_vignetting(rng: &mut Rng) -> Vignetting {
    [rng.range(-0.4, 0.1), rng.range(-0.2, 0.2)]
}

/// L = ½ Σ (out − y)² through the transform and the vignetting: dL/dt, dL/dk and dL/d image of
/// the twin against central differences of L (written out here, not through the twin).
#[test]
fn appearance_gradient_matches_finite_differences() {
    let mut rng = Rng::new(11);
    let (w, h) = (9u32, 7u32);
    let cam = camera(w, h);
    let n = (w * h) as usize;
    let (t, vig, x, y) =
        (random_transform(&mut rng), random_vignetting(&mut rng), random_image(&mut rng, n), random_image(&mut rng, n));
    let loss = |t: &ColourTransform, k: &Vignetting, x: &[[f32; 4]]| -> f64 {
        let t64 = t.map(f64::from);
        x.iter()
            .zip(&y)
            .enumerate()
            .map(|(i, (p, q))| {
                let (px, py) = ((i % w as usize) as f64 + 0.5, (i / w as usize) as f64 + 0.5);
                let nx = (px - cam.cx as f64) / cam.fx as f64;
                let ny = (py - cam.cy as f64) / cam.fy as f64;
                let r2 = nx * nx + ny * ny;
                let v = 1.0 + k[0] as f64 * r2 + k[1] as f64 * r2 * r2;
                (0..3)
                    .map(|c| {
                        let p = p.map(f64::from);
                        let o = t64[4 * c] * p[0] + t64[4 * c + 1] * p[1] + t64[4 * c + 2] * p[2] + t64[4 * c + 3];
                        0.5 * (v * o - q[c] as f64).powi(2)
                    })
                    .sum::<f64>()
            })
            .sum()
    };
    let out = apply_photo(&t, &vig, &cam, &x);
    let v_out: Vec<[f32; 4]> = out.iter().zip(&y).map(|(o, q)| [o[0] - q[0], o[1] - q[1], o[2] - q[2], 0.0]).collect();
    let (v_image, v_t) = backward(&t, &vig, &cam, &x, &v_out);
    let e = 1e-3f32;
    for k in 0..12 {
        let (mut tp, mut tm) = (t, t);
        tp[k] += e;
        tm[k] -= e;
        let numeric = (loss(&tp, &vig, &x) - loss(&tm, &vig, &x)) / (2.0 * e as f64);
        assert!((numeric - v_t[k]).abs() < 1e-3 * numeric.abs().max(1.0), "parameter {k}: {} vs {numeric}", v_t[k]);
    }
    for k in 0..2 {
        let (mut kp, mut km) = (vig, vig);
        kp[k] += e;
        km[k] -= e;
        let numeric = (loss(&t, &kp, &x) - loss(&t, &km, &x)) / (2.0 * e as f64);
        let got = v_t[12 + k];
        assert!((numeric - got).abs() < 1e-3 * numeric.abs().max(1e-1), "vignetting k{}: {got} vs {numeric}", k + 1);
    }
    for i in [0, 13, n - 1] {
        for c in 0..3 {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i][c] += e;
            xm[i][c] -= e;
            let numeric = (loss(&t, &vig, &xp) - loss(&t, &vig, &xm)) / (2.0 * e as f64);
            let got = v_image[i][c] as f64;
            assert!(
                (numeric - got).abs() < 1e-3 * numeric.abs().max(1e-2),
                "pixel {i} channel {c}: {got} vs {numeric}"
            );
        }
        assert_eq!(v_image[i][3], 0.0);
    }
    // The radius: 0 at the principal point, as the module documents (fx, fy apart).
    let c = Camera { cx: 2.5, cy: 3.5, ..cam.clone() };
    assert_eq!(radius2(&c, 3 * w as usize + 2), 0.0);
    let r2 = radius2(&c, 3 * w as usize + 3);
    assert!((r2 - 1.0 / (c.fx * c.fx)).abs() < 1e-9, "{r2}");
    assert_eq!(falloff(&[-0.5, 0.25], 2.0), 1.0 - 1.0 + 1.0);
}

#[test]
fn gpu_appearance_matches_cpu_twin() {
    let (gpu, k) = gpu();
    let cas = Kernels::with_policy(&gpu, KernelPolicy { float_atomics: false, ..k.policy }).unwrap();
    let mut rng = Rng::new(12);
    for (w, h) in [(37usize, 29usize), (64, 48), (5, 3), (320, 240)] {
        let n = w * h;
        let cam = camera(w as u32, h as u32);
        let (t, vig, x) = (random_transform(&mut rng), random_vignetting(&mut rng), random_image(&mut rng, n));
        let v_out: Vec<[f32; 4]> = (0..n).map(|_| [rng.normal(), rng.normal(), rng.normal(), 0.0]).collect();
        let want_out = apply_photo(&t, &vig, &cam, &x);
        let (want_v, want_g) = backward(&t, &vig, &cam, &x, &v_out);
        for kk in [&k, &cas] {
            let ab = AppearanceBufs::new(&gpu, n).unwrap();
            let image = gpu.upload("image", &x).unwrap();
            let v_adjusted = gpu.upload("v_adjusted", &v_out).unwrap();
            gpu.submit_and_wait(|rec| {
                rec.fill(&ab.adjusted, instgs_vk::render::raster::POISON);
                rec.fill(&ab.v_render, instgs_vk::render::raster::POISON);
                ab.record_apply(rec, kk, &image, &t, &vig, &cam)?;
                ab.record_backward(rec, kk, &image, &v_adjusted, &t, &vig, &cam)
            })
            .unwrap();
            let out: Vec<[f32; 4]> = gpu.read(&ab.adjusted, n).unwrap();
            let v: Vec<[f32; 4]> = gpu.read(&ab.v_render, n).unwrap();
            for i in 0..n {
                for c in 0..4 {
                    assert!(
                        (out[i][c] - want_out[i][c]).abs() < 1e-5,
                        "{w}x{h} pixel {i}: {:?} vs {:?}",
                        out[i],
                        want_out[i]
                    );
                    assert!((v[i][c] - want_v[i][c]).abs() < 1e-5, "{w}x{h} pixel {i}: {:?} vs {:?}", v[i], want_v[i]);
                }
            }
            let g = ab.read_grads().unwrap();
            let scale = want_g.iter().fold(1.0f64, |m, v| m.max(v.abs()));
            for j in 0..14 {
                assert!(
                    (g[j] as f64 - want_g[j]).abs() < 1e-4 * scale,
                    "{w}x{h} gradient {j}: {} vs {} ({} atomics)",
                    g[j],
                    want_g[j],
                    if kk.policy.float_atomics { "float" } else { "compare-and-swap" }
                );
            }
        }
    }
    assert_clean(&gpu);
}

/// The compensated metrics see through a photo's exposure: an image whose right half is the
/// truth under an affine change scores as the truth (∞ dB), and the raw metrics do not.
#[test]
fn compensated_scores_undo_a_colour_change() {
    let mut rng = Rng::new(13);
    let (w, h) = (40, 30);
    let truth = random_image(&mut rng, w * h);
    let t: ColourTransform = [0.8, 0.0, 0.0, 0.05, 0.0, 0.85, 0.0, 0.02, 0.0, 0.0, 0.9, 0.0];
    let photo = apply(&t, &truth);
    let (psnr, ssim) = compensated_scores(&truth, &photo, w, h);
    assert!(psnr > 60.0 && ssim > 0.9999, "{psnr} {ssim}");
    assert!(instgs_vk::util::psnr(&truth, &photo) < 30.0);
    // Fitted on the left half only: a right half that differs is not fitted away.
    let mut other = photo.clone();
    for y in 0..h {
        for x in w / 2..w {
            other[y * w + x][1] = 1.0 - other[y * w + x][1];
        }
    }
    assert!(compensated_scores(&truth, &other, w, h).0 < 20.0);
    let g = fit(&truth, &photo, |i| i % w < w / 2);
    assert!(g.iter().zip(&t).all(|(a, b)| (a - b).abs() < 1e-3), "{g:?}");
}

/// Photos of ducks6 whose exposure differs (each training photo's RGB scaled by its own gain,
/// 0.75–1.25) taken through a lens that vignettes (every photo's RGB times 1 + k1 r² with
/// k1 = −0.6: 19 % darker at the corners): a run with colour transforms learns gains that follow
/// the photos' (relative to their mean, as the transforms keep the identity as their mean) and
/// the lens's falloff, and writes them beside the scene, never into it.
#[test]
fn training_learns_each_photos_exposure_and_the_lens_vignetting() {
    const VIGNETTING: Vignetting = [-0.6, 0.0];
    let src = shared_data("scenes/ducks6");
    let dir = tempdir("appearance-exposure");
    let n_train = 12;
    let mut gains = Vec::new();
    let mut corner_r2 = 0.0f32;
    for split in ["train", "test"] {
        let text = std::fs::read_to_string(src.join(format!("transforms_{split}.json"))).unwrap();
        let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
        let (fl_x, fl_y) = (v["fl_x"].as_f64().unwrap() as f32, v["fl_y"].as_f64().unwrap() as f32);
        let (cx, cy) = (v["cx"].as_f64().unwrap() as f32, v["cy"].as_f64().unwrap() as f32);
        corner_r2 = (cx / fl_x).powi(2) + (cy / fl_y).powi(2);
        let frames = v["frames"].as_array_mut().unwrap();
        frames.truncate(if split == "train" { n_train } else { 3 });
        std::fs::create_dir_all(dir.join(split)).unwrap();
        for (i, f) in frames.iter().enumerate() {
            let rel = format!("{}.png", f["file_path"].as_str().unwrap());
            let mut img = image::open(src.join(&rel)).unwrap().to_rgb8();
            let g = if split == "train" { 0.75 + 0.5 * ((i * 7) % n_train) as f32 / (n_train - 1) as f32 } else { 1.0 };
            if split == "train" {
                gains.push(g);
            }
            for (x, y, p) in img.enumerate_pixels_mut() {
                let (nx, ny) = ((x as f32 + 0.5 - cx) / fl_x, (y as f32 + 0.5 - cy) / fl_y);
                let v = falloff(&VIGNETTING, nx * nx + ny * ny);
                p.0 = p.0.map(|c| (c as f32 * g * v).round().min(255.0) as u8);
            }
            img.save(dir.join(&rel)).unwrap();
        }
        std::fs::write(dir.join(format!("transforms_{split}.json")), v.to_string()).unwrap();
    }
    std::fs::copy(src.join("points3d.ply"), dir.join("points3d.ply")).unwrap();
    let cfg = dir.join("cfg.toml");
    std::fs::write(
        &cfg,
        "iterations = 240\ntest_interval = 0\ncheckpoint_interval = 0\n[densify]\nfrom_iter = 40\ninterval = 40\nopacity_reset_interval = 0\n[appearance]\nmodel = \"affine\"\nfrom_iter = 20\nlr_init = 0.03\nlr_final = 0.01\n",
    )
    .unwrap();
    let out = dir.join("run");
    let o = run_bin(
        &["train", "--data", dir.to_str().unwrap(), "--downscale", "4", "--out", out.to_str().unwrap()]
            .into_iter()
            .chain(["--config", cfg.to_str().unwrap(), "--quiet"])
            .collect::<Vec<_>>(),
        &[],
    );
    assert!(o.ok, "{}", o.stderr);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("appearance.json")).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.len(), n_train);
    // The learned gain of a photo: the mean of its transform's diagonal.
    let learned: Vec<f64> =
        views.iter().map(|e| (0..3).map(|c| e["transform"][c][c].as_f64().unwrap()).sum::<f64>() / 3.0).collect();
    let mean_gain = gains.iter().map(|&g| g as f64).sum::<f64>() / n_train as f64;
    let truth: Vec<f64> = gains.iter().map(|&g| g as f64 / mean_gain).collect();
    let corr = {
        let (ma, mb) = (learned.iter().sum::<f64>() / n_train as f64, truth.iter().sum::<f64>() / n_train as f64);
        let cov: f64 = learned.iter().zip(&truth).map(|(a, b)| (a - ma) * (b - mb)).sum();
        let va: f64 = learned.iter().map(|a| (a - ma).powi(2)).sum();
        let vb: f64 = truth.iter().map(|b| (b - mb).powi(2)).sum();
        cov / (va * vb).sqrt()
    };
    assert!(corr > 0.9, "learned gains {learned:?} against {truth:?}: correlation {corr}");
    // The mean transform stays the identity.
    let mean_learned = learned.iter().sum::<f64>() / n_train as f64;
    assert!((mean_learned - 1.0).abs() < 1e-3, "{mean_learned}");
    // The lens: darker towards the corners, by much of the photos' darkening there. The scene
    // takes up part of it early in training (these 240 iterations learn about 56 % of it at the
    // corners, at rates above the default's), so the bound is loose.
    let k = [v["vignetting"]["k1"].as_f64().unwrap() as f32, v["vignetting"]["k2"].as_f64().unwrap() as f32];
    let corner = corner_r2;
    let steps: Vec<f32> = (0..=4).map(|i| falloff(&k, corner * i as f32 / 4.0)).collect();
    assert!(steps.windows(2).all(|w| w[1] < w[0]), "learned vignetting {k:?}: falloff {steps:?} not decreasing");
    let (got, want) = (1.0 - falloff(&k, corner), 1.0 - falloff(&VIGNETTING, corner));
    assert!(
        got > 0.35 * want && got < 1.3 * want,
        "learned vignetting {k:?}: {got} darker at the corners (r² = {corner}), the lens {want}"
    );
    // The scene file holds the scene alone (a plain Inria PLY).
    let scene = instgs_vk::formats::ply::read_ply(&out.join("point_cloud.ply")).unwrap();
    assert!(!scene.is_empty());
}
