//! `RUN/report.md`: what a pipeline run produced, from the stages' JSON files (rewritten after
//! every stage, so an unfinished run reports what it has).
use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;

use crate::pipeline::stage::{PipelineArgs, Stage, STAGES};

fn read(run: &Path, file: &str) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(run.join(file)).ok()?).ok()
}

fn num(v: &serde_json::Value, key: &str) -> Option<f64> {
    key.split('.').try_fold(v, |v, k| v.get(k))?.as_f64()
}

fn mb(bytes: f64) -> String {
    format!("{:.2}", bytes / 1e6)
}

pub fn write(run: &Path, a: &PipelineArgs, stages: &[(Stage, bool, f64)]) -> Result<()> {
    let mut md = String::new();
    let _ = writeln!(md, "# InstGS run: `{}`\n", a.data.display());
    let _ = writeln!(
        md,
        "Written by `instgs-vk train` (version {}). Files are in this folder; `pipeline.json` holds \
         every stage's settings.\n",
        env!("CARGO_PKG_VERSION")
    );
    stages_section(&mut md, stages);
    let eval = read(run, "eval.json");
    let bench = read(run, "bench.json");
    comparison_section(&mut md, run, eval.as_ref(), bench.as_ref());
    curve_section(&mut md, run);
    segmentation_section(&mut md, run);
    registration_section(&mut md, run);
    pictures_section(&mut md, eval.as_ref());
    curves_section(&mut md, run);
    crate::util::write_atomic(&run.join("report.md"), |f| {
        use std::io::Write;
        f.write_all(md.as_bytes())
    })
}

/// The stage table: status and seconds of every stage.
fn stages_section(md: &mut String, stages: &[(Stage, bool, f64)]) {
    let _ = writeln!(md, "## Stages\n\n| stage | status | time (s) |\n|---|---|---|");
    let mut total = 0.0;
    for s in STAGES {
        let (status, secs) = match stages.iter().find(|r| r.0 == s) {
            Some((_, true, t)) => ("finished", Some(*t)),
            Some((_, false, t)) => ("interrupted or running", Some(*t)),
            None => ("not run", None),
        };
        total += secs.unwrap_or(0.0);
        let t = secs.map(|t| format!("{t:.1}")).unwrap_or_else(|| "—".into());
        let _ = writeln!(md, "| {} | {status} | {t} |", s.name());
    }
    let _ = writeln!(md, "| total | | {total:.1} |\n");
}

