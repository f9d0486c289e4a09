//! `instgs-vk curve`: the memory–quality curve of a finished run, the way compaction papers
//! compare (LightGaussian, Compact3D: quality against size). At each memory budget (a fraction
//! of the plain scene's GPU bytes) InstGS spends the budget on its templates and background
//! ([`crate::instancing::compact::Spending`], from the instance stage's whole instanced scene)
//! and is optimised jointly; the plain scene is pruned to the same GPU bytes by significance
//! (`compact::prune_to_bytes`) and fine-tuned as long, with the same schedule (`[joint]`).
//! Both are scored on the held-out views. With the run's own InstGS, pruned and plain scenes
//! (the default budget), the points go to `RUN/rate_distortion.json` and
//! `RUN/rate_distortion.png`, and the report shows them. At the run's own InstGS PSNR the
//! memory pruning needs is interpolated between the pruned points about it, and the plain
//! scene pruned to just that memory and fine-tuned as long is benched against InstGS. Each
//! point is resumable: its training runs keep checkpoints under `RUN/curve/`, and a finished
//! point is kept in `RUN/curve/points.json`.
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::formats::AnyScene;
use crate::render::upload::GpuScene;

use super::stages::{Ctx, Init, PRUNED_FILE, WHOLE_FILE};
use super::{MaskIds, PipelineArgs, Stage, State};

/// One scene's scores and sizes.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Scored {
    pub file: String,
    pub gpu_bytes: u64,
    pub file_bytes: u64,
    pub splats: usize,
    /// Held-out PSNR (dB) and SSIM, raw and colour-compensated ([`crate::train::eval`]).
    pub psnr: f64,
    pub ssim: f64,
    pub psnr_compensated: f64,
}

/// InstGS and the pruned plain scene at one budget.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Point {
    /// The budget as a fraction of the plain scene's GPU bytes (None: the run's own default,
    /// which the instance stage's quality budget chose).
    pub fraction: Option<f64>,
    pub instgs: Scored,
    pub pruned: Scored,
}

/// `RUN/rate_distortion.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Curve {
    pub plain: Scored,
    /// Fine-tuning iterations of every point (the joint schedule).
    pub iterations: u64,
    /// By GPU bytes.
    pub points: Vec<Point>,
    /// Per point, InstGS's PSNR minus the pruned scene's (dB); and the budgets where InstGS loses.
    pub gain_db: Vec<f64>,
    pub instgs_loses_at: Vec<String>,
    /// The run's own InstGS against pruning at the same quality (None without a pruned point
    /// at least as good as it).
    pub equal_quality: Option<EqualQuality>,
}

/// The default InstGS scene against the plain scene pruned to the same held-out PSNR.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EqualQuality {
    pub instgs_psnr: f64,
    pub instgs_gpu_bytes: u64,
    /// GPU bytes pruning needs to reach InstGS's PSNR: linear between the two pruned points
    /// about it; and that over InstGS's.
    pub pruned_gpu_bytes_needed: f64,
    pub memory_ratio: f64,
    /// The pruned scene InstGS is benched against, interleaved, from the held-out cameras
    /// (`bench`: culling and level of detail on): the plain scene pruned to the bytes above and
    /// fine-tuned as long as every point, when it reaches InstGS's PSNR (within 0.05 dB);
    /// otherwise the smallest pruned point at least as good (`at_needed_bytes` false).
    pub pruned_file: String,
    pub pruned_psnr: f64,
    pub pruned_gpu_bytes: u64,
    pub at_needed_bytes: bool,
    pub fps_instgs: f64,
    pub fps_pruned: f64,
    pub fps_ratio: f64,
}

/// Points already finished, by their budget's name.
type Done = std::collections::BTreeMap<String, Point>;

/// What `instgs-vk curve` was asked.
pub struct CurveArgs {
    pub run: PipelineArgs,
    /// Budgets as fractions of the plain scene's GPU bytes.
    pub budgets: Vec<f64>,
}

