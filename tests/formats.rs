//! Other tools' scene files (`instgs_vk::formats`): the shared real files against their decoded
//! PLYs (renders from the same cameras, Gaussian counts), our writers read back by our readers
//! (attribute errors within each format's quantisation), detection by content, clear errors.
mod common;

use std::path::Path;

use common::{assert_clean, gpu, shared_data};
use instgs_vk::formats::ply::{read_ply, write_compressed_ply};
use instgs_vk::formats::{self, Format};
use instgs_vk::model::camera::{orbit_around, UpAxis};
use instgs_vk::model::scene::Scene;
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::render::upload::GpuScene;
use instgs_vk::util::psnr;

/// The worst PSNR over 4 orbit views (320×240) of `b` against `a`.
fn render_agreement(a: &Scene, b: &Scene) -> f64 {
    let (gpu, k) = gpu();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    let (ga, gb) = (GpuScene::new(&gpu, a).unwrap(), GpuScene::new(&gpu, b).unwrap());
    let mut worst = f64::INFINITY;
    for cam in orbit_around(a, 4, UpAxis::NegY, 320, 240) {
        let x = r.render(&ga, &cam, [0.0; 3]).unwrap().image;
        let y = r.render(&gb, &cam, [0.0; 3]).unwrap().image;
        worst = worst.min(psnr(&x, &y));
    }
    assert_clean(&gpu);
    worst
}

/// A path in this run's folder under cargo's temporary directory (target/tmp/formats, emptied
/// once per run).
fn tmp(name: &str) -> std::path::PathBuf {
    static DIR: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    DIR.get_or_init(|| common::tempdir("formats")).join(name)
}

/// Largest absolute difference per attribute: (means, log-scales, quats up to sign, opacity
/// as alpha, sh0, shN).
fn max_errors(a: &Scene, b: &Scene) -> [f32; 6] {
    assert_eq!(a.len(), b.len());
    assert_eq!(a.sh_degree, b.sh_degree);
    let coeffs = a.sh_coeffs();
    let mut e = [0.0f32; 6];
    let sig = |x: f32| 1.0 / (1.0 + (-x).exp());
    for i in 0..a.len() {
        for k in 0..3 {
            e[0] = e[0].max((a.means[i][k] - b.means[i][k]).abs());
            e[1] = e[1].max((a.scales[i][k] - b.scales[i][k]).abs());
        }
        let n = |q: [f32; 4]| {
            let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            q.map(|v| v / l)
        };
        let (qa, qb) = (n(a.quats[i]), n(b.quats[i]));
        let dot: f32 = (0..4).map(|k| qa[k] * qb[k]).sum();
        let s = if dot < 0.0 { -1.0 } else { 1.0 };
        for k in 0..4 {
            e[2] = e[2].max((qa[k] - s * qb[k]).abs());
        }
        e[3] = e[3].max((sig(a.opacities[i]) - sig(b.opacities[i])).abs());
        for j in 0..coeffs * 3 {
            let d = (a.sh[i * coeffs * 3 + j] - b.sh[i * coeffs * 3 + j]).abs();
            let slot = if j < 3 { 4 } else { 5 };
            e[slot] = e[slot].max(d);
        }
    }
    e
}

#[test]
fn spz_v4_reads_like_its_decoded_ply() {
    let path = shared_data("splats/biker.spz");
    assert_eq!(formats::detect(&path).unwrap(), Format::Spz);
    let spz = formats::read_scene(&path).unwrap();
    let ply = read_ply(&shared_data("splats/biker.ply")).unwrap();
    assert_eq!(spz.len(), ply.len());
    // The same Gaussians in the same order, in the PLY's frame (y and z negated on reading).
    let e = max_errors(&ply, &spz);
    assert!(e[0] <= 2e-4, "positions differ by {}", e[0]);
    let db = render_agreement(&ply, &spz);
    eprintln!("biker.spz against biker.ply: {db:.1} dB (worst of 4 views); errors {e:?}");
    assert!(db >= 45.0, "biker.spz renders {db:.1} dB from biker.ply");
}

#[test]
fn sog_reads_like_its_decoded_ply() {
    for (dir, ply) in [("playbot/2_0", "playbot_lod2.ply"), ("playbot/6_0/meta.json", "playbot_lod6.ply")] {
        let path = shared_data(&format!("splats/{dir}"));
        assert_eq!(formats::detect(&path).unwrap(), Format::Sog);
        let sog = formats::read_scene(&path).unwrap();
        let reference = read_ply(&shared_data(&format!("splats/{ply}"))).unwrap();
        assert_eq!(sog.len(), reference.len(), "{dir}");
        assert_eq!(sog.sh_degree, 2, "{dir}");
        let db = render_agreement(&reference, &sog);
        eprintln!("{dir} against {ply}: {db:.1} dB (worst of 4 views)");
        assert!(db >= 45.0, "{dir} renders {db:.1} dB from {ply}");
    }
}

#[test]
fn compressed_ply_with_sh_round_trips() {
    // playbot has SH degree 2: our writer's `sh` element, read back.
    let source = read_ply(&shared_data("splats/playbot_lod2.ply")).unwrap();
    let out = tmp("playbot.compressed.ply");
    write_compressed_ply(&source, &out).unwrap();
    assert_eq!(formats::detect(&out).unwrap(), Format::Ply);
    let back = formats::read_scene(&out).unwrap();
    let e = max_errors(&source, &back);
    // SH: 8 bits over ±4 (one bin 1/32, half a bin at most off, and the clamp beyond ±4).
    let clamped = source.sh.iter().enumerate().any(|(j, v)| j % 27 >= 3 && v.abs() > 4.0);
    assert!(clamped || e[5] <= 1.0 / 32.0 + 1e-6, "SH error {}", e[5]);
    assert!(e[3] <= 0.5 / 255.0 + 1e-6, "opacity error {}", e[3]);
    let db = render_agreement(&source, &back);
    eprintln!("playbot_lod2 through our compressed PLY with SH: {db:.1} dB; errors {e:?}");
    assert!(db >= 45.0, "{db:.1} dB");
    // The shared compressed files (no SH) still read as before.
    let guitar = formats::read_scene(&shared_data("splats/guitar.compressed.ply")).unwrap();
    assert_eq!(guitar.len(), 90_854);
}

#[test]
fn spz_writer_round_trips_within_its_quantisation() {
    // fruit_drops has SH degree 3.
    for name in ["biker.ply", "fruit_drops_minimal.ply"] {
        let source = read_ply(&shared_data(&format!("splats/{name}"))).unwrap();
        let out = tmp(&format!("{name}.spz"));
        formats::spz::write_spz(&source, &out).unwrap();
        let back = formats::read_scene(&out).unwrap();
        let e = max_errors(&source, &back);
        eprintln!("{name} through .spz: errors {e:?}");
        assert!(e[0] <= 0.5 / 4096.0 + 1e-6, "{name}: position error {}", e[0]);
        assert!(e[3] <= 0.5 / 255.0 + 1e-6, "{name}: opacity error {}", e[3]);
        // Log-scales in 1/16 steps from −10 (clamped to the byte's range outside it).
        let inside = source.scales.iter().flatten().all(|&v| (-10.0..=5.9).contains(&v));
        assert!(!inside || e[1] <= 1.0 / 32.0 + 1e-5, "{name}: scale error {}", e[1]);
        assert!(e[2] <= 2e-3, "{name}: rotation error {}", e[2]);
        let db = render_agreement(&source, &back);
        eprintln!("{name} through .spz: {db:.1} dB");
        assert!(db >= 30.0, "{name}: {db:.1} dB");
        // Writing what we read back moves nothing by more than rounding: the quantisation is
        // stable under itself.
        let again = tmp(&format!("{name}.2.spz"));
        formats::spz::write_spz(&back, &again).unwrap();
        let e2 = max_errors(&back, &formats::read_scene(&again).unwrap());
        assert!(e2.iter().all(|&v| v <= 2e-3), "{name}: a second round trip moved {e2:?}");
    }
}

