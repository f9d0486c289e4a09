//! The stages of the pipeline, one method each on [`Ctx`] (what every stage reads: the
//! arguments, configuration, dataset and device); [`super::run`] decides which run.
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use crate::bench::BenchInput;
use crate::dataset::Dataset;
use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::render::raster::Forward;
use crate::train::config::{BackgroundKeep, PipelineConfig};
use crate::train::{self, INTERRUPTED};
use crate::util::{Progress, ProgressMode};
use anyhow::{anyhow, bail, Context, Result};

use super::{interrupted, MaskIds, PipelineArgs, Stage};

/// Registration and acceptance as `[instance]` sets them (the instance stage's, and the
/// discovery's in the segment stage).
fn instance_options(c: &crate::train::config::InstanceStage) -> Result<crate::instancing::options::InstanceOptions> {
    Ok(crate::instancing::options::InstanceOptions {
        init: clap::ValueEnum::from_str(&c.init, true).map_err(|e| anyhow!("instance.init: {e}"))?,
        with_scale: !c.rigid,
        use_colour: c.colour,
        colour_weight: c.colour_weight,
        seed: c.seed,
        accept: crate::instancing::options::Acceptance {
            min_fitness: c.min_fitness,
            scale_tolerance: c.scale_tolerance,
            min_render_iou: c.min_render_iou,
            min_render_psnr: c.min_render_psnr,
            min_render_views: c.min_render_views,
            ..Default::default()
        },
        synchronise: c.synchronise && c.render_check,
        neighbours: c.neighbours,
        ..Default::default()
    })
}

/// The "plain, pruned" baseline's scene in a run folder.
pub const PRUNED_FILE: &str = "pruned.ply";
/// The instanced scene before compaction (templates whole, the whole background), in a run folder.
pub const WHOLE_FILE: &str = "instanced_whole.instgs";

/// What a training stage starts from.
pub(super) enum Init {
    /// The dataset (plain 3DGS).
    Dataset,
    /// A plain scene, fine-tuned without densification (the pruned baseline).
    Plain(crate::model::scene::Scene),
    /// An instanced scene (joint optimisation).
    Instanced(crate::model::instanced::InstancedScene),
}

pub(super) struct Ctx<'a> {
    pub(super) a: &'a PipelineArgs,
    pub(super) cfg: &'a PipelineConfig,
    pub(super) ds: &'a Dataset,
    pub(super) gpu: &'a Arc<Gpu>,
    pub(super) k: &'a Arc<Kernels>,
    pub(super) mask_ids: MaskIds,
}