/// Adds the budgets' points to a finished run (see the module docs) and rewrites its report.
pub fn curve(c: CurveArgs) -> Result<()> {
    let a = &c.run;
    let run = a.out.as_path();
    for f in &c.budgets {
        if !(*f > 0.0 && *f <= 1.0) {
            bail!("--budgets: {f} is not a fraction of the plain scene's memory in (0, 1]");
        }
    }
    let state = State::read(run)?;
    for s in [Stage::Instance, Stage::Eval] {
        if !state.done(s) {
            bail!(
                "{}: stage {} has not finished; run `instgs-vk train` on this run folder first",
                run.display(),
                s.name()
            );
        }
    }
    if !run.join(WHOLE_FILE).exists() {
        bail!(
            "{}: not written by this run's instance stage (it predates the curve); redo it with `instgs-vk train ... --from instance`",
            run.join(WHOLE_FILE).display()
        );
    }
    let cfg = crate::train::config::PipelineConfig::load(a.config.as_deref())?;
    let load = crate::dataset::LoadOptions { downscale: a.downscale, background: cfg.plain.background };
    let ds = crate::dataset::load(&a.data, &load)?;
    let (gpu, k) = crate::gpu::kernels::open_device(a.device.clone())?;
    ctrlc::set_handler(|| crate::train::INTERRUPTED.store(true, std::sync::atomic::Ordering::SeqCst))
        .context("cannot install the Ctrl-C handler")?;
    let ctx = Ctx { a, cfg: &cfg, ds: &ds, gpu: &gpu, k: &k, mask_ids: MaskIds::Global };
    let dir = run.join("curve");
    std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let done_path = dir.join("points.json");
    let mut done: Done = match std::fs::read_to_string(&done_path) {
        Ok(t) => serde_json::from_str(&t).with_context(|| format!("{}: damaged", done_path.display()))?,
        Err(_) => Done::new(),
    };
    let plain_path = run.join("point_cloud.ply");
    let plain_scene = crate::formats::ply::read_ply(&plain_path)?;
    let plain_bytes = GpuScene::new(&gpu, &plain_scene)?.gpu_bytes();
    let mut spending = None;
    for &f in &c.budgets {
        let name = format!("{f:.3}");
        if done.contains_key(&name) {
            eprintln!("[curve] budget {name}: done earlier");
            continue;
        }
        if spending.is_none() {
            let whole = crate::formats::instgs::read(&run.join(WHOLE_FILE))?;
            spending = Some(crate::instancing::compact::Spending::new(
                &gpu,
                &k,
                whole,
                &ds.train,
                cfg.instance.outline_fraction,
                crate::formats::instgs::Dtype::offsets(&cfg.instance.offset_dtype)?,
                |l| eprintln!("[curve] {l}"),
            )?);
        }
        let budget = (f * plain_bytes as f64) as u64;
        let point = ctx.curve_point(&dir.join(&name), f, budget, spending.as_ref().expect("ranked"), &plain_scene)?;
        let Some(point) = point else { bail!("interrupted; run the same command again to resume") };
        done.insert(name, point);
        crate::util::write_json(&done_path, &serde_json::to_value(&done)?, true)?;
    }
    let plain = ctx.score(&plain_path)?;
    let default = Point {
        fraction: None,
        instgs: ctx.score(&run.join("scene.instgs"))?,
        pruned: ctx.score(&run.join(PRUNED_FILE))?,
    };
    let mut points: Vec<Point> = done.into_values().chain([default]).collect();
    points.sort_by_key(|p| p.instgs.gpu_bytes);
    let gain_db: Vec<f64> = points.iter().map(|p| p.instgs.psnr - p.pruned.psnr).collect();
    let instgs_loses_at = points
        .iter()
        .zip(&gain_db)
        .filter(|(_, g)| **g < 0.0)
        .map(|(p, g)| format!("{:.2} MB: {g:+.2} dB", p.instgs.gpu_bytes as f64 / 1e6))
        .collect();
    let equal_quality = ctx.equal_quality(&dir, &points, &plain_scene)?;
    let curve = Curve { plain, iterations: cfg.joint.iterations, points, gain_db, instgs_loses_at, equal_quality };
    crate::util::write_json(&run.join(CURVE_FILE), &serde_json::to_value(&curve)?, true)?;
    crate::train::plot::write_rate_distortion(&plot_of(&curve, &a.data), &run.join(CURVE_PLOT))?;
    super::report::write(run, a, &State::read(run)?.summary())?;
    eprintln!(
        "{} and {}; report: {}",
        run.join(CURVE_FILE).display(),
        run.join(CURVE_PLOT).display(),
        run.join("report.md").display()
    );
    Ok(())
}

/// The curve's files in a run folder.
pub const CURVE_FILE: &str = "rate_distortion.json";
pub const CURVE_PLOT: &str = "rate_distortion.png";

