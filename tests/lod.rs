//! Rendering instanced scenes with per-frame instance selection: `instance_select` against its
//! CPU twin, the packed expansion of the chosen levels against the plain render of the same
//! Gaussians expanded on the CPU, lossless culling, and level of detail on real splats.
//! Validation on, outputs poisoned.
mod common;

use common::*;
use glam::Vec3;
use instgs_vk::model::camera::Camera;
use instgs_vk::model::instanced::{Group, InstancedScene, Offsets};
use instgs_vk::render::lod::{build_levels, select_instance, RenderConfig};
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::render::upload::GpuScene;
use instgs_vk::shared::*;
use instgs_vk::util::psnr;

/// Instances spread in front of, beside and behind a camera at the origin looking along +z.
fn spread_scene(rng: &mut Rng) -> InstancedScene {
    let mut s = random_instanced(rng, 1, 40, &[(300, 9), (200, 7)]);
    for g in &mut s.groups {
        for i in &mut g.instances {
            let t = Vec3::new(rng.range(-9.0, 9.0), rng.range(-4.0, 4.0), rng.range(-6.0, 30.0));
            i.transform =
                instgs_vk::model::instanced::Similarity::from_parts(i.transform.rotation, i.transform.scale, t);
        }
    }
    for m in &mut s.background.means {
        m[2] += 4.0;
    }
    s
}

fn camera() -> Camera {
    look_at(Vec3::ZERO, Vec3::new(0.0, 0.0, 1.0), Vec3::new(0.0, -1.0, 0.0), 128, 96, 110.0)
}

/// The frame's splats expanded on the CPU: background, then each selected instance's level.
fn selected_scene(scene: &InstancedScene, cfg: &RenderConfig, counts: &[u32], levels: &[u32]) -> InstancedScene {
    let mut out = InstancedScene { sh_degree: scene.sh_degree, background: scene.background.clone(), groups: vec![] };
    let mut k = 0;
    for g in &scene.groups {
        let kk = g.instances.len();
        let mut all = vec![(g.template.clone(), g.offsets.clone())];
        all.extend(build_levels(&g.template, &g.offsets, kk, &cfg.lod.fractions));
        for (ki, inst) in g.instances.iter().enumerate() {
            if counts[k] > 0 {
                let (t, o) = &all[levels[k] as usize];
                let n = t.len();
                assert_eq!(counts[k] as usize, n);
                let r = ki * n..(ki + 1) * n;
                out.groups.push(Group {
                    name: format!("{}-{ki}", g.name),
                    template: t.clone(),
                    instances: vec![inst.clone()],
                    offsets: Offsets {
                        d_means: o.d_means[r.clone()].to_vec(),
                        d_sh0: o.d_sh0[r.clone()].to_vec(),
                        d_opacities: o.d_opacities[r].to_vec(),
                    },
                });
            }
            k += 1;
        }
    }
    out
}