/// Plain 3DGS against InstGS (and the pruned baseline): quality from eval.json, speed and memory from bench.json.
fn comparison_section(
    md: &mut String,
    run: &Path,
    eval: Option<&serde_json::Value>,
    bench: Option<&serde_json::Value>,
) {
    if eval.is_some() || bench.is_some() {
        let _ = writeln!(md, "## Plain 3DGS against InstGS\n");
        if let Some(e) = &eval {
            let _ = writeln!(
                md,
                "Quality on the {} views ({}×{}, {} views), rendered exactly.",
                e["split"].as_str().unwrap_or("?"),
                e["width"],
                e["height"],
                e["plain"]["views"].as_array().map_or(0, |v| v.len())
            );
            if e["plain"].get("psnr_instances_mean").is_some() {
                let _ = writeln!(
                    md,
                    "Instance and background pixels are those of the views' masks (id ≠ 0 and id = 0); their PSNR \
                     is each view's over those pixels, averaged."
                );
            }
        }
        if let Some(b) = &bench {
            let _ = writeln!(
                md,
                "Speed and memory from one `bench` run on {} ({} cameras, {} frames each, plain and InstGS \
                 interleaved; InstGS rendered as the player does, `configs/render.toml`). FPS ratio: median over \
                 paired frames.",
                b["device"].as_str().unwrap_or("?"),
                b["views"],
                b["frames"]
            );
        }
        // The "plain, pruned" column where the run has that baseline.
        let pruned = eval.as_ref().is_some_and(|e| e.get("pruned").is_some())
            || bench.as_ref().is_some_and(|b| b.get("compare_more").is_some());
        if pruned {
            let _ = writeln!(
                md,
                "*plain, pruned*: the plain scene pruned to InstGS's GPU memory by significance and fine-tuned as \
                 long as the joint stage (`pruned.json`) — what instancing adds over pruning alone."
            );
            if let Some(w) = read(run, "pruned.json").and_then(|p| num(&p, "tile_cost_weight")).filter(|w| *w > 0.0) {
                let _ = writeln!(
                    md,
                    "Both were trained with the frame-cost regulariser (`tile_cost_weight = {w:e}`, docs/pipeline.md)."
                );
            }
            let _ = writeln!(
                md,
                "\n| | plain 3DGS | plain, pruned | InstGS | InstGS vs plain | InstGS vs plain, pruned |\n|---|---|---|---|---|---|"
            );
        } else {
            let _ = writeln!(md, "\n| | plain 3DGS | InstGS | InstGS vs plain |\n|---|---|---|---|");
        }
        // One row: the plain, pruned and InstGS values, formatted; the comparisons (difference or
        // ratio) of InstGS against plain and against pruned.
        let row = |md: &mut String,
                   name: &str,
                   [p, q, i]: [Option<f64>; 3],
                   fmt: &dyn Fn(f64) -> String,
                   cmp: &dyn Fn(f64, f64) -> String| {
            let f = |v: Option<f64>| v.map(fmt).unwrap_or_else(|| "—".into());
            let c = |base: Option<f64>| base.zip(i).map(|(b, i)| cmp(b, i)).unwrap_or_else(|| "—".into());
            if pruned {
                let _ = writeln!(md, "| {name} | {} | {} | {} | {} | {} |", f(p), f(q), f(i), c(p), c(q));
            } else {
                let _ = writeln!(md, "| {name} | {} | {} | {} |", f(p), f(i), c(p));
            }
        };
        let db = |b: f64, i: f64| format!("{:+.2} dB", i - b);
        let times = |b: f64, i: f64| format!("{:.3}×", i / b);
        if let Some(e) = &eval {
            let three = |key: &str| ["plain", "pruned", "instgs"].map(|s| num(e, &format!("{s}.{key}")));
            row(md, "PSNR (dB)", three("psnr_mean"), &|v| format!("{v:.2}"), &db);
            for (key, name) in [
                ("psnr_instances_mean", "PSNR on instance pixels (dB)"),
                ("psnr_background_mean", "PSNR on background pixels (dB)"),
            ] {
                let v = three(key);
                if v.iter().any(Option::is_some) {
                    row(md, name, v, &|v| format!("{v:.2}"), &db);
                }
            }
            row(md, "SSIM", three("ssim_mean"), &|v| format!("{v:.4}"), &|b, i| format!("{:+.4}", i - b));
            row(md, "PSNR, colour-compensated (dB)", three("psnr_compensated_mean"), &|v| format!("{v:.2}"), &db);
            row(md, "SSIM, colour-compensated", three("ssim_compensated_mean"), &|v| format!("{v:.4}"), &|b, i| {
                format!("{:+.4}", i - b)
            });
        }
        if let Some(b) = &bench {
            // bench.json: InstGS's numbers, plain's under `compare`, pruned's under `compare_more`.
            let three = |key: &str| [num(b, &format!("compare.{key}")), num(&b["compare_more"][0], key), num(b, key)];
            row(md, "splats rendered", three("splats"), &|v| format!("{v:.0}"), &times);
            row(md, "tile intersections, median", three("intersections"), &|v| format!("{v:.0}"), &times);
            row(md, "scene memory on the GPU (MB)", three("scene_gpu_bytes"), &mb, &times);
            row(md, "file size (MB)", three("file_bytes"), &mb, &times);
            row(md, "frame time, median (ms)", three("frame_ms_median"), &|v| format!("{v:.2}"), &times);
            row(md, "FPS (median)", three("fps_median"), &|v| format!("{v:.1}"), &times);
        }
        if let Some(e) = &eval {
            let _ = writeln!(
                md,
                "\nColour-compensated: {} (raw: the render as it is, whole image).",
                e["compensated"]
                    .as_str()
                    .unwrap_or("the photo's colour transform fitted on its left half, scored on its right half")
            );
            let k = |key: &str| e["vignetting"][key].as_f64().unwrap_or(0.0);
            let (k1, k2) = (k("k1"), k("k2"));
            if k1 != 0.0 || k2 != 0.0 {
                let _ = writeln!(
                    md,
                    "\nEvery render scored through the lens's vignetting the plain stage learned: \
                     1 + k1 r² + k2 r⁴ with k1 = {k1:.4}, k2 = {k2:.4} (r: distance from the principal point in focal lengths)."
                );
            }
        }
        if let Some((bg, inst)) =
            bench.as_ref().and_then(|b| num(b, "background_intersections").zip(num(b, "instanced_intersections")))
        {
            let _ = writeln!(
                md,
                "\nWhere InstGS's frame goes: {bg:.0} tile intersections from its background, {inst:.0} from its \
                 instances' splats (medians over the frames; a frame's time follows its intersections on a CPU device)."
            );
        }
        md.push('\n');
        cameras_paragraph(md, run);
        compaction_paragraph(md, run);
    }
}

