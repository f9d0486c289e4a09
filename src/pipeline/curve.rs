//! `instgs-vk curve`: the memory–quality curve of a finished run, the way compaction papers
//! compare (LightGaussian, Compact3D: quality against size). At each memory budget (a fraction
//! of the plain scene's GPU bytes) InstGS spends the budget on its templates and background
//! ([`crate::instancing::compact::Spending`], from the instance stage's whole instanced scene)
//! and is optimised jointly; the plain scene is pruned to the same GPU bytes by significance
//! (`compact::prune_to_bytes`) and fine-tuned as long, with the same schedule (`[joint]`).
//! Both are scored on the held-out views. With the run's own InstGS, pruned and plain scenes
//! (the default budget), the points go to `RUN/rate_distortion.json` and
//! `RUN/rate_distortion.png`, and the report shows them. At the run's own InstGS PSNR (equal
//! quality) the plain scene is pruned to the memory interpolated between the pruned scenes
//! about it and fine-tuned as long, again until one lands within 0.1 dB of InstGS (at most three
//! times: a pruned scene's PSNR is not linear in its memory); the memory pruning needs is
//! interpolated between the two that then straddle InstGS's PSNR, and both are benched against
//! InstGS, their frame rates interpolated to its PSNR. The files too: the run's InstGS as
//! `convert --compress` writes it against every pruned scene as `.sog` (SOG, what a user would
//! compress a plain scene to), the `.sog` bytes for InstGS's PSNR interpolated the same way.
//! Each point is resumable: its training
//! runs keep checkpoints under `RUN/curve/`, and a finished point is kept in
//! `RUN/curve/points.json`.
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
    /// Per point, the GPU memory pruning needs to reach InstGS's PSNR over InstGS's own:
    /// linear between the pruned scenes about it (every point's and the equal-quality
    /// search's); None outside them.
    pub pruning_needs: Vec<Option<f64>>,
    /// The same two with the colour-compensated PSNR (the measure for a capture, whose photos
    /// each have their own exposure and white balance).
    #[serde(default)]
    pub gain_db_compensated: Vec<f64>,
    #[serde(default)]
    pub pruning_needs_compensated: Vec<Option<f64>>,
    /// The run's own InstGS against pruning at the same quality (None without a pruned point
    /// at least as good as it).
    pub equal_quality: Option<EqualQuality>,
    /// The run's own InstGS compressed against the pruned scenes as `.sog` (absent in curves
    /// made before it was measured).
    #[serde(default)]
    pub compressed: Option<CompressedFiles>,
}

/// Compressed files at equal quality: the run's `scene.instgs` as `convert --compress` writes it
/// (`RUN/curve/scene.compressed.instgs`) against every pruned scene as `.sog` (beside its PLY).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CompressedFiles {
    pub instgs: Scored,
    /// By file bytes.
    pub pruned_sog: Vec<Scored>,
    /// File bytes a pruned `.sog` needs for the compressed InstGS's PSNR (linear between the two
    /// about it; None outside them), and InstGS's file bytes over that; the same two with the
    /// colour-compensated PSNR.
    pub sog_bytes_needed: Option<f64>,
    pub file_ratio: Option<f64>,
    pub sog_bytes_needed_compensated: Option<f64>,
    pub file_ratio_compensated: Option<f64>,
}

/// The default InstGS scene against the plain scene pruned to the same held-out PSNR.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EqualQuality {
    pub instgs_psnr: f64,
    pub instgs_gpu_bytes: u64,
    /// GPU bytes pruning needs to reach InstGS's PSNR: linear between the two pruned scenes
    /// about it (`below`, `above`); and that over InstGS's.
    pub pruned_gpu_bytes_needed: f64,
    pub memory_ratio: f64,
    /// The pruned scenes about InstGS's PSNR: the largest below it (None when even the
    /// smallest pruned point reaches it; then the needed bytes are at most `above`'s) and the
    /// smallest at or above it. The search trains the plain scene pruned to the interpolated
    /// bytes (fine-tuned as long as every point) until one lands within
    /// [`EQUAL_TOLERANCE_DB`] of InstGS's PSNR, at most [`EQUAL_TRAININGS`] times (`trained`:
    /// those scenes, also on the curve's plot).
    pub below: Option<Benched>,
    pub above: Benched,
    pub trained: Vec<Scored>,
    /// Frame rates (`bench`, InstGS and both pruned scenes interleaved from the held-out
    /// cameras, culling and level of detail on): InstGS's, the pruned scenes' interpolated
    /// linearly in PSNR to InstGS's, and InstGS's over that (the paired ratios interpolated).
    pub fps_instgs: f64,
    pub fps_pruned: f64,
    pub fps_ratio: f64,
}

