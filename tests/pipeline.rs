//! The main job through the binary (`instgs-vk train` on a dataset with instance masks), on the
//! bundled demo scene at 80×60 with a tiny schedule: a run interrupted in every stage resumes
//! and finishes (plain results within a tolerance of an uninterrupted run's); a dataset without masks trains plain 3DGS and
//! says so, or with `--discover auto` runs the pipeline on the instances it finds; masks that
//! do not fit the images are refused before any training; the whole pipeline
//! gives the same results bit for bit with every new device buffer poisoned. Validation on.
use std::path::{Path, PathBuf};

use instgs_vk::pipeline::STAGES;

mod common;
use common::*;

/// A tiny schedule: short plain training with densification, short joint optimisation.
const TINY: &str = "iterations = 60\ntest_interval = 30\ncheckpoint_interval = 20\n\
[densify]\nfrom_iter = 10\nuntil_iter = 50\ninterval = 10\nopacity_reset_interval = 0\n\
[joint]\niterations = 20\ntest_interval = 10\ncheckpoint_interval = 5\n\
[eval]\nimages = 2\n[bench]\nframes = 1\nwarmup = 0\n";

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("pipeline").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn demo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("demo/ducks6-mini")
}

/// A copy of the demo scene, then `damage` applied to it.
fn demo_copy(name: &str, damage: impl Fn(&Path)) -> PathBuf {
    fn copy(src: &Path, dst: &Path) {
        std::fs::create_dir_all(dst).unwrap();
        for e in std::fs::read_dir(src).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                copy(&e.path(), &dst.join(e.file_name()));
            } else {
                std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
            }
        }
    }
    let d = tmp(name).join("data");
    copy(&demo(), &d);
    damage(&d);
    d
}

fn args<'a>(data: &'a str, out: &'a str, cfg: &'a str) -> Vec<&'a str> {
    vec!["train", "--data", data, "--downscale", "2", "--out", out, "--config", cfg, "--quiet"]
}