#[test]
fn splat_writer_round_trips_within_its_quantisation() {
    let source = read_ply(&shared_data("splats/guitar.ply")).unwrap();
    let out = tmp("guitar.splat");
    formats::splat::write_splat(&source, &out).unwrap();
    assert_eq!(formats::detect(&out).unwrap(), Format::Splat);
    let back = formats::read_scene(&out).unwrap();
    let e = max_errors(&source, &back);
    assert_eq!(e[0], 0.0, "positions are f32");
    assert!(e[1] <= 1e-5, "scales are f32 (linear): {}", e[1]);
    assert!(e[3] <= 0.5 / 255.0 + 1e-6, "opacity error {}", e[3]);
    // Colours in [0, 1] keep 8 bits (half a step off at most); others are clamped.
    let c0 = 0.282_094_8;
    let colour = |s: &Scene, i: usize, c: usize| 0.5 + c0 * s.sh[3 * i + c];
    let mut worst = 0.0f32;
    for i in 0..source.len() {
        for c in 0..3 {
            if (0.0..=1.0).contains(&colour(&source, i, c)) {
                worst = worst.max((colour(&source, i, c) - colour(&back, i, c)).abs());
            }
        }
    }
    assert!(worst <= 0.5 / 255.0 + 1e-5, "colour error {worst}");
    let db = render_agreement(&source, &back);
    eprintln!("guitar through .splat: {db:.1} dB; errors {e:?}");
    assert!(db >= 30.0, "{db:.1} dB");
}

#[test]
fn infinite_opacity_logits_are_clamped_and_nan_refused() {
    // A PLY as splat-transform writes fully opaque splats: opacity ±inf (our writers refuse to
    // write such a scene, so the file is made by hand).
    let props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"];
    let props: String =
        props.iter().chain(&["rot_0", "rot_1", "rot_2", "rot_3"]).map(|p| format!("property float {p}\n")).collect();
    let ply = |opacities: &[f32]| {
        let mut b =
            format!("ply\nformat binary_little_endian 1.0\nelement vertex {}\n{props}end_header\n", opacities.len())
                .into_bytes();
        for &o in opacities {
            for v in [0.0, 0.0, 0.0, 0.5, 0.5, 0.5, o, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0f32] {
                b.extend_from_slice(&v.to_le_bytes());
            }
        }
        b
    };
    let out = tmp("inf.ply");
    std::fs::write(&out, ply(&[0.0, 1.0, f32::INFINITY, f32::NEG_INFINITY])).unwrap();
    let back = formats::read_scene(&out).unwrap();
    assert_eq!(back.opacities[2], formats::quant::OPACITY_LOGIT_LIMIT);
    assert_eq!(back.opacities[3], -formats::quant::OPACITY_LOGIT_LIMIT);
    assert!((formats::quant::OPACITY_LOGIT_LIMIT - 1019f32.ln()).abs() < 1e-5);
    std::fs::write(&out, ply(&[0.0, f32::NAN])).unwrap();
    let e = format!("{:#}", formats::read_scene(&out).unwrap_err());
    assert!(e.contains("inf.ply") && e.contains("non-finite opacity"), "{e}");
    // Our writer refuses the NaN scene instead of writing a file the reader refuses.
    let mut s = back.clone();
    s.opacities[1] = f32::NAN;
    let e = format!("{:#}", instgs_vk::formats::ply::write_ply(&s, &tmp("nan.ply")).unwrap_err());
    assert!(e.contains("nan.ply: not written") && e.contains("non-finite opacity"), "{e}");
    assert!(!tmp("nan.ply").exists());
}

#[test]
fn unreadable_files_name_what_they_are_and_what_we_read() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (file, detected) in [("docs/curves.png", "a PNG image"), ("Cargo.toml", "text")] {
        let e = format!("{:#}", formats::read_scene(&root.join(file)).unwrap_err());
        assert!(e.contains(file) && e.contains(detected) && e.contains(".spz") && e.contains("SOG"), "{e}");
    }
    // A .spz cut short, and a gzip stream that is not a .spz.
    let bytes = std::fs::read(shared_data("splats/biker.spz")).unwrap();
    let cut = tmp("cut.spz");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = format!("{:#}", formats::read_scene(&cut).unwrap_err());
    assert!(e.contains("cut.spz") && e.contains("truncated"), "{e}");
    let gz = tmp("other.spz");
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    std::io::Write::write_all(&mut enc, b"hello, not a splat file").unwrap();
    std::fs::write(&gz, enc.finish().unwrap()).unwrap();
    let e = format!("{:#}", formats::read_scene(&gz).unwrap_err());
    assert!(e.contains("other.spz") && e.contains("not a .spz"), "{e}");
    // A .splat whose size is not a multiple of 32.
    let odd = tmp("odd.splat");
    std::fs::write(&odd, [0u8; 33]).unwrap();
    let e = format!("{:#}", formats::read_scene(&odd).unwrap_err());
    assert!(e.contains("odd.splat") && e.contains("32-byte rows"), "{e}");
}

#[test]
fn dataset_cameras_export_and_read_back() {
    // A COLMAP capture (one camera per image, heights 328-331) and a NeRF-synthetic scene.
    for (data, split, n) in [("colmap/statue", "all", 23), ("colmap/statue", "test", 3), ("scenes/ducks6", "test", 12)]
    {
        let dir = shared_data(data);
        let cams = instgs_vk::dataset::dataset_cameras_with_images(&dir, split).unwrap();
        assert_eq!(cams.len(), n, "{data} {split}");
        let images: Vec<String> = cams.iter().map(|(_, p)| p.display().to_string()).collect();
        let only: Vec<_> = cams.iter().map(|(c, _)| c.clone()).collect();
        let json = instgs_vk::model::camera::transforms_json(&only, &images);
        let out = tmp(&format!("{}-{split}.json", data.replace('/', "-")));
        std::fs::write(&out, serde_json::to_string(&json).unwrap()).unwrap();
        let back = instgs_vk::dataset::dataset_cameras_with_images(&out, "train").unwrap();
        assert_eq!(back.len(), n);
        for ((a, pa), (b, pb)) in cams.iter().zip(&back) {
            assert_eq!(a.name, b.name);
            assert_eq!((a.width, a.height, a.fx, a.fy, a.cx, a.cy), (b.width, b.height, b.fx, b.fy, b.cx, b.cy));
            assert!((a.viewmat - b.viewmat).abs().to_cols_array().iter().all(|&d| d < 1e-5), "{}", a.name);
            assert_eq!(pa, pb);
        }
    }
}

