//! Gradients: the CPU twins (f64) against central finite differences, and every backward kernel
//! against its CPU twin on random scenes (SH degrees 0–3, splats straddling tiles, the
//! T < 1e-4 cut-off, a background colour), with both kernel policies and both the float-atomic
//! and the compare-and-swap accumulation. Validation layers on.
mod common;
use std::sync::Arc;

use common::*;
use glam::Vec3;
use instgs_vk::gpu::kernels::{KernelPolicy, Kernels};
use instgs_vk::model::scene::Scene;
use instgs_vk::render::raster::backward::Grads;
use instgs_vk::render::raster::{frame_params, Rasterizer};
use instgs_vk::render::reference::{
    self,
    backward::{Gaussian, Splat},
};
use instgs_vk::render::upload::GpuScene;

fn assert_close(what: &str, analytic: f64, numeric: f64, rel: f64, abs: f64) {
    assert!(
        (analytic - numeric).abs() <= abs + rel * analytic.abs().max(numeric.abs()),
        "{what}: analytic {analytic:e} vs numeric {numeric:e}"
    );
}

fn test_camera(w: u32, h: u32) -> instgs_vk::model::camera::Camera {
    look_at(Vec3::new(0.3, -0.4, -4.0), Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), w, h, 0.9 * w as f32)
}

#[test]
fn projection_vjp_matches_finite_differences() {
    let mut rng = Rng::new(11);
    let cam = test_camera(64, 48);
    for deg in 0..=3u32 {
        let scene = random_scene(&mut rng, 40, deg);
        let mut fp = frame_params(scene.len(), deg, &cam, [0.0; 3], 0);
        fp.sh_degree = deg;
        // The frame-cost regulariser w T (ln s_x + ln s_y + ln s_z), T held constant, on odd degrees.
        fp.tile_cost_weight = if deg % 2 == 1 { 0.3 } else { 0.0 };
        let mut checked = 0;
        for i in 0..scene.len() {
            let g = Gaussian::of_scene(&scene, i);
            let t = glam::Mat4::from_cols_array_2d(&fp.viewmat).transform_point3(Vec3::from(scene.means[i]));
            if t.z < 0.5 {
                continue;
            }
            // Some Gaussians far outside the view exercise the Jacobian clamp.
            let mut g = g;
            if i % 5 == 0 {
                g.mean[0] += 6.0;
            }
            let v = Splat::from_flat(&(0..9).map(|_| rng.range(-1.0, 1.0) as f64).collect::<Vec<_>>());
            let tiles = 1 + i as u32 % 7;
            let analytic = reference::backward::project_vjp(&fp, &g, &v, tiles).flat();
            let x = g.flat();
            let f = |x: &[f64]| {
                let s = reference::backward::project(&fp, &Gaussian::from_flat(x));
                // The colour clamp at 0 is a kink; keep away from it in this test.
                let data = s.flat().iter().zip(v.flat()).map(|(a, b)| a * b).sum::<f64>();
                data + fp.tile_cost_weight as f64 * tiles as f64 * (x[3] + x[4] + x[5])
            };
            let raw = reference::backward::project(&fp, &g);
            if raw.colour.iter().any(|&c| c.abs() < 1e-3) {
                continue;
            }
            for p in 0..x.len() {
                let h = 1e-6 * x[p].abs().max(1.0);
                let mut xp = x.clone();
                let mut xm = x.clone();
                xp[p] += h;
                xm[p] -= h;
                let numeric = (f(&xp) - f(&xm)) / (2.0 * h);
                assert_close(&format!("deg {deg} Gaussian {i} parameter {p}"), analytic[p], numeric, 1e-5, 1e-6);
            }
            checked += 1;
        }
        assert!(checked > 10, "degree {deg}: only {checked} Gaussians checked");
    }
}