fn plot_of(c: &Curve, data: &Path) -> crate::train::plot::RateDistortion {
    let name = data.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mb = |s: &Scored| s.gpu_bytes as f64 / 1e6;
    crate::train::plot::RateDistortion {
        title: format!("{name}: held-out PSNR against GPU memory ({} fine-tuning iterations per point)", c.iterations),
        instgs: c.points.iter().map(|p| (mb(&p.instgs), p.instgs.psnr)).collect(),
        pruned: c.points.iter().map(|p| (mb(&p.pruned), p.pruned.psnr)).collect(),
        plain: (mb(&c.plain), c.plain.psnr),
        default_mb: c.points.iter().find(|p| p.fraction.is_none()).map(|p| mb(&p.instgs)),
    }
}

impl Ctx<'_> {
    /// InstGS and the pruned plain scene at `budget` bytes, trained in `dir`; None when
    /// interrupted.
    fn curve_point(
        &self,
        dir: &Path,
        fraction: f64,
        budget: u64,
        spending: &crate::instancing::compact::Spending,
        plain: &crate::model::scene::Scene,
    ) -> Result<Option<Point>> {
        let label = format!("budget {fraction:.3} ({:.2} MB)", budget as f64 / 1e6);
        let inst_dir = dir.join("instgs");
        let scene = spending.at(self.gpu, budget)?;
        let bytes = GpuScene::stored_bytes(self.gpu, &scene, spending.storage())?;
        eprintln!(
            "[curve] {label}: InstGS keeps {} template and {} background Gaussians ({:.2} MB); joint optimisation",
            scene.groups.iter().map(|g| g.template.len()).sum::<usize>(),
            scene.background.len(),
            bytes as f64 / 1e6
        );
        if !self.train_point(&inst_dir, Init::Instanced(scene), Stage::Joint)? {
            return Ok(None);
        }
        let instgs = self.score(&inst_dir.join("scene.instgs"))?;
        let Some(pruned) = self.pruned_point(&dir.join("pruned"), instgs.gpu_bytes, plain, &label)? else {
            return Ok(None);
        };
        let point = Point { fraction: Some(fraction), instgs, pruned };
        eprintln!(
            "[curve] {label}: InstGS {:.2} dB at {:.2} MB, pruned {:.2} dB at {:.2} MB",
            point.instgs.psnr,
            point.instgs.gpu_bytes as f64 / 1e6,
            point.pruned.psnr,
            point.pruned.gpu_bytes as f64 / 1e6
        );
        Ok(Some(point))
    }

    /// The plain scene pruned to `bytes` by significance and fine-tuned in `dir` (resumed from
    /// its checkpoint), scored; None when interrupted.
    fn pruned_point(
        &self,
        dir: &Path,
        bytes: u64,
        plain: &crate::model::scene::Scene,
        label: &str,
    ) -> Result<Option<Scored>> {
        let init = if crate::train::checkpoint_path(dir).exists() {
            crate::model::scene::Scene::default()
        } else {
            let sig = read_significance(&self.a.out.join("significance.bin"), plain.len())?;
            let keep = crate::instancing::compact::prune_to_bytes(self.gpu, plain, &sig, bytes)?;
            eprintln!("[curve] {label}: the plain scene pruned to {} Gaussians; fine-tuning", keep.len());
            plain.select(&keep)
        };
        if !self.train_point(dir, Init::Plain(init), Stage::Pruned)? {
            return Ok(None);
        }
        Ok(Some(self.score(&dir.join("point_cloud.ply"))?))
    }

    /// The run's own InstGS (the point without a fraction) against pruning at its PSNR: the
    /// memory pruning needs (interpolated between the pruned points about it), and the frame
    /// rate against the plain scene pruned to just that memory (trained in `curve_dir`) — or,
    /// where that falls short of InstGS's PSNR, against the smallest pruned point at least as
    /// good. None without a pruned point at least as good.
    fn equal_quality(
        &self,
        curve_dir: &Path,
        points: &[Point],
        plain: &crate::model::scene::Scene,
    ) -> Result<Option<EqualQuality>> {
        let Some(own) = points.iter().find(|p| p.fraction.is_none()) else { return Ok(None) };
        let target = own.instgs.psnr;
        let mut pruned: Vec<&Scored> = points.iter().map(|p| &p.pruned).collect();
        pruned.sort_by_key(|s| s.gpu_bytes);
        let Some(good) = pruned.iter().find(|s| s.psnr >= target - 0.05) else { return Ok(None) };
        let needed = match pruned.windows(2).find(|w| w[0].psnr < target && w[1].psnr >= target) {
            Some(w) => {
                let t = (target - w[0].psnr) / (w[1].psnr - w[0].psnr);
                w[0].gpu_bytes as f64 + t * (w[1].gpu_bytes as f64 - w[0].gpu_bytes as f64)
            }
            None => good.gpu_bytes as f64,
        };
        let mut versus = (*good).clone();
        let mut at_needed_bytes = false;
        if (needed as u64) < good.gpu_bytes {
            let bytes = needed.ceil() as u64;
            let label = format!("equal quality ({:.2} MB)", bytes as f64 / 1e6);
            let Some(s) = self.pruned_point(&curve_dir.join(format!("equal-{bytes}")), bytes, plain, &label)? else {
                bail!("interrupted; run the same command again to resume")
            };
            eprintln!("[curve] {label}: pruned {:.2} dB against InstGS's {target:.2} dB", s.psnr);
            if s.psnr >= target - 0.05 {
                versus = s;
                at_needed_bytes = true;
            }
        }
        let render = crate::render::lod::RenderConfig::load(None)?;
        let cams: Vec<_> = self.views().iter().map(|v| v.camera.clone()).collect();
        let (a, b) = (PathBuf::from(&own.instgs.file), PathBuf::from(&versus.file));
        let forward = crate::render::raster::Forward::Compute;
        let v = crate::bench::bench_scenes(
            self.gpu,
            self.k,
            crate::bench::BenchInput::read(&a, render.clone(), forward)?,
            vec![crate::bench::BenchInput::read(&b, render, forward)?],
            &cams,
            (self.cfg.bench.frames, self.cfg.bench.warmup),
            self.cfg.plain.background,
            ("[curve] equal quality: ", crate::util::ProgressMode::Tenths),
        )?;
        let fps = |x: &serde_json::Value| x["fps_median"].as_f64().unwrap_or(f64::NAN);
        Ok(Some(EqualQuality {
            instgs_psnr: target,
            instgs_gpu_bytes: own.instgs.gpu_bytes,
            pruned_gpu_bytes_needed: needed,
            memory_ratio: needed / own.instgs.gpu_bytes as f64,
            pruned_file: versus.file,
            pruned_psnr: versus.psnr,
            pruned_gpu_bytes: versus.gpu_bytes,
            at_needed_bytes,
            fps_instgs: fps(&v),
            fps_pruned: fps(&v["compare"]),
            fps_ratio: v["ratios"]["fps"].as_f64().unwrap_or(f64::NAN),
        }))
    }

    /// Fine-tunes `init` in `dir` with the joint schedule (resumed from its checkpoint).
    fn train_point(&self, dir: &Path, init: Init, s: Stage) -> Result<bool> {
        self.train(dir, init, &self.cfg.joint, s, false)
    }

    /// The held-out scores (rendered exactly, as `eval`), GPU bytes (as `bench` and the player
    /// hold it: an instanced scene with its levels of detail) and file bytes of a scene file.
    pub(super) fn score(&self, path: &Path) -> Result<Scored> {
        let scene = AnyScene::read(path)?;
        let gs = scene.upload(self.gpu).with_context(|| path.display().to_string())?;
        let mut r = crate::render::raster::Rasterizer::new(self.gpu, self.k)?;
        let e = crate::train::evaluate(&mut r, &gs, self.views(), self.cfg.plain.background, |_, _| Ok(()))?;
        let render = crate::render::lod::RenderConfig::load(None)?;
        Ok(Scored {
            file: path.display().to_string(),
            gpu_bytes: scene.upload_for_rendering(self.gpu, &render)?.gpu_bytes(),
            file_bytes: crate::formats::file_bytes(path)?,
            splats: scene.splats(),
            psnr: e.psnr,
            ssim: e.ssim,
            psnr_compensated: e.psnr_compensated,
        })
    }
}

/// `significance.bin`: one f32 per Gaussian of the plain scene.
pub(super) fn read_significance(path: &Path, n: usize) -> Result<Vec<f32>> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    if bytes.len() != 4 * n {
        bail!("{}: {} bytes for {n} Gaussians; redo the segment stage (--from segment)", path.display(), bytes.len());
    }
    Ok(bytemuck::pod_collect_to_vec(&bytes))
}