#[test]
fn sog_writer_round_trips_within_its_quantisation() {
    // fruit_drops: SH degree 3 (the palette), 4.7k Gaussians.
    let source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    let out = tmp("sog/meta.json");
    formats::sog::write_sog(&source, &out).unwrap();
    assert_eq!(formats::detect(out.parent().unwrap()).unwrap(), Format::Sog);
    let back = formats::read_scene(&out).unwrap();
    let e = max_errors(&source, &back);
    let db = render_agreement(&source, &back);
    eprintln!("fruit_drops through SOG: {db:.1} dB; errors {e:?}");
    // Positions: 16 bits over the log range; opacity: 8 bits.
    assert!(e[0] <= 1e-4, "position error {}", e[0]);
    assert!(e[3] <= 0.5 / 255.0 + 1e-6, "opacity error {}", e[3]);
    // Codebooks and the SH palette are k-means: no fixed bound, the picture is the measure.
    assert!(db >= 38.0, "{db:.1} dB");
}

#[test]
fn sog_holds_colours_near_f32_max_and_refuses_such_positions() {
    // The codebooks' k-means once started from the values' span in f32, which overflows to
    // infinity for values near ±f32::MAX (found by fuzzing instgs_parse); such a scene is
    // written now, its extremes kept.
    let mut source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    let row = source.sh_coeffs() * 3;
    source.sh[0] = 3.0e38;
    source.sh[row] = -3.0e38;
    source.sh[3] = 3.0e38; // a coefficient of the SH bands (the palette's codebook)
    let out = tmp("sog-extremes/meta.json");
    formats::sog::write_sog(&source, &out).unwrap();
    let back = formats::read_scene(&out).unwrap();
    assert!(back.sh.iter().all(|v| v.is_finite()));
    for (i, want) in [(0, 3.0e38f32), (row, -3.0e38)] {
        assert!((back.sh[i] / want - 1.0).abs() < 0.01, "sh[{i}] {} for {want}", back.sh[i]);
    }
    // A position near f32::MAX has a log the reader's exp cannot undo: refused in one line
    // naming the file, nothing written (found by fuzzing instgs_parse).
    source.means[1][0] = -f32::MAX;
    let out = tmp("sog-far/meta.json");
    let e = format!("{:#}", formats::sog::write_sog(&source, &out).unwrap_err());
    assert!(e.contains("sog-far/meta.json") && e.contains("Gaussian 1's position"), "{e}");
    assert!(!e.contains('\n') && !out.parent().unwrap().exists(), "{e}");
}

#[test]
fn a_sog_bundle_reads_like_its_folder() {
    // One zip file (splat-transform 3.x's default SOG output) holds the folder's files.
    let source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    let folder = tmp("sog-bundle/folder/meta.json");
    formats::sog::write_sog(&source, &folder).unwrap();
    let bundle = tmp("sog-bundle/scene.sog");
    formats::write_scene(&source, &bundle).unwrap();
    assert_eq!(formats::detect(&bundle).unwrap(), Format::Sog);
    let from_folder = formats::read_scene(&folder).unwrap();
    let from_bundle = formats::read_scene(&bundle).unwrap();
    assert!(from_bundle == from_folder, "the bundle decodes as its folder does");
    assert_eq!(formats::file_bytes(&bundle).unwrap(), std::fs::metadata(&bundle).unwrap().len());
    // Its entries: meta.json first, then the images the folder has, stored.
    let mut zip = zip::ZipArchive::new(std::fs::File::open(&bundle).unwrap()).unwrap();
    let names: Vec<String> = (0..zip.len()).map(|i| zip.by_index(i).unwrap().name().unwrap().to_string()).collect();
    assert_eq!(names[0], "meta.json");
    let mut on_disk: Vec<String> = std::fs::read_dir(folder.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    on_disk.sort();
    let mut sorted = names.clone();
    sorted.sort();
    assert_eq!(sorted, on_disk);
    // A deflated bundle (zip's other common method) reads the same.
    let deflated = tmp("sog-bundle/deflated.sog");
    let mut w = zip::ZipWriter::new(std::fs::File::create(&deflated).unwrap());
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    for n in &names {
        w.start_file(n.as_str(), opts).unwrap();
        std::io::Write::write_all(&mut w, &std::fs::read(folder.parent().unwrap().join(n)).unwrap()).unwrap();
    }
    w.finish().unwrap();
    assert!(formats::read_scene(&deflated).unwrap() == from_folder);
}

/// A SOG version 1 folder for `s` (splat-transform's legacy layout, written here because no
/// shared file has it): per-channel 8-bit lerps for scales and sh0 (opacity logit included),
/// one SH palette entry per Gaussian lerped between scalar bounds.
fn write_sog_v1(s: &Scene, dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let n = s.len();
    let coeffs = s.sh_coeffs() - 1;
    let w = 64;
    let h = n.div_ceil(w);
    let webp = |name: &str, w: usize, h: usize, rgba: &[u8]| {
        let mut bytes = Vec::new();
        image::codecs::webp::WebPEncoder::new_lossless(&mut bytes)
            .encode(rgba, w as u32, h as u32, image::ExtendedColorType::Rgba8)
            .unwrap();
        std::fs::write(dir.join(name), bytes).unwrap();
    };
    let bounds = |f: &dyn Fn(usize) -> Vec<f32>, k: usize| {
        let mut lo = vec![f32::MAX; k];
        let mut hi = vec![f32::MIN; k];
        for i in 0..n {
            for (c, v) in f(i).into_iter().enumerate() {
                lo[c] = lo[c].min(v);
                hi[c] = hi[c].max(v);
            }
        }
        (lo, hi)
    };
    let byte = |v: f32, lo: f32, hi: f32| ((v - lo) / (hi - lo).max(1e-12) * 255.0).round().clamp(0.0, 255.0) as u8;
    let log = |x: f32| x.signum() * (x.abs() + 1.0).ln();
    let (mlo, mhi) = bounds(&|i| s.means[i].iter().map(|&x| log(x)).collect(), 3);
    let (slo, shi) = bounds(&|i| s.scales[i].to_vec(), 3);
    let c = s.sh_coeffs() * 3;
    let (clo, chi) = bounds(&|i| vec![s.sh[i * c], s.sh[i * c + 1], s.sh[i * c + 2], s.opacities[i]], 4);
    let rest: Vec<f32> = (0..n).flat_map(|i| s.sh[i * c + 3..(i + 1) * c].to_vec()).collect();
    let (rlo, rhi) = rest.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let mut img =
        [vec![0u8; w * h * 4], vec![0u8; w * h * 4], vec![0u8; w * h * 4], vec![0u8; w * h * 4], vec![0u8; w * h * 4]];
    let mut labels = vec![0u8; w * h * 4];
    let (cw, ch) = (64 * coeffs, n.div_ceil(64));
    let mut centroids = vec![0u8; cw * ch * 4];
    for i in 0..n {
        let o = i * 4;
        for a in 0..3 {
            let q = (((log(s.means[i][a]) - mlo[a]) / (mhi[a] - mlo[a]) * 65535.0).round()) as u32;
            img[0][o + a] = (q & 255) as u8;
            img[1][o + a] = (q >> 8) as u8;
            img[3][o + a] = byte(s.scales[i][a], slo[a], shi[a]);
            img[4][o + a] = byte(s.sh[i * c + a], clo[a], chi[a]);
        }
        img[4][o + 3] = byte(s.opacities[i], clo[3], chi[3]);
        let l = s.quats[i].iter().map(|v| v * v).sum::<f32>().sqrt();
        let mut q = s.quats[i].map(|v| v / l);
        let largest = (0..4).max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs())).unwrap();
        if q[largest] < 0.0 {
            q = q.map(|v| -v);
        }
        let mut k = 0;
        for (j, v) in q.iter().enumerate() {
            if j != largest {
                img[2][o + k] = ((v * std::f32::consts::SQRT_2 + 1.0) * 0.5 * 255.0).round() as u8;
                k += 1;
            }
        }
        img[2][o + 3] = 252 + largest as u8;
        labels[o] = (i & 255) as u8;
        labels[o + 1] = (i >> 8) as u8;
        for j in 0..coeffs {
            let t = ((i / 64) * cw + (i % 64) * coeffs + j) * 4;
            for ch in 0..3 {
                centroids[t + ch] = byte(s.sh[i * c + 3 + j * 3 + ch], rlo, rhi);
            }
        }
    }
    let names = ["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"];
    for (name, data) in names.iter().zip(&img) {
        webp(name, w, h, data);
    }
    webp("shN_labels.webp", w, h, &labels);
    webp("shN_centroids.webp", cw, ch, &centroids);
    let meta = serde_json::json!({
        "means": {"shape": [n, 3], "mins": mlo, "maxs": mhi, "files": [names[0], names[1]]},
        "scales": {"mins": slo, "maxs": shi, "files": [names[3]]},
        "quats": {"files": [names[2]]},
        "sh0": {"mins": clo, "maxs": chi, "files": [names[4]]},
        "shN": {"mins": rlo, "maxs": rhi, "files": ["shN_centroids.webp", "shN_labels.webp"]},
    });
    std::fs::write(dir.join("meta.json"), meta.to_string()).unwrap();
}