/// How the instanced scene was made compact: the background's pruning and the rebalance.
/// How far the plain stage moved the training cameras (RUN/cameras.json), when it refined them.
fn cameras_paragraph(md: &mut String, run: &Path) {
    let Some(v) = read(run, crate::train::CAMERAS_FILE) else { return };
    let Some(views) = v["views"].as_array() else { return };
    let norm = |e: &serde_json::Value, key: &str| {
        (0..3).map(|k| e[key][k].as_f64().unwrap_or(0.0).powi(2)).sum::<f64>().sqrt()
    };
    let stats = |key: &str, scale: f64| {
        let x: Vec<f64> = views.iter().map(|e| norm(e, key) * scale).collect();
        let rms = (x.iter().map(|v| v * v).sum::<f64>() / x.len().max(1) as f64).sqrt();
        (rms, x.iter().copied().fold(0.0, f64::max))
    };
    let (rot, rot_max) = stats("rotation", 180.0 / std::f64::consts::PI);
    let (tr, tr_max) = stats("translation", 1.0);
    let _ = writeln!(
        md,
        "The plain stage refined the {} training cameras (`cameras.json`): corrections {rot:.3}° rms (largest          {rot_max:.3}°) and {tr:.4} units rms (largest {tr_max:.4}) in the cameras' frames; the later stages used          them, the held-out cameras are the dataset's.\n",
        views.len()
    );
}

fn compaction_paragraph(md: &mut String, run: &Path) {
    if let Some(seg) = read(run, "segment.json") {
        let bg = num(&seg, "background").unwrap_or(0.0);
        let objects: f64 = seg["instances"].as_array().into_iter().flatten().filter_map(|r| num(r, "gaussians")).sum();
        let pruning = read(run, "instance.json").map(|v| v["background_pruning"].clone()).unwrap_or_default();
        if let (Some(keep), Some(dropped)) = (num(&pruning, "keep"), num(&pruning, "dropped")) {
            let rule = &pruning["rule"];
            let how = match (num(rule, "budget_db"), num(rule, "psnr_whole"), num(rule, "psnr_pruned")) {
                (Some(b), Some(w), Some(p)) => format!(
                    "the smallest share whose pruned plain scene stays within the budget of {b} dB on {} training \
                     views ({w:.2} → {p:.2} dB) before the joint optimisation",
                    rule["views"]
                ),
                _ => format!("`instance.background_keep` = {keep}"),
            };
            let _ = writeln!(
                md,
                "Of the plain scene's {:.0} Gaussians, {:.0} ({:.1} %) belong to instances; of its {:.0} background \
                 Gaussians InstGS keeps the {:.0} most significant ({:.1} %: {how}; the {} near an instance rank \
                 first).\n",
                bg + objects,
                objects,
                100.0 * objects / (bg + objects),
                bg,
                bg - dropped,
                100.0 * keep,
                rule["protected"]
            );
            let rb = read(run, "instance.json").map(|v| v["rebalance"].clone()).unwrap_or_default();
            if let Some(accepted) = rb["accepted"].as_bool() {
                let _ = writeln!(
                    md,
                    "Then templates and background were ranked under one memory budget (significance per byte, \
                     `instance.rebalance`): templates {} → {} Gaussians, background {} → {}, {:.2} → {:.2} dB on {} \
                     training views before the joint optimisation — {}.\n",
                    rb["template_gaussians_before"],
                    rb["template_gaussians_after"],
                    rb["background_before"],
                    rb["background_after"],
                    num(&rb, "psnr_before").unwrap_or(f64::NAN),
                    num(&rb, "psnr_after").unwrap_or(f64::NAN),
                    rb["views"],
                    if accepted { "kept" } else { "refused, the scene as instanced stays" }
                );
            }
        } else if bg + objects > 0.0 {
            let _ = writeln!(
                md,
                "Of the plain scene's {:.0} Gaussians, {:.0} ({:.1} %) belong to instances; the {:.0} background \
                 Gaussians stay plain in InstGS, so its memory cannot fall below {:.3}× of the plain scene's \
                 without touching the background.\n",
                bg + objects,
                objects,
                100.0 * objects / (bg + objects),
                bg,
                bg / (bg + objects)
            );
        }
    }
}

