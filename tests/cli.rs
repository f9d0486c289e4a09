//! The binary: renders pictures, and bad input ends in one clear error line, exit code != 0,
//! never a panic or a hang.
mod common;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::*;

struct Out {
    code: Option<i32>,
    stdout: String,
    stderr: String,
}

fn run(args: &[&str]) -> Out {
    let mut child = Command::new(env!("CARGO_BIN_EXE_instgs-vk"))
        .args(args)
        .env("INSTGS_VALIDATION", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > Duration::from_secs(300) {
            child.kill().unwrap();
            panic!("instgs-vk {args:?} hung");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let o = child.wait_with_output().unwrap();
    Out {
        code: o.status.code(),
        stdout: String::from_utf8_lossy(&o.stdout).into(),
        stderr: String::from_utf8_lossy(&o.stderr).into(),
    }
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// One `error:` line that contains every `needle`, exit code 1, no panic.
fn assert_clear_error(o: &Out, needles: &[&str]) {
    assert_eq!(o.code, Some(1), "stderr: {}", o.stderr);
    assert!(!o.stderr.contains("panicked"), "panic: {}", o.stderr);
    let errors: Vec<&str> = o.stderr.lines().filter(|l| !l.starts_with("device:")).collect();
    assert!(errors.len() == 1 && errors[0].starts_with("error: "), "stderr: {}", o.stderr);
    for n in needles {
        assert!(errors[0].contains(n), "'{}' lacks '{n}'", errors[0]);
    }
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

const HEADER: &str = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nproperty float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\nproperty float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n";

fn ply_with(header: &str, values: &[f32]) -> Vec<u8> {
    let mut b = header.as_bytes().to_vec();
    for v in values {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

#[test]
fn render_writes_one_picture_per_orbit_camera() {
    let d = dir("render");
    let guitar = shared_data("splats/guitar.ply");
    let out = d.join("out");
    let o =
        run(&["render", "--scene", s(&guitar), "--orbit", "3", "--width", "96", "--height", "64", "--out", s(&out)]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(!o.stderr.contains("validation"), "{}", o.stderr);
    assert!(o.stdout.contains("blend"), "per-pass times expected: {}", o.stdout);
    for k in 0..3 {
        let img = image::open(out.join(format!("view_{k:03}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (96, 64));
    }
    // Cameras from a NeRF-synthetic file, named after file_path.
    let cams = shared_data("scenes/ducks6/transforms_test.json");
    let out2 = d.join("out2");
    let o = run(&[
        "render",
        "--scene",
        s(&guitar),
        "--cameras",
        s(&cams),
        "--width",
        "80",
        "--height",
        "60",
        "--out",
        s(&out2),
    ]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(out2.join("r_000.png").exists() && out2.join("r_011.png").exists());
    let o = run(&["info", s(&guitar), "--json"]);
    let v: serde_json::Value = serde_json::from_str(&o.stdout).unwrap();
    assert_eq!(v["gaussians"], 90854);
    assert_eq!(v["sh_degree"], 0);
}

#[test]
fn bad_input_ends_in_one_clear_error() {
    let d = dir("bad");
    let guitar = shared_data("splats/guitar.ply");
    let full = std::fs::read(&guitar).unwrap();

    let truncated = d.join("truncated.ply");
    std::fs::write(&truncated, &full[..full.len() / 3]).unwrap();
    assert_clear_error(&run(&["info", s(&truncated)]), &["truncated.ply", "truncated"]);

    let nan = d.join("nan.ply");
    let mut vals = [0.0f32; 14];
    vals[0] = f32::NAN;
    vals[10] = 1.0;
    std::fs::write(&nan, ply_with(HEADER, &vals)).unwrap();
    assert_clear_error(&run(&["info", s(&nan)]), &["nan.ply", "non-finite position"]);

    let missing = d.join("missing.ply");
    std::fs::write(&missing, ply_with(&HEADER.replace("property float opacity\n", ""), &[0.0; 13])).unwrap();
    assert_clear_error(&run(&["info", s(&missing)]), &["missing.ply", "'opacity' is missing"]);

    let empty = d.join("empty.ply");
    std::fs::write(&empty, HEADER.replace("vertex 1", "vertex 0")).unwrap();
    assert_clear_error(&run(&["info", s(&empty)]), &["empty.ply", "no Gaussians"]);

    let garbage = d.join("garbage.ply");
    std::fs::write(&garbage, b"not a ply at all").unwrap();
    assert_clear_error(&run(&["info", s(&garbage)]), &["garbage.ply"]);

    assert_clear_error(&run(&["info", s(&d.join("absent.ply"))]), &["absent.ply", "cannot open"]);

    let no_frames = d.join("transforms.json");
    std::fs::write(&no_frames, r#"{"camera_angle_x": 0.8, "w": 64, "h": 48, "frames": []}"#).unwrap();
    let out = d.join("out");
    let o = run(&["render", "--scene", s(&guitar), "--cameras", s(&no_frames), "--out", s(&out)]);
    assert_clear_error(&o, &["transforms.json", "no frames"]);

    let zero = d.join("zero.json");
    std::fs::write(&zero, r#"{"camera_angle_x": 0.8, "w": 0, "h": 48, "frames": [{"file_path": "a", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#).unwrap();
    assert_clear_error(
        &run(&["render", "--scene", s(&guitar), "--cameras", s(&zero), "--out", s(&out)]),
        &["zero.json", "empty"],
    );

    let o = run(&["render", "--scene", s(&guitar), "--orbit", "2", "--width", "0", "--out", s(&out)]);
    assert_clear_error(&o, &["--width"]);
}
