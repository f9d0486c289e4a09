//! Gradient-driven segmentation (InstGS Eq. 3–5) on a scene with known labels: instances of a
//! random template in front of a background, masks rendered from the true labels.
mod common;

use common::*;
use glam::Vec3;
use instgs_vk::segment::{
    associate, instance_iou, instance_iou_per_frame, instance_regions, segment, AssociateOptions,
};
use instgs_vk::util::ProgressMode;

/// Three instances of a random template in front of a wall; ten views and their masks rendered
/// from the true labels: (plain scene, labels, views, masks).
fn known_scene(
    gpu: &std::sync::Arc<instgs_vk::gpu::Gpu>,
    k: &std::sync::Arc<instgs_vk::gpu::kernels::Kernels>,
) -> (instgs_vk::model::scene::Scene, Vec<u32>, Vec<instgs_vk::dataset::View>, Vec<Vec<u16>>) {
    let mut rng = Rng::new(9);
    let mut scene = random_instanced(&mut rng, 1, 0, &[(150, 3)]);
    // Instances apart (x = -1.2, 0, 1.2), opaque enough to occlude, no offsets.
    for (i, inst) in scene.groups[0].instances.iter_mut().enumerate() {
        let x = inst.transform;
        inst.transform = instgs_vk::model::instanced::Similarity::from_parts(
            x.rotation,
            1.0,
            Vec3::new(1.2 * i as f32 - 1.2, 0.0, 0.0),
        );
    }
    scene.groups[0].offsets = instgs_vk::model::instanced::Offsets::zeros(450);
    // Splats within their object (a trained object's are; a huge one spilling far past the
    // instance's silhouette belongs to no mask).
    for sc in &mut scene.groups[0].template.scales {
        *sc = sc.map(|v| v.min(-2.8));
    }
    // Background: a wall of Gaussians behind the instances.
    let mut wall = random_scene(&mut rng, 400, 1);
    for m in &mut wall.means {
        *m = [m[0] * 2.0, m[1] * 1.5, 2.0 + 0.1 * m[2]];
    }
    scene.background = wall;
    let plain = scene.expand();
    let truth: Vec<u32> = (0..plain.len()).map(|i| if i < 400 { 0 } else { 1 + ((i - 400) / 150) as u32 }).collect();
    // Views and their masks from the true labels (each pixel: the instance whose Gaussians
    // carry more than half of it).
    let views: Vec<instgs_vk::dataset::View> = (0..10)
        .map(|i| {
            let a = -0.6 + 1.2 * i as f32 / 9.0;
            let eye = Vec3::new(4.5 * a.sin(), -0.8, -4.5 * a.cos());
            let camera = look_at(eye, Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 96, 64, 80.0);
            instgs_vk::dataset::View { camera, image: Vec::new(), path: Default::default(), undistort: None }
        })
        .collect();
    let masks: Vec<Vec<u16>> = views
        .iter()
        .map(|v| {
            let mut m = vec![0u16; 96 * 64];
            for id in 1..=3u32 {
                let mut s = plain.clone();
                s.sh_degree = 0;
                let c0 = instgs_vk::math::SH_C0_F32;
                s.sh = truth.iter().flat_map(|&l| [if l == id { 0.5 / c0 } else { -0.5 / c0 }; 3]).collect();
                let gs = instgs_vk::render::upload::GpuScene::new(gpu, &s).unwrap();
                let f = instgs_vk::render::raster::Rasterizer::new(gpu, k)
                    .unwrap()
                    .render(&gs, &v.camera, [0.0; 3])
                    .unwrap();
                for (px, p) in m.iter_mut().zip(&f.image) {
                    if p[0] > 0.5 {
                        *px = id as u16;
                    }
                }
            }
            m
        })
        .collect();
    (plain, truth, views, masks)
}