/// The segmentation's instances (or the instances discovered without masks).
fn segmentation_section(md: &mut String, run: &Path) {
    if let Some(s) = read(run, "segment.json").filter(|s| s["method"] == "discover") {
        let _ = writeln!(
            md,
            "## Instances discovered without masks (`{}`)\n\nEvery instance below passed the instance stage's checks against the group's first (groups.json); refused candidates stay background.\n\n| group | instance | Gaussians |\n|---|---|---|",
            s["discover"].as_str().unwrap_or("?")
        );
        for r in s["instances"].as_array().into_iter().flatten() {
            let _ = writeln!(md, "| {} | {} | {} |", r["group"].as_str().unwrap_or("?"), r["id"], r["gaussians"]);
        }
        let _ = writeln!(md, "| background | | {} |\n", s["background"]);
        for r in s["refused"].as_array().into_iter().flatten().filter_map(|r| r.as_str()) {
            let _ = writeln!(md, "- refused: {r}");
        }
        md.push('\n');
    } else if let Some(s) = read(run, "segment.json") {
        let _ = writeln!(
            md,
            "## Segmentation (gradient-driven, α = {:.2})\n\n| group | instance | Gaussians | held-out IoU |\n|---|---|---|---|",
            num(&s, "alpha").unwrap_or(f64::NAN)
        );
        for r in s["instances"].as_array().into_iter().flatten() {
            let iou = num(r, "test_iou").map(|v| format!("{v:.3} ({} views)", r["test_views"])).unwrap_or("—".into());
            let _ =
                writeln!(md, "| {} | {} | {} | {iou} |", r["group"].as_str().unwrap_or("?"), r["id"], r["gaussians"]);
        }
        let _ = writeln!(md, "| background | | {} | |\n", s["background"]);
    }
}