#[test]
fn selection_matches_cpu_twin_and_renders_the_chosen_levels() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(5);
    let scene = spread_scene(&mut rng);
    let mut cfg = RenderConfig::load(None).unwrap();
    cfg.lod.splats_per_pixel = 0.05;
    let gs = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg).unwrap();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    let cam = camera();
    let f = r.render(&gs, &cam, [0.0; 3]).unwrap();
    let st = r.read_state().unwrap();
    let sel = st.selection.expect("a selection");
    let fp = r.last_frame_params().unwrap();
    let groups: Vec<GroupInfo> = gpu.read(&gs.inst.groups, scene.groups.len()).unwrap();
    let xforms: Vec<InstanceXform> = gpu.read(&gs.inst.xforms, gs.inst.instances).unwrap();
    let args = gs.inst.select.unwrap();
    let mut gi = 0;
    for (i, x) in xforms.iter().enumerate() {
        while gi + 1 < groups.len() && i as u32 >= groups[gi + 1].instance_first {
            gi += 1;
        }
        let want = select_instance(&groups[gi], x, &fp, &args);
        assert_eq!((sel.inst_count[i], sel.inst_level[i]), want, "instance {i}");
    }
    let culled = sel.inst_count.iter().filter(|&&c| c == 0).count();
    let coarse = sel.inst_level.iter().zip(&sel.inst_count).filter(|&(&l, &c)| l > 0 && c > 0).count();
    let fine = sel.inst_level.iter().zip(&sel.inst_count).filter(|&(&l, &c)| l == 0 && c > 0).count();
    assert!(culled >= 2 && coarse >= 2 && fine >= 1, "culled {culled}, coarse {coarse}, level 0 {fine}");
    let total: u32 = sel.inst_count.iter().sum();
    assert_eq!(st.counts[COUNT_GAUSSIANS as usize], scene.background.len() as u32 + total);
    // More than the first per-splat capacity (a quarter of all pairs): the buffers grew.
    assert!(total as usize > scene.splats() / 4, "{total} of {}", scene.splats());

    // The packed splats are exactly the chosen levels of the visible instances.
    let selected = selected_scene(&scene, &cfg, &sel.inst_count, &sel.inst_level);
    let mut plain_r = Rasterizer::new(&gpu, &k).unwrap();
    let plain = plain_r.render(&GpuScene::new(&gpu, &selected.expand()).unwrap(), &cam, [0.0; 3]).unwrap();
    let plain_st = plain_r.read_state().unwrap();
    let n = st.counts[COUNT_GAUSSIANS as usize] as usize;
    assert_eq!(st.projected.tiles_touched[..n], plain_st.projected.tiles_touched[..]);
    assert_eq!(f.visible, plain.visible);
    let db = psnr(&f.image, &plain.image);
    assert!(db >= 60.0, "selected vs expanded: {db:.1} dB");
    // `bench`'s split: the background's intersections are its splats' tile counts, and all the
    // splats' counts are the frame's intersections.
    let nb = scene.background.len();
    let background: u64 = plain_st.projected.tiles_touched[..nb].iter().map(|&t| t as u64).sum();
    assert!(background > 0 && background < f.intersections as u64, "{background} of {}", f.intersections);
    assert_eq!(r.intersections_of_first(nb).unwrap(), background);
    assert_eq!(r.intersections_of_first(usize::MAX).unwrap(), f.intersections as u64);
    assert_clean(&gpu);
}

#[test]
fn culling_is_lossless() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(9);
    let scene = spread_scene(&mut rng);
    let cfg = RenderConfig::load(None).unwrap().exact();
    let culled = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg).unwrap();
    let every = GpuScene::instanced(&gpu, &scene).unwrap();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    for turn in 0..4 {
        let a = std::f32::consts::FRAC_PI_2 * turn as f32;
        let cam = look_at(Vec3::ZERO, Vec3::new(a.sin(), 0.1, a.cos()), Vec3::new(0.0, -1.0, 0.0), 128, 96, 110.0);
        let fc = r.render(&culled, &cam, [0.2; 3]).unwrap();
        let sc = r.read_state().unwrap();
        let fe = r.render(&every, &cam, [0.2; 3]).unwrap();
        assert_eq!(fc.visible, fe.visible, "turn {turn}");
        let db = psnr(&fc.image, &fe.image);
        assert!(db >= 60.0, "turn {turn}: culled vs every pair {db:.1} dB");
        let sel = sc.selection.unwrap();
        assert!(sel.inst_level.iter().all(|&l| l == 0));
        assert!(sel.inst_count.contains(&0), "turn {turn}: nothing culled");
    }
    assert_clean(&gpu);
}