#[test]
fn camera_vjp_matches_finite_differences() {
    // dL/dW and dL/dt of viewmat = [W | t] with the centre held, and dL/dcampos, of one
    // projected splat (preprocess_backward's camera terms).
    let mut rng = Rng::new(12);
    let cam = test_camera(64, 48);
    let mut checked = 0;
    for deg in [1u32, 3] {
        let scene = random_scene(&mut rng, 30, deg);
        let mut fp = frame_params(scene.len(), deg, &cam, [0.0; 3], 0);
        fp.sh_degree = deg;
        for i in 0..scene.len() {
            let mut g = Gaussian::of_scene(&scene, i);
            if i % 5 == 0 {
                g.mean[0] += 6.0; // the Jacobian clamp
            }
            let t = glam::Mat4::from_cols_array_2d(&fp.viewmat).transform_point3(Vec3::from(scene.means[i]));
            let raw = reference::backward::project(&fp, &g);
            if t.z < 0.5 || raw.colour.iter().any(|&c| c.abs() < 1e-3) {
                continue;
            }
            let v = Splat::from_flat(&(0..9).map(|_| rng.range(-1.0, 1.0) as f64).collect::<Vec<_>>());
            let analytic = reference::backward::project_camera_vjp(&fp, &g, &v);
            // The frame parameters as f64: the 12 viewmat entries of [W | t], then campos.
            let mut x: Vec<f64> =
                (0..4).flat_map(|c| (0..3).map(move |r| (c, r))).map(|(c, r)| fp.viewmat[c][r] as f64).collect();
            x.extend(fp.campos[..3].iter().map(|&v| v as f64));
            let f = |x: &[f64]| {
                let mut q = fp;
                for c in 0..4 {
                    for r in 0..3 {
                        q.viewmat[c][r] = x[3 * c + r] as f32;
                    }
                }
                for r in 0..3 {
                    q.campos[r] = x[12 + r] as f32;
                }
                reference::backward::project(&q, &g).flat().iter().zip(v.flat()).map(|(a, b)| a * b).sum::<f64>()
            };
            for p in 0..15 {
                let h = 1e-3;
                let (mut xp, mut xm) = (x.clone(), x.clone());
                xp[p] += h;
                xm[p] -= h;
                let numeric = (f(&xp) - f(&xm)) / (2.0 * h);
                assert_close(&format!("deg {deg} Gaussian {i} camera term {p}"), analytic[p], numeric, 2e-3, 1e-3);
            }
            checked += 1;
        }
    }
    assert!(checked > 10, "only {checked} Gaussians checked");
}

#[test]
fn camera_correction_gradient_matches_finite_differences() {
    // train::cameras::delta_grad: from the camera terms to dL/d(ω, τ) of viewmat = [exp(ω) | τ]
    // viewmat₀, through the centre campos = −Wᵀt, at a correction far from zero.
    use instgs_vk::train::cameras::{corrected, delta_grad};
    let mut rng = Rng::new(21);
    let cam = test_camera(64, 48);
    for _ in 0..5 {
        let terms: Vec<f32> = (0..15).map(|_| rng.range(-1.0, 1.0)).collect();
        let d: [f32; 6] = std::array::from_fn(|_| rng.range(-0.3, 0.3));
        let analytic = delta_grad(&cam, &d, &terms);
        let f = |d: &[f64; 6]| {
            let c = corrected(&cam, &d.map(|v| v as f32));
            let v = glam::DMat4::from_cols_array_2d(&c.viewmat.to_cols_array_2d().map(|c| c.map(f64::from)));
            let (w, t) = (glam::DMat3::from_mat4(v), v.w_axis.truncate());
            let centre = -(w.transpose() * t);
            let x: Vec<f64> = w.to_cols_array().into_iter().chain(t.to_array()).chain(centre.to_array()).collect();
            x.iter().zip(&terms).map(|(a, &b)| a * b as f64).sum::<f64>()
        };
        for p in 0..6 {
            let h = 1e-3;
            let (mut dp, mut dm) = (d.map(f64::from), d.map(f64::from));
            dp[p] += h;
            dm[p] -= h;
            let numeric = (f(&dp) - f(&dm)) / (2.0 * h);
            assert_close(&format!("correction parameter {p}"), analytic[p], numeric, 2e-3, 2e-3);
        }
    }
}