#[test]
fn sog_version_1_reads_within_its_quantisation() {
    let source = read_ply(&shared_data("splats/playbot_lod6.ply")).unwrap();
    let dir = tmp("sog-v1");
    write_sog_v1(&source, &dir);
    assert_eq!(formats::detect(&dir).unwrap(), Format::Sog);
    let back = formats::read_scene(&dir).unwrap();
    let e = max_errors(&source, &back);
    let db = render_agreement(&source, &back);
    eprintln!("playbot_lod6 through SOG version 1: {db:.1} dB; errors {e:?}");
    assert!(e[0] <= 1e-3, "position error {}", e[0]);
    assert!(db >= 40.0, "{db:.1} dB");
}

#[test]
fn a_colmap_point_that_is_not_finite_is_refused_at_the_door() {
    // Was a panic inside the k-d tree of the initial scales (issue 24).
    let dir = tmp("colmap-nan");
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    for f in ["cameras.bin", "images.bin", "points3D.bin"] {
        std::fs::copy(shared_data(&format!("colmap/statue/sparse/0/{f}")), sparse.join(f)).unwrap();
    }
    let mut points = std::fs::read(sparse.join("points3D.bin")).unwrap();
    // count u64, then the first point: id u64, x f64 …
    points[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(sparse.join("points3D.bin"), &points).unwrap();
    let e = format!("{:#}", instgs_vk::dataset::read_colmap(&sparse).unwrap_err());
    assert!(e.contains("points3D.bin") && e.contains("non-finite"), "{e}");
}

/// SOG's means are lerp(mins, maxs, q) whatever the bounds' order: a file written with them
/// swapped (and every q mirrored) reads as the same scene.
#[test]
fn sog_bounds_in_either_order_read_the_same() {
    let source = read_ply(&shared_data("splats/playbot_lod6.ply")).unwrap();
    let dir = tmp("sog-swapped");
    formats::sog::write_sog(&source, &dir.join("meta.json")).unwrap();
    let before = formats::read_scene(&dir).unwrap();
    let meta_path = dir.join("meta.json");
    let mut meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&meta_path).unwrap()).unwrap();
    let m = meta["means"].clone();
    meta["means"]["mins"] = m["maxs"].clone();
    meta["means"]["maxs"] = m["mins"].clone();
    for k in 0..2 {
        let f = dir.join(m["files"][k].as_str().unwrap());
        let mut img = image::open(&f).unwrap().to_rgba8();
        for p in img.pixels_mut() {
            for c in 0..3 {
                p.0[c] = 255 - p.0[c];
            }
        }
        let mut bytes = Vec::new();
        image::codecs::webp::WebPEncoder::new_lossless(&mut bytes)
            .encode(img.as_raw(), img.width(), img.height(), image::ExtendedColorType::Rgba8)
            .unwrap();
        std::fs::write(&f, bytes).unwrap();
    }
    std::fs::write(&meta_path, meta.to_string()).unwrap();
    let after = formats::read_scene(&dir).unwrap();
    let e = max_errors(&before, &after);
    assert!(e[0] <= 1e-5 * 10.0, "positions moved by {}", e[0]);
}

/// A .splat's name decides, whatever its first bytes look like (a row whose x starts with
/// gzip's magic is still a row).
#[test]
fn a_splat_file_is_read_as_splat_whatever_its_first_bytes() {
    let dir = tmp("splat-gzip-like");
    std::fs::create_dir_all(&dir).unwrap();
    let mut row = [0u8; 32];
    row[0..4].copy_from_slice(&[0x1f, 0x8b, 0x08, 0x3f]);
    row[12..24].copy_from_slice(&[0.01f32, 0.01, 0.01].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<_>>());
    row[24..28].copy_from_slice(&[200, 100, 50, 255]);
    row[28..32].copy_from_slice(&[255, 128, 128, 128]);
    let p = dir.join("s.splat");
    std::fs::write(&p, row).unwrap();
    assert_eq!(formats::detect(&p).unwrap(), Format::Splat);
    assert_eq!(formats::read_scene(&p).unwrap().len(), 1);
}

/// Multi-file outputs appear whole or not at all: a write that fails halfway leaves the folder
/// as it was (an existing SOG still reads the same) and no temporary folder behind.
#[test]
fn a_failed_folder_write_changes_nothing() {
    let source = read_ply(&shared_data("splats/playbot_lod6.ply")).unwrap();
    let dir = tmp("sog-overwrite");
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("sog");
    formats::sog::write_sog(&source, &out.join("meta.json")).unwrap();
    let snapshot = |d: &Path| -> Vec<(String, Vec<u8>)> {
        let mut v: Vec<_> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().path())
            .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
            .collect();
        v.sort();
        v
    };
    let before = snapshot(&out);
    let e = instgs_vk::util::write_dir_atomic(&out, Some("meta.json"), |tmp| {
        std::fs::write(tmp.join("meta.json"), "{}")?;
        std::fs::write(tmp.join("means_l.webp"), "half")?;
        anyhow::bail!("disk full (simulated)")
    });
    assert!(e.is_err());
    assert_eq!(snapshot(&out), before, "the old SOG changed");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "a temporary folder stayed behind");
    assert_eq!(formats::read_scene(&out).unwrap().len(), source.len());
    // A folder the failed write would have created does not appear.
    let fresh = dir.join("fresh");
    assert!(instgs_vk::util::write_dir_atomic(&fresh, None, |_| anyhow::bail!("no")).is_err());
    assert!(!fresh.exists());
}