/// A pruned scene with its frame rate beside InstGS's.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Benched {
    pub scene: Scored,
    pub fps: f64,
    /// InstGS's FPS over this scene's (median of paired frames).
    pub fps_ratio: f64,
}

/// How close (dB) a pruned scene's held-out PSNR must come to InstGS's to end the search.
pub const EQUAL_TOLERANCE_DB: f64 = 0.1;
/// At most this many pruned scenes trained by the equal-quality search.
pub const EQUAL_TRAININGS: usize = 3;

/// Among scenes sorted by GPU bytes, the adjacent pair whose PSNRs straddle `target` (the
/// first below it, the second at or above it) and the bytes linear interpolation between them
/// gives: (index below, bytes). None when no adjacent pair straddles it.
pub fn bracket(by_bytes: &[(u64, f64)], target: f64) -> Option<(usize, f64)> {
    let i = by_bytes.windows(2).position(|w| w[0].1 < target && w[1].1 >= target)?;
    let ((b0, p0), (b1, p1)) = (by_bytes[i], by_bytes[i + 1]);
    Some((i, at_psnr((p0, b0 as f64), (p1, b1 as f64), target)))
}

/// The equal-quality search's next step: the bytes to prune the plain scene to, or None once a
/// scene lies within `tolerance` dB of `target`, no pair straddles it, or the interpolated bytes
/// fall within 0.5 % of a scene already trained (`by_bytes` sorted by bytes).
pub fn next_equal_bytes(by_bytes: &[(u64, f64)], target: f64, tolerance: f64) -> Option<u64> {
    if by_bytes.iter().any(|&(_, p)| (p - target).abs() <= tolerance) {
        return None;
    }
    let (_, bytes) = bracket(by_bytes, target)?;
    let near = by_bytes.iter().any(|&(b, _)| (b as f64 - bytes).abs() <= 0.005 * bytes);
    (!near).then_some(bytes.ceil() as u64)
}