/// Random splats over a small image, every splat listed in every tile (blend skips the ones
/// that do not reach a pixel), front to back in index order.
fn random_splats(rng: &mut Rng, n: usize, w: u32, h: u32, opaque: bool) -> Vec<Splat> {
    (0..n)
        .map(|_| {
            let sx = rng.range(1.5, 8.0) as f64;
            let sy = rng.range(1.5, 8.0) as f64;
            let rho = rng.range(-0.6, 0.6) as f64;
            let (a, b, c) = (sx * sx, rho * sx * sy, sy * sy);
            let det = a * c - b * b;
            Splat {
                xy: [rng.range(-4.0, w as f32 + 4.0) as f64, rng.range(-4.0, h as f32 + 4.0) as f64],
                conic: [c / det, -b / det, a / det],
                opacity: if opaque { rng.range(0.9, 0.985) } else { rng.range(0.05, 0.9) } as f64,
                colour: [rng.f32() as f64, rng.f32() as f64, rng.f32() as f64],
            }
        })
        .collect()
}

#[test]
fn blend_backward_matches_finite_differences() {
    let mut rng = Rng::new(5);
    let (w, h) = (36u32, 28u32);
    let cam = test_camera(w, h);
    for opaque in [false, true] {
        let n = 24;
        let splats = random_splats(&mut rng, n, w, h, opaque);
        let fp = frame_params(n, 0, &cam, [0.2, 0.5, 0.7], 0);
        let tiles = (fp.tiles_x * fp.tiles_y) as usize;
        let ranges = vec![[0u32, n as u32]; tiles];
        let ids: Vec<u32> = (0..n as u32).collect();
        let v_image: Vec<[f64; 3]> = (0..w * h)
            .map(|_| [rng.range(-1.0, 1.0) as f64, rng.range(-1.0, 1.0) as f64, rng.range(-1.0, 1.0) as f64])
            .collect();
        let (_, ts, _) = reference::backward::blend(&fp, &ranges, &ids, &splats);
        if opaque {
            assert!(ts.iter().any(|&t| t < 0.01), "no pixel near saturation");
        }
        let analytic = reference::backward::blend_backward(&fp, &ranges, &ids, &splats, &v_image);
        let f = |s: &[Splat]| {
            let (img, _, _) = reference::backward::blend(&fp, &ranges, &ids, s);
            img.iter().zip(&v_image).map(|(a, b)| a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).sum::<f64>()
        };
        // A step that moves some pixel's alpha across the 1/255 cut-off (or T across 1e-4)
        // makes a jump, not a slope: such steps show as disagreeing differences at h and h/4
        // and are skipped (and counted).
        let numeric = |i: usize, p: usize, hh: f64| {
            let x = splats[i].flat();
            let mut sp = splats.clone();
            let mut sm = splats.clone();
            let mut xp = x;
            let mut xm = x;
            xp[p] += hh;
            xm[p] -= hh;
            sp[i] = Splat::from_flat(&xp);
            sm[i] = Splat::from_flat(&xm);
            (f(&sp) - f(&sm)) / (2.0 * hh)
        };
        let mut skipped = 0;
        for i in 0..n {
            let an = analytic[i].flat();
            for (p, &an_p) in an.iter().enumerate() {
                let hh = 1e-7 * splats[i].flat()[p].abs().max(1.0);
                let (n1, n2) = (numeric(i, p, hh), numeric(i, p, hh / 4.0));
                if (n1 - n2).abs() > 1e-4 * n1.abs().max(n2.abs()) + 1e-5 {
                    skipped += 1;
                    continue;
                }
                assert_close(&format!("opaque {opaque} splat {i} parameter {p}"), an_p, n2, 1e-4, 1e-6);
            }
        }
        assert!(skipped <= 3, "{skipped} of {} finite differences jumped", 9 * n);
    }
}