/// Registration and templates: every instance's checks and pose errors.
fn registration_section(md: &mut String, run: &Path) {
    if let Some(s) = read(run, "instance.json") {
        let _ = writeln!(
            md,
            "## Registration and templates (init `{}`)\n\n{} template Gaussians, {} background Gaussians, {} splats.\n",
            s["init"].as_str().unwrap_or("?"),
            s["template_gaussians"],
            s["background_gaussians"],
            s["splats"]
        );
        let acc = &s["acceptance"];
        let limit = |k: &str| num(acc, k).unwrap_or(f64::NAN);
        let _ = writeln!(
            md,
            "Each instance is registered onto its group's reference (the instance with the most opaque Gaussians) \
             and accepted only when the pose passes every check: both fitnesses ≥ {}, scale within ±{:.0} % of the \
             clouds' size ratio{}. A refused instance stays plain (its Gaussians remain background). \
             {}*borderline*: accepted with a check within 0.05 (1 dB for PSNR) of its limit.\n",
            limit("min_fitness"),
            100.0 * limit("scale_tolerance"),
            if s["render_check"].as_bool() == Some(true) {
                format!(
                    ", and the render check: silhouette IoU with the masks ≥ {} of the instance's own silhouette's (*render IoU* gives the IoU, then that share) and PSNR ≥ {} dB against the instance's own render",
                    limit("min_render_iou"),
                    limit("min_render_psnr")
                )
            } else {
                " (no render check ran)".into()
            },
            if s["synchronise"].as_bool() == Some(true) {
                "Where a group has three or more accepted instances besides its reference, each is also registered onto a few others \
                 (its pose graph's edges, chosen by size signature) and every pose is synchronised (the least-squares mean of its \
                 estimates through them); a registration whose cycles do not close is refused. A synchronised pose is kept when it \
                 passes the same checks; *synchronised* gives how far that moved it. "
            } else {
                ""
            }
        );
        let _ = writeln!(
            md,
            "| group | instance | status | Gaussians | fitness | reverse fitness | scale | render IoU | render PSNR (dB) | synchronised (°) | rotation error (°) | translation error (% of size) | scale error (%) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        let f = |r: &serde_json::Value, k: &str, m: f64, d: usize| {
            num(r, k).map(|v| format!("{:.*}", d, v * m)).unwrap_or_else(|| "—".into())
        };
        let mut reasons = Vec::new();
        for r in s["instances"].as_array().into_iter().flatten() {
            let status = r["status"].as_str().unwrap_or("?");
            let near = |k: &str, lim: &str, margin: f64| num(r, k).is_some_and(|v| v < limit(lim) + margin);
            let borderline = status == "accepted"
                && (near("fitness", "min_fitness", 0.05)
                    || near("fitness_reverse", "min_fitness", 0.05)
                    || near("render_relative_iou", "min_render_iou", 0.05)
                    || near("render_psnr", "min_render_psnr", 1.0));
            let shown = match status {
                "refused" | "plain" => format!("**{status}**"),
                "accepted" if borderline => "accepted, *borderline*".into(),
                other => other.into(),
            };
            if let Some(why) = r["reason"].as_str() {
                reasons.push(format!("- {} {}: {status}: {why}", r["group"].as_str().unwrap_or("?"), r["id"]));
            }
            let _ = writeln!(
                md,
                "| {} | {} | {shown} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                r["group"].as_str().unwrap_or("?"),
                r["id"],
                r["gaussians"],
                f(r, "fitness", 1.0, 3),
                f(r, "fitness_reverse", 1.0, 3),
                f(r, "scale", 1.0, 4),
                match (num(r, "render_iou"), num(r, "render_relative_iou")) {
                    (Some(iou), Some(share)) => format!("{iou:.3} ({share:.2})"),
                    _ => f(r, "render_iou", 1.0, 3),
                },
                f(r, "render_psnr", 1.0, 1),
                f(r, "synchronised_moved_deg", 1.0, 2),
                f(r, "rotation_error_deg", 1.0, 2),
                f(r, "translation_error_fraction", 100.0, 2),
                f(r, "scale_error_fraction", 100.0, 2)
            );
        }
        if !reasons.is_empty() {
            let _ = writeln!(md, "\n{}", reasons.join("\n"));
        }
        graph_lines(md, &s);
        md.push('\n');
    }
}

/// The pose graphs (edges, cycles, refused registrations) and the stage's time per step.
fn graph_lines(md: &mut String, s: &serde_json::Value) {
    let mut lines = Vec::new();
    for g in s["graphs"].as_array().into_iter().flatten() {
        let open = g["open_cycles"].as_array().map_or(0, |a| a.len());
        let refused: Vec<String> = g["refused"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|e| {
                format!(
                    "{} → {} ({:.1}°, {:.1} %)",
                    e["from"],
                    e["to"],
                    num(e, "rotation_deg").unwrap_or(f64::NAN),
                    100.0 * num(e, "translation_fraction").unwrap_or(f64::NAN)
                )
            })
            .collect();
        lines.push(format!(
            "- pose graph of {}: {} edges, {} cycles, {open} open; registrations refused: {}",
            g["group"].as_str().unwrap_or("?"),
            g["edges"],
            g["cycles"],
            if refused.is_empty() { "none".to_string() } else { refused.join(", ") }
        ));
    }
    let t = &s["timing"];
    if t.is_object() {
        let sec = |k: &str| num(t, k).unwrap_or(f64::NAN);
        lines.push(format!(
            "- time: candidates {:.0} s, registration {:.0} s, synchronisation {:.0} s, render checks {:.0} s ({} checks), templates {:.0} s, compaction {:.0} s; {} registrations, {} graph edges",
            sec("candidates_s"),
            sec("registration_s"),
            sec("synchronisation_s"),
            sec("render_checks_s"),
            t["render_checks"],
            sec("templates_s"),
            sec("compaction_s"),
            t["registrations"],
            t["edges"]
        ));
    }
    if !lines.is_empty() {
        let _ = writeln!(md, "\n{}", lines.join("\n"));
    }
}