#[test]
fn level_of_detail_keeps_distant_guitars() {
    let (gpu, k) = gpu();
    let demo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("demo/guitar.compressed.ply");
    let guitar = instgs_vk::formats::ply::read_ply(&demo).unwrap();
    let (lo, hi) = guitar.robust_bounds(0.0);
    let size = (hi - lo).length();
    let mut rng = Rng::new(2);
    let instances: Vec<_> = (0..6)
        .map(|i| instgs_vk::model::instanced::Instance {
            id: format!("{i}"),
            transform: instgs_vk::model::instanced::Similarity::from_parts(
                glam::Quat::from_rotation_y(rng.range(-0.5, 0.5)),
                1.0,
                Vec3::new((i % 3) as f32 - 1.0, (i / 3) as f32 - 0.5, 0.0) * size,
            ),
        })
        .collect();
    let scene = InstancedScene {
        sh_degree: guitar.sh_degree,
        background: instgs_vk::model::scene::Scene { sh_degree: guitar.sh_degree, ..Default::default() },
        groups: vec![Group {
            name: "guitar".into(),
            offsets: Offsets::zeros(guitar.len() * instances.len()),
            template: guitar,
            instances,
        }],
    };
    let cfg = RenderConfig::load(None).unwrap();
    let lod = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg).unwrap();
    let exact = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg.clone().exact()).unwrap();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let centre = 0.5 * (lo + hi);
    let cam = look_at(centre + Vec3::new(0.0, 0.0, -2.2 * size), centre, Vec3::new(0.0, -1.0, 0.0), 160, 120, 140.0);
    let fl = r.render(&lod, &cam, [0.0; 3]).unwrap();
    let levels = r.read_state().unwrap().selection.unwrap().inst_level;
    let fe = r.render(&exact, &cam, [0.0; 3]).unwrap();
    assert!(levels.iter().all(|&l| l > 0), "levels {levels:?}");
    assert!(fl.intersections * 2 < fe.intersections, "{} vs {}", fl.intersections, fe.intersections);
    let db = psnr(&fl.image, &fe.image);
    assert!(db >= 28.0, "level of detail vs exact: {db:.1} dB");
    assert_clean(&gpu);
}

/// PSNR between frames of `a` and `b` uploaded with the default level of detail (from
/// [`camera`]), each checked to hold its offsets as the given storage.
fn lod_psnr(
    gpu: &std::sync::Arc<instgs_vk::gpu::Gpu>,
    r: &mut Rasterizer,
    a: (&InstancedScene, u32),
    b: (&InstancedScene, u32),
) -> f64 {
    let cfg = RenderConfig::load(None).unwrap();
    let frame = |(scene, storage): (&InstancedScene, u32), r: &mut Rasterizer| {
        let gs = GpuScene::instanced_for_rendering(gpu, scene, &cfg).unwrap();
        assert_eq!(gs.inst.storage, storage);
        r.render(&gs, &camera(), [0.0; 3]).unwrap().image
    };
    let (fa, fb) = (frame(a, r), frame(b, r));
    psnr(&fa, &fb)
}

#[test]
fn product_quantised_offsets_render_as_their_decoded_values() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(13);
    let scene = spread_scene(&mut rng);
    let bytes = instgs_vk::formats::instgs::to_bytes(&scene, instgs_vk::formats::instgs::Dtype::Pq8);
    let f32_bytes = instgs_vk::formats::instgs::to_bytes(&scene, instgs_vk::formats::instgs::Dtype::F32);
    assert!(bytes.len() < f32_bytes.len() / 2, "{} vs {}", bytes.len(), f32_bytes.len());
    let decoded = instgs_vk::formats::instgs::from_bytes(&bytes, "pq8").unwrap();
    assert_ne!(decoded.groups[0].offsets, scene.groups[0].offsets, "k-means codes are lossy");
    let cfg = RenderConfig::load(None).unwrap();
    let coded = GpuScene::instanced_for_rendering(&gpu, &decoded, &cfg.clone().exact()).unwrap();
    assert_eq!(coded.inst.storage, OFFSETS_PQ8);
    let plain = GpuScene::instanced(&gpu, &decoded).unwrap();
    assert_eq!(plain.inst.storage, OFFSETS_F32);
    assert!(coded.gpu_bytes() < plain.gpu_bytes());
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    for turn in 0..2 {
        let a = std::f32::consts::PI * turn as f32;
        let cam = look_at(Vec3::ZERO, Vec3::new(a.sin(), 0.0, a.cos()), Vec3::new(0.0, -1.0, 0.0), 128, 96, 110.0);
        let fc = r.render(&coded, &cam, [0.0; 3]).unwrap();
        let fp = r.render(&plain, &cam, [0.0; 3]).unwrap();
        let db = psnr(&fc.image, &fp.image);
        assert!(db >= 60.0, "coded vs f32 offsets: {db:.1} dB");
    }
    // With level of detail the coarser levels' offsets take their nearest codes.
    let db = lod_psnr(&gpu, &mut r, (&decoded, OFFSETS_PQ8), (&scene, OFFSETS_F32));
    assert!(db >= 30.0, "level of detail, coded vs original offsets: {db:.1} dB");
    assert_clean(&gpu);
}