/// max |a − b| / max |b| over a field.
fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
    a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// blend_backward's outputs as f64: v_xys, v_conics, v_splat_opacities, v_colours.
fn read_blend_grads(gpu: &Arc<instgs_vk::gpu::Gpu>, grads: &Grads, n: usize) -> [Vec<f64>; 4] {
    let read = |b: &instgs_vk::gpu::Buffer, len: usize| -> Vec<f64> {
        gpu.read::<f32>(b, len).unwrap().into_iter().map(|v| v as f64).collect()
    };
    [
        read(&grads.v_xys, 2 * n),
        read(&grads.v_conics, 3 * n),
        read(&grads.v_splat_opacities, n),
        read(&grads.v_colours, 3 * n),
    ]
}

/// `got` ([`read_blend_grads`]) against the f64 twin fed with the GPU's splats, ranges and
/// order for `v_image`; every output non-zero somewhere.
fn assert_blend_grads_match_twin(
    got: &[Vec<f64>; 4],
    fp: &instgs_vk::shared::FrameParams,
    st: &instgs_vk::render::raster::FrameState,
    v_image: &[[f32; 4]],
    k: &Kernels,
) {
    let n = got[2].len();
    let splats: Vec<Splat> = (0..n).map(|i| Splat::of_projected(&st.projected, i)).collect();
    let v64: Vec<[f64; 3]> = v_image.iter().map(|v| [v[0] as f64, v[1] as f64, v[2] as f64]).collect();
    let want = reference::backward::blend_backward(fp, &st.ranges, &st.isect_ids, &splats, &v64);
    let wanted: [Vec<f64>; 4] = [
        want.iter().flat_map(|s| s.xy).collect(),
        want.iter().flat_map(|s| s.conic).collect(),
        want.iter().map(|s| s.opacity).collect(),
        want.iter().flat_map(|s| s.colour).collect(),
    ];
    for (name, (g, w)) in ["v_xys", "v_conics", "v_splat_opacities", "v_colours"].iter().zip(got.iter().zip(&wanted)) {
        let e = rel_err(g, w);
        assert!(e < 2e-3, "{name}: relative error {e:e} (policy {:?})", k.policy);
        assert!(w.iter().any(|v| *v != 0.0), "{name}: all zero");
    }
}

