//! Every forward pass against its CPU twin, and whole images against the CPU render, on random
//! scenes and on real trained splats. Validation layers on; output buffers poisoned first.
mod common;
use common::*;
use glam::Vec3;
use instgs_vk::formats::ply::read_ply;
use instgs_vk::model::camera::{orbit_around, Camera, UpAxis};
use instgs_vk::model::scene::Scene;
use instgs_vk::render::raster::{frame_params, Rasterizer};
use instgs_vk::render::reference;
use instgs_vk::render::upload::GpuScene;
use instgs_vk::shared::*;
use instgs_vk::util::psnr;

/// (name, expected, got, relative tolerance, absolute tolerance)
type Field<'a> = (&'a str, &'a [f32], &'a [f32], f32, f32);

fn close(a: f32, b: f32, rel: f32, abs: f32) -> bool {
    (a - b).abs() <= abs + rel * a.abs().max(b.abs())
}

/// Renders on the GPU with both kernel policies and checks each pass against the CPU twin fed
/// with the GPU's inputs. Returns the lowest PSNR of a GPU image against the CPU render.
fn check_passes(scene: &Scene, cam: &Camera, bg: [f32; 3]) -> f64 {
    both_policies().iter().map(|k| check_passes_with(k, scene, cam, bg)).fold(f64::INFINITY, f64::min)
}

fn check_passes_with(
    k: &std::sync::Arc<instgs_vk::gpu::kernels::Kernels>,
    scene: &Scene,
    cam: &Camera,
    bg: [f32; 3],
) -> f64 {
    let (gpu, _) = gpu();
    let gs = GpuScene::new(&gpu, scene).unwrap();
    let mut r = Rasterizer::new(&gpu, k).unwrap();
    r.poison = true;
    let frame = r.render(&gs, cam, bg).unwrap();
    let st = r.read_state().unwrap();
    let n = scene.len();
    let cap = st.counts[COUNT_ISECT as usize].max(1);
    let fp = frame_params(n, scene.sh_degree, cam, bg, cap);

    // preprocess: same culling and radii (a float may land on the other side of a ceil for a
    // very few Gaussians), values to float precision.
    let want = reference::forward::preprocess(scene, &fp);
    let got = &st.projected;
    let mut mismatched = 0;
    for i in 0..n {
        if want.tiles_touched[i] != got.tiles_touched[i] || want.radii[i] != got.radii[i] {
            mismatched += 1;
            let close_radii = (0..2).all(|a| want.radii[i][a].abs_diff(got.radii[i][a]) <= 1);
            assert!(close_radii, "Gaussian {i}: radii {:?} vs {:?}", want.radii[i], got.radii[i]);
            continue;
        }
        if want.tiles_touched[i] == 0 {
            continue;
        }
        let fields: [Field; 4] = [
            ("xy", &want.xys[i], &got.xys[i], 1e-5, 1e-3),
            ("conic", &want.conics[i], &got.conics[i], 2e-3, 1e-6),
            ("colour", &want.colours[i][..3], &got.colours[i][..3], 1e-4, 1e-5),
            ("depth", std::slice::from_ref(&want.depths[i]), std::slice::from_ref(&got.depths[i]), 1e-6, 1e-6),
        ];
        for (name, w, g, rel, abs) in fields {
            assert!(w.iter().zip(g).all(|(a, b)| close(*a, *b, rel, abs)), "{name} of Gaussian {i}: {w:?} vs {g:?}");
        }
    }
    assert!(mismatched <= n / 500, "{mismatched} of {n} Gaussians differ in radius or tiles");

    // scan visible + compact + depth sort, from the GPU's preprocess output.
    let gpu_proj = &st.projected;
    let (dkeys, dids) = reference::forward::depth_order(gpu_proj);
    assert_eq!(st.counts[COUNT_VISIBLE as usize] as usize, dids.len(), "visible count");
    assert!(st.depth_keys == dkeys && st.depth_ids == dids, "depth order differs");

    // scan of tiles touched in depth order.
    let touched: Vec<u32> = dids.iter().map(|&i| gpu_proj.tiles_touched[i as usize]).collect();
    let (offsets, total) = reference::forward::exclusive_scan(&touched);
    assert!(st.isect_offsets == offsets, "intersection offsets differ");
    assert_eq!(st.counts[COUNT_ISECT_NEEDED as usize], total);
    assert_eq!(st.counts[COUNT_ISECT as usize], total, "capacity should have grown");

    // emit + tile sort.
    let (ikeys, iids) = reference::forward::emit(&fp, gpu_proj, &dids);
    // emit's tile costs (f32 maths as the kernel's; a row bound may round differently).
    let costs = reference::forward::tile_costs(&fp, gpu_proj, &dids, k.policy.blend_pixels_per_thread);
    for (t, (got, want)) in st.tile_costs.iter().zip(&costs).enumerate() {
        assert!(got.abs_diff(*want) <= 2 + want / 1000, "tile {t}: cost {got}, CPU twin {want}");
    }
    let (skeys, sids) = reference::forward::stable_sort(&ikeys, &iids);
    assert!(st.isect_keys == skeys && st.isect_ids == sids, "sorted intersections differ");

    // ranges.
    let ranges = reference::forward::tile_ranges(&skeys, (fp.tiles_x * fp.tiles_y) as usize);
    assert!(st.ranges == ranges, "tile ranges differ");

    // blend, from the GPU's own lists.
    let img = reference::forward::blend(&fp, &st.ranges, &st.isect_ids, gpu_proj);
    let p = psnr(&img, &frame.image);
    assert!(p >= 60.0, "blend differs from its CPU twin: PSNR {p:.1} dB");
    let max_t = img.iter().zip(&frame.image).map(|(a, b)| (a[3] - b[3]).abs()).fold(0.0f32, f32::max);
    assert!(max_t <= 1e-2, "transmittance differs by {max_t}");
    assert!(frame.image.iter().all(|p| p.iter().all(|v| v.is_finite())), "unwritten (poisoned) pixels");

    // The whole pipeline against the CPU render.
    let full = reference::forward::render(scene, &fp);
    let p = psnr(&full, &frame.image);
    assert_clean(&gpu);
    p
}