#[test]
fn f16_offsets_stay_f16_on_the_device_and_render_as_their_f32_values() {
    // An f16 file's offsets are held as seven halves per pair (14 bytes instead of 28) and
    // unpacked by instance.glsl: the frames equal those of the same values as f32 arrays. An odd
    // number of pairs (9 × 301 + 7 × 200) puts the last pair's halves at the buffer's end.
    use instgs_vk::formats::instgs::{from_bytes, to_bytes, Dtype};
    let (gpu, k) = gpu();
    let mut rng = Rng::new(17);
    let mut scene = random_instanced(&mut rng, 1, 40, &[(301, 9), (200, 7)]);
    for g in &mut scene.groups {
        for i in &mut g.instances {
            let t = Vec3::new(rng.range(-3.0, 3.0), rng.range(-2.0, 2.0), rng.range(4.0, 12.0));
            i.transform =
                instgs_vk::model::instanced::Similarity::from_parts(i.transform.rotation, i.transform.scale, t);
        }
    }
    for m in &mut scene.background.means {
        m[2] += 6.0;
    }
    let halves = from_bytes(&to_bytes(&scene, Dtype::F16), "f16").unwrap();
    assert_ne!(halves.groups[0].offsets, scene.groups[0].offsets, "f16 rounds");
    let cfg = RenderConfig::load(None).unwrap();
    let compact = GpuScene::instanced_for_rendering(&gpu, &halves, &cfg.clone().exact()).unwrap();
    let wide = GpuScene::instanced(&gpu, &halves).unwrap();
    let other = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg.clone().exact()).unwrap();
    assert_eq!(
        (compact.inst.storage, wide.inst.storage, other.inst.storage),
        (OFFSETS_F16, OFFSETS_F32, OFFSETS_F32),
        "only offsets that f16 holds exactly are stored as f16"
    );
    let pairs = wide.inst.pairs as u64;
    assert_eq!(pairs % 2, 1);
    // 28 bytes per pair against 4 per two halves; each side keeps placeholders (16 bytes, the
    // smallest buffer) for the other's buffers: the three f32 arrays, d_codes.
    assert_eq!(wide.gpu_bytes() + 3 * 16, compact.gpu_bytes() + 28 * pairs + 16 - 4 * (7 * pairs).div_ceil(2));
    // A memory budget counts the bytes as stored: f16 as the file's viewer holds them (before
    // its levels of detail), whether or not the offsets are f16 values yet; pq8 counted as f16.
    for s in [&scene, &halves] {
        assert_eq!(GpuScene::stored_bytes(&gpu, s, Dtype::F16).unwrap(), compact.gpu_bytes());
        assert_eq!(GpuScene::stored_bytes(&gpu, s, Dtype::Pq8).unwrap(), compact.gpu_bytes());
        assert_eq!(GpuScene::stored_bytes(&gpu, s, Dtype::F32).unwrap(), wide.gpu_bytes());
    }
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    for turn in 0..3 {
        let a = 0.4 * turn as f32 - 0.4;
        let cam = look_at(Vec3::ZERO, Vec3::new(a.sin(), 0.0, a.cos()), Vec3::new(0.0, -1.0, 0.0), 128, 96, 110.0);
        let fc = r.render(&compact, &cam, [0.0; 3]).unwrap();
        let fw = r.render(&wide, &cam, [0.0; 3]).unwrap();
        assert!(fc.intersections > 1000, "the instances are in view");
        assert_eq!(fc.image, fw.image, "f16 offsets vs the same values as f32 (view {turn})");
    }
    // With level of detail the coarser levels' merged offsets are rounded to f16.
    let db = lod_psnr(&gpu, &mut r, (&halves, OFFSETS_F16), (&scene, OFFSETS_F32));
    assert!(db >= 50.0, "level of detail, f16 vs f32 offsets: {db:.1} dB");
    assert_clean(&gpu);
}