fn fixture(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/splat-transform").join(name)
}

#[test]
fn gltf_round_trips_a_scene_exactly_in_renders() {
    // Our .glb and .gltf of a real splat read back: floats, so only the exp/ln of scales and
    // the sigmoid/logit of opacities round.
    let source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    for name in ["fruit.glb", "fruit.gltf"] {
        let out = tmp(name);
        formats::write_scene(&source, &out).unwrap();
        assert_eq!(formats::detect(&out).unwrap(), Format::Gltf, "{name}");
        let back = formats::read_scene(&out).unwrap();
        let e = max_errors(&source, &back);
        assert!(
            e[0] < 1e-6 && e[1] < 1e-5 && e[2] < 1e-6 && e[3] < 1e-6 && e[4] == 0.0 && e[5] == 0.0,
            "{name}: {e:?}"
        );
        let db = render_agreement(&source, &back);
        assert!(db >= 90.0, "{name}: {db:.1} dB");
    }
    // A .gltf whose buffer is a file beside it (what most exporters write) reads the same.
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(tmp("fruit.gltf")).unwrap()).unwrap();
    let uri = doc["buffers"][0]["uri"].as_str().unwrap().to_string();
    std::fs::write(tmp("fruit.bin"), base64::decode(&uri[uri.find(',').unwrap() + 1..]).unwrap()).unwrap();
    doc["buffers"][0]["uri"] = "fruit.bin".into();
    std::fs::write(tmp("beside.gltf"), serde_json::to_vec(&doc).unwrap()).unwrap();
    assert!(formats::read_scene(&tmp("beside.gltf")).unwrap() == formats::read_scene(&tmp("fruit.gltf")).unwrap());
}

#[test]
fn gltf_frame_is_a_half_turn_about_z_with_sh_signs() {
    // One splat with one SH coefficient at a time: the glTF file holds (−x, −y, z), the
    // quaternion turned and the coefficient times (−1)^m; reading turns it back.
    let mut s = Scene {
        means: vec![[0.1, 0.2, 0.3]],
        scales: vec![[-1.0, -2.0, -3.0]],
        quats: vec![[0.9, 0.1, 0.2, 0.3]],
        opacities: vec![0.5],
        sh: vec![0.0; 48],
        sh_degree: 3,
    };
    for k in 0..16 {
        s.sh.iter_mut().for_each(|v| *v = 0.0);
        s.sh[k * 3] = 1.0;
        let mut turned = s.clone();
        formats::gltf::half_turn_z(&mut turned);
        assert_eq!(turned.means[0], [-0.1, -0.2, 0.3]);
        let l = (k as f64).sqrt().floor() as i64;
        let m = k as i64 - l * l - l;
        assert_eq!(turned.sh[k * 3], if m % 2 == 0 { 1.0 } else { -1.0 }, "k {k}");
        let out = tmp("frame.glb");
        formats::write_scene(&s, &out).unwrap();
        let back = formats::read_scene(&out).unwrap();
        assert!(max_errors(&s, &back).iter().all(|e| *e < 1e-6), "k {k}");
    }
    // The rotation: R(q') = Rz(π)·R(q).
    let q = glam::Quat::from_xyzw(0.1, 0.2, 0.3, 0.9).normalize();
    let mut t = s.clone();
    t.quats[0] = [q.w, q.x, q.y, q.z];
    formats::gltf::half_turn_z(&mut t);
    let [w, x, y, z] = t.quats[0];
    let turned = glam::Quat::from_xyzw(x, y, z, w);
    let expect = glam::Quat::from_rotation_z(std::f32::consts::PI) * q;
    assert!(turned.dot(expect).abs() > 1.0 - 1e-6);
}

#[test]
fn splat_transform_files_read_like_their_ply() {
    // Fixtures splat-transform 3.7.0 wrote from 300 splats of fruit_drops (SH 3 and SH 0):
    // every format it writes, decoded by our readers, against the PLY it read.
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for sh in ["sh0", "sh3"] {
        let ply = read_ply(&fixture(&format!("{sh}.ply"))).unwrap();
        for (ext, floor) in [("glb", 90.0), ("compressed.ply", 50.0), ("sog", 50.0)] {
            let file = fixture(&format!("{sh}.st.{ext}"));
            let s = formats::read_scene(&file).unwrap();
            assert_eq!(s.len(), ply.len(), "{sh} {ext}");
            assert_eq!(s.sh_degree, ply.sh_degree, "{sh} {ext}");
            let db = render_agreement(&ply, &s);
            assert!(db >= floor, "{sh}.st.{ext}: {db:.1} dB");
            eprintln!("{sh}.st.{ext}: {db:.1} dB");
        }
        // Its .spz has no axis change: our reading (the specification's) sees it turned,
        // --spz-frame as-stored reads it as splat-transform meant.
        let spz = fixture(&format!("{sh}.st.spz"));
        let spec = formats::read_scene(&spz).unwrap();
        let out = tmp(&format!("{sh}-as-stored.ply"));
        let bin = env!("CARGO_BIN_EXE_instgs-vk");
        let st = std::process::Command::new(bin)
            .args(["convert", "--spz-frame", "as-stored"])
            .arg(&spz)
            .arg(&out)
            .current_dir(root)
            .output()
            .unwrap();
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        let as_stored = read_ply(&out).unwrap();
        let (db_spec, db_stored) = (render_agreement(&ply, &spec), render_agreement(&ply, &as_stored));
        eprintln!("{sh}.st.spz: as stored {db_stored:.1} dB, by the spec {db_spec:.1} dB");
        assert!(
            db_stored >= 40.0 && db_spec < 20.0,
            "{sh}.st.spz: as stored {db_stored:.1} dB, by the spec {db_spec:.1} dB"
        );
    }
}