impl Ctx<'_> {
    fn run_dir(&self) -> &Path {
        &self.a.out
    }

    fn progress_mode(&self) -> ProgressMode {
        if self.a.progress {
            ProgressMode::Auto
        } else {
            ProgressMode::Tenths
        }
    }

    /// Runs one stage: Ok(true) finished, Ok(false) interrupted (nothing half-written).
    /// Runs stage `s`; Ok(false) when interrupted (the stage resumes or is redone on the next run).
    pub(super) fn stage(&self, s: Stage, hooked: bool) -> Result<bool> {
        if hooked && !matches!(s, Stage::Plain | Stage::Joint) {
            INTERRUPTED.store(true, Ordering::SeqCst);
        }
        match s {
            Stage::Plain => self.plain(hooked),
            Stage::Segment if self.mask_ids == MaskIds::Discovered => self.discover(),
            Stage::Segment => self.segment(),
            Stage::Instance => self.instance(),
            Stage::Joint => self.joint(hooked),
            Stage::Pruned => self.pruned(hooked),
            Stage::Eval => self.eval(),
            Stage::Bench => self.bench(),
        }
    }

    /// Plain 3DGS on the dataset, or a copy of `--init SCENE`.
    fn plain(&self, hooked: bool) -> Result<bool> {
        let run = self.run_dir();
        let s = Stage::Plain;
        if let Some(p) = &self.a.init {
            let to = run.join("point_cloud.ply");
            if crate::formats::detect(p)? == crate::formats::Format::Ply {
                let bytes = std::fs::read(p).with_context(|| format!("{}: cannot read", p.display()))?;
                crate::util::write_atomic(&to, |f| {
                    use std::io::Write;
                    f.write_all(&bytes)
                })?;
            } else {
                crate::formats::ply::write_ply(&crate::formats::read_scene(p)?, &to)?;
            }
            eprintln!("{}: plain scene from {}", run.join("point_cloud.ply").display(), p.display());
            return Ok(!interrupted());
        }
        self.train(run, Init::Dataset, &self.cfg.plain, s, hooked)
    }

    /// Gradient-driven segmentation with the dataset's masks.
    fn segment(&self) -> Result<bool> {
        let run = self.run_dir();
        let s = Stage::Segment;
        let scene = crate::formats::ply::read_ply(&run.join("point_cloud.ply"))?;
        let per_frame = self.mask_ids == MaskIds::PerFrame;
        let seg = crate::segment::run::segment_scene(
            self.gpu,
            self.k,
            &scene,
            &self.a.data,
            self.ds,
            "train",
            self.cfg.segment.alpha,
            per_frame,
            (&s.label(), self.progress_mode()),
        )?;
        if interrupted() {
            return Ok(false);
        }
        crate::util::write_json(&run.join("segment.json"), &seg.summary, true)?;
        crate::util::write_atomic(&run.join("significance.bin"), |f| {
            use std::io::Write;
            f.write_all(bytemuck::cast_slice(&seg.significance))
        })?;
        crate::util::write_json(&run.join("labels.json"), &seg.doc, false)?;
        Ok(true)
    }

    /// Background budget, registration with its checks, templates and offsets.
    fn instance(&self) -> Result<bool> {
        let run = self.run_dir();
        let _s = Stage::Instance;
        let c = &self.cfg.instance;
        let opts = instance_options(c)?;
        let dtype = crate::formats::instgs::Dtype::offsets(&c.offset_dtype)?;
        // Ground-truth poses where the dataset has them: its groups file, or for ids that
        // are not the truth's, ground_truth.json matched by the instances' centres.
        use crate::instancing::build::TruthIds;
        let gt = self.a.data.join(crate::instancing::pose_error::GROUND_TRUTH_FILE);
        let by_centre = gt.exists().then(|| (gt.clone(), TruthIds::ByCentre));
        let (groups, truth) = match self.mask_ids {
            MaskIds::Global => {
                let g = self.a.data.join("instances.json");
                (g.clone(), Some((g, TruthIds::Same)))
            }
            MaskIds::PerFrame => (run.join("labels.json"), by_centre),
            MaskIds::Discovered => (run.join("groups.json"), by_centre),
        };
        let mut check = if c.render_check {
            // Masks select the views only where their ids are the labels' ids.
            let masks = match self.mask_ids {
                MaskIds::Global => Some(crate::dataset::masks::load_masks(&self.a.data, "train", &self.ds.train)?),
                MaskIds::PerFrame | MaskIds::Discovered => None,
            };
            let cams = self.ds.train.iter().map(|v| v.camera.clone()).collect();
            Some(crate::instancing::verify::ImageCheck::new(self.gpu, self.k, cams, masks)?)
        } else {
            None
        };
        let views = &self.ds.train;
        // Scored as trained: each render through its photo's colour transform (captures).
        let colours = self.photo_appearance(&self.cfg.plain)?;
        let colours = colours.as_ref();
        let bg = self.cfg.plain.background;
        let (gpu, k) = (self.gpu, self.k);
        let mut rule = |scene: &crate::model::scene::Scene, labels: &[u32], sig: &[f32]| {
            let (ranking, protected) =
                crate::instancing::compact::protect_outlines(scene, labels, sig, c.outline_fraction);
            match c.background_keep {
                BackgroundKeep::Fraction(f) => Ok((
                    f,
                    ranking,
                    serde_json::json!({"fixed": f, "outline_fraction": c.outline_fraction, "protected": protected}),
                )),
                BackgroundKeep::Auto(_) => {
                    let b = crate::instancing::compact::background_budget(
                        gpu,
                        k,
                        scene,
                        labels,
                        &ranking,
                        protected,
                        views,
                        colours,
                        bg,
                        c.background_budget_db,
                        |l| eprintln!("{l}"),
                    )?;
                    let mut how = serde_json::to_value(&b)?;
                    how["outline_fraction"] = c.outline_fraction.into();
                    Ok((b.keep, ranking, how))
                }
            }
        };
        let mut rebalance = |inst: &crate::model::instanced::InstancedScene, dropped: &crate::model::scene::Scene| {
            let (out, how) = crate::instancing::compact::rebalance(
                gpu,
                k,
                inst,
                dropped,
                views,
                colours,
                bg,
                c.outline_fraction,
                c.render_weight,
                dtype,
                |l| eprintln!("{l}"),
            )?;
            Ok((out, serde_json::to_value(&how)?))
        };
        let rebalance = c.rebalance.then_some(&mut rebalance as &mut crate::instancing::build::RebalanceRule);
        let r = crate::instancing::build::instance(
            &run.join("point_cloud.ply"),
            &run.join("labels.json"),
            &groups,
            truth.as_ref().map(|(p, ids)| (p.as_path(), *ids)),
            &opts,
            dtype,
            Some((&run.join("significance.bin"), &mut rule, rebalance)),
            check.as_mut().map(|c| c as &mut dyn crate::instancing::pose::RenderCheck),
            None,
            Some(&run.join(WHOLE_FILE)),
            &run.join("init.instgs"),
        );
        match r {
            Ok(v) => {
                crate::util::write_json(&run.join("instance.json"), &v, true)?;
                Ok(true)
            }
            Err(_) if interrupted() => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// Joint optimisation of the instanced scene.
    fn joint(&self, hooked: bool) -> Result<bool> {
        let run = self.run_dir();
        let s = Stage::Joint;
        let init = crate::formats::instgs::read(&run.join("init.instgs"))?;
        let dir = run.join("joint");
        if !self.train(&dir, Init::Instanced(init), &self.cfg.joint, s, hooked)? {
            return Ok(false);
        }
        std::fs::rename(dir.join("scene.instgs"), run.join("scene.instgs"))
            .with_context(|| format!("{}: cannot move the result", dir.join("scene.instgs").display()))?;
        Ok(true)
    }

    /// `bench --compare` of InstGS against plain (and pruned) from the held-out cameras.
    fn bench(&self) -> Result<bool> {
        let run = self.run_dir();
        let s = Stage::Bench;
        let cams: Vec<_> = self.views().iter().map(|v| v.camera.clone()).collect();
        let render = crate::render::lod::RenderConfig::load(None)?;
        let a = run.join("scene.instgs");
        let b = run.join("point_cloud.ply");
        let c = run.join(PRUNED_FILE);
        let mut others = vec![BenchInput::read(&b, render.clone(), Forward::Compute)?];
        if self.a.pruned_baseline && c.exists() {
            others.push(BenchInput::read(&c, render.clone(), Forward::Compute)?);
        }
        let v = crate::bench::bench_scenes(
            self.gpu,
            self.k,
            BenchInput::read(&a, render.clone(), Forward::Compute)?,
            others,
            &cams,
            (self.cfg.bench.frames, self.cfg.bench.warmup),
            self.cfg.plain.background,
            (&s.label(), self.progress_mode()),
        )?;
        if interrupted() {
            return Ok(false);
        }
        crate::util::write_json(&run.join("bench.json"), &v, true)?;
        Ok(true)
    }

    /// The held-out views (the training views when the dataset holds none out).
    pub(super) fn views(&self) -> &[crate::dataset::View] {
        if self.ds.test.is_empty() {
            &self.ds.train
        } else {
            &self.ds.test
        }
    }

    /// The training photos' colour transforms and the lens's vignetting the plain stage learned
    /// (RUN/appearance.json), one transform per training view, when `cfg` models them
    /// (captures); None otherwise.
    pub(super) fn photo_appearance(
        &self,
        cfg: &crate::train::config::Config,
    ) -> Result<Option<crate::render::appearance::PhotoAppearance>> {
        let path = self.run_dir().join(train::APPEARANCE_FILE);
        if path.exists() && cfg.appearance.enabled(self.ds.kind) {
            Ok(Some(train::read_appearance(&path, self.ds)?))
        } else {
            Ok(None)
        }
    }

    /// The lens's vignetting the plain stage learned (captures; none otherwise): every scene of
    /// a run is scored through it.
    pub(super) fn photo_lens(&self) -> Result<crate::render::appearance::Vignetting> {
        Ok(self.photo_appearance(&self.cfg.plain)?.map_or(crate::render::appearance::NO_VIGNETTING, |a| a.vignetting))
    }

    pub(super) fn train(
        &self,
        out: &Path,
        init: Init,
        cfg: &crate::train::config::Config,
        s: Stage,
        hooked: bool,
    ) -> Result<bool> {
        let resume = train::checkpoint_path(out).exists();
        // The later stages start from the photos' colour transforms the plain stage learned.
        let appearance = match init {
            Init::Dataset => None,
            _ => self.photo_appearance(cfg)?,
        };
        let (init, init_scene) = match init {
            Init::Dataset => (None, None),
            Init::Instanced(scene) => (Some(scene), None),
            Init::Plain(scene) => (None, Some(scene)),
        };
        let opts = train::RunOptions {
            init,
            init_scene,
            appearance,
            label: s.label(),
            stop_after: hooked.then_some((cfg.iterations / 2).max(1)),
            offset_dtype: crate::formats::instgs::Dtype::offsets(&self.cfg.instance.offset_dtype)?,
            ..train::RunOptions::new(out.to_path_buf(), resume, self.a.progress)
        };
        let r = train::run(self.gpu, self.k, self.ds, cfg, &opts)?;
        let test = r.test_psnr.map(|p| format!(", test PSNR {p:.2} dB")).unwrap_or_default();
        eprintln!(
            "{}{} iterations, {} splats{test}, {:.2} it/s",
            s.label(),
            r.iterations,
            r.splats,
            r.iterations_per_second
        );
        Ok(!r.interrupted)
    }

    /// The "plain, pruned" baseline: the plain scene's most significant Gaussians that fit in
    /// the InstGS scene's GPU memory (`compact::prune_to_bytes`), fine-tuned for as many
    /// iterations as the joint stage with its schedule; `RUN/pruned.ply` and `RUN/pruned.json`.
    /// Skipped (and an earlier result removed) with `--no-pruned-baseline`.
    fn pruned(&self, hooked: bool) -> Result<bool> {
        let run = self.run_dir();
        let out = run.join(PRUNED_FILE);
        if !self.a.pruned_baseline {
            for p in [out, run.join("pruned.json")] {
                if p.exists() {
                    std::fs::remove_file(&p).with_context(|| format!("{}: cannot remove", p.display()))?;
                }
            }
            eprintln!("{}skipped (--no-pruned-baseline)", Stage::Pruned.label());
            return Ok(true);
        }
        let dir = run.join("pruned");
        let init = if train::checkpoint_path(&dir).exists() {
            // Resumed from its checkpoint: the pruned scene is in there.
            crate::model::scene::Scene::default()
        } else {
            let plain = crate::formats::ply::read_ply(&run.join("point_cloud.ply"))?;
            let sig_path = run.join("significance.bin");
            let bytes = std::fs::read(&sig_path).with_context(|| format!("{}: cannot read", sig_path.display()))?;
            if bytes.len() != 4 * plain.len() {
                bail!(
                    "{}: {} bytes for {} Gaussians; redo the segment stage (--from segment)",
                    sig_path.display(),
                    bytes.len(),
                    plain.len()
                );
            }
            let significance: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes);
            let render = crate::render::lod::RenderConfig::load(None)?;
            let target = AnyScene::read(&run.join("init.instgs"))?.upload_for_rendering(self.gpu, &render)?.gpu_bytes();
            let keep = crate::instancing::compact::prune_to_bytes(self.gpu, &plain, &significance, target)?;
            let summary = serde_json::json!({
                "gaussians": plain.len(), "kept": keep.len(), "target_gpu_bytes": target,
                "ranking": "significance (blending weight summed over the training views)",
                "fine_tune_iterations": self.cfg.joint.iterations,
                "tile_cost_weight": self.cfg.joint.tile_cost_weight,
            });
            eprintln!(
                "{}kept {} of {} Gaussians ({:.1} %) to fit InstGS's {:.2} MB; fine-tuning {} iterations",
                Stage::Pruned.label(),
                keep.len(),
                plain.len(),
                100.0 * keep.len() as f64 / plain.len().max(1) as f64,
                target as f64 / 1e6,
                self.cfg.joint.iterations
            );
            std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
            crate::util::write_json(&dir.join("pruned.json"), &summary, true)?;
            plain.select(&keep)
        };
        if !self.train(&dir, Init::Plain(init), &self.cfg.joint, Stage::Pruned, hooked)? {
            return Ok(false);
        }
        for (from, to) in [(dir.join("point_cloud.ply"), out), (dir.join("pruned.json"), run.join("pruned.json"))] {
            std::fs::copy(&from, &to)
                .with_context(|| format!("{}: cannot copy to {}", from.display(), to.display()))?;
        }
        Ok(true)
    }

    /// The segment stage without masks: `crate::discover` finds the instances (labels.json,
    /// groups.json), and the plain scene's significance (every Gaussian's blending weight over
    /// the training views, as segmentation measures it) is written for background pruning.
    fn discover(&self) -> Result<bool> {
        let run = self.run_dir();
        let spec = self.a.discover.as_ref().expect("discovering");
        let scene = crate::formats::ply::read_ply(&run.join("point_cloud.ply"))?;
        let label = Stage::Segment.label();
        let started = Instant::now();
        let opts =
            crate::discover::DiscoverOptions { instance: instance_options(&self.cfg.instance)?, ..Default::default() };
        let found = crate::discover::run::search(
            self.gpu,
            self.k,
            &scene,
            spec,
            &self.ds.train,
            &opts,
            self.cfg.instance.render_check,
            |l| eprintln!("{label}{l}"),
        )?;
        if interrupted() {
            return Ok(false);
        }
        let blank: Vec<Vec<u16>> =
            self.ds.train.iter().map(|v| vec![0; (v.camera.width * v.camera.height) as usize]).collect();
        let weight = crate::segment::segment(self.gpu, self.k, &scene, &self.ds.train, &blank, &[], 0.0)?.weight;
        crate::util::write_atomic(&run.join("significance.bin"), |f| {
            use std::io::Write;
            f.write_all(bytemuck::cast_slice(&weight))
        })?;
        crate::discover::run::write_outputs(
            &scene,
            &found,
            &self.a.data,
            &run.join("labels.json"),
            &run.join("groups.json"),
            started.elapsed().as_secs_f64(),
        )?;
        let labels = found.labels(scene.len());
        let instances: Vec<serde_json::Value> = found
            .groups
            .iter()
            .filter(|g| g.members.len() > 1)
            .flat_map(|g| {
                g.members
                    .iter()
                    .map(move |m| serde_json::json!({"group": g.name, "id": m.id, "gaussians": m.gaussians.len()}))
            })
            .collect();
        let summary = serde_json::json!({
            "method": "discover",
            "discover": format!("{spec:?}"),
            "background": labels.iter().filter(|&&l| l == 0).count(),
            "instances": instances,
            "refused": found.refused,
        });
        crate::util::write_json(&run.join("segment.json"), &summary, true)?;
        Ok(true)
    }

    fn eval(&self) -> Result<bool> {
        let run = self.run_dir();
        let bg = self.cfg.plain.background;
        let views = self.views();
        let split = if self.ds.test.is_empty() { "train" } else { "test" };
        let vignetting = self.photo_lens()?;
        let mut r = crate::render::raster::Rasterizer::new(self.gpu, self.k)?;
        let n_images = self.cfg.eval.images.min(views.len());
        // Evenly spread views for the pictures.
        let pick: Vec<usize> = (0..n_images).map(|i| i * views.len() / n_images.max(1)).collect();
        // Per picked view, the baselines' frames (plain, then plain pruned) for the pictures.
        let mut baseline_frames: BTreeMap<usize, Vec<Vec<[f32; 4]>>> = BTreeMap::new();
        // The split's masks, where it has them: PSNR over instance pixels (any id but 0) and
        // background pixels separately, to see where the two scenes differ.
        let masks = if self.a.data.join("masks").join(split).is_dir() {
            crate::dataset::masks::load_masks(&self.a.data, split, views)
                .map_err(|e| eprintln!("warning: {e:#}; PSNR over instance and background pixels left out"))
                .ok()
        } else {
            None
        };
        let mut results = Vec::new();
        let pruned = self.a.pruned_baseline && run.join(PRUNED_FILE).exists();
        let scenes = [("plain", "point_cloud.ply"), ("pruned", PRUNED_FILE), ("instgs", "scene.instgs")];
        for (name, file) in scenes.into_iter().filter(|(n, _)| pruned || *n != "pruned") {
            let path = run.join(file);
            let scene = AnyScene::read(&path)?;
            let gs = scene.upload(self.gpu).with_context(|| path.display().to_string())?;
            let mut index = 0usize;
            let mut pictures = Vec::new();
            let mut regions = [(0.0, 0usize), (0.0, 0usize)];
            let label = format!("{}{name}: ", Stage::Eval.label());
            let mut progress = Progress::new(&label, "view", "views/s", views.len() as u64, 0, self.progress_mode());
            let e = train::evaluate(&mut r, &gs, views, bg, &vignetting, |v, f, photo| {
                if interrupted() {
                    bail!("interrupted");
                }
                progress.set(index as u64 + 1, "");
                if let Some(m) = &masks {
                    let m = &m[index];
                    for (k, object) in [true, false].into_iter().enumerate() {
                        if let Some(db) = crate::util::psnr_where(photo, &v.image, |i| (m[i] != 0) == object) {
                            regions[k].0 += db;
                            regions[k].1 += 1;
                        }
                    }
                }
                if pick.contains(&index) {
                    if name == "instgs" {
                        pictures.push((index, v.camera.name.clone(), f.image.clone()));
                    } else {
                        baseline_frames.entry(index).or_default().push(f.image.clone());
                    }
                }
                index += 1;
                Ok(())
            });
            progress.finish();
            let e = match e {
                Err(_) if interrupted() => return Ok(false),
                other => other?,
            };
            eprintln!(
                "{name}: {split} PSNR {:.3} dB, SSIM {:.4}; compensated {:.3} dB, {:.4} ({} views)",
                e.psnr,
                e.ssim,
                e.psnr_compensated,
                e.ssim_compensated,
                e.views.len()
            );
            if name == "instgs" {
                let dir = run.join("images");
                std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
                for (i, view_name, img) in &pictures {
                    let v = &views[*i];
                    let baselines = baseline_frames.get(i).ok_or_else(|| anyhow!("missing plain render"))?;
                    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
                    let err = crate::util::error_image(img, &v.image);
                    let mut panels: Vec<&[[f32; 4]]> = vec![&v.image];
                    panels.extend(baselines.iter().map(|b| &b[..]));
                    panels.extend([&img[..], &err[..]]);
                    let strip = crate::util::side_by_side(&panels, w, h);
                    let n = panels.len() as u32;
                    crate::util::save_png(&dir.join(format!("{view_name}.png")), n * w as u32, h as u32, &strip)?;
                }
            }
            let per: Vec<_> = e.views.iter().map(train::ViewScore::json).collect();
            let mut out = serde_json::json!({
                "scene": path.display().to_string(), "splats": scene.splats(),
                "psnr_mean": e.psnr, "ssim_mean": e.ssim,
                "psnr_compensated_mean": e.psnr_compensated, "ssim_compensated_mean": e.ssim_compensated,
                "views": per,
            });
            for ((sum, n), key) in regions.into_iter().zip(["psnr_instances_mean", "psnr_background_mean"]) {
                if n > 0 {
                    out[key] = (sum / n as f64).into();
                }
            }
            results.push((name, out));
        }
        let mut v = serde_json::json!({
            "split": split, "width": views[0].camera.width, "height": views[0].camera.height,
            "compensated": train::eval::COMPENSATED_NOTE,
            "vignetting": {"k1": vignetting[0], "k2": vignetting[1]},
        });
        for (name, r) in results {
            v[name] = r;
        }
        v["images"] = pick.iter().map(|&i| format!("images/{}.png", views[i].camera.name)).collect();
        crate::util::write_json(&run.join("eval.json"), &v, true)?;
        Ok(true)
    }
}