fn stage_done(run: &Path, stage: &str) -> bool {
    let text = std::fs::read_to_string(run.join("pipeline.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["stages"][stage]["done"].as_bool() == Some(true)
}

#[test]
fn a_run_interrupted_in_every_stage_resumes_and_finishes() {
    let base = tmp("resume");
    let cfg = base.join("tiny.toml");
    // With the training cameras refined (as for a capture): the stages after the plain one train
    // on the corrected cameras, and their checkpoints resume on them.
    let tiny = format!("{TINY}[cameras]\nrefine = true\nfrom_iter = 10\n");
    std::fs::write(&cfg, &tiny).unwrap();
    let data = demo();
    let (d, c) = (data.to_str().unwrap(), cfg.to_str().unwrap());

    let whole = base.join("whole");
    let o = run_bin(&args(d, whole.to_str().unwrap(), c), &[]);
    assert!(o.ok, "{}", o.stderr);
    for s in STAGES.map(|s| s.name()) {
        assert!(o.stderr.contains(&format!("{s}] finished")), "{s} did not finish:\n{}", o.stderr);
    }

    let parts = base.join("parts");
    let p = parts.to_str().unwrap();
    for (i, s) in STAGES.map(|s| s.name()).iter().enumerate() {
        let o = run_bin(&args(d, p, c), &[("INSTGS_INTERRUPT_IN", s)]);
        assert!(!o.ok && o.stderr.contains(&format!("interrupted in stage {s}")), "{s}:\n{}", o.stderr);
        assert!(o.stderr.contains("run the same command again to resume"), "{}", o.stderr);
        for (j, t) in STAGES.map(|s| s.name()).iter().enumerate() {
            assert_eq!(stage_done(&parts, t), j < i, "after interrupting {s}: stage {t}");
        }
        let report = std::fs::read_to_string(parts.join("report.md")).unwrap();
        assert!(report.contains(&format!("| {s} | interrupted or running |")), "{report}");
    }
    // The training stages stopped half-way with a checkpoint and went on from it.
    let o = run_bin(&args(d, p, c), &[]);
    assert!(o.ok, "{}", o.stderr);
    assert!(
        parts.join("cameras.json").is_file()
            && o.stderr.contains("the training cameras as the plain stage corrected them")
    );
    for s in STAGES.map(|s| s.name()) {
        assert!(stage_done(&parts, s), "{s}");
    }
    for (dir, n) in [(parts.clone(), 60), (parts.join("joint"), 20)] {
        let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
        let its: Vec<u64> = text.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
        assert_eq!(its, (1..=n).collect::<Vec<u64>>(), "{}: every iteration once", dir.display());
    }
    // Float atomics make lavapipe training differ from run to run in the last bits (two
    // uninterrupted runs differ too), densification amplifies that, and on this tiny, briefly
    // trained scene the registration can then land elsewhere: the plain results agree within
    // a tolerance, the instanced ones are only checked to be sane.
    let psnr = |run: &Path| {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("eval.json")).unwrap()).unwrap();
        (v["plain"]["psnr_mean"].as_f64().unwrap(), v["instgs"]["psnr_mean"].as_f64().unwrap())
    };
    let ((p0, i0), (p1, i1)) = (psnr(&whole), psnr(&parts));
    assert!((p0 - p1).abs() < 1.0, "plain: uninterrupted {p0:.2} dB, resumed {p1:.2} dB");
    assert!(p1 > 15.0 && i0 > 12.0 && i1 > 12.0, "plain {p1:.2} dB, InstGS {i0:.2} / {i1:.2} dB");
    let report = std::fs::read_to_string(parts.join("report.md")).unwrap();
    for needle in [
        "## Plain 3DGS against InstGS",
        "| | plain 3DGS | plain, pruned | InstGS |",
        "PSNR (dB)",
        "PSNR, colour-compensated",
        "PSNR on instance pixels",
        "FPS (median)",
        "tile intersections, median",
        "Where InstGS's frame goes: ",
        "held-out IoU",
        "rotation error",
        "The plain stage refined the 24 training cameras",
    ] {
        assert!(report.contains(needle), "report lacks {needle}:\n{report}");
    }
    let images: Vec<_> = std::fs::read_dir(parts.join("images")).unwrap().collect();
    assert_eq!(images.len(), 2);

    // A re-run of a finished run does nothing, also when the run predates a configuration key
    // (it counts as its default); --from redoes a stage and what follows.
    let state = parts.join("pipeline.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    v["stages"]["instance"]["settings"]["instance"].as_object_mut().unwrap().remove("background_keep").unwrap();
    std::fs::write(&state, v.to_string()).unwrap();
    let o = run_bin(&args(d, p, c), &[]);
    assert!(o.ok && o.stderr.matches("done earlier").count() == STAGES.len(), "{}", o.stderr);
    let o = run_bin(&[args(d, p, c), vec!["--from", "eval", "--until", "eval"]].concat(), &[]);
    assert!(o.ok && o.stderr.contains("[6/7 eval] finished"), "{}", o.stderr);
    assert!(!stage_done(&parts, "bench"));
    // Changed settings are not silently mixed with earlier results.
    std::fs::write(&cfg, format!("{tiny}\n[segment]\nalpha = 0.5\n")).unwrap();
    let o = run_bin(&args(d, p, c), &[]);
    assert!(!o.ok && o.stderr.contains("stage segment was run with other settings"), "{}", o.stderr);
    assert!(o.stderr.contains("--from segment"), "{}", o.stderr);
    // A refused run changes nothing, not even with --from.
    let o = run_bin(&[args(d, p, c), vec!["--from", "joint"]].concat(), &[]);
    assert!(!o.ok && o.stderr.contains("stage segment was run with other settings"), "{}", o.stderr);
    assert!(stage_done(&parts, "joint") && parts.join("joint/checkpoint.bin").exists());
}

#[test]
fn poisoned_device_memory_changes_no_result() {
    // Every new device buffer filled with 0xffffffff (INSTGS_POISON=1) against a run without:
    // on a GPU fresh memory holds whatever was there before, so a kernel or host step that reads
    // memory nothing wrote would give other results there. The whole pipeline, with an opacity
    // reset, on lavapipe with one thread (bit-exact runs); skipped where lavapipe is missing.
    let Some(lavapipe) = lavapipe_one_thread_env() else {
        eprintln!("no lavapipe here: skipped (runs repeat bit for bit only there)");
        return;
    };
    let base = tmp("poison");
    let cfg = base.join("tiny.toml");
    std::fs::write(&cfg, TINY.replace("opacity_reset_interval = 0", "opacity_reset_interval = 30")).unwrap();
    let data = demo();
    let (d, c) = (data.to_str().unwrap(), cfg.to_str().unwrap());
    let runs = [("clean", None), ("poisoned", Some(("INSTGS_POISON", "1")))].map(|(name, extra)| {
        let out = base.join(name);
        let env: Vec<(&str, &str)> = lavapipe.iter().copied().chain(extra).collect();
        let o = run_bin(&args(d, out.to_str().unwrap(), c), &env);
        assert!(o.ok, "{name}: {}", o.stderr);
        out
    });
    for f in ["point_cloud.ply", "labels.json", "init.instgs", "scene.instgs", "joint/metrics.csv", "pruned.ply"] {
        let [a, b] = [&runs[0], &runs[1]].map(|r| std::fs::read(r.join(f)).unwrap());
        if f.ends_with(".csv") {
            // Without the elapsed-time column.
            let cols = |t: &[u8]| -> Vec<String> {
                let text = String::from_utf8_lossy(t);
                text.lines()
                    .map(|l| {
                        l.split(',').enumerate().filter(|(i, _)| *i != 6).map(|(_, c)| c).collect::<Vec<_>>().join(",")
                    })
                    .collect()
            };
            assert_eq!(cols(&a), cols(&b), "{f} differs with poisoned memory");
        } else {
            assert!(a == b, "{f} differs with poisoned memory");
        }
    }
    let eval = |r: &Path| -> serde_json::Value {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(r.join("eval.json")).unwrap()).unwrap();
        serde_json::json!([v["plain"]["psnr_mean"], v["instgs"]["psnr_mean"], v["instgs"]["ssim_mean"]])
    };
    assert_eq!(eval(&runs[0]), eval(&runs[1]), "eval differs with poisoned memory");
}

