//! The loss and Adam: SSIM against scikit-image's values (fixture from tools/ssim_fixture.py),
//! the CPU loss gradient against finite differences, the GPU loss and Adam kernels against their
//! CPU twins. Validation layers on.
mod common;
use common::*;
use instgs_vk::gpu::kernels::{KernelPolicy, Kernels};
use instgs_vk::render::reference;
use std::sync::Arc;

use instgs_vk::gpu::Gpu;
use instgs_vk::render::raster::backward::Grads;
use instgs_vk::render::upload::GpuScene;
use instgs_vk::shared::*;
use instgs_vk::train::optim::{
    adam_parts, record_adam, record_loss, AdamState, LearningRates, LossBufs, BETA1, BETA2, EPS,
};

fn fixture() -> serde_json::Value {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/ssim_skimage.json");
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn floats(v: &serde_json::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

#[test]
fn ssim_matches_scikit_image() {
    let f = fixture();
    let (w, h) = (f["width"].as_u64().unwrap() as usize, f["height"].as_u64().unwrap() as usize);
    let (x, y) = (floats(&f["x"]), floats(&f["y"]));
    let (s, cot) = reference::backward::ssim_plane(&x, &y, w, h);
    // The map where the window does not reach the border (padding differs: zero vs reflect).
    let want = floats(&f["ssim_map"]);
    let mut interior = Vec::new();
    for r in 5..h - 5 {
        for c in 5..w - 5 {
            let i = r * w + c;
            assert!((s[i] - want[i]).abs() < 1e-9, "SSIM at ({c}, {r}): {} vs scikit-image {}", s[i], want[i]);
            interior.push(s[i]);
        }
    }
    let mean = interior.iter().sum::<f64>() / interior.len() as f64;
    assert!((mean - f["mssim_interior"].as_f64().unwrap()).abs() < 1e-9);
    // d mean(S) / dx where no window of a pixel that sees x(q) reaches the border.
    let filtered: Vec<Vec<f64>> = cot.iter().map(|c| reference::backward::gauss_filter(c, w, h)).collect();
    let want = floats(&f["grad_mean_ssim"]);
    let n = (w * h) as f64;
    for r in 10..h - 10 {
        for c in 10..w - 10 {
            let i = r * w + c;
            let g = (filtered[0][i] + 2.0 * x[i] * filtered[1][i] + y[i] * filtered[2][i]) / n;
            assert!(
                (g - want[i]).abs() < 1e-9 + 1e-5 * want[i].abs(),
                "gradient at ({c}, {r}): {g:e} vs scikit-image {:e}",
                want[i]
            );
        }
    }
}

fn random_image(rng: &mut Rng, n: usize) -> Vec<[f64; 3]> {
    (0..n).map(|_| [rng.f32() as f64, rng.f32() as f64, rng.f32() as f64]).collect()
}

#[test]
fn loss_gradient_matches_finite_differences() {
    let mut rng = Rng::new(4);
    let (w, h) = (19, 14);
    let x = random_image(&mut rng, w * h);
    let y = random_image(&mut rng, w * h);
    let (_, _, _, g) = reference::backward::loss(&x, &y, w, h, 0.2);
    for _ in 0..60 {
        let i = (rng.u32() as usize) % (w * h);
        let c = (rng.u32() as usize) % 3;
        let e = 1e-6;
        let mut xp = x.clone();
        let mut xm = x.clone();
        xp[i][c] += e;
        xm[i][c] -= e;
        let numeric = (reference::backward::loss(&xp, &y, w, h, 0.2).0
            - reference::backward::loss(&xm, &y, w, h, 0.2).0)
            / (2.0 * e);
        assert!(
            (numeric - g[i][c]).abs() < 1e-7 + 1e-5 * numeric.abs(),
            "pixel {i} channel {c}: {} vs {numeric}",
            g[i][c]
        );
    }
}

#[test]
fn gpu_loss_matches_cpu_twin() {
    let (gpu, k) = gpu();
    let cas = Kernels::with_policy(&gpu, KernelPolicy { float_atomics: false, ..k.policy }).unwrap();
    let mut rng = Rng::new(8);
    for (w, h) in [(37usize, 29usize), (64, 48), (5, 3)] {
        let x = random_image(&mut rng, w * h);
        let y: Vec<[f64; 3]> =
            x.iter().map(|p| p.map(|v| (v + 0.2 * rng.range(-1.0, 1.0) as f64).clamp(0.0, 1.0))).collect();
        let to_gpu = |im: &[[f64; 3]]| -> Vec<[f32; 4]> {
            im.iter().map(|p| [p[0] as f32, p[1] as f32, p[2] as f32, 0.25]).collect()
        };
        let x32 = to_gpu(&x);
        let y32 = to_gpu(&y);
        let x64: Vec<[f64; 3]> = x32.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        let y64: Vec<[f64; 3]> = y32.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        let (_, l1, ssim, want) = reference::backward::loss(&x64, &y64, w, h, 0.2);
        for kk in [&k, &cas] {
            let lb = LossBufs::new(&gpu, w as u32, h as u32).unwrap();
            gpu.write(&lb.target, &y32).unwrap();
            let image = gpu.upload("image", &x32).unwrap();
            gpu.submit_and_wait(|rec| {
                rec.fill(&lb.v_image, instgs_vk::render::raster::POISON);
                record_loss(rec, kk, &image, &lb, 0.2)
            })
            .unwrap();
            let sums: Vec<f32> = gpu.read(&lb.sums, LOSS_SLOTS as usize).unwrap();
            let (gl1, gssim) = lb.means(&sums);
            assert!(
                (gl1 - l1).abs() < 1e-5 && (gssim - ssim).abs() < 1e-5,
                "{w}x{h}: ({gl1}, {gssim}) vs ({l1}, {ssim})"
            );
            let got: Vec<[f32; 4]> = gpu.read(&lb.v_image, w * h).unwrap();
            let scale = want.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            for i in 0..w * h {
                for c in 0..3 {
                    let e = (got[i][c] as f64 - want[i][c]).abs();
                    assert!(e <= 1e-4 * scale, "{w}x{h} pixel {i} channel {c}: {} vs {}", got[i][c], want[i][c]);
                }
                assert_eq!(got[i][3], 0.0);
            }
        }
    }
    assert_clean(&gpu);
}

/// The dispatches of a parameter group update every float exactly once, each at its row's
/// learning rate (true: lr_head).
#[test]
fn adam_parts_cover_every_float_once_at_its_rate() {
    for (rows, stride, head) in
        [(5, 3, 3), (4, 3, 3), (7, 1, 1), (3, 4, 4), (6, 48, 3), (5, 27, 3), (9, 12, 3), (0, 3, 3)]
    {
        let total = rows * stride;
        let mut seen: Vec<Option<bool>> = vec![None; total as usize];
        for p in adam_parts(total, stride, head) {
            let width = if p.vec4 { 4 } else { 1 };
            for e in 0..p.count {
                for c in 0..width {
                    let (i, col) = (p.first + e * width + c, (e % p.stride) * width + c);
                    assert!(seen[i as usize].is_none(), "{rows}x{stride}: float {i} updated twice");
                    seen[i as usize] = Some(col < p.head);
                }
            }
        }
        for (i, s) in seen.iter().enumerate() {
            assert_eq!(*s, Some(i as u32 % stride < head), "{rows}x{stride} head {head}: float {i}");
        }
    }
}

/// Every SH degree (rows of 3, 12, 27 and 48 coefficients: whole vec4s or not) and Gaussian
/// counts that leave 0 to 3 floats after the last whole vec4 of a buffer.
#[test]
fn gpu_adam_matches_cpu_twin() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(21);
    for (n, degree) in [(700, 2), (701, 3), (702, 1), (703, 0), (1, 3)] {
        adam_case(&gpu, &k, &mut rng, n, degree);
    }
    assert_clean(&gpu);
}

fn adam_case(gpu: &Arc<Gpu>, k: &Kernels, rng: &mut Rng, n: usize, degree: u32) {
    let scene = random_scene(rng, n, degree);
    let gs = GpuScene::new(gpu, &scene).unwrap();
    let grads = Grads::new(gpu, &gs).unwrap();
    let st = AdamState::new(gpu, &gs).unwrap();
    let lr = LearningRates {
        means: 1.6e-4,
        scales: 5e-3,
        quats: 1e-3,
        opacities: 0.025,
        sh0: 2.5e-3,
        sh_rest: 1.25e-4,
        cameras: [0.0; 2],
    };
    assert_eq!(scene.len(), n);
    let flat = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    let mut params: Vec<Vec<f64>> = vec![
        flat(bytemuck::cast_slice(&scene.means)),
        flat(bytemuck::cast_slice(&scene.scales)),
        flat(bytemuck::cast_slice(&scene.quats)),
        flat(&scene.opacities),
        flat(&scene.sh),
    ];
    let mut m: Vec<Vec<f64>> = params.iter().map(|p| vec![0.0; p.len()]).collect();
    let mut v = m.clone();
    for step in 1..=3u64 {
        let gbufs = [&grads.v_means, &grads.v_scales, &grads.v_quats, &grads.v_opacities, &grads.v_sh];
        let mut g32s = Vec::new();
        for (i, b) in gbufs.iter().enumerate() {
            let g: Vec<f32> = (0..params[i].len()).map(|_| rng.normal() * 0.01).collect();
            gpu.write(b, &g).unwrap();
            g32s.push(g);
        }
        gpu.submit_and_wait(|rec| record_adam(rec, k, &gs, &grads, &st, &lr, step)).unwrap();
        for (i, g) in g32s.iter().enumerate() {
            let base = reference::backward::AdamStep { lr: 0.0, beta1: BETA1, beta2: BETA2, eps: EPS as f64, step };
            let g = flat(g);
            let stride = params[i].len() / n;
            // Per element: the group's learning rate (SH: dc for the first 3 of each Gaussian).
            for j in 0..params[i].len() {
                let lr_j = match i {
                    0 => lr.means,
                    1 => lr.scales,
                    2 => lr.quats,
                    3 => lr.opacities,
                    _ if j % stride < 3 => lr.sh0,
                    _ => lr.sh_rest,
                } as f64;
                let a = reference::backward::AdamStep { lr: lr_j, ..base };
                let (p, mm, vv) = (&mut params[i][j..j + 1], &mut m[i][j..j + 1], &mut v[i][j..j + 1]);
                reference::backward::adam(p, &g[j..j + 1], mm, vv, a);
            }
        }
        let bufs = [&gs.means, &gs.scales, &gs.quats, &gs.opacities, &gs.sh];
        for (i, b) in bufs.iter().enumerate() {
            let got: Vec<f32> = gpu.read(b, params[i].len()).unwrap();
            for j in 0..got.len() {
                let d = (got[j] as f64 - params[i][j]).abs();
                assert!(
                    d <= 1e-6 * params[i][j].abs().max(1.0),
                    "{n} Gaussians, degree {degree}, step {step} buffer {i} element {j}: {} vs {}",
                    got[j],
                    params[i][j]
                );
            }
        }
    }
}