#[test]
fn instanced_gltf_shares_templates_and_reads_back_the_instanced_scene() {
    let mut rng = common::Rng::new(46);
    let scene = common::random_instanced(&mut rng, 3, 200, &[(150, 4), (80, 3)]);
    let glb = tmp("instanced.glb");
    formats::gltf::write_instanced_gltf(&scene, &glb, formats::gltf::Accessors::Float).unwrap();
    let formats::AnyScene::Instanced(back) = formats::AnyScene::read(&glb).unwrap() else { panic!("read as plain") };
    assert_eq!(back.groups.len(), 2);
    for (a, b) in scene.groups.iter().zip(&back.groups) {
        assert_eq!(a.name, b.name);
        assert_eq!(
            a.instances.iter().map(|i| &i.id).collect::<Vec<_>>(),
            b.instances.iter().map(|i| &i.id).collect::<Vec<_>>()
        );
        let e = max_errors(&a.template, &b.template);
        assert!(e.iter().all(|v| *v < 1e-5), "template {e:?}");
        for (x, y) in a.instances.iter().zip(&b.instances) {
            let (x, y) = (x.transform, y.transform);
            assert!((x.scale - y.scale).abs() < 1e-5 && x.translation.distance(y.translation) < 1e-5);
            assert!(x.rotation.dot(y.rotation).abs() > 1.0 - 1e-6);
        }
        let d = |u: &[[f32; 3]], v: &[[f32; 3]]| {
            u.iter().flatten().zip(v.iter().flatten()).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max)
        };
        assert!(d(&a.offsets.d_means, &b.offsets.d_means) < 1e-5);
        assert!(d(&a.offsets.d_sh0, &b.offsets.d_sh0) < 1e-5);
        let o =
            a.offsets.d_opacities.iter().zip(&b.offsets.d_opacities).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
        assert!(o < 1e-3, "Δo {o}");
    }
    assert!(max_errors(&scene.background, &back.background).iter().all(|v| *v < 1e-5));
    let db = render_agreement(&scene.expand(), &back.expand());
    assert!(db >= 60.0, "{db:.1} dB");
    // Every accessor is one a primitive of the scene uses (the validator's UNUSED_OBJECT): the
    // templates' own rows are attributes of their first instances.
    let (doc, _) = glb_parts(&glb);
    let mut used: Vec<u64> = doc["meshes"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|m| m["primitives"].as_array().unwrap().iter())
        .flat_map(|p| p["attributes"].as_object().unwrap().values().map(|a| a.as_u64().unwrap()))
        .collect();
    used.sort();
    used.dedup();
    assert_eq!(used, (0..doc["accessors"].as_array().unwrap().len() as u64).collect::<Vec<_>>());
    // A plain reading (any other viewer's) is the expanded scene; the file is smaller than
    // the expanded .glb.
    let plain = formats::read_scene(&glb).unwrap();
    assert!(render_agreement(&scene.expand(), &plain) >= 60.0);
    let expanded = tmp("expanded.glb");
    formats::write_scene(&scene.expand(), &expanded).unwrap();
    let (shared, full) = (std::fs::metadata(&glb).unwrap().len(), std::fs::metadata(&expanded).unwrap().len());
    // 430 rows for 1040 splats: the background's 200 rows are whole in both.
    assert!(shared * 4 < full * 3, "{shared} vs {full} bytes");
}

#[test]
fn quantised_gltf_round_trips_within_16_bits_and_is_smaller() {
    use formats::gltf::Accessors;
    // A plain scene (SH degree 3): 16-bit positions under the node's dequantisation, 16-bit
    // rotations; KHR_mesh_quantization required.
    let source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    let (float, quantised) = (tmp("fruit-float.glb"), tmp("fruit-quantised.glb"));
    formats::gltf::write_gltf(&source, &float, Accessors::Float).unwrap();
    formats::gltf::write_gltf(&source, &quantised, Accessors::Quantized).unwrap();
    let (doc, _) = glb_parts(&quantised);
    assert_eq!(doc["extensionsRequired"], serde_json::json!(["KHR_mesh_quantization"]));
    let position =
        &doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"].as_u64().unwrap() as usize];
    assert_eq!((position["componentType"].as_u64(), position["normalized"].as_bool()), (Some(5122), Some(true)));
    let back = formats::read_scene(&quantised).unwrap();
    let db = render_agreement(&source, &back);
    let ratio = std::fs::metadata(&quantised).unwrap().len() as f64 / std::fs::metadata(&float).unwrap().len() as f64;
    eprintln!("fruit_drops through a quantised .glb: {db:.1} dB, {ratio:.3}x the float file's bytes");
    assert!(db >= 45.0, "{db:.1} dB");
    assert!(ratio < 1.0, "{ratio}");
    // An instanced scene: read back instanced, each instance's transform out of its node's
    // matrix (transform · dequantisation), within 16 bits of the float file's scene.
    let mut rng = common::Rng::new(47);
    let scene = common::random_instanced(&mut rng, 3, 200, &[(150, 4), (80, 3)]);
    let (float, quantised) = (tmp("instanced-float.glb"), tmp("instanced-quantised.glb"));
    formats::gltf::write_instanced_gltf(&scene, &float, Accessors::Float).unwrap();
    formats::gltf::write_instanced_gltf(&scene, &quantised, Accessors::Quantized).unwrap();
    let formats::AnyScene::Instanced(back) = formats::AnyScene::read(&quantised).unwrap() else {
        panic!("read as plain")
    };
    for (a, b) in scene.groups.iter().zip(&back.groups) {
        for (x, y) in a.instances.iter().zip(&b.instances) {
            let (x, y) = (x.transform, y.transform);
            assert!((x.scale - y.scale).abs() < 1e-4 && x.translation.distance(y.translation) < 1e-4, "{x:?} {y:?}");
            assert!(x.rotation.dot(y.rotation).abs() > 1.0 - 1e-6);
        }
    }
    let db = render_agreement(&scene.expand(), &back.expand());
    let plain_db = render_agreement(&scene.expand(), &formats::read_scene(&quantised).unwrap());
    let ratio = std::fs::metadata(&quantised).unwrap().len() as f64 / std::fs::metadata(&float).unwrap().len() as f64;
    eprintln!("an instanced scene through a quantised .glb: {db:.1} dB (read plainly {plain_db:.1} dB), {ratio:.3}x");
    assert!(db >= 45.0 && plain_db >= 45.0, "{db:.1} / {plain_db:.1} dB");
    assert!(ratio < 1.0, "{ratio}");
    // Positions spanning more than a node's scale may hold (1e-6..1e6, as the readers check
    // every node): refused in one line naming the file, none written; floats still write
    // (found by the convert_any fuzz target, 2026-11-28).
    let mut far = source.clone();
    far.means[0] = [3e7, 0.0, 0.0];
    let out = tmp("far-quantised.glb");
    let e = formats::gltf::write_gltf(&far, &out, Accessors::Quantized).unwrap_err();
    let e = format!("{e:#}");
    assert!(e.contains("far-quantised.glb") && e.contains("without --quantize") && !e.contains('\n'), "{e}");
    assert!(!out.exists());
    formats::gltf::write_gltf(&far, &tmp("far-float.glb"), Accessors::Float).unwrap();
    assert_eq!(formats::read_scene(&tmp("far-float.glb")).unwrap().len(), far.len());
}

