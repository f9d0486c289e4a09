//! Scene files: PLY round trips, ASCII and big-endian input, SuperSplat compressed PLY.
mod common;
use common::*;
use instgs_vk::formats::ply::{read_ply, write_ply};
use instgs_vk::model::camera::{orbit_around, UpAxis};
use instgs_vk::model::scene::Scene;
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::render::upload::GpuScene;
use instgs_vk::util::psnr;

fn bits(s: &Scene) -> Vec<u32> {
    let mut v: Vec<u32> = Vec::new();
    v.extend(s.means.iter().flatten().map(|x| x.to_bits()));
    v.extend(s.scales.iter().flatten().map(|x| x.to_bits()));
    v.extend(s.quats.iter().flatten().map(|x| x.to_bits()));
    v.extend(s.opacities.iter().map(|x| x.to_bits()));
    v.extend(s.sh.iter().map(|x| x.to_bits()));
    v
}

#[test]
fn ply_write_read_round_trips_bit_exactly() {
    let dir = tempdir("roundtrip");
    let mut rng = Rng::new(3);
    for deg in 0..=3 {
        let mut s = random_scene(&mut rng, 500, deg);
        s.means[0][0] = -0.0;
        s.sh[1] = f32::MIN_POSITIVE / 4.0; // a subnormal
        let p = dir.join(format!("deg{deg}.ply"));
        write_ply(&s, &p).unwrap();
        let r = read_ply(&p).unwrap();
        assert_eq!(r.sh_degree, deg);
        assert!(bits(&r) == bits(&s), "degree {deg} does not round-trip");
    }
    let guitar = read_ply(&shared_data("splats/guitar.ply")).unwrap();
    let p = dir.join("guitar.ply");
    write_ply(&guitar, &p).unwrap();
    assert!(bits(&read_ply(&p).unwrap()) == bits(&guitar));
    // Our writer produces the Inria layout byte for byte (zero normals, f_rest channel-major).
    let original = std::fs::read(shared_data("splats/guitar.ply")).unwrap();
    let ours = std::fs::read(&p).unwrap();
    let body = |b: &[u8]| b[b.windows(11).position(|w| w == b"end_header\n").unwrap() + 11..].to_vec();
    assert!(body(&original) == body(&ours), "vertex data differs from the Inria layout");
}

#[test]
fn reads_shared_splats_with_sh_and_extra_properties() {
    let s = read_ply(&shared_data("splats/playbot_lod2.ply")).unwrap();
    assert_eq!((s.len(), s.sh_degree), (125_000, 2));
    // 59 standard properties plus an unknown `transform`, SH degree 3.
    let s = read_ply(&shared_data("splats/fruit_drops_minimal.ply")).unwrap();
    assert_eq!((s.len(), s.sh_degree), (4721, 3));
}

fn header(format: &str, n: usize) -> String {
    let mut h = format!("ply\nformat {format} 1.0\ncomment test\nelement vertex {n}\n");
    for p in [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
        "rot_2", "rot_3", "extra",
    ] {
        h += &format!("property float {p}\n");
    }
    h + "end_header\n"
}

#[test]
fn reads_ascii_and_big_endian() {
    let dir = tempdir("formats");
    let rows: Vec<[f32; 15]> = (0..3)
        .map(|i| {
            let f = i as f32;
            [f, 0.5 * f, -f, 0.25, -0.5, 1.0, 2.0, -3.0, -3.5, -4.0, 1.0, 0.0, 0.5, 0.0, 9.0]
        })
        .collect();
    let mut ascii = header("ascii", 3);
    for r in &rows {
        ascii += &r.iter().map(|v| v.to_string()).collect::<Vec<_>>().join(" ");
        ascii += "\n";
    }
    std::fs::write(dir.join("a.ply"), ascii).unwrap();
    let mut be = header("binary_big_endian", 3).into_bytes();
    for r in &rows {
        for v in r {
            be.extend_from_slice(&v.to_be_bytes());
        }
    }
    std::fs::write(dir.join("b.ply"), be).unwrap();
    let a = read_ply(&dir.join("a.ply")).unwrap();
    let b = read_ply(&dir.join("b.ply")).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.means[2], [2.0, 1.0, -2.0]);
    assert_eq!(a.quats[1], [1.0, 0.0, 0.5, 0.0]);
    assert_eq!(a.sh, [0.25, -0.5, 1.0].repeat(3));
}

#[test]
fn compressed_ply_decodes_like_its_plain_ply() {
    let (gpu, k) = gpu();
    let mut r = Rasterizer::new(&gpu, &k).unwrap();
    for name in ["guitar", "biker"] {
        let plain = read_ply(&shared_data(&format!("splats/{name}.ply"))).unwrap();
        let comp = read_ply(&shared_data(&format!("splats/{name}.compressed.ply"))).unwrap();
        assert_eq!(comp.len(), plain.len());
        let (lo, hi) = plain.bounds();
        let tol = (hi - lo).max_element() * 1e-5;
        for i in 0..plain.len() {
            for a in 0..3 {
                assert!((comp.means[i][a] - plain.means[i][a]).abs() <= tol, "{name} mean {i}");
                assert!((comp.scales[i][a] - plain.scales[i][a]).abs() <= 1e-4, "{name} scale {i}");
                assert!((comp.sh[3 * i + a] - plain.sh[3 * i + a]).abs() <= 1e-4, "{name} colour {i}");
            }
            let dot: f32 = (0..4).map(|a| comp.quats[i][a] * plain.quats[i][a]).sum();
            assert!(dot.abs() > 0.9999, "{name} rotation {i}");
            assert!((comp.opacities[i] - plain.opacities[i]).abs() <= 1e-3, "{name} opacity {i}");
        }
        let (gp, gc) = (GpuScene::new(&gpu, &plain).unwrap(), GpuScene::new(&gpu, &comp).unwrap());
        for cam in orbit_around(&plain, 2, UpAxis::NegY, 320, 240) {
            let a = r.render(&gp, &cam, [0.0; 3]).unwrap().image;
            let b = r.render(&gc, &cam, [0.0; 3]).unwrap().image;
            let p = psnr(&a, &b);
            assert!(p >= 50.0, "{name}: compressed vs plain PSNR {p:.1} dB");
        }
    }
    assert_clean(&gpu);
}