#[test]
fn segmentation_recovers_known_instances() {
    let (gpu, k) = gpu();
    let (plain, truth, views, masks) = known_scene(&gpu, &k);
    let seg = segment(&gpu, &k, &plain, &views, &masks, &[1, 2, 3], 0.8).unwrap();
    // Gaussians that show: labelled as they truly are.
    let s_all: Vec<f32> = (0..plain.len()).map(|i| seg.g.iter().map(|g| g[i].abs()).fold(0.0, f32::max)).collect();
    let shown: Vec<usize> = (0..plain.len()).filter(|&i| s_all[i] > 1.0).collect();
    let right = shown.iter().filter(|&&i| seg.labels[i] == truth[i]).count();
    assert!(right as f64 >= 0.95 * shown.len() as f64, "{right} of {} labelled right", shown.len());
    let regions = instance_regions(&gpu, &k, &plain, &seg.labels, &views, &[1, 2, 3]).unwrap();
    for id in 1..=3 {
        let iou = instance_iou(&regions[id as usize - 1], &masks, id);
        let mean = iou.iter().sum::<f64>() / iou.len() as f64;
        assert!(mean >= 0.9, "instance {id}: IoU {mean:.3}");
    }
    // Three instances share a render, a colour channel each: each region is the one rendered
    // for its instance alone.
    assert_eq!(instance_regions(&gpu, &k, &plain, &seg.labels, &views, &[2]).unwrap()[0], regions[1]);
    assert_eq!(instance_regions(&gpu, &k, &plain, &seg.labels, &views, &[3]).unwrap()[0], regions[2]);
    // α = 0: no background removal; the wall Gaussians seen behind an instance's mask pixels
    // (none here: they are occluded) aside, labels barely change; α large: fewer positives.
    let strict = segment(&gpu, &k, &plain, &views, &masks, &[1, 2, 3], 4.0).unwrap();
    let positives = |l: &[u32]| l.iter().filter(|&&x| x != 0).count();
    assert!(positives(&strict.labels) <= positives(&seg.labels));
    // Bad input: an id that is not an instance is reported; an instance whose masks claim no
    // Gaussian (mask pixels where nothing is rendered) is an error naming it.
    let mut odd = masks.clone();
    odd[0][0] = 7;
    let r = segment(&gpu, &k, &plain, &views, &odd, &[1, 2, 3], 0.8).unwrap();
    assert_eq!(r.unknown_ids, [7]);
    let mut empty = masks.clone();
    for m in &mut empty {
        m.iter_mut().for_each(|x| *x = if *x == 2 { 0 } else { *x });
    }
    empty[0][0] = 2;
    let e = segment(&gpu, &k, &plain, &views, &empty, &[1, 2, 3], 0.8).err().unwrap().to_string();
    assert!(e.contains("instance 2") && e.contains("no Gaussian"), "{e}");
    let e = segment(&gpu, &k, &plain, &views, &masks[..3], &[1, 2, 3], 0.8).err().unwrap().to_string();
    assert!(e.contains("10 views but 3 masks"), "{e}");
    assert_clean(&gpu);
}

#[test]
fn segmentation_scores_match_the_cpu_twin() {
    // One view: g = (1 + α)·GSeg(M) − α·GSeg(1), GSeg(M)_i = mean over channels of the f64
    // blend-backward twin's colour gradient for v_image = M (one mask at a time).
    let (gpu, k) = gpu();
    let mut rng = Rng::new(4);
    let scene = random_scene(&mut rng, 300, 1);
    let camera = look_at(Vec3::new(0.3, -0.4, -4.0), Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 64, 48, 60.0);
    // Five instances: one backward pass carries three masks (a channel each), the next two.
    let mask: Vec<u16> = (0..64 * 48)
        .map(|p| match (p % 64, p / 64) {
            (x, y) if x < 30 && y < 24 => 1,
            (x, _) if x < 30 => 3,
            (x, y) if x < 45 && y < 20 => 2,
            (_, y) if y < 20 => 4,
            (x, _) if x > 50 => 5,
            _ => 0,
        })
        .collect();
    let view = instgs_vk::dataset::View {
        camera: camera.clone(),
        image: Vec::new(),
        path: Default::default(),
        undistort: None,
    };
    let alpha = 0.8;
    let seg = segment(&gpu, &k, &scene, &[view], std::slice::from_ref(&mask), &[1, 2, 3, 4, 5], alpha).unwrap();
    let mut r = instgs_vk::render::raster::Rasterizer::new(&gpu, &k).unwrap();
    r.render(&instgs_vk::render::upload::GpuScene::new(&gpu, &scene).unwrap(), &camera, [0.0; 3]).unwrap();
    let st = r.read_state().unwrap();
    let fp = r.last_frame_params().unwrap();
    let splats: Vec<_> = (0..scene.len())
        .map(|i| instgs_vk::render::reference::backward::Splat::of_projected(&st.projected, i))
        .collect();
    let gseg = |keep: &dyn Fn(u16) -> bool| -> Vec<f64> {
        let v: Vec<[f64; 3]> = mask.iter().map(|&m| if keep(m) { [1.0; 3] } else { [0.0; 3] }).collect();
        instgs_vk::render::reference::backward::blend_backward(&fp, &st.ranges, &st.isect_ids, &splats, &v)
            .iter()
            .map(|s| s.colour.iter().sum::<f64>() / 3.0)
            .collect()
    };
    let all = gseg(&|_| true);
    for (j, id) in [1u16, 2, 3, 4, 5].into_iter().enumerate() {
        let m = gseg(&|x| x == id);
        let want: Vec<f64> = (0..scene.len()).map(|i| (1.0 + alpha as f64) * m[i] - alpha as f64 * all[i]).collect();
        let scale = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let err = seg.g[j].iter().zip(&want).fold(0.0f64, |a, (g, w)| a.max((*g as f64 - w).abs()));
        assert!(scale > 0.1 && err < 2e-3 * scale, "instance {id}: max error {err:e} of {scale:e}");
    }
    assert_clean(&gpu);
}