#[test]
fn tilesets_round_trip_within_spz_with_a_tile_per_instance() {
    // A plain scene (SH degree 3): one tile, as .spz's quantisation allows (version 3 inside),
    // in glTF's frame as stored.
    let source = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    let out = tmp("plain-tiles/tileset.json");
    formats::gltf::write_tileset(&source, &out).unwrap();
    assert_eq!(formats::detect(&out).unwrap(), Format::Tiles);
    let back = formats::read_scene(&out).unwrap();
    let e = max_errors(&source, &back);
    eprintln!("fruit_drops through a tileset: errors {e:?}");
    assert!(e[0] <= 0.5 / 4096.0 + 1e-6 && e[3] <= 0.5 / 255.0 + 1e-6, "{e:?}");
    assert!(e[2] <= 2e-3, "rotation error {}", e[2]);
    let db = render_agreement(&source, &back);
    eprintln!("fruit_drops through a tileset: {db:.1} dB");
    assert!(db >= 30.0, "{db:.1} dB");
    // Each tile's glTF: both extensions required, one node, one primitive, no accessor data.
    let (doc, _) = glb_parts(&out.with_file_name("tile-0.glb"));
    assert_eq!(doc["extensionsRequired"], serde_json::json!(["KHR_gaussian_splatting", formats::gltf::SPZ_EXTENSION]));
    assert!(doc["accessors"].as_array().unwrap().iter().all(|a| a.get("bufferView").is_none()));
    // An instanced scene: a background tile and a tile per instance in the scene's frame (no
    // tile transform: CesiumJS evaluates every tile's SH in the first tile's frame); the root's
    // box holds every tile's; read back as the expanded scene.
    let mut rng = common::Rng::new(55);
    let scene = common::random_instanced(&mut rng, 3, 200, &[(150, 4), (80, 3)]);
    let out = tmp("instanced-tiles/tileset.json");
    formats::gltf::write_instanced_tileset(&scene, &out).unwrap();
    let tileset: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let tiles = tileset["root"]["children"].as_array().unwrap();
    assert_eq!(tiles.len(), 1 + 4 + 3);
    assert!(tiles.iter().all(|t| t.get("transform").is_none()));
    let range = |b: &serde_json::Value| {
        let v: Vec<f64> = b["boundingVolume"]["box"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        [0, 1, 2].map(|a| (v[a] - v[3 + 4 * a], v[a] + v[3 + 4 * a]))
    };
    let root = range(&tileset["root"]);
    for t in tiles {
        let r = range(t);
        assert!((0..3).all(|a| r[a].0 >= root[a].0 - 1e-5 && r[a].1 <= root[a].1 + 1e-5), "{r:?} outside {root:?}");
    }
    let expanded = scene.expand();
    let back = formats::read_scene(&out).unwrap();
    assert_eq!(back.len(), expanded.len());
    let db = render_agreement(&expanded, &back);
    eprintln!("an instanced scene through a tileset: {db:.1} dB");
    assert!(db >= 30.0, "{db:.1} dB");
}

/// Rewrites one accessor of a GLB's JSON to new bytes appended to its BIN chunk.
fn replace_accessor(
    doc: &mut serde_json::Value,
    bin: &mut Vec<u8>,
    acc: usize,
    bytes: &[u8],
    component: u32,
    normalized: bool,
) {
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let views = doc["bufferViews"].as_array_mut().unwrap();
    views.push(serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()}));
    let view = views.len() - 1;
    bin.extend_from_slice(bytes);
    let a = &mut doc["accessors"][acc];
    a["bufferView"] = view.into();
    a["componentType"] = component.into();
    a["normalized"] = normalized.into();
    a.as_object_mut().unwrap().remove("min");
    a.as_object_mut().unwrap().remove("max");
}

/// A GLB's JSON and BIN chunk.
fn glb_parts(path: &Path) -> (serde_json::Value, Vec<u8>) {
    let bytes = std::fs::read(path).unwrap();
    let glb = gltf::binary::Glb::from_slice(&bytes).unwrap();
    (serde_json::from_slice(&glb.json).unwrap(), glb.bin.unwrap().into_owned())
}

fn write_glb_parts(path: &Path, doc: &mut serde_json::Value, bin: Vec<u8>) {
    doc["buffers"][0]["byteLength"] = bin.len().into();
    let json = serde_json::to_vec(&doc).unwrap();
    let header = gltf::binary::Header { magic: *b"glTF", version: 2, length: 0 };
    std::fs::write(path, gltf::binary::Glb { header, json: json.into(), bin: Some(bin.into()) }.to_vec().unwrap())
        .unwrap();
}

/// The float accessor `name` of the first primitive, and its index.
fn float_attribute(doc: &serde_json::Value, bin: &[u8], name: &str) -> (usize, Vec<f32>) {
    let acc = doc["meshes"][0]["primitives"][0]["attributes"][name].as_u64().unwrap() as usize;
    let v = &doc["bufferViews"][doc["accessors"][acc]["bufferView"].as_u64().unwrap() as usize];
    let (o, l) = (v["byteOffset"].as_u64().unwrap() as usize, v["byteLength"].as_u64().unwrap() as usize);
    (acc, bin[o..o + l].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect())
}

#[test]
fn quantised_gltf_accessors_read() {
    // The extension's quantised forms. A: POSITION as unsigned shorts dequantised by the
    // node's translation and scale (KHR_mesh_quantization; SCALE then in the node's units),
    // ROTATION as normalized shorts, OPACITY as normalized unsigned bytes.
    let source = read_ply(&fixture("sh3.ply")).unwrap();
    let plain = tmp("float.glb");
    formats::write_scene(&source, &plain).unwrap();
    let (mut doc, mut bin) = glb_parts(&plain);
    let (p, pos) = float_attribute(&doc, &bin, "POSITION");
    let lo: Vec<f32> = (0..3).map(|d| pos.iter().skip(d).step_by(3).copied().fold(f32::INFINITY, f32::min)).collect();
    let hi: Vec<f32> =
        (0..3).map(|d| pos.iter().skip(d).step_by(3).copied().fold(f32::NEG_INFINITY, f32::max)).collect();
    let step = (0..3).map(|d| hi[d] - lo[d]).fold(0.0f32, f32::max) / 65535.0;
    let q16: Vec<u8> =
        pos.iter().enumerate().flat_map(|(i, v)| (((v - lo[i % 3]) / step).round() as u16).to_le_bytes()).collect();
    replace_accessor(&mut doc, &mut bin, p, &q16, 5123, false);
    doc["accessors"][p]["min"] = serde_json::json!([0, 0, 0]);
    doc["accessors"][p]["max"] =
        serde_json::json!((0..3).map(|d| ((hi[d] - lo[d]) / step).round()).collect::<Vec<_>>());
    let (r, rot) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:ROTATION");
    let r16: Vec<u8> = rot.iter().flat_map(|v| ((v * 32767.0).round() as i16).to_le_bytes()).collect();
    replace_accessor(&mut doc, &mut bin, r, &r16, 5122, true);
    let (s, scales) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:SCALE");
    let units: Vec<u8> = scales.iter().flat_map(|v| (v / step).to_le_bytes()).collect();
    replace_accessor(&mut doc, &mut bin, s, &units, 5126, false);
    let (a, alpha) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:OPACITY");
    let a8: Vec<u8> = alpha.iter().map(|v| (v * 255.0).round() as u8).collect();
    replace_accessor(&mut doc, &mut bin, a, &a8, 5121, true);
    doc["nodes"][0]["translation"] = serde_json::json!(lo);
    doc["nodes"][0]["scale"] = serde_json::json!([step, step, step]);
    doc["extensionsRequired"] = serde_json::json!(["KHR_mesh_quantization"]);
    doc["extensionsUsed"] = serde_json::json!(["KHR_gaussian_splatting", "KHR_mesh_quantization"]);
    let out = tmp("quantised.glb");
    write_glb_parts(&out, &mut doc, bin);
    let back = formats::read_scene(&out).unwrap();
    let e = max_errors(&source, &back);
    // Positions within half a step (and f32 rounding), opacity within half of 1/255, SH exact.
    assert!(
        e[0] <= step * 0.51 + 1e-6 && e[1] < 1e-4 && e[2] < 1e-4 && e[3] <= 0.5 / 255.0 + 1e-6 && e[5] < 1e-6,
        "{e:?} step {step}"
    );
    assert!(render_agreement(&source, &back) >= 50.0);
    // B: SCALE as normalized signed shorts (linear scales below 1, in world units).
    let (mut doc, mut bin) = glb_parts(&plain);
    let (s, scales) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:SCALE");
    assert!(scales.iter().all(|v| *v < 1.0));
    let s16: Vec<u8> = scales.iter().flat_map(|v| ((v * 32767.0).round().max(1.0) as i16).to_le_bytes()).collect();
    replace_accessor(&mut doc, &mut bin, s, &s16, 5122, true);
    let out = tmp("quantised-scale.glb");
    write_glb_parts(&out, &mut doc, bin);
    let back = formats::read_scene(&out).unwrap();
    let db = render_agreement(&source, &back);
    assert!(db >= 40.0, "{db:.1} dB");
    // An integer type the extension does not allow there is refused by name.
    let (mut doc, mut bin) = glb_parts(&plain);
    let (a, alpha) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:OPACITY");
    let a8: Vec<u8> = alpha.iter().map(|v| (v * 127.0).round() as u8).collect();
    replace_accessor(&mut doc, &mut bin, a, &a8, 5120, true);
    let out = tmp("bad-opacity.glb");
    write_glb_parts(&out, &mut doc, bin);
    let e = format!("{:#}", formats::read_scene(&out).unwrap_err());
    assert!(e.contains("bad-opacity.glb") && e.contains("OPACITY") && e.contains("I8"), "{e}");
}