#[test]
fn a_dataset_without_masks_trains_plain_3dgs_and_says_so() {
    let data = demo_copy("no-masks", |d| {
        std::fs::remove_dir_all(d.join("masks")).unwrap();
        std::fs::remove_file(d.join("instances.json")).unwrap();
    });
    let out = data.parent().unwrap().join("run");
    let o = run_bin(
        &["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iterations", "5", "--quiet"],
        &[],
    );
    assert!(o.ok, "{}", o.stderr);
    assert!(o.stderr.contains("no instance masks") && o.stderr.contains("plain 3DGS only"), "{}", o.stderr);
    assert!(out.join("point_cloud.ply").exists() && !out.join("pipeline.json").exists());
    // Pipeline options on such a dataset are refused with the reason.
    let o = run_bin(
        &["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--until", "segment"],
        &[],
    );
    assert!(!o.ok && o.stderr.contains("no instance masks"), "{}", o.stderr);
}

#[test]
fn without_masks_discover_runs_the_whole_pipeline() {
    // The demo without its masks and groups file, `--discover auto`, the tiny schedule: every
    // stage runs, the segment stage writes the discovery's files and the report says how the
    // instances were found (at 80×60 after 60 iterations it may find none: then the scene
    // stays plain, which the pipeline must carry through too).
    let data = demo_copy("discover", |d| {
        std::fs::remove_dir_all(d.join("masks")).unwrap();
        std::fs::remove_file(d.join("instances.json")).unwrap();
    });
    let base = data.parent().unwrap().to_path_buf();
    let cfg = base.join("tiny.toml");
    std::fs::write(&cfg, TINY).unwrap();
    let run = base.join("run");
    let (d, r, c) = (data.to_str().unwrap(), run.to_str().unwrap(), cfg.to_str().unwrap());
    let mut a = args(d, r, c);
    a.extend(["--discover", "auto"]);
    let o = run_bin(&a, &[]);
    assert!(o.ok, "{}", o.stderr);
    assert!(o.stderr.contains("instances discovered without masks"), "{}", o.stderr);
    for s in STAGES {
        assert!(stage_done(&run, s.name()), "stage {} not done", s.name());
    }
    for f in ["labels.json", "groups.json", "significance.bin", "scene.instgs", "report.md"] {
        assert!(run.join(f).exists(), "{f} missing");
    }
    let report = std::fs::read_to_string(run.join("report.md")).unwrap();
    assert!(report.contains("Instances discovered without masks"), "{report}");
    // A bad --discover value is refused by the argument parser.
    let mut a = args(d, r, c);
    a.extend(["--discover", "1,2,3"]);
    let o = run_bin(&a, &[]);
    assert!(!o.ok && o.stderr.contains("--box") && o.stderr.contains("auto"), "{}", o.stderr);
}