/// The backward kernels against their CPU twins, with the frame-cost regulariser at
/// `tile_cost_weight`.
fn check_backward(
    k: &Arc<Kernels>,
    scene: &Scene,
    cam: &instgs_vk::model::camera::Camera,
    seed: u64,
    tile_cost_weight: f32,
) {
    let (gpu, _) = gpu();
    let bg = [0.1, 0.3, 0.6];
    let mut gs = GpuScene::new(&gpu, scene).unwrap();
    // The camera gradients too (training's camera refinement): they change nothing else.
    gs.camera_grads = true;
    let mut r = Rasterizer::new(&gpu, k).unwrap();
    r.poison = true;
    r.tile_cost_weight = tile_cost_weight;
    r.render(&gs, cam, bg).unwrap();
    let st = r.read_state().unwrap();
    let fp = r.last_frame_params().unwrap();
    assert_eq!(fp.tile_cost_weight, tile_cost_weight);
    let n = scene.len();
    let npx = (cam.width * cam.height) as usize;
    let mut rng = Rng::new(seed);
    let v_image: Vec<[f32; 4]> =
        (0..npx).map(|_| [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 0.0]).collect();
    let v_buf = gpu.upload("v_image", &v_image).unwrap();
    let grads = Grads::new(&gpu, &gs).unwrap();
    gpu.submit_and_wait(|rec| {
        grads.record_reset_stats(rec);
        for b in [
            &grads.v_means,
            &grads.v_scales,
            &grads.v_quats,
            &grads.v_opacities,
            &grads.v_sh,
            &grads.terms,
            &grads.v_camera,
        ] {
            rec.fill(b, instgs_vk::render::raster::POISON);
        }
        r.record_backward(rec, &gs, &v_buf, &grads)
    })
    .unwrap();
    assert_clean(&gpu);

    // blend_backward against the f64 twin fed with the GPU's splats, ranges and order.
    let splats: Vec<Splat> = (0..n).map(|i| Splat::of_projected(&st.projected, i)).collect();
    let (_, _, lasts) = reference::backward::blend(&fp, &st.ranges, &st.isect_ids, &splats);
    let gpu_last = r.read_last().unwrap();
    let same = lasts.iter().zip(&gpu_last).filter(|(a, b)| a == b).count();
    assert!(same as f64 >= 0.999 * npx as f64, "last: {same} of {npx} pixels agree");
    let got = read_blend_grads(&gpu, &grads, n);
    assert_blend_grads_match_twin(&got, &fp, &st, &v_image, k);
    let read = |b: &instgs_vk::gpu::Buffer, len: usize| -> Vec<f64> {
        gpu.read::<f32>(b, len).unwrap().into_iter().map(|v| v as f64).collect()
    };

    // preprocess_backward against project_vjp fed with the GPU's splat gradients.
    let v_splat: Vec<Splat> = (0..n)
        .map(|i| Splat {
            xy: [got[0][2 * i], got[0][2 * i + 1]],
            conic: [got[1][3 * i], got[1][3 * i + 1], got[1][3 * i + 2]],
            opacity: got[2][i],
            colour: [got[3][3 * i], got[3][3 * i + 1], got[3][3 * i + 2]],
        })
        .collect();
    let coeffs = scene.sh_coeffs();
    let g_means = read(&grads.v_means, 3 * n);
    let g_scales = read(&grads.v_scales, 3 * n);
    let g_quats = read(&grads.v_quats, 4 * n);
    let g_opac = read(&grads.v_opacities, n);
    let g_sh = read(&grads.v_sh, 3 * coeffs * n);
    let counts: Vec<u32> = gpu.read(&grads.grad2d_count, n).unwrap();
    let mut want_flat = Vec::new();
    let mut got_flat = Vec::new();
    let terms = instgs_vk::shared::CAMERA_GRAD_TERMS as usize;
    let (mut want_camera, mut camera_scale) = (vec![0.0f64; terms], vec![0.0f64; terms]);
    for i in 0..n {
        let visible = st.projected.tiles_touched[i] > 0;
        assert_eq!(counts[i], visible as u32, "grad2d_count of Gaussian {i}");
        let got_i: Vec<f64> = g_means[3 * i..3 * i + 3]
            .iter()
            .chain(&g_scales[3 * i..3 * i + 3])
            .chain(&g_quats[4 * i..4 * i + 4])
            .chain(&g_opac[i..i + 1])
            .chain(&g_sh[3 * coeffs * i..3 * coeffs * (i + 1)])
            .copied()
            .collect();
        if !visible {
            assert!(got_i.iter().all(|&v| v == 0.0), "culled Gaussian {i} has gradients");
            continue;
        }
        let tiles = st.projected.tiles_touched[i];
        let want_i = reference::backward::project_vjp(&fp, &Gaussian::of_scene(scene, i), &v_splat[i], tiles).flat();
        let camera_i = reference::backward::project_camera_vjp(&fp, &Gaussian::of_scene(scene, i), &v_splat[i]);
        for c in 0..terms {
            want_camera[c] += camera_i[c];
            camera_scale[c] += camera_i[c].abs();
        }
        // Per Gaussian: relative to the largest gradient of that Gaussian.
        let e = rel_err(&got_i, &want_i);
        let scale = want_i.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(e < 5e-3 || scale < 1e-9, "Gaussian {i}: relative error {e:e}\n gpu {got_i:?}\n cpu {want_i:?}");
        want_flat.extend(want_i);
        got_flat.extend(got_i);
    }
    assert!(rel_err(&got_flat, &want_flat) < 1e-3);
    // camera_grad_reduce: the frame's camera gradient, the sum of the visible splats' terms.
    let got_camera = read(&grads.v_camera, terms);
    for c in 0..terms {
        assert!(
            (got_camera[c] - want_camera[c]).abs() <= 1e-4 * camera_scale[c] + 1e-9,
            "camera term {c}: gpu {} cpu {} (sum of |terms| {})",
            got_camera[c],
            want_camera[c],
            camera_scale[c]
        );
    }
}