#[test]
fn passes_match_cpu_twin_on_random_scenes() {
    let mut rng = Rng::new(11);
    for deg in 0..=3 {
        let scene = random_scene(&mut rng, 4000, deg);
        // 203x157: partial tiles on the right and bottom; an off-centre principal point.
        let cam = look_at(Vec3::new(0.4, -0.6, -4.0), Vec3::new(0.1, 0.0, 0.2), -Vec3::Y, 203, 157, 180.0);
        let p = check_passes(&scene, &cam, [0.2, 0.5, 0.9]);
        assert!(p >= 50.0, "degree {deg}: GPU vs CPU image PSNR {p:.1} dB");
    }
}

#[test]
fn passes_match_cpu_twin_on_a_real_splat() {
    // 152k splats: the scans and sorts run over many blocks.
    let scene = read_ply(&shared_data("splats/biker.ply")).unwrap();
    let cam = &orbit_around(&scene, 3, UpAxis::NegY, 256, 192)[2];
    let p = check_passes(&scene, cam, [0.0, 0.0, 0.0]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn crowded_tiles_match() {
    // More splats in a tile than the row-loop pipeline of the CPU policy takes (see
    // crowded_scene): blend's CROWDED_TILES pipeline against the CPU twin.
    let (scene, cam) = crowded_scene(&mut Rng::new(4), 16000);
    let p = check_passes(&scene, &cam, [0.2, 0.4, 0.6]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn a_tile_past_lavapipes_loop_limit_matches() {
    // 70 000 splats in one tile: blend's CROWDED_TILES pipeline past 65 535 splats.
    let (scene, cam) = overfull_tile_scene(&mut Rng::new(8), 70000);
    let p = check_passes(&scene, &cam, [0.2, 0.4, 0.6]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn camera_inside_the_scene_culls_and_matches() {
    // Gaussians behind, beside and in front of the camera, some closer than the near plane.
    let mut rng = Rng::new(12);
    let scene = random_scene(&mut rng, 3000, 1);
    let cam = look_at(Vec3::new(0.0, 0.0, -0.2), Vec3::new(0.3, 0.1, 1.0), -Vec3::Y, 160, 120, 90.0);
    let p = check_passes(&scene, &cam, [0.0, 0.0, 0.0]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn large_and_small_splats_side_by_side_match() {
    // Every other Gaussian huge (hundreds of tiles), the rest small: the GPU policy's subgroups
    // test the large ones' tiles together (glsl/tiles_subgroup.glsl) while their small
    // neighbours loop on their own; counts, lists and images against the CPU twin.
    let mut rng = Rng::new(14);
    let mut scene = random_scene(&mut rng, 2000, 1);
    for (i, s) in scene.scales.iter_mut().enumerate() {
        if i % 2 == 0 {
            *s = [-0.7, -0.9, -1.2];
        }
    }
    let cam = look_at(Vec3::new(0.2, -0.3, -4.5), Vec3::ZERO, -Vec3::Y, 320, 240, 260.0);
    let p = check_passes(&scene, &cam, [0.1, 0.1, 0.1]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn intersection_buffers_grow_when_a_frame_needs_more() {
    // 400 huge Gaussians each covering most of a 640x480 image: far more intersections than
    // the initial capacity (65536).
    let mut rng = Rng::new(13);
    let mut scene = random_scene(&mut rng, 400, 0);
    for s in &mut scene.scales {
        *s = [0.0, 0.0, -0.5];
    }
    let cam = look_at(Vec3::new(0.0, 0.0, -5.0), Vec3::ZERO, -Vec3::Y, 640, 480, 500.0);
    let p = check_passes(&scene, &cam, [1.0, 1.0, 1.0]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

#[test]
fn images_match_cpu_twin_on_real_splats() {
    let (gpu, k) = gpu();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    for name in ["guitar.ply", "biker.ply", "playbot_lod2.ply"] {
        let scene = read_ply(&shared_data(&format!("splats/{name}"))).unwrap();
        let gs = GpuScene::new(&gpu, &scene).unwrap();
        for cam in orbit_around(&scene, 3, UpAxis::NegY, 320, 240).iter().take(2) {
            let frame = r.render(&gs, cam, [0.0, 0.0, 0.0]).unwrap();
            let fp = frame_params(scene.len(), scene.sh_degree, cam, [0.0; 3], frame.intersections);
            let want = reference::forward::render(&scene, &fp);
            let p = psnr(&want, &frame.image);
            assert!(p >= 50.0, "{name} {}: GPU vs CPU PSNR {p:.1} dB", cam.name);
            let lit = frame.image.iter().filter(|px| px[3] < 0.5).count();
            assert!(lit > frame.image.len() / 50, "{name} {}: the object is barely in view", cam.name);
        }
    }
    assert_clean(&gpu);
}

#[test]
fn buffers_past_max_storage_buffer_range_are_refused() {
    use instgs_vk::render::upload::check_scene_fits;
    let mib128 = 128 << 20;
    // 1M Gaussians at SH degree 3: a 192 MB SH buffer.
    let e = check_scene_fits(1_000_000, 1_000_000, 3, mib128).unwrap_err().to_string();
    assert!(e.contains("scene too large") && e.contains("maxStorageBufferRange"), "{e}");
    check_scene_fits(600_000, 600_000, 3, mib128).unwrap();
    check_scene_fits(1_000_000, 1_000_000, 0, mib128).unwrap();
    // An instanced scene: few rows, but 9M splats need 144 MB per-frame conics.
    let e = check_scene_fits(90_000, 9_000_000, 0, mib128).unwrap_err().to_string();
    assert!(e.contains("9000000 splats"), "{e}");

    // An image whose output buffer would pass the device's own limit is refused before
    // anything is allocated.
    let (gpu, k) = gpu();
    let mut rng = Rng::new(5);
    let scene = random_scene(&mut rng, 10, 0);
    let gs = GpuScene::new(&gpu, &scene).unwrap();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let width = 16384u32;
    let height = (gpu.info.max_storage_buffer_range / 16 / width as u64 + 1).min(u32::MAX as u64) as u32;
    let cam = look_at(Vec3::new(0.0, 0.0, -5.0), Vec3::ZERO, -Vec3::Y, width, height, 1000.0);
    let e = r.render(&gs, &cam, [0.0; 3]).err().expect("refused").to_string();
    assert!(e.contains("too large for one storage buffer"), "{e}");
    assert_clean(&gpu);
}

/// The CPU pipeline after preprocess, from given per-Gaussian data.
fn cpu_render_from(fp: &instgs_vk::shared::FrameParams, p: &reference::forward::Projected) -> Vec<[f32; 4]> {
    let (_, ids) = reference::forward::depth_order(p);
    let (keys, ids) = reference::forward::emit(fp, p, &ids);
    let (keys, ids) = reference::forward::stable_sort(&keys, &ids);
    let ranges = reference::forward::tile_ranges(&keys, (fp.tiles_x * fp.tiles_y) as usize);
    reference::forward::blend(fp, &ranges, &ids, p)
}

#[test]
fn tight_extents_render_the_3_sigma_image() {
    // Inria covers the square of half-width ceil(3 sqrt(lambda_max)); our per-axis, opacity-
    // aware extents must drop only pixels whose alpha is below 1/255: the same image as 3-sigma
    // squares (both with the conservative tile rectangle).
    let mut rng = Rng::new(21);
    let random = random_scene(&mut rng, 3000, 1);
    let biker = read_ply(&shared_data("splats/biker.ply")).unwrap();
    for scene in [&random, &biker] {
        let cam = &orbit_around(scene, 2, UpAxis::NegY, 320, 240)[1];
        let fp = frame_params(scene.len(), scene.sh_degree, cam, [0.3, 0.3, 0.3], 0);
        let ours = reference::forward::preprocess(scene, &fp);
        let mut inria = ours.clone();
        let mut shrunk = 0;
        for i in 0..scene.len() {
            if ours.tiles_touched[i] == 0 {
                continue;
            }
            // The 2D covariance is the inverse of the conic.
            let [ca, cb, cc, _] = ours.conics[i];
            let det = ca * cc - cb * cb;
            let (a, c) = (cc / det, ca / det);
            let det2 = a * c - (cb / det) * (cb / det);
            let mid = 0.5 * (a + c);
            let lambda = mid + (mid * mid - det2).max(0.1).sqrt();
            let r = (3.0 * lambda.sqrt()).ceil() as u32;
            assert!(ours.radii[i][0] <= r + 1 && ours.radii[i][1] <= r + 1, "extent larger than Inria's");
            inria.radii[i] = [r, r];
            let (lo, hi) = reference::forward::tile_rect(&fp, inria.xys[i], [r, r]);
            inria.tiles_touched[i] = ((hi[0] - lo[0]) * (hi[1] - lo[1])) as u32;
            shrunk += (inria.tiles_touched[i] > ours.tiles_touched[i]) as usize;
        }
        assert!(shrunk > 0, "the test should exercise smaller extents");
        let a = cpu_render_from(&fp, &ours);
        let b = cpu_render_from(&fp, &inria);
        let max = a.iter().zip(&b).flat_map(|(p, q)| (0..4).map(move |k| (p[k] - q[k]).abs())).fold(0.0f32, f32::max);
        assert!(max <= 1e-5, "images differ by {max}");
    }
}

#[test]
fn extreme_splats_are_culled_cleanly() {
    // exp(scale) overflowing to infinity, and enormous splats right at the near plane, must be
    // culled or drawn without NaN or undefined conversions, as in the CPU twin.
    let mut rng = Rng::new(31);
    let mut scene = random_scene(&mut rng, 500, 0);
    for i in 0..20 {
        scene.scales[i] = [95.0, 95.0, 95.0];
    }
    for i in 20..40 {
        scene.scales[i] = [3.0, 3.0, 3.0];
        scene.means[i] = [0.0, 0.0, -4.0 + 0.012 * (i - 19) as f32];
    }
    let cam = look_at(Vec3::new(0.0, 0.0, -4.0), Vec3::ZERO, -Vec3::Y, 96, 64, 80.0);
    let p = check_passes(&scene, &cam, [0.1, 0.2, 0.3]);
    assert!(p >= 50.0, "PSNR {p:.1} dB");
}

/// splat_hits_tile against every pixel centre of the tile: a tile where some pixel centre has
/// alpha >= 1/255 is always kept, and a kept tile is within the margin of one (random oblique
/// ellipses around and inside tiles).
#[test]
fn tile_test_keeps_every_tile_a_splat_reaches() {
    let mut rng = Rng::new(17);
    let (mut kept, mut dropped) = (0, 0);
    for _ in 0..20000 {
        let (sx, sy) = (rng.range(0.5, 30.0), rng.range(0.5, 30.0));
        let th = rng.range(0.0, std::f32::consts::PI);
        let (c, s) = (th.cos(), th.sin());
        // Conic = R diag(1/sx^2, 1/sy^2) R^T.
        let (ia, ib) = (1.0 / (sx * sx), 1.0 / (sy * sy));
        let co = [c * c * ia + s * s * ib, c * s * (ia - ib), s * s * ia + c * c * ib, rng.range(0.004, 1.0)];
        let xy = [rng.range(-40.0, 56.0), rng.range(-40.0, 56.0)];
        let lim = 2.0 * (255.0 * co[3] as f64).ln();
        let mut least = f64::MAX;
        for py in 0..TILE_SIZE {
            for px in 0..TILE_SIZE {
                let (dx, dy) = (px as f64 + 0.5 - xy[0] as f64, py as f64 + 0.5 - xy[1] as f64);
                let (a, b, c) = (co[0] as f64, co[1] as f64, co[2] as f64);
                least = least.min(a * dx * dx + 2.0 * b * dx * dy + c * dy * dy);
            }
        }
        let hit = reference::forward::splat_hits_tile(xy, co, [0, 0]);
        assert!(hit || least > lim, "dropped a tile with q = {least} <= {lim}: xy {xy:?}, co {co:?}");
        // A pixel centre lies within half a pixel per axis of the least q's point, where q grows
        // by at most 2 sqrt(l q) |d| + l |d|^2, |d|^2 <= 1/2 (l >= the largest eigenvalue).
        let (cut, l) = (lim * 1.001 + 0.001, (co[0] + co[2]) as f64);
        assert!(!hit || least <= cut + (2.0 * l * cut).sqrt() + l / 2.0, "kept a tile with q = {least} > {lim}");
        if hit {
            kept += 1;
        } else {
            dropped += 1;
        }
    }
    assert!(kept > 1000 && dropped > 1000, "kept {kept}, dropped {dropped}");
}

/// The tiles of a splat's rectangle that it misses carry no pixel: the image from emit's
/// intersections equals the one from whole rectangles, with fewer intersections.
#[test]
fn tile_culling_drops_intersections_not_pixels() {
    let mut rng = Rng::new(5);
    let random = random_scene(&mut rng, 3000, 1);
    let biker = read_ply(&shared_data("splats/biker.ply")).unwrap();
    for scene in [&random, &biker] {
        let cam = &orbit_around(scene, 2, UpAxis::NegY, 320, 240)[0];
        let fp = frame_params(scene.len(), scene.sh_degree, cam, [0.3, 0.3, 0.3], 0);
        let p = reference::forward::preprocess(scene, &fp);
        let (_, order) = reference::forward::depth_order(&p);
        let culled = reference::forward::emit(&fp, &p, &order);
        let mut whole = (Vec::new(), Vec::new());
        for &i in &order {
            let (lo, hi) = reference::forward::tile_rect(&fp, p.xys[i as usize], p.radii[i as usize]);
            for [x, y] in reference::forward::rect_tiles(lo, hi) {
                whole.0.push(y as u32 * fp.tiles_x + x as u32);
                whole.1.push(i);
            }
        }
        assert!(culled.0.len() < whole.0.len() * 19 / 20, "{} of {} intersections", culled.0.len(), whole.0.len());
        let render = |(keys, ids): &(Vec<u32>, Vec<u32>)| {
            let (keys, ids) = reference::forward::stable_sort(keys, ids);
            reference::forward::blend(
                &fp,
                &reference::forward::tile_ranges(&keys, (fp.tiles_x * fp.tiles_y) as usize),
                &ids,
                &p,
            )
        };
        assert!(render(&culled) == render(&whole), "culling changed the image");
    }
}

/// The draw path (`Forward::Quads`) and the compute path render one frame; returns the PSNR of
/// the draw against the compute image and against the CPU render. Output buffers poisoned.
fn quads_against_compute(scene: &Scene, cam: &Camera, bg: [f32; 3]) -> (f64, f64) {
    use instgs_vk::render::raster::Forward;
    let (gpu, k) = gpu();
    let gs = GpuScene::new(&gpu, scene).unwrap();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    let compute = r.render(&gs, cam, bg).unwrap();
    r.set_forward(Forward::Quads).unwrap();
    let quads = r.render(&gs, cam, bg).unwrap();
    assert!(quads.image.iter().all(|p| p.iter().all(|v| v.is_finite())), "unwritten (poisoned) pixels");
    assert_eq!(quads.visible, compute.visible);
    // The compute path stops a pixel before the splat that takes T below 1e-4 (Inria), so at
    // T < 1e-4 / (1 - 0.99); the draw blends on.
    let max_t = compute.image.iter().zip(&quads.image).map(|(a, b)| (a[3] - b[3]).abs()).fold(0.0f32, f32::max);
    assert!(max_t <= 0.0101, "transmittance differs by {max_t}");
    let fp = frame_params(scene.len(), scene.sh_degree, cam, bg, compute.intersections.max(1));
    let cpu = reference::forward::render(scene, &fp);
    assert_clean(&gpu);
    (psnr(&compute.image, &quads.image), psnr(&cpu, &quads.image))
}

#[test]
fn quads_match_the_compute_path_on_random_scenes() {
    if !gpu().0.info.draws {
        eprintln!("skipped: the device cannot draw");
        return;
    }
    let mut rng = Rng::new(23);
    for deg in [0, 3] {
        let scene = random_scene(&mut rng, 4000, deg);
        let cam = look_at(Vec3::new(0.4, -0.6, -4.0), Vec3::new(0.1, 0.0, 0.2), -Vec3::Y, 203, 157, 180.0);
        let (vs_compute, vs_cpu) = quads_against_compute(&scene, &cam, [0.2, 0.5, 0.9]);
        assert!(vs_compute >= 60.0 && vs_cpu >= 50.0, "degree {deg}: {vs_compute:.1} / {vs_cpu:.1} dB");
    }
    // Hundreds of splats over a few tiles: pixels saturate, where the two paths part.
    let (scene, cam) = crowded_scene(&mut rng, 3000);
    let (vs_compute, vs_cpu) = quads_against_compute(&scene, &cam, [1.0, 1.0, 1.0]);
    assert!(vs_compute >= 60.0 && vs_cpu >= 50.0, "crowded: {vs_compute:.1} / {vs_cpu:.1} dB");
}

#[test]
fn quads_match_the_compute_path_on_real_splats() {
    if !gpu().0.info.draws {
        eprintln!("skipped: the device cannot draw");
        return;
    }
    for name in ["guitar.ply", "biker.ply", "playbot_lod2.ply"] {
        let scene = read_ply(&shared_data(&format!("splats/{name}"))).unwrap();
        for cam in orbit_around(&scene, 3, UpAxis::NegY, 320, 240).iter().take(2) {
            let (vs_compute, vs_cpu) = quads_against_compute(&scene, cam, [0.0, 0.0, 0.0]);
            // The bar is 45 dB; the draw order per pixel is the compute path's.
            assert!(vs_compute >= 60.0, "{name} {}: quads vs compute {vs_compute:.1} dB", cam.name);
            assert!(vs_cpu >= 50.0, "{name} {}: quads vs CPU {vs_cpu:.1} dB", cam.name);
        }
    }
}

#[test]
fn auto_forward_picks_a_path_and_renders_the_same_image() {
    use instgs_vk::render::raster::Forward;
    let (gpu, k) = gpu();
    let mut rng = Rng::new(29);
    let scene = random_scene(&mut rng, 2000, 1);
    let gs = GpuScene::new(&gpu, &scene).unwrap();
    let cam = look_at(Vec3::new(0.0, 0.0, -4.0), Vec3::ZERO, -Vec3::Y, 160, 120, 150.0);
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let compute = r.render(&gs, &cam, [0.0; 3]).unwrap();
    r.set_forward(Forward::Auto).unwrap();
    let auto = r.render(&gs, &cam, [0.0; 3]).unwrap();
    assert_ne!(r.forward(), Forward::Auto);
    if !gpu.info.draws {
        assert_eq!(r.forward(), Forward::Compute);
    }
    let p = psnr(&compute.image, &auto.image);
    assert!(p >= 60.0, "auto ({:?}) vs compute: {p:.1} dB", r.forward());
    assert_clean(&gpu);
}