#[test]
fn association_recovers_instances_from_scrambled_per_frame_ids() {
    let (gpu, k) = gpu();
    let (plain, truth, views, masks) = known_scene(&gpu, &k);
    // Every frame renumbers its masks at random (ids 1..=40), all of one category; a stray
    // fourth mask of a few pixels in one frame has no counterpart elsewhere; one view lacks an
    // instance.
    let mut rng = Rng::new(11);
    let mut key: Vec<std::collections::BTreeMap<u16, u16>> = Vec::new();
    let mut scrambled = masks.clone();
    let mut cats = Vec::new();
    for (v, m) in scrambled.iter_mut().enumerate() {
        let mut map = std::collections::BTreeMap::new();
        while map.len() < 3 {
            let new = 1 + (rng.u32() % 40) as u16;
            if !map.values().any(|&x| x == new) {
                map.insert(map.len() as u16 + 1, new);
            }
        }
        // View 7 does not show instance 3 (as if occluded or out of frame).
        if v == 7 {
            map.remove(&3);
        }
        m.iter_mut().for_each(|x| *x = if *x == 0 { 0 } else { map.get(x).copied().unwrap_or(0) });
        let mut c: std::collections::BTreeMap<u16, String> = map.values().map(|&n| (n, "blob".to_string())).collect();
        if v == 4 {
            let stray = (1..=40).find(|x| !map.values().any(|y| y == x)).unwrap();
            m[..6].fill(stray);
            c.insert(stray, "blob".into());
        }
        cats.push(c);
        key.push(map.into_iter().map(|(t, n)| (n, t)).collect());
    }
    let a = associate(
        &gpu,
        &k,
        &plain,
        &views,
        &scrambled,
        &cats,
        &AssociateOptions::default(),
        ("", ProgressMode::Tenths),
    )
    .unwrap();
    assert_eq!(a.groups.len(), 1);
    assert_eq!(a.groups[0].ids, [1, 2, 3]);
    // Each instance gathers exactly one true instance's masks, one per view.
    let mut found = Vec::new();
    for ms in a.members.values() {
        let truths: std::collections::BTreeSet<u16> = ms.iter().map(|(v, id)| key[*v][id]).collect();
        assert_eq!(truths.len(), 1, "an instance mixes true instances {truths:?}");
        let expect = if truths.contains(&3) { views.len() - 1 } else { views.len() };
        assert_eq!(ms.len(), expect, "one mask per view that shows the instance");
        found.extend(truths);
    }
    found.sort();
    assert_eq!(found, [1, 2, 3]);
    assert!(a.dropped.iter().all(|(v, _)| *v == 4) && a.dropped.len() <= 1);
    // The rewritten masks segment like the true ones (up to the instances' numbering).
    let ids: Vec<u32> = a.groups[0].ids.clone();
    let seg = segment(&gpu, &k, &plain, &views, &a.masks, &ids, 0.8).unwrap();
    let truth_of = |id: u32| key[a.members[&id][0].0][&a.members[&id][0].1] as u32;
    let agree = (0..plain.len())
        .filter(|&i| truth[i] != 0 && seg.labels[i] != 0)
        .filter(|&i| truth_of(seg.labels[i]) == truth[i])
        .count();
    let labelled = (0..plain.len()).filter(|&i| truth[i] != 0 && seg.labels[i] != 0).count();
    assert!(labelled > 300 && agree == labelled, "{agree} of {labelled}");
    // Held-out IoU against such masks: each view's mask of the instance's category that overlaps
    // it most, as the rewritten masks give it (the view that misses instance 3 is skipped).
    let regions = instance_regions(&gpu, &k, &plain, &seg.labels, &views, &ids).unwrap();
    for (&id, r) in ids.iter().zip(&regions) {
        let per_frame = instance_iou_per_frame(r, &scrambled, &cats, "blob");
        let global = instance_iou(r, &a.masks, id);
        let shown = a.members[&id].len();
        assert_eq!(per_frame.len(), shown, "instance {id}");
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean(&per_frame) > 0.7 && mean(&per_frame) >= mean(&global) - 1e-9, "{per_frame:?} {global:?}");
    }
    assert_clean(&gpu);
}