#[test]
fn what_a_gltf_says_is_checked_against_what_it_holds() {
    // docs/robustness.md, "What a file may make us read": the answers hostile glTF files get
    // when they are readable (the refusals are in tests/bad_input.rs).
    let source = read_ply(&fixture("sh0.ply")).unwrap();
    let plain = tmp("checked.glb");
    formats::write_scene(&source, &plain).unwrap();
    // 1. An application attribute `_KHR_gaussian_splatting:SCALE` does not stand in for ours.
    let (mut doc, mut bin) = glb_parts(&plain);
    let (s, scales) = float_attribute(&doc, &bin, "KHR_gaussian_splatting:SCALE");
    let other = doc["accessors"][s].clone();
    doc["accessors"].as_array_mut().unwrap().push(other);
    let fake = doc["accessors"].as_array().unwrap().len() - 1;
    let doubled: Vec<u8> = scales.iter().flat_map(|v| (2.0 * v).to_le_bytes()).collect();
    replace_accessor(&mut doc, &mut bin, fake, &doubled, 5126, false);
    doc["meshes"][0]["primitives"][0]["attributes"]["_KHR_gaussian_splatting:SCALE"] = fake.into();
    let out = tmp("app-attribute.glb");
    write_glb_parts(&out, &mut doc, bin);
    let back = formats::read_scene(&out).unwrap();
    assert!(max_errors(&source, &back)[2] < 1e-5, "{:?}", max_errors(&source, &back));
    // 2. Linear colours are brought to sRGB: the DC colour encoded by the transfer function.
    let (mut doc, bin) = glb_parts(&plain);
    doc["meshes"][0]["primitives"][0]["extensions"]["KHR_gaussian_splatting"]["colorSpace"] =
        "lin_rec709_display".into();
    let out = tmp("linear.glb");
    write_glb_parts(&out, &mut doc, bin);
    let back = formats::read_scene(&out).unwrap();
    let c0 = instgs_vk::math::SH_C0_F32;
    for i in (0..source.len()).step_by(37) {
        let lin = (0.5 + c0 * source.sh[i * 3]).clamp(0.0, 1.0);
        let srgb = if lin <= 0.0031308 { 12.92 * lin } else { 1.055 * lin.powf(1.0 / 2.4) - 0.055 };
        assert!((0.5 + c0 * back.sh[i * 3] - srgb).abs() < 1e-4, "splat {i}");
    }
    // 3. A POINTS primitive's indices choose its splats (and their order).
    let (mut doc, mut bin) = glb_parts(&plain);
    let at = bin.len();
    bin.extend_from_slice(&[5, 0, 0, 0, 2, 0, 0, 0]);
    doc["bufferViews"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"buffer": 0, "byteOffset": at, "byteLength": 8}));
    let view = doc["bufferViews"].as_array().unwrap().len() - 1;
    doc["accessors"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"bufferView": view, "componentType": 5125, "count": 2, "type": "SCALAR"}));
    doc["meshes"][0]["primitives"][0]["indices"] = (doc["accessors"].as_array().unwrap().len() - 1).into();
    let out = tmp("indexed.glb");
    write_glb_parts(&out, &mut doc, bin);
    let back = formats::read_scene(&out).unwrap();
    assert_eq!(back.len(), 2);
    assert!(max_errors(&source.select(&[5, 2]), &back).iter().all(|e| *e < 1e-5));
    // 4. An instanced glTF whose extras no longer describe its nodes is read as the node tree.
    let mut rng = common::Rng::new(54);
    let scene = common::random_instanced(&mut rng, 3, 50, &[(40, 3)]);
    let glb = tmp("edited.glb");
    formats::gltf::write_instanced_gltf(&scene, &glb, formats::gltf::Accessors::Float).unwrap();
    let expanded = scene.expand();
    type Edit<'a> = (&'a str, &'a dyn Fn(&mut serde_json::Value, &mut Vec<u8>));
    let edits: [Edit; 3] = [
        ("two instances name one node", &|d, _| {
            let n = d["extras"]["instgs"]["groups"][0]["instances"][0]["node"].clone();
            d["extras"]["instgs"]["groups"][0]["instances"][1]["node"] = n;
        }),
        ("the background names an instance's node", &|d, _| {
            let n = d["extras"]["instgs"]["groups"][0]["instances"][0]["node"].clone();
            d["extras"]["instgs"]["background"][0] = n;
        }),
        ("a template moved by 1e7", &|d, bin| {
            let first =
                &d["nodes"][d["extras"]["instgs"]["groups"][0]["instances"][0]["node"].as_u64().unwrap() as usize];
            let mesh = &d["meshes"][first["mesh"].as_u64().unwrap() as usize];
            let acc = mesh["primitives"][0]["attributes"]["_INSTGS_TEMPLATE_POSITION"].as_u64().unwrap() as usize;
            let v = &d["bufferViews"][d["accessors"][acc]["bufferView"].as_u64().unwrap() as usize];
            let (o, l) = (v["byteOffset"].as_u64().unwrap() as usize, v["byteLength"].as_u64().unwrap() as usize);
            for c in bin[o..o + l].chunks_exact_mut(4) {
                let x = f32::from_le_bytes((&*c).try_into().unwrap()) + 1e7;
                c.copy_from_slice(&x.to_le_bytes());
            }
        }),
    ];
    for (what, edit) in edits {
        let (mut doc, mut bin) = glb_parts(&glb);
        edit(&mut doc, &mut bin);
        let out = tmp("edited-extras.glb");
        write_glb_parts(&out, &mut doc, bin);
        let formats::AnyScene::Plain(back) = formats::AnyScene::read(&out).unwrap() else {
            panic!("{what}: read from the extras")
        };
        let db = render_agreement(&expanded, &back);
        assert!(db >= 60.0, "{what}: the node tree renders {db:.1} dB from the scene");
    }
}