/// The memory–quality curve (`instgs-vk curve`), where it was made.
fn curve_section(md: &mut String, run: &Path) {
    let Some(c) = read(run, crate::pipeline::curve::CURVE_FILE) else { return };
    let _ = writeln!(
        md,
        "## Memory and quality\n\nHeld-out PSNR against GPU memory (`instgs-vk curve`): InstGS at each memory budget \
         against the plain scene pruned to the same memory, both fine-tuned {} iterations; plain 3DGS {:.2} dB at {} MB. \
         Numbers: `{}`.\n\n![memory and quality]({})\n\n| budget | InstGS MB | InstGS PSNR (dB) | pruned MB | pruned PSNR (dB) | InstGS − pruned (dB) | memory pruning needs for InstGS's PSNR | colour-compensated: InstGS − pruned, pruning needs | InstGS file MB | pruned file MB |\n|---|---|---|---|---|---|---|---|---|---|",
        c["iterations"],
        num(&c, "plain.psnr").unwrap_or(f64::NAN),
        mb(num(&c, "plain.gpu_bytes").unwrap_or(f64::NAN)),
        crate::pipeline::curve::CURVE_FILE,
        crate::pipeline::curve::CURVE_PLOT
    );
    for (i, p) in c["points"].as_array().into_iter().flatten().enumerate() {
        let needs_of = |key: &str| match c[key][i].as_f64() {
            Some(r) => format!("{r:.2}×"),
            None => "outside the pruned scenes".into(),
        };
        let needs = needs_of("pruning_needs");
        let compensated = match c["gain_db_compensated"][i].as_f64() {
            Some(g) => format!("{g:+.2} dB, {}", needs_of("pruning_needs_compensated")),
            None => "not measured".into(),
        };
        let budget = match num(p, "fraction") {
            Some(f) => format!("{:.0} % of plain", 100.0 * f),
            None => "default".into(),
        };
        let v = |k: &str| num(p, k).unwrap_or(f64::NAN);
        let _ = writeln!(
            md,
            "| {budget} | {} | {:.2} | {} | {:.2} | {:+.2} | {needs} | {compensated} | {} | {} |",
            mb(v("instgs.gpu_bytes")),
            v("instgs.psnr"),
            mb(v("pruned.gpu_bytes")),
            v("pruned.psnr"),
            v("instgs.psnr") - v("pruned.psnr"),
            mb(v("instgs.file_bytes")),
            mb(v("pruned.file_bytes"))
        );
    }
    let e = &c["equal_quality"];
    if e.is_object() {
        let v = |k: &str| num(e, k).unwrap_or(f64::NAN);
        let scene = |b: &serde_json::Value| {
            let v = |k: &str| num(b, k).unwrap_or(f64::NAN);
            format!("{} MB at {:.2} dB, {:.1} FPS", mb(v("scene.gpu_bytes")), v("scene.psnr"), v("fps"))
        };
        let about = match e["below"].is_object() {
            true => format!("between the pruned scenes about it: {} and {}", scene(&e["below"]), scene(&e["above"])),
            false => format!("at most: the smallest pruned scene, {}, reaches it already", scene(&e["above"])),
        };
        let trained = e["trained"].as_array().map_or(0, |t| t.len());
        let _ = writeln!(
            md,
            "\nAt InstGS's {:.2} dB ({} MB), pruning needs {} MB to match it ({:.2}× InstGS's memory, {about}; \
             {trained} pruned scene(s) trained to find them). At that PSNR InstGS renders at {:.2}× the pruned scene's frame rate \
             ({:.1} against {:.1} FPS interpolated; `bench` interleaved, culling and level of detail on).",
            v("instgs_psnr"),
            mb(v("instgs_gpu_bytes")),
            mb(v("pruned_gpu_bytes_needed")),
            v("memory_ratio"),
            v("fps_ratio"),
            v("fps_instgs"),
            v("fps_pruned")
        );
    }
    let f = &c["compressed"];
    if f.is_object() {
        let v = |k: &str| num(f, k).unwrap_or(f64::NAN);
        let sogs: Vec<String> = f["pruned_sog"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|s| {
                format!(
                    "{} MB at {:.2} dB",
                    mb(num(s, "file_bytes").unwrap_or(f64::NAN)),
                    num(s, "psnr").unwrap_or(f64::NAN)
                )
            })
            .collect();
        let needs = |bytes: &str, ratio: &str| match num(f, bytes) {
            Some(b) => format!(
                "a pruned `.sog` needs {} MB (linear between the two about it), InstGS's file {:.2}× it",
                mb(b),
                v(ratio)
            ),
            None => "no two of them straddle it".into(),
        };
        let _ = writeln!(
            md,
            "\nCompressed files: InstGS as `instgs-vk convert scene.instgs OUT.instgs --compress` writes it, {} MB at \
             {:.2} dB ({:.2} compensated); the pruned scenes as `.sog`: {}. For InstGS's PSNR {}; for its compensated PSNR {}.",
            mb(v("instgs.file_bytes")),
            v("instgs.psnr"),
            v("instgs.psnr_compensated"),
            sogs.join(", "),
            needs("sog_bytes_needed", "file_ratio"),
            needs("sog_bytes_needed_compensated", "file_ratio_compensated")
        );
    }
    let loses: Vec<&str> = c["instgs_loses_at"].as_array().into_iter().flatten().filter_map(|v| v.as_str()).collect();
    let _ = writeln!(
        md,
        "\n{}\n",
        if loses.is_empty() {
            "InstGS is ahead of the pruned scene at every budget measured.".to_string()
        } else {
            format!("InstGS loses to the pruned scene at: {}.", loses.join("; "))
        }
    );
}