/// One `error:` line containing every needle, and no training started (no checkpoint).
fn assert_refused(o: &BinOut, out: &Path, needles: &[&str]) {
    assert!(!o.ok, "accepted:\n{}", o.stderr);
    let last = o.stderr.lines().last().unwrap_or_default();
    assert!(last.starts_with("error: "), "{}", o.stderr);
    for n in needles {
        assert!(last.contains(n), "'{last}' lacks '{n}'");
    }
    assert!(!out.join("checkpoint.bin").exists(), "training started");
    assert!(!o.stderr.contains("[1/7 plain] started"), "{}", o.stderr);
}

#[test]
fn masks_that_do_not_match_the_images_are_refused_before_training() {
    type Case<'a> = (&'a str, &'a dyn Fn(&Path), &'a [&'a str]);
    let cases: [Case; 4] = [
        (
            "missing",
            &|d| std::fs::remove_file(d.join("masks/train/r_004.png")).unwrap(),
            &["masks/train", "r_004.png", "no mask"],
        ),
        (
            "wrong-size",
            &|d| image::GrayImage::new(100, 50).save(d.join("masks/train/r_002.png")).unwrap(),
            &["r_002.png", "100x50", "160x120"],
        ),
        (
            "unknown-instance",
            &|d| {
                let p = d.join("instances.json");
                let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
                v["groups"][0]["instances"].as_array_mut().unwrap().push(serde_json::json!({"id": 42}));
                std::fs::write(&p, v.to_string()).unwrap();
            },
            &["instances.json", "instance 42", "no training mask"],
        ),
        (
            "no-groups",
            &|d| std::fs::remove_file(d.join("instances.json")).unwrap(),
            &["instances.json", "Bringing your own masks"],
        ),
    ];
    for (name, damage, needles) in cases {
        let data = demo_copy(name, damage);
        let out = data.parent().unwrap().join("run");
        let o = run_bin(&["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"], &[]);
        assert_refused(&o, &out, needles);
    }
}

#[test]
fn per_frame_masks_from_a_2d_segmenter_are_associated_then_instanced() {
    // A 2D segmenter's output: ids renumbered independently in every frame, a category per id,
    // no instances.json (its poses as ground_truth.json, matched to the instances by centre).
    let data = demo_copy("per-frame", |d| {
        std::fs::rename(d.join("instances.json"), d.join("ground_truth.json")).unwrap();
        std::fs::remove_dir_all(d.join("masks/test")).unwrap();
        for (f, e) in std::fs::read_dir(d.join("masks/train")).unwrap().enumerate() {
            let path = e.unwrap().path();
            let mut m = image::open(&path).unwrap().to_luma16();
            // A different permutation of 1..=6 per frame.
            let perm: Vec<u16> = (0..6).map(|i| ((i + f) * 5 % 6 + 1) as u16).collect();
            for p in m.pixels_mut() {
                if p.0[0] != 0 {
                    p.0[0] = perm[p.0[0] as usize - 1];
                }
            }
            m.save(&path).unwrap();
            let cats: serde_json::Map<String, serde_json::Value> =
                (1..=6).map(|i| (i.to_string(), "duck".into())).collect();
            std::fs::write(path.with_extension("json"), serde_json::Value::Object(cats).to_string()).unwrap();
        }
    });
    let base = data.parent().unwrap().to_path_buf();
    let cfg = base.join("tiny.toml");
    // Also background pruning: half of the background stays (the rebalance off, which would
    // share the bytes again between templates and background).
    std::fs::write(&cfg, format!("{TINY}[instance]\nbackground_keep = 0.5\nrebalance = false\n")).unwrap();
    let out = base.join("run");
    let o = run_bin(
        &[args(data.to_str().unwrap(), out.to_str().unwrap(), cfg.to_str().unwrap()), vec!["--until", "instance"]]
            .concat(),
        &[],
    );
    assert!(o.ok, "{}", o.stderr);
    assert!(o.stderr.contains("per-frame ids"), "{}", o.stderr);
    let labels: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("labels.json")).unwrap()).unwrap();
    let groups = labels["groups"].as_array().unwrap();
    assert_eq!(groups.len(), 1, "one category, one group: {groups:?}");
    let found = groups[0]["instances"].as_array().unwrap().len();
    assert!((4..=6).contains(&found), "{found} ducks associated");
    assert!(out.join("init.instgs").exists());
    let json = |f: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(out.join(f)).unwrap()).unwrap()
    };
    let before = json("segment.json")["background"].as_u64().unwrap();
    let inst = json("instance.json");
    let after = inst["background_gaussians"].as_u64().unwrap();
    // Instances refused at registration stay plain: their Gaussians join the kept background.
    let plain: u64 = inst["instances"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| matches!(r["status"].as_str(), Some("refused" | "plain")))
        .map(|r| r["gaussians"].as_u64().unwrap())
        .sum();
    assert_eq!(after, before.div_ceil(2) + plain, "background {before} → {after}");
    // Pose errors against ground_truth.json: every accepted duck found its true one.
    let accepted: Vec<&serde_json::Value> =
        inst["instances"].as_array().unwrap().iter().filter(|r| r["status"] == "accepted").collect();
    assert!(!accepted.is_empty());
    for r in accepted {
        assert!(r["rotation_error_deg"].as_f64().is_some(), "no ground truth matched: {r}");
    }
}

