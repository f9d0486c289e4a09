//! The binary: renders pictures, composes, converts and benchmarks scenes; a few readers' checks
//! at the library level (the bad-input table of every reader and command: tests/bad_input.rs).
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
fn compose_info_convert_and_render_an_instanced_scene() {
    let d = dir("instanced");
    let mut rng = Rng::new(12);
    let mut tpl = template(&mut rng, 300, 2);
    tpl.opacities.iter_mut().for_each(|o| *o = o.max(0.0));
    let tpl_path = d.join("mug.ply");
    instgs_vk::formats::ply::write_ply(&tpl, &tpl_path).unwrap();
    let bg_path = d.join("floor.ply");
    instgs_vk::formats::ply::write_ply(&random_scene(&mut rng, 50, 2), &bg_path).unwrap();
    // The prototype's convention: instance 1 is the template frame; others map world → template.
    let graph = serde_json::json!([{"template_id": "mug", "instances": [
        {"instance_id": "1", "transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
        {"instance_id": "2", "transform": [[0,0.5,0,-0.5],[-0.5,0,0,0.25],[0,0,0.5,0],[0,0,0,1]]},
        {"instance_id": "3", "transform": [[1,0,0,0.8],[0,1,0,-0.6],[0,0,1,0.3],[0,0,0,1]]}]}]);
    let graph_path = d.join("scene_graph.json");
    std::fs::write(&graph_path, graph.to_string()).unwrap();
    let scene = d.join("scene.instgs");
    let o = run(&[
        "compose",
        "--template",
        &format!("mug={}", s(&tpl_path)),
        "--scene-graph",
        s(&graph_path),
        "--background",
        s(&bg_path),
        "--random-offsets",
        "0.02",
        "--seed",
        "3",
        "--offset-dtype",
        "f16",
        "--out",
        s(&scene),
    ]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let o = run(&["info", s(&scene), "--json"]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let v: serde_json::Value = serde_json::from_str(&o.stdout).unwrap();
    assert_eq!(v["groups"][0]["name"], "mug");
    assert_eq!(v["groups"][0]["template_gaussians"], 300);
    assert_eq!(v["splats"], 50 + 900);
    let inst = &v["groups"][0]["instances"];
    assert_eq!(inst.as_array().unwrap().len(), 3);
    assert_eq!(inst[1]["id"], "2");
    // Template → world: the inverse of the scene graph's matrix (scale 2, a quarter turn).
    let m: Vec<Vec<f64>> = serde_json::from_value(inst[1]["transform"].clone()).unwrap();
    let want = [[0.0, -2.0, 0.0, 0.5], [2.0, 0.0, 0.0, 1.0], [0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
    for r in 0..4 {
        for c in 0..4 {
            assert!((m[r][c] - want[r][c]).abs() < 1e-5, "{m:?}");
        }
    }
    let parts: Vec<String> =
        v["parts"].as_array().unwrap().iter().map(|p| p["name"].as_str().unwrap().into()).collect();
    assert_eq!(parts, ["header", "background", "mug/template", "mug/offsets"]);
    // Expanded PLY and scene graph out; the PLY renders like the instanced scene.
    let ply = d.join("expanded.ply");
    assert_eq!(run(&["convert", s(&scene), s(&ply)]).code, Some(0));
    let graph_out = d.join("graph_out.json");
    assert_eq!(run(&["convert", s(&scene), s(&graph_out)]).code, Some(0));
    // The instanced scene again, compressed: the same structure, a version-3 file.
    let small = d.join("small.instgs");
    let o = run(&["convert", s(&scene), s(&small), "--compress"]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let c = instgs_vk::formats::instgs::read(&small).unwrap();
    assert_eq!((c.background.len(), c.groups[0].instances.len()), (50, 3));
    let back: serde_json::Value = serde_json::from_slice(&std::fs::read(&graph_out).unwrap()).unwrap();
    assert_eq!(back[0]["instances"][2]["instance_id"], "3");
    let renders: Vec<PathBuf> = [&scene, &ply]
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let out = d.join(format!("render{i}"));
            let o =
                run(&["render", "--scene", s(p), "--orbit", "2", "--width", "80", "--height", "60", "--out", s(&out)]);
            assert_eq!(o.code, Some(0), "{}", o.stderr);
            assert!(!o.stderr.contains("validation"), "{}", o.stderr);
            out.join("view_001.png")
        })
        .collect();
    let (a, b) = (image::open(&renders[0]).unwrap().to_rgb8(), image::open(&renders[1]).unwrap().to_rgb8());
    let differ =
        a.pixels().zip(b.pixels()).filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > 1)).count();
    assert_eq!(differ, 0);
    assert!(a.pixels().any(|p| p.0 != [0, 0, 0]));
    // bench takes .instgs scenes too and reports the expanded splat count.
    let json = d.join("bench.json");
    let bench = |extra: &[&str], frames: &str| -> (Out, serde_json::Value) {
        let mut args = vec!["bench", "--scene", s(&scene)];
        args.extend_from_slice(extra);
        args.extend(["--orbit", "1", "--width", "64", "--height", "48", "--frames", frames, "--json", s(&json)]);
        let o = run(&args);
        assert_eq!(o.code, Some(0), "{}", o.stderr);
        let b = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
        (o, b)
    };
    let (_, b) = bench(&[], "1");
    assert_eq!(b["splats"], 950);
    // Its intersections by part (one frame: the parts add up); a plain scene has no parts.
    let part = |b: &serde_json::Value, k: &str| b[k].as_f64().unwrap_or_else(|| panic!("{k}: {b}"));
    assert!(part(&b, "instanced_intersections") > 0.0, "{b}");
    assert_eq!(
        part(&b, "background_intersections") + part(&b, "instanced_intersections"),
        part(&b, "intersections"),
        "{b}"
    );
    // --compare: the expanded PLY interleaved with the instanced scene, ratios A over B.
    let (o, b) = bench(&["--compare", s(&ply)], "2");
    assert!(o.stdout.contains("A over B"), "{}", o.stdout);
    assert_eq!(b["compare"]["splats"], 950);
    assert_eq!(b["compare"]["intersections"], b["intersections"], "same picture, same work");
    assert!(b["compare"]["background_intersections"].is_null(), "{b}");
    let fb = b["file_bytes"].as_f64().unwrap() / b["compare"]["file_bytes"].as_f64().unwrap();
    assert_eq!(b["ratios"]["file_bytes"].as_f64().unwrap(), fb);
    assert!(b["ratios"]["scene_gpu_bytes"].as_f64().unwrap() < 1.0, "{b}");
    for key in ["frame_ms_median", "frame_ms_p90", "fps_median", "scene_gpu_bytes", "frame_gpu_bytes", "passes"] {
        assert!(!b[key].is_null() && !b["compare"][key].is_null(), "{key}");
    }
    // The instanced scene as glTF (templates shared): bench and the player open it like the
    // .instgs, as the same instanced scene.
    let glb = d.join("scene.glb");
    assert_eq!(run(&["convert", s(&scene), s(&glb)]).code, Some(0));
    let info = run(&["info", s(&glb)]);
    assert!(info.stdout.contains("instanced") && info.stdout.contains("950"), "{}", info.stdout);
    let (o, b2) = {
        let mut args = vec!["bench", "--scene", s(&glb), "--compare", s(&scene)];
        args.extend(["--orbit", "1", "--width", "64", "--height", "48", "--frames", "1", "--json", s(&json)]);
        let o = run(&args);
        assert_eq!(o.code, Some(0), "{}", o.stderr);
        (o, serde_json::from_slice::<serde_json::Value>(&std::fs::read(&json).unwrap()).unwrap())
    };
    assert_eq!(b2["splats"], 950);
    assert_eq!(b2["intersections"], b2["compare"]["intersections"], "{b2}");
    // Instanced on the GPU too (expanded, its 950 splats would take 2.6× the .instgs's bytes);
    // the .instgs's f16 offsets stay f16 there, the glTF's do not (its Δp pass through the node
    // transforms): 14 bytes more per offset pair, levels of detail included.
    let r = b2["ratios"]["scene_gpu_bytes"].as_f64().unwrap();
    assert!((1.0..1.25).contains(&r), "instanced on the GPU too: {b2}");
    let worst: f64 = o.stdout.split("dB mean, ").nth(1).and_then(|t| t.split(' ').next()).unwrap().parse().unwrap();
    assert!(worst >= 60.0, "{}", o.stdout);
    let frames = d.join("glb-frames");
    let o =
        run(&["view", s(&glb), "--headless", "--frames", "1", "--width", "64", "--height", "48", "--out", s(&frames)]);
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    assert!(frames.join("frame_000.png").is_file());
    // Bad input.
    let o = run(&[
        "compose",
        "--template",
        &format!("cup={}", s(&tpl_path)),
        "--scene-graph",
        s(&graph_path),
        "--out",
        s(&d.join("x.instgs")),
    ]);
    assert_clear_error(&o, &["template_id \"mug\"", "cup"]);
    assert_clear_error(&run(&["convert", s(&scene), s(&d.join("x.txt"))]), &[".ply", ".json"]);
    std::fs::write(d.join("bad.instgs"), b"INSTGS\0\0\x05\0\0\0{\"a\":").unwrap();
    assert_clear_error(&run(&["info", s(&d.join("bad.instgs"))]), &["bad.instgs", "malformed JSON header"]);
    assert_clear_error(
        &run(&["render", "--scene", s(&d.join("bad.instgs")), "--orbit", "1", "--out", s(&d)]),
        &["bad.instgs"],
    );
}

#[test]
fn instance_turns_a_labelled_plain_scene_into_an_instanced_one() {
    // A plain scene with a known object placed twice (labels 1, 2) over a background (0).
    let d = dir("instance");
    let mut rng = Rng::new(13);
    let mut plain = instgs_vk::model::scene::Scene { sh_degree: 0, ..Default::default() };
    let mut labels = Vec::new();
    for (id, shift) in [(1u32, -1.0f32), (2, 1.0)] {
        for j in 0..1500 {
            let (a, b) = (j as f32 * 0.37, j as f32 * 0.011);
            let r = if j % 3 == 0 { 0.15 } else { 0.3 };
            let p = [
                r * a.cos() * b.sin() + shift + if j % 3 == 0 { 0.3 } else { 0.0 },
                r * a.sin() * b.sin(),
                0.6 * b.cos(),
            ];
            plain.means.push(p);
            plain.scales.push([-4.0; 3]);
            plain.quats.push([1.0, 0.0, 0.0, 0.0]);
            plain.opacities.push(2.0);
            plain.sh.extend_from_slice(&[rng.range(-1.0, 1.0), 0.0, 0.0]);
            labels.push(id);
        }
    }
    let mut bg = random_scene(&mut rng, 100, 0);
    bg.means.iter_mut().for_each(|m| m[2] -= 3.0);
    for i in 0..bg.len() {
        plain.means.push(bg.means[i]);
        plain.scales.push(bg.scales[i]);
        plain.quats.push(bg.quats[i]);
        plain.opacities.push(bg.opacities[i]);
        plain.sh.extend_from_slice(&bg.sh[i * 3..i * 3 + 3]);
        labels.push(0);
    }
    let ply = d.join("plain.ply");
    instgs_vk::formats::ply::write_ply(&plain, &ply).unwrap();
    let labels_path = d.join("labels.json");
    std::fs::write(&labels_path, serde_json::json!({"ids": [1, 2], "labels": labels}).to_string()).unwrap();
    let groups = serde_json::json!({"groups": [{"name": "blob", "instances": [{"id": 1}, {"id": 2}]}]});
    std::fs::write(d.join("instances.json"), groups.to_string()).unwrap();
    let out = d.join("scene.instgs");
    let report = d.join("report.json");
    let args = |labels: &Path, init: &str| -> Vec<String> {
        ["instance", "--scene", s(&ply), "--labels", s(labels), "--data", s(&d), "--init", init, "--out", s(&out)]
            .iter()
            .map(|x| x.to_string())
            .collect()
    };
    let mut a = args(&labels_path, "merge");
    a.extend(["--report".to_string(), s(&report).to_string()]);
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(o.code, Some(0), "{}", o.stderr);
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let t = &r["instances"][1];
    assert_eq!(t["id"], 2);
    assert!((t["scale"].as_f64().unwrap() - 1.0).abs() < 0.02, "{t}");
    let o = run(&["info", s(&out), "--json"]);
    let v: serde_json::Value = serde_json::from_str(&o.stdout).unwrap();
    assert_eq!(v["groups"][0]["name"], "blob");
    assert_eq!(v["groups"][0]["template_gaussians"], 1500);
    assert_eq!(v["background_gaussians"], 100);
    // Bad input: labels of another scene, an unknown id, a missing instance.
    let short = d.join("short.bin");
    std::fs::write(&short, [0u8; 12]).unwrap();
    let bad = |labels: &Path| run(&args(labels, "first").iter().map(String::as_str).collect::<Vec<_>>());
    assert_clear_error(&bad(&short), &["short.bin", "3 labels for a scene of 3100 Gaussians"]);
    let mut odd = labels.clone();
    odd[0] = 9;
    std::fs::write(&labels_path, serde_json::json!({"ids": [1, 2], "labels": odd}).to_string()).unwrap();
    let name = labels_path.file_name().unwrap().to_str().unwrap();
    assert_clear_error(&bad(&labels_path), &[name, "label 9 is not an instance of"]);
    let none: Vec<u32> = labels.iter().map(|&l| if l == 2 { 0 } else { l }).collect();
    std::fs::write(&labels_path, serde_json::json!({"ids": [1, 2], "labels": none}).to_string()).unwrap();
    assert_clear_error(&bad(&labels_path), &["instance 2 claims no Gaussian"]);
    assert!(!d.join("scene.instgs.tmp").exists());
}

#[test]
fn a_closed_output_pipe_ends_quietly() {
    // `instgs-vk info … | head -1`: the reader goes away; no panic message, no error line.
    let guitar = shared_data("splats/guitar.ply");
    let mut child = Command::new(env!("CARGO_BIN_EXE_instgs-vk"))
        .args(["info", s(&guitar), "--json"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// Values checked where they are read (issue 24): a damaged checkpoint, a pipeline table in a
/// plain configuration, overlapping `.instgs` sections, a cut-short `.instgs` (the table of every
/// reader and command is tests/bad_input.rs).
#[test]
fn values_are_checked_at_the_door() {
    use instgs_vk::train::config::Config;
    use instgs_vk::train::{read_checkpoint, write_checkpoint, TrainState};
    let d = dir("door");
    let mut rng = Rng::new(24);

    // A checkpoint with a NaN among its parameters is refused when it is read.
    let ckpt = d.join("checkpoint.bin");
    write_checkpoint(&ckpt, &TrainState::new(random_scene(&mut rng, 8, 1)), &Config::load(None).unwrap(), None)
        .unwrap();
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let hlen = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    bytes[20 + hlen..24 + hlen].copy_from_slice(&f32::NAN.to_le_bytes());
    // Sealed again (the CRC-32 trailer), so the value check is what refuses it.
    let body = bytes.len() - 4;
    let crc = crc32fast::hash(&bytes[..body]);
    bytes[body..].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(&ckpt, &bytes).unwrap();
    let e = format!("{:#}", read_checkpoint(&ckpt).err().unwrap());
    assert!(e.contains("checkpoint.bin") && e.contains("non-finite position"), "{e}");

    // A pipeline table in the configuration of a run that trains one scene.
    let e = format!("{:#}", Config::from_toml("[joint]\niterations = 5\n", "run.toml").err().unwrap());
    assert!(e.contains("run.toml") && e.contains("`[joint]` is a pipeline table"), "{e}");

    // An .instgs whose sections share bytes.
    let scene = random_instanced(&mut rng, 1, 5, &[(4, 2)]);
    let good = instgs_vk::formats::instgs::to_bytes(&scene, instgs_vk::formats::instgs::Dtype::F32);
    let hlen = u32::from_le_bytes(good[8..12].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&good[12..12 + hlen]).unwrap();
    let first = header["sections"][0]["offset"].clone();
    header["sections"][1]["offset"] = first;
    let text = serde_json::to_vec(&header).unwrap();
    let start = (12 + hlen).div_ceil(16) * 16;
    let mut bad = good[..8].to_vec();
    bad.extend_from_slice(&(text.len() as u32).to_le_bytes());
    bad.extend_from_slice(&text);
    bad.resize((12 + text.len()).div_ceil(16) * 16, 0);
    bad.extend_from_slice(&good[start..]);
    let overlap = d.join("overlap.instgs");
    std::fs::write(&overlap, &bad).unwrap();
    assert_clear_error(&run(&["info", s(&overlap)]), &["overlap.instgs", "overlap"]);

    let short = d.join("short.instgs");
    std::fs::write(&short, &good[..10]).unwrap();
    assert_clear_error(&run(&["info", s(&short)]), &["short.instgs", "cut short"]);
}