/// Linear interpolation of `(psnr, y)` pairs at `target`.
pub fn at_psnr(lo: (f64, f64), hi: (f64, f64), target: f64) -> f64 {
    let t = (target - lo.0) / (hi.0 - lo.0);
    lo.1 + t * (hi.1 - lo.1)
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
                cfg.instance.render_weight,
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
    let gain_db_compensated: Vec<f64> =
        points.iter().map(|p| p.instgs.psnr_compensated - p.pruned.psnr_compensated).collect();
    let instgs_loses_at = points
        .iter()
        .zip(&gain_db)
        .filter(|(_, g)| **g < 0.0)
        .map(|(p, g)| format!("{:.2} MB: {g:+.2} dB", p.instgs.gpu_bytes as f64 / 1e6))
        .collect();
    let equal_quality = ctx.equal_quality(&dir, &points, &plain_scene)?;
    let pruned = pruned_scenes(&points, equal_quality.as_ref());
    let needs = |psnr: fn(&Scored) -> f64| -> Vec<Option<f64>> {
        let by_bytes: Vec<(u64, f64)> = pruned.iter().map(|s| (s.gpu_bytes, psnr(s))).collect();
        points
            .iter()
            .map(|p| bracket(&by_bytes, psnr(&p.instgs)).map(|(_, bytes)| bytes / p.instgs.gpu_bytes as f64))
            .collect()
    };
    let pruning_needs = needs(|s| s.psnr);
    let pruning_needs_compensated = needs(|s| s.psnr_compensated);
    eprintln!("[curve] compressed files: InstGS as `convert --compress` writes it, the pruned scenes as .sog");
    let compressed = Some(ctx.compressed_files(&dir, &pruned)?);
    let curve = Curve {
        plain,
        iterations: cfg.joint.iterations,
        points,
        gain_db,
        instgs_loses_at,
        pruning_needs,
        gain_db_compensated,
        pruning_needs_compensated,
        equal_quality,
        compressed,
    };
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

/// Every pruned scene measured — each point's and the equal-quality search's — by GPU bytes.
fn pruned_scenes<'a>(points: &'a [Point], equal: Option<&'a EqualQuality>) -> Vec<&'a Scored> {
    let mut v: Vec<&Scored> =
        points.iter().map(|p| &p.pruned).chain(equal.into_iter().flat_map(|e| &e.trained)).collect();
    v.sort_by_key(|s| s.gpu_bytes);
    v
}

fn plot_of(c: &Curve, data: &Path) -> crate::train::plot::RateDistortion {
    let name = data.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mb = |s: &Scored| s.gpu_bytes as f64 / 1e6;
    crate::train::plot::RateDistortion {
        title: format!("{name}: held-out PSNR against GPU memory ({} fine-tuning iterations per point)", c.iterations),
        instgs: c.points.iter().map(|p| (mb(&p.instgs), p.instgs.psnr)).collect(),
        pruned: pruned_scenes(&c.points, c.equal_quality.as_ref()).iter().map(|s| (mb(s), s.psnr)).collect(),
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
    /// pruned scenes about it (the search of [`EqualQuality`], its trainings in `curve_dir`),
    /// the memory pruning needs between them and the frame rate there. None without a pruned
    /// scene at least as good as InstGS.
    fn equal_quality(
        &self,
        curve_dir: &Path,
        points: &[Point],
        plain: &crate::model::scene::Scene,
    ) -> Result<Option<EqualQuality>> {
        let Some(own) = points.iter().find(|p| p.fraction.is_none()) else { return Ok(None) };
        let target = own.instgs.psnr;
        let mut pruned: Vec<Scored> = points.iter().map(|p| p.pruned.clone()).collect();
        let mut trained = Vec::new();
        let by_bytes = loop {
            pruned.sort_by_key(|s| s.gpu_bytes);
            let by_bytes: Vec<(u64, f64)> = pruned.iter().map(|s| (s.gpu_bytes, s.psnr)).collect();
            let next = next_equal_bytes(&by_bytes, target, EQUAL_TOLERANCE_DB);
            let Some(bytes) = next.filter(|_| trained.len() < EQUAL_TRAININGS) else { break by_bytes };
            let label = format!("equal quality ({:.2} MB)", bytes as f64 / 1e6);
            let Some(s) = self.pruned_point(&curve_dir.join(format!("equal-{bytes}")), bytes, plain, &label)? else {
                bail!("interrupted; run the same command again to resume")
            };
            eprintln!("[curve] {label}: pruned {:.2} dB against InstGS's {target:.2} dB", s.psnr);
            trained.push(s.clone());
            pruned.push(s);
        };
        let (below, above, needed) = match bracket(&by_bytes, target) {
            Some((i, bytes)) => (Some(pruned[i].clone()), pruned[i + 1].clone(), bytes),
            None => {
                // No pair straddles InstGS's PSNR: the smallest pruned scene reaches it already,
                // or none does.
                let Some(first) = pruned.first().filter(|s| s.psnr >= target) else { return Ok(None) };
                (None, first.clone(), first.gpu_bytes as f64)
            }
        };
        let render = crate::render::lod::RenderConfig::load(None)?;
        let cams: Vec<_> = self.views().iter().map(|v| v.camera.clone()).collect();
        let forward = crate::render::raster::Forward::Compute;
        let own_path = PathBuf::from(&own.instgs.file);
        let paths: Vec<PathBuf> =
            [Some(&above), below.as_ref()].into_iter().flatten().map(|s| PathBuf::from(&s.file)).collect();
        let mut others = Vec::new();
        for p in &paths {
            others.push(crate::bench::BenchInput::read(p, render.clone(), forward)?);
        }
        let v = crate::bench::bench_scenes(
            self.gpu,
            self.k,
            crate::bench::BenchInput::read(&own_path, render.clone(), forward)?,
            others,
            &cams,
            (self.cfg.bench.frames, self.cfg.bench.warmup),
            self.cfg.plain.background,
            ("[curve] equal quality: ", crate::util::ProgressMode::Tenths),
        )?;
        let num = |x: &serde_json::Value| x.as_f64().unwrap_or(f64::NAN);
        let benched = |s: Scored, x: &serde_json::Value, ratios: &serde_json::Value| Benched {
            scene: s,
            fps: num(&x["fps_median"]),
            fps_ratio: num(&ratios["fps"]),
        };
        let above = benched(above, &v["compare"], &v["ratios"]);
        let below = below.map(|s| benched(s, &v["compare_more"][0], &v["compare_more"][0]["ratios"]));
        let (fps_pruned, fps_ratio) = match &below {
            Some(b) => {
                let (lo, hi) = (b.scene.psnr, above.scene.psnr);
                (
                    at_psnr((lo, b.fps), (hi, above.fps), target),
                    at_psnr((lo, b.fps_ratio), (hi, above.fps_ratio), target),
                )
            }
            None => (above.fps, above.fps_ratio),
        };
        Ok(Some(EqualQuality {
            instgs_psnr: target,
            instgs_gpu_bytes: own.instgs.gpu_bytes,
            pruned_gpu_bytes_needed: needed,
            memory_ratio: needed / own.instgs.gpu_bytes as f64,
            below,
            above,
            trained,
            fps_instgs: num(&v["fps_median"]),
            fps_pruned,
            fps_ratio,
        }))
    }

    /// The run's InstGS compressed against the `pruned` scenes as `.sog` (each written beside
    /// its PLY), all scored on the held-out views.
    fn compressed_files(&self, dir: &Path, pruned: &[&Scored]) -> Result<CompressedFiles> {
        let path = dir.join("scene.compressed.instgs");
        crate::formats::instgs::write_compressed(
            &crate::formats::instgs::read(&self.a.out.join("scene.instgs"))?,
            &path,
        )?;
        let instgs = self.score(&path)?;
        let mut pruned_sog = Vec::new();
        for s in pruned {
            let ply = Path::new(&s.file);
            let sog = ply.with_extension("sog");
            crate::formats::sog::write_sog_bundle(&crate::formats::ply::read_ply(ply)?, &sog)?;
            pruned_sog.push(self.score(&sog)?);
        }
        pruned_sog.sort_by_key(|s| s.file_bytes);
        let needed = |psnr: fn(&Scored) -> f64| {
            let by_bytes: Vec<(u64, f64)> = pruned_sog.iter().map(|s| (s.file_bytes, psnr(s))).collect();
            bracket(&by_bytes, psnr(&instgs)).map(|(_, bytes)| bytes)
        };
        let (raw, compensated) = (needed(|s| s.psnr), needed(|s| s.psnr_compensated));
        let ratio = |b: Option<f64>| b.map(|b| instgs.file_bytes as f64 / b);
        Ok(CompressedFiles {
            sog_bytes_needed: raw,
            file_ratio: ratio(raw),
            sog_bytes_needed_compensated: compensated,
            file_ratio_compensated: ratio(compensated),
            instgs,
            pruned_sog,
        })
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
        let lens = self.photo_lens()?;
        let e = crate::train::evaluate(&mut r, &gs, self.views(), self.cfg.plain.background, &lens, |_, _, _| Ok(()))?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bracket_takes_the_first_pair_that_straddles_the_target() {
        let pts = [(100, 30.0), (200, 32.0), (300, 33.0)];
        assert_eq!(bracket(&pts, 31.0), Some((0, 150.0)));
        assert_eq!(bracket(&pts, 32.0), Some((0, 200.0)));
        // Not monotone (trainings scatter): the smallest memory that reaches the target.
        let noisy = [(100, 30.0), (200, 32.5), (250, 32.1), (300, 33.0)];
        assert_eq!(bracket(&noisy, 32.25).map(|b| b.0), Some(0));
        assert_eq!(bracket(&pts, 29.0), None, "every scene reaches it");
        assert_eq!(bracket(&pts, 34.0), None, "no scene reaches it");
        assert!((at_psnr((30.0, 10.0), (32.0, 6.0), 31.5) - 7.0).abs() < 1e-12);
    }

    /// A pruned scene's PSNR rises ever more slowly with its memory (concave), so the bytes
    /// interpolated between two far points overstate what pruning needs; the search trains the
    /// interpolated bytes again until a scene lands within the tolerance.
    #[test]
    fn equal_quality_search_lands_within_the_tolerance() {
        let psnr = |b: u64| 34.0 - 4.0 * (-(b as f64) / 3.0e6).exp();
        let target = 32.2;
        let mut pts: Vec<(u64, f64)> = [2_000_000u64, 10_000_000].iter().map(|&b| (b, psnr(b))).collect();
        let (_, first) = bracket(&pts, target).unwrap();
        let mut trained = 0;
        while let Some(b) = next_equal_bytes(&pts, target, EQUAL_TOLERANCE_DB) {
            assert!(trained < EQUAL_TRAININGS, "no convergence: {pts:?}");
            pts.push((b, psnr(b)));
            pts.sort_by_key(|p| p.0);
            trained += 1;
        }
        assert!(pts.iter().any(|p| (p.1 - target).abs() <= EQUAL_TOLERANCE_DB), "{pts:?}");
        let (_, needed) = bracket(&pts, target).unwrap();
        let truth = -3.0e6 * ((34.0 - target) / 4.0f64).ln();
        assert!(first > 1.2 * truth, "the first interpolation overstates: {first} against {truth}");
        assert!((needed - truth).abs() < 0.1 * truth, "{needed} against {truth}");
        // Within the tolerance already, outside every bracket, or next to a trained scene: no step.
        assert_eq!(next_equal_bytes(&[(1, 32.15), (2, 33.0)], target, EQUAL_TOLERANCE_DB), None);
        assert_eq!(next_equal_bytes(&[(1, 33.0), (2, 34.0)], target, EQUAL_TOLERANCE_DB), None);
        assert_eq!(next_equal_bytes(&[(1000, 31.0), (1001, 33.0)], target, EQUAL_TOLERANCE_DB), None);
    }
}