#[test]
fn mask_and_category_files_are_checked() {
    use instgs_vk::dataset::masks::{load_frame_categories, read_mask};
    let d = tempdir("seg_masks");
    let masks = d.join("masks").join("train");
    std::fs::create_dir_all(&masks).unwrap();
    let m = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(10, 8, |x, _| image::Luma([(x / 4) as u16]));
    m.save(masks.join("r_000.png")).unwrap();
    assert_eq!(read_mask(&masks.join("r_000.png"), 10, 8).unwrap()[9], 2);
    let e = format!("{:#}", read_mask(&masks.join("r_000.png"), 12, 8).unwrap_err());
    assert!(e.contains("r_000.png") && e.contains("10x8") && e.contains("12x8"), "{e}");
    image::RgbImage::new(10, 8).save(masks.join("rgb.png")).unwrap();
    let e = format!("{:#}", read_mask(&masks.join("rgb.png"), 10, 8).unwrap_err());
    assert!(e.contains("rgb.png") && e.contains("greyscale"), "{e}");
    // Per-frame categories: every id of the mask needs one.
    let camera = look_at(Vec3::new(0.0, 0.0, -3.0), Vec3::ZERO, Vec3::new(0.0, -1.0, 0.0), 10, 8, 10.0);
    let view = instgs_vk::dataset::View {
        camera,
        image: Vec::new(),
        path: d.join("train").join("r_000.png"),
        undistort: None,
    };
    let mask = read_mask(&masks.join("r_000.png"), 10, 8).unwrap();
    let load = |text: &str| {
        std::fs::write(masks.join("r_000.json"), text).unwrap();
        load_frame_categories(&d, "train", std::slice::from_ref(&view), std::slice::from_ref(&mask))
    };
    let ok = load(r#"{"1": "mug", "2": "ball", "9": "unused"}"#).unwrap();
    assert_eq!(ok[0][&2], "ball");
    let e = format!("{:#}", load(r#"{"1": "mug"}"#).unwrap_err());
    assert!(e.contains("r_000.json") && e.contains("mask id 2") && e.contains("no category"), "{e}");
    let e = format!("{:#}", load(r#"{"x": "mug"}"#).unwrap_err());
    assert!(e.contains("\"x\" is not a mask id"), "{e}");
    let e = format!("{:#}", load(r#"{"0": "mug", "1": "a", "2": "b"}"#).unwrap_err());
    assert!(e.contains("id 0 is the background"), "{e}");
    std::fs::remove_file(masks.join("r_000.json")).unwrap();
    let e = format!("{:#}", load_frame_categories(&d, "train", &[view], &[mask]).unwrap_err());
    assert!(e.contains("r_000.json") && e.contains("cannot read"), "{e}");
    // Mask names: the image's own name, or its stem with .png as 2D segmenters write them.
    use instgs_vk::dataset::masks::mask_path;
    let photo = d.join("images").join("img_001.jpg");
    let e = format!("{:#}", mask_path(&d, "train", &photo).unwrap_err());
    assert!(e.contains("img_001.jpg") && e.contains("img_001.png") && e.contains("missing"), "{e}");
    m.save_with_format(masks.join("img_001.png"), image::ImageFormat::Png).unwrap();
    assert_eq!(mask_path(&d, "train", &photo).unwrap(), masks.join("img_001.png"));
    m.save_with_format(masks.join("img_001.jpg"), image::ImageFormat::Png).unwrap();
    assert_eq!(mask_path(&d, "train", &photo).unwrap(), masks.join("img_001.jpg"));
}