#[test]
fn an_instance_moved_in_place_renders_like_the_scene_uploaded_again() {
    // The player's editor turns and scales one instance: its transform and Δp are rewritten on
    // the device (`GpuScene::write_instance`), the coarser levels' merged Δp mapped alike.
    let (gpu, k) = gpu();
    let mut rng = Rng::new(21);
    let mut scene = spread_scene(&mut rng);
    let cfg = RenderConfig::load(None).unwrap();
    let mut gs = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg).unwrap();
    assert!(gs.inst.group_infos.iter().all(|g| g.levels > 1), "levels built");
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    r.poison = true;
    let cam = camera();
    let before = r.render(&gs, &cam, [0.0; 3]).unwrap();
    let (group, inst) = (1, 3);
    let g = &mut scene.groups[group];
    let t = g.template.len();
    let x = g.instances[inst].transform;
    let (rotation, scale) = (glam::Quat::from_rotation_y(0.7), 1.3f32);
    let linear = glam::Mat3::from_quat(rotation) * scale;
    g.instances[inst].transform = instgs_vk::model::instanced::Similarity::from_parts(
        rotation * x.rotation,
        scale * x.scale,
        rotation * (x.translation * scale) + Vec3::new(0.5, 0.2, 1.0),
    );
    for d in &mut g.offsets.d_means[inst * t..(inst + 1) * t] {
        *d = (linear * Vec3::from(*d)).to_array();
    }
    let d_means = g.offsets.d_means[inst * t..(inst + 1) * t].to_vec();
    assert!(gs.write_instance(&gpu, group, inst, &g.instances[inst].transform, &d_means, linear).unwrap());
    let again = GpuScene::instanced_for_rendering(&gpu, &scene, &cfg).unwrap();
    let a = r.render(&gs, &cam, [0.0; 3]).unwrap();
    let b = r.render(&again, &cam, [0.0; 3]).unwrap();
    let db = psnr(&a.image, &b.image);
    assert!(db >= 60.0, "moved in place vs uploaded again: {db:.1} dB");
    let moved = psnr(&before.image, &a.image);
    assert!(moved < 40.0, "the edit shows in the frame ({moved:.1} dB against the frame before)");
    // Product-quantised offsets share one codebook: a turn needs a new upload.
    let bytes = instgs_vk::formats::instgs::to_bytes(&scene, instgs_vk::formats::instgs::Dtype::Pq8);
    let decoded = instgs_vk::formats::instgs::from_bytes(&bytes, "pq8").unwrap();
    let mut coded = GpuScene::instanced_for_rendering(&gpu, &decoded, &cfg).unwrap();
    let x = decoded.groups[group].instances[inst].transform;
    assert!(!coded.write_instance(&gpu, group, inst, &x, &d_means, linear).unwrap());
    assert!(coded.write_instance(&gpu, group, inst, &x, &d_means, glam::Mat3::IDENTITY).unwrap());
    assert_clean(&gpu);
}