#[test]
fn the_demo_accepts_no_wrong_pose() {
    // The bundled demo with its own settings (160×120, 600 plain iterations) up to the instance
    // stage: no accepted pose is a wrong one (within 10°, the distance that tells distinct poses
    // apart, and 5 % of instances.json), all but one are within 5°, and the method shows (at
    // least three of the five registered ducks are accepted). The ducks are about 25 pixels
    // wide: over 12 plain trainings (60 accepted ducks) the poses came within 0.2–2.8°, but a
    // rare training leaves one shape-ambiguous duck 5–6° off (5.15° and 6.09° seen in a test run
    // and in CI; lavapipe training is not bit-reproducible, BENCHMARKS.md "The demo").
    let base = tmp("demo-poses");
    let cfg = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("configs/demo.toml");
    let run = base.join("run");
    let o = run_bin(
        &[
            "train",
            "--data",
            demo().to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--config",
            cfg.to_str().unwrap(),
            "--until",
            "instance",
            "--quiet",
        ],
        &[],
    );
    assert!(o.ok, "{}", o.stderr);
    let text = std::fs::read_to_string(run.join("instance.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let rows = v["instances"].as_array().unwrap();
    assert_eq!(rows.len(), 6);
    let (mut accepted, mut past_5_deg) = (0, 0);
    for r in rows {
        let status = r["status"].as_str().unwrap();
        if status != "accepted" {
            assert!(status == "reference" || r["reason"].as_str().is_some_and(|w| !w.is_empty()), "{r}");
            continue;
        }
        accepted += 1;
        let rot = r["rotation_error_deg"].as_f64().unwrap();
        let trans = r["translation_error_fraction"].as_f64().unwrap();
        let scale = r["scale_error_fraction"].as_f64().unwrap();
        assert!(
            rot <= instgs_vk::instancing::pose::RIVAL_DEG && trans <= 0.05 && scale.abs() <= 0.05,
            "accepted a wrong pose: {r}\n{}",
            o.stderr
        );
        past_5_deg += usize::from(rot > instgs_vk::instancing::synchronise::RESIDUAL_DEG);
    }
    assert!(past_5_deg <= 1, "{past_5_deg} accepted ducks more than 5° off:\n{text}\n{}", o.stderr);
    assert!(accepted >= 3, "only {accepted} of 5 ducks accepted:\n{}", o.stderr);
    // Templates and background ranked under one budget: decided against the training views,
    // never above the instanced scene's bytes when kept, and the file holds what was decided.
    let rb = &v["rebalance"];
    let kept = rb["accepted"].as_bool().unwrap();
    assert!(rb["psnr_after"].as_f64().unwrap() >= rb["psnr_before"].as_f64().unwrap() || !kept, "{rb}");
    if kept {
        assert!(rb["bytes_after"].as_u64().unwrap() <= rb["bytes_before"].as_u64().unwrap(), "{rb}");
        assert_eq!(v["template_gaussians"], rb["template_gaussians_after"], "{rb}");
        assert_eq!(v["background_gaussians"], rb["background_after"], "{rb}");
    }
    let scene = instgs_vk::formats::instgs::read(&run.join("init.instgs")).unwrap();
    assert_eq!(serde_json::json!(scene.background.len()), v["background_gaussians"]);
}

#[test]
fn a_dataset_edited_in_place_redoes_the_stages_that_read_it() {
    // Same names, same cameras, other contents: a mask changed redoes the segmentation (the
    // plain scene stays), an image changed redoes everything.
    let data = demo_copy("edited", |_| {});
    let base = data.parent().unwrap().to_path_buf();
    let cfg = base.join("tiny.toml");
    std::fs::write(&cfg, TINY).unwrap();
    let run = base.join("run");
    let (d, r, c) = (data.to_str().unwrap(), run.to_str().unwrap(), cfg.to_str().unwrap());
    fn until(a: Vec<&str>) -> Vec<&str> {
        [a, vec!["--until", "segment"]].concat()
    }
    let o = run_bin(&until(args(d, r, c)), &[]);
    assert!(o.ok, "{}", o.stderr);
    let o = run_bin(&until(args(d, r, c)), &[]);
    assert!(o.ok && o.stderr.matches("done earlier").count() == 2, "{}", o.stderr);
    let mask = data.join("masks/train/r_004.png");
    let mut m = image::open(&mask).unwrap().to_luma16();
    m.put_pixel(0, 0, image::Luma([m.get_pixel(0, 0).0[0] ^ 1]));
    m.save(&mask).unwrap();
    let o = run_bin(&until(args(d, r, c)), &[]);
    assert!(o.ok, "{}", o.stderr);
    assert!(o.stderr.contains("the masks of") && o.stderr.contains("changed since stage segment ran"), "{}", o.stderr);
    assert!(
        o.stderr.contains("[1/7 plain] done earlier") && o.stderr.contains("[2/7 segment] finished"),
        "{}",
        o.stderr
    );
    let image = data.join("train/r_002.png");
    let mut img = image::open(&image).unwrap().to_rgb8();
    img.put_pixel(5, 5, image::Rgb([1, 2, 3]));
    img.save(&image).unwrap();
    let o = run_bin(&until(args(d, r, c)), &[]);
    assert!(o.ok, "{}", o.stderr);
    assert!(o.stderr.contains("the images of") && o.stderr.contains("changed since stage plain ran"), "{}", o.stderr);
    assert!(o.stderr.contains("[1/7 plain] finished"), "{}", o.stderr);
}