/// The held-out views' pictures.
fn pictures_section(md: &mut String, eval: Option<&serde_json::Value>) {
    if let Some(e) = &eval {
        let panels = if e.get("pruned").is_some() {
            "Ground truth | plain 3DGS | plain, pruned | InstGS | InstGS error × 4"
        } else {
            "Ground truth | plain 3DGS | InstGS | InstGS error × 4"
        };
        let _ = writeln!(md, "## Held-out views\n\n{panels}\n");
        for img in e["images"].as_array().into_iter().flatten() {
            if let Some(p) = img.as_str() {
                let _ = writeln!(md, "![{p}]({p})\n");
            }
        }
    }
}

/// The training curves of the stages that trained.
fn curves_section(md: &mut String, run: &Path) {
    let curves: Vec<(&str, &str)> = [
        ("plain 3DGS", "curves.png"),
        ("joint optimisation", "joint/curves.png"),
        ("plain, pruned: fine-tuning", "pruned/curves.png"),
    ]
    .into_iter()
    .filter(|(_, p)| run.join(p).exists())
    .collect();
    if !curves.is_empty() {
        let _ = writeln!(md, "## Training curves\n");
        for (name, p) in curves {
            let _ = writeln!(md, "{name}:\n\n![{name}]({p})\n");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_comparison_says_when_both_scenes_were_regularised() {
        let run = std::env::temp_dir().join(format!("instgs-report-{}", std::process::id()));
        std::fs::create_dir_all(&run).unwrap();
        let eval = serde_json::json!({ "split": "test", "pruned": {}, "plain": {} });
        let section = |weight: f64| {
            std::fs::write(run.join("pruned.json"), serde_json::json!({ "tile_cost_weight": weight }).to_string())
                .unwrap();
            let mut md = String::new();
            comparison_section(&mut md, &run, Some(&eval), None);
            md
        };
        assert!(section(3e-8).contains("frame-cost regulariser (`tile_cost_weight = 3e-8`"));
        assert!(!section(0.0).contains("regulariser"));
        std::fs::remove_dir_all(&run).unwrap();
    }
}