#[test]
fn crowded_tiles_match_cpu_twins() {
    // Tiles beyond the row-loop pipelines' splat budget go to the CROWDED_TILES pipelines.
    let (gpu, _) = gpu();
    let (scene, cam) = crowded_scene(&mut Rng::new(5), 16000);
    let gs = GpuScene::new(&gpu, &scene).unwrap();
    for (policy, crowded) in [(KernelPolicy::CPU, true), (KernelPolicy::GPU, false)] {
        let mut r = Rasterizer::new(&gpu, &Kernels::with_policy(&gpu, policy).unwrap()).unwrap();
        r.render(&gs, &cam, [0.0; 3]).unwrap();
        let most = r.read_state().unwrap().tile_costs.into_iter().max().unwrap();
        let over = most > instgs_vk::shared::BLEND_LOOP_ITERATIONS;
        assert_eq!(over, crowded, "{policy:?}: a tile's loop cost is {most}");
    }
    for k in both_policies() {
        check_backward(&k, &scene, &cam, 3, 0.0);
    }
}

#[test]
fn a_tile_past_lavapipes_loop_limit_matches_cpu_twins() {
    // 72 000 splats in one tile: blend_backward's CROWDED_TILES pipeline past 65 535 splats.
    let (scene, cam) = overfull_tile_scene(&mut Rng::new(6), 70000);
    for k in both_policies() {
        check_backward(&k, &scene, &cam, 4, 0.0);
    }
}

#[test]
fn backward_kernels_match_cpu_twins() {
    let (gpu, _) = gpu();
    let mut rng = Rng::new(99);
    let cam = look_at(Vec3::new(0.2, -0.3, -4.5), Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 83, 61, 70.0);
    let policies: Vec<Arc<Kernels>> = both_policies()
        .into_iter()
        .chain([Kernels::with_policy(&gpu, KernelPolicy { float_atomics: false, ..KernelPolicy::CPU }).unwrap()])
        .collect();
    for deg in 0..=3u32 {
        // 301 Gaussians: for degrees 0 and 2 the SH rows (and the buffer) end inside a vec4.
        let mut scene = random_scene(&mut rng, 301, deg);
        // Large splats centred beyond 1.3x the field of view that still reach into the image:
        // the Jacobian clamp and its gradient.
        for i in 0..24 {
            let side = if i % 2 == 0 { 1.0 } else { -1.0 };
            scene.means[i] = [side * rng.range(3.8, 5.0), rng.range(-1.0, 1.0), rng.range(-0.5, 0.5)];
            scene.scales[i] = [rng.range(0.0, 0.5), rng.range(-0.5, 0.3), rng.range(-0.5, 0.3)];
            scene.opacities[i] = rng.range(0.0, 3.0);
        }
        // The frame-cost regulariser on odd degrees (on the order of the data gradients here).
        let tile_cost_weight = if deg % 2 == 1 { 0.5 } else { 0.0 };
        for k in &policies {
            check_backward(k, &scene, &cam, 7 + deg as u64, tile_cost_weight);
        }
    }
}

#[test]
fn backward_with_a_lower_active_sh_degree() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(3);
    let scene = random_scene(&mut rng, 200, 3);
    let cam = test_camera(48, 40);
    let mut gs = GpuScene::new(&gpu, &scene).unwrap();
    gs.active_sh_degree = 1;
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.render(&gs, &cam, [0.0; 3]).unwrap();
    let fp = r.last_frame_params().unwrap();
    assert_eq!(fp.sh_degree, 1);
    let v_buf = gpu.upload("v_image", &vec![[0.5f32, -0.25, 1.0, 0.0]; 48 * 40]).unwrap();
    let grads = Grads::new(&gpu, &gs).unwrap();
    gpu.submit_and_wait(|rec| {
        grads.record_reset_stats(rec);
        r.record_backward(rec, &gs, &v_buf, &grads)
    })
    .unwrap();
    let g_sh: Vec<f32> = gpu.read(&grads.v_sh, 48 * scene.len()).unwrap();
    let mut nonzero_low = false;
    for i in 0..scene.len() {
        let c = &g_sh[48 * i..48 * (i + 1)];
        assert!(c[12..].iter().all(|&v| v == 0.0), "Gaussian {i}: gradient above the active degree");
        nonzero_low |= c[..12].iter().any(|&v| v != 0.0);
    }
    assert!(nonzero_low);
    assert_clean(&gpu);
}

#[test]
fn blend_backward_from_masked_counts_matches_the_twin() {
    // `record_blend_backward_from` with the frame's `last` counts zeroed outside the pixels
    // where v_image is non-zero (the segmentation's per-mask passes): the twin's gradients of
    // that v_image over the whole frame, with both kernel policies; all counts zero: no
    // gradient at all (the counts given are the ones walked).
    let (gpu, _) = gpu();
    let mut rng = Rng::new(21);
    let scene = random_scene(&mut rng, 400, 1);
    let cam = test_camera(83, 61);
    let gs = GpuScene::new(&gpu, &scene).unwrap();
    let n = scene.len();
    for k in both_policies() {
        let mut r = Rasterizer::new(&gpu, &k).unwrap();
        r.render(&gs, &cam, [0.0; 3]).unwrap();
        let st = r.read_state().unwrap();
        let fp = r.last_frame_params().unwrap();
        // A region across tile borders: columns 11..47, rows 5..29, and a lone pixel.
        let inside = |p: usize| {
            let (x, y) = (p % 83, p / 83);
            (11..47).contains(&x) && (5..29).contains(&y) || (x, y) == (70, 50)
        };
        let v_image: Vec<[f32; 4]> = (0..83 * 61)
            .map(|p| {
                if inside(p) {
                    [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 0.0]
                } else {
                    [0.0; 4]
                }
            })
            .collect();
        let last = r.read_last().unwrap();
        let masked: Vec<u32> = last.iter().enumerate().map(|(p, &l)| if inside(p) { l } else { 0 }).collect();
        let v_buf = gpu.upload("v_image", &v_image).unwrap();
        let grads = Grads::new(&gpu, &gs).unwrap();
        let run = |counts: &[u32]| -> [Vec<f64>; 4] {
            let l = gpu.upload("last", counts).unwrap();
            gpu.submit_and_wait(|rec| {
                for b in [&grads.v_xys, &grads.v_conics, &grads.v_colours, &grads.v_splat_opacities] {
                    rec.fill(b, instgs_vk::render::raster::POISON);
                }
                r.record_blend_backward_from(rec, &gs, &v_buf, &grads, &l)
            })
            .unwrap();
            read_blend_grads(&gpu, &grads, n)
        };
        assert_blend_grads_match_twin(&run(&masked), &fp, &st, &v_image, &k);
        let none = run(&vec![0; 83 * 61]);
        assert!(none.iter().flatten().all(|&v| v == 0.0), "zero counts still walked splats ({:?})", k.policy);
        let short = gpu.upload("last", &[0u32; 16]).unwrap();
        let e = gpu
            .submit_and_wait(|rec| r.record_blend_backward_from(rec, &gs, &v_buf, &grads, &short))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("the frame needs"), "{e}");
    }
    assert_clean(&gpu);
}
