//! Plain 3DGS training on the GPU, Inria's recipe: one random training view per iteration,
//! L = (1 − λ) L1 + λ (1 − SSIM), Adam per parameter group with the position learning rate
//! decaying exponentially, SH degree raised every `sh_increase_interval` iterations, and
//! clone / split / prune densification with periodic opacity resets (on the CPU, between
//! iterations). Forward, loss, backward and Adam run on the GPU; the host reads back only the
//! rendered image (for the training PSNR) and the loss sums, plus the whole state at
//! densification steps and checkpoints.
//!
//! Instanced scenes (`--init scene.instgs`, InstGS joint optimisation): templates, offsets and
//! background are optimised together through the instancing rasterizer, without densification
//! (`configs/instanced.toml`); the run writes `scene.instgs`.
//!
//! Differences from Inria, on purpose: the Adam step also runs on densification iterations
//! (Inria skips it for the replaced tensors). The screen-size prune is off by default, as in
//! effect in Inria (its radii are zeroed just before they are read, so it never fires); when on
//! (`max_screen_size > 0`) it uses the radii seen since the last densification.

pub mod appearance;
pub mod cameras;
pub mod checkpoint;
pub mod config;
pub mod densify;
pub mod eval;
pub mod optim;
pub mod plot;
pub mod session;
pub mod state;
pub mod trainer;

pub use appearance::{read_appearance, vignetting_beside, write_appearance, APPEARANCE_FILE};
pub use cameras::{apply_cameras, write_cameras, CameraState, CAMERAS_FILE};
pub use checkpoint::{
    checkpoint_dataset, checkpoint_from_bytes, checkpoint_is_whole, checkpoint_path, read_checkpoint, write_checkpoint,
};
pub use densify::{densify, initial_scene, knn_log_scales, reset_opacity, DensifyStats};
pub use eval::{evaluate, Evaluation, ViewScore};
pub use state::{AppearanceState, Layout, LayoutGroup, TrainState};
pub use trainer::{StepStats, Trainer};

use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use rand::{Rng, SeedableRng};

use crate::dataset::{Dataset, DatasetIdentity};
use crate::gpu::kernels::Kernels;
use crate::gpu::Gpu;
use crate::model::instanced::InstancedScene;
use crate::train::config::Config;
use crate::util::{Progress, ProgressMode};

/// The training view of iteration `it` (from 1): every epoch visits each view once, in an order
/// drawn from (seed, epoch) — stateless, so a resumed run draws the same views.
pub fn view_index(seed: u64, it: u64, n: usize) -> usize {
    let epoch = (it - 1) / n as u64;
    let mut order: Vec<usize> = (0..n).collect();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed ^ epoch.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    for i in (1..n).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    order[((it - 1) % n as u64) as usize]
}

// ---------------------------------------------------------------------------------------------
// The training run

/// Set by Ctrl-C: the loop writes a checkpoint and stops.
pub static INTERRUPTED: AtomicBool = AtomicBool::new(false);

pub struct RunOptions {
    pub out: PathBuf,
    pub resume: bool,
    /// Joint optimisation of this instanced scene (else plain training from the dataset).
    pub init: Option<InstancedScene>,
    /// Fine-tuning of this plain scene at its full SH degree (the pruned baseline; the
    /// configuration should not densify), instead of training from the dataset's points.
    pub init_scene: Option<crate::model::scene::Scene>,
    /// Show progress: a bar on a terminal, else a line every 10 % or [`crate::util::LINE_SECONDS`] (false:
    /// a line every 10 % only).
    pub progress: bool,
    /// Written before the progress bar and the progress lines (the pipeline's stage).
    pub label: String,
    /// Stop as Ctrl-C would once this many iterations of this session are done (tests of
    /// interrupting and resuming).
    pub stop_after: Option<u64>,
    /// A fresh run that learns colour transforms starts from these (one per training view, and
    /// the lens's vignetting: the joint stage from the plain stage's); else from the identity
    /// and no vignetting.
    pub appearance: Option<crate::render::appearance::PhotoAppearance>,
    /// How an instanced result stores its offsets (`scene.instgs`).
    pub offset_dtype: crate::formats::instgs::Dtype,
}

impl RunOptions {
    /// Plain training into `out` (no init, no label, no forced stop).
    pub fn new(out: PathBuf, resume: bool, progress: bool) -> RunOptions {
        RunOptions {
            out,
            resume,
            init: None,
            init_scene: None,
            progress,
            label: String::new(),
            stop_after: None,
            appearance: None,
            offset_dtype: crate::formats::instgs::Dtype::F32,
        }
    }
}

/// Whether iteration `it` densifies the scene (plain runs; never the last iteration).
fn densifies(d: &crate::train::config::DensifyConfig, it: u64) -> bool {
    it < d.until_iter && it > d.from_iter && it.is_multiple_of(d.interval)
}

/// Whether iteration `it` resets the opacities (plain runs; never the last iteration).
fn resets_opacities(d: &crate::train::config::DensifyConfig, it: u64) -> bool {
    d.opacity_reset_interval > 0 && it.is_multiple_of(d.opacity_reset_interval) && it < d.until_iter
}

/// The figure of a run's metrics with its schedule's events (`curves.png`).
pub fn curves(rows: &[MetricsRow], cfg: &Config, plain: bool, ds: &Dataset) -> crate::train::plot::Curves {
    let d = &cfg.densify;
    let kind = if plain { "Plain 3DGS training" } else { "Joint optimisation of the instanced scene" };
    crate::train::plot::Curves {
        title: format!(
            "{kind}: {} iterations, {} training views, {} held-out views",
            cfg.iterations,
            ds.train.len(),
            ds.test.len()
        ),
        loss: rows.iter().map(|r| (r.iteration, r.loss)).collect(),
        train_psnr: rows.iter().map(|r| (r.iteration, r.train_psnr)).collect(),
        test_psnr: rows.iter().filter_map(|r| r.test_psnr.map(|p| (r.iteration, p))).collect(),
        densify: (plain && d.until_iter > d.from_iter).then_some((d.from_iter, d.until_iter.min(cfg.iterations))),
        opacity_resets: if plain {
            (1..cfg.iterations).filter(|&it| resets_opacities(d, it)).collect()
        } else {
            Vec::new()
        },
        iterations: cfg.iterations,
    }
}

/// One row of `metrics.csv`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MetricsRow {
    pub iteration: u64,
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    pub train_psnr: f64,
    pub splats: usize,
    pub elapsed_s: f64,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
}

const CSV_HEADER: &str = "iteration,loss,l1,ssim,train_psnr,splats,elapsed_s,test_psnr,test_ssim";

impl MetricsRow {
    fn csv(&self) -> String {
        let opt = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_default();
        format!(
            "{},{:.6},{:.6},{:.6},{:.4},{},{:.3},{},{}",
            self.iteration,
            self.loss,
            self.l1,
            self.ssim,
            self.train_psnr,
            self.splats,
            self.elapsed_s,
            opt(self.test_psnr),
            opt(self.test_ssim)
        )
    }

    fn parse(line: &str) -> Option<MetricsRow> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 9 {
            return None;
        }
        let opt = |s: &str| if s.is_empty() { Some(None) } else { s.parse().ok().map(Some) };
        Some(MetricsRow {
            iteration: f[0].parse().ok()?,
            loss: f[1].parse().ok()?,
            l1: f[2].parse().ok()?,
            ssim: f[3].parse().ok()?,
            train_psnr: f[4].parse().ok()?,
            splats: f[5].parse().ok()?,
            elapsed_s: f[6].parse().ok()?,
            test_psnr: opt(f[7])?,
            test_ssim: opt(f[8])?,
        })
    }
}

/// The outcome of a run.
pub struct RunSummary {
    pub iterations: u64,
    pub splats: usize,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    /// Wall time of the run, resumed parts and the final writes included.
    pub seconds: f64,
    /// This invocation's iterations over their own wall time (held-out evaluations,
    /// densification and checkpoints included; startup and the final writes not).
    pub iterations_per_second: f64,
    pub interrupted: bool,
    /// Median GPU milliseconds per pass over this session's iterations.
    pub pass_medians: Vec<(String, f64)>,
}

/// `INSTGS_FAULT_NAN_AT=N`: put a NaN into a parameter before iteration N (tests of the
/// divergence handling).
fn fault_nan_at() -> Option<u64> {
    std::env::var("INSTGS_FAULT_NAN_AT").ok()?.parse().ok()
}

/// The state a run starts from: its checkpoint and metrics when resuming (the same data and
/// configuration, iterations aside), else the initial scene (`opts.init`, `opts.init_scene` or
/// the dataset's points), with the colour transforms the configuration asks for.
fn start_state(
    ds: &Dataset,
    cfg: &Config,
    opts: &RunOptions,
    ckpt: &std::path::Path,
    dataset: &DatasetIdentity,
    metrics_path: &std::path::Path,
) -> Result<(TrainState, Vec<MetricsRow>)> {
    let (mut state, rows) = if opts.resume {
        if let Some(was) = checkpoint_dataset(ckpt)? {
            if let Some(why) = was.mismatch(dataset) {
                bail!(
                    "{}: the checkpoint was trained on other data: {why}; resume it on its own data, or choose another --out",
                    ckpt.display()
                );
            }
        }
        let (st, saved) =
            read_checkpoint(ckpt).with_context(|| "cannot resume (run without --resume to start afresh)")?;
        let same = Config { iterations: cfg.iterations, ..saved.clone() };
        if &same != cfg {
            bail!(
                "{}: the checkpoint was written with another configuration; resume with the same --config",
                ckpt.display()
            );
        }
        let text = std::fs::read_to_string(metrics_path).unwrap_or_default();
        let rows: Vec<MetricsRow> =
            text.lines().skip(1).filter_map(MetricsRow::parse).filter(|r| r.iteration <= st.iteration).collect();
        (st, rows)
    } else {
        if ckpt.exists() {
            bail!("{} exists: continue it with --resume, or choose another --out", ckpt.display());
        }
        let mut st = match (&opts.init, &opts.init_scene) {
            (Some(scene), _) => TrainState::instanced(scene),
            (None, Some(scene)) => {
                let mut st = TrainState::new(scene.clone());
                st.active_sh_degree = scene.sh_degree;
                st
            }
            (None, None) => TrainState::new(initial_scene(ds, cfg)),
        };
        if cfg.appearance.enabled(ds.kind) {
            st.appearance = match &opts.appearance {
                Some(p) if p.colours.len() == ds.train.len() => {
                    AppearanceState::from_params(p.colours.clone(), p.vignetting)
                }
                Some(p) => bail!(
                    "{} colour transforms for {} training views: they belong to another dataset",
                    p.colours.len(),
                    ds.train.len()
                ),
                None => AppearanceState::identity(ds.train.len()),
            };
        }
        if cfg.cameras.refine && opts.init.is_none() && opts.init_scene.is_none() {
            st.cameras = CameraState::identity(ds.train.iter().map(|v| v.camera.clone()).collect());
        }
        (st, Vec::new())
    };
    // The cameras a checkpoint's corrections apply to are the dataset's (not stored).
    if !state.cameras.is_empty() {
        if state.cameras.deltas.len() != ds.train.len() {
            bail!(
                "{}: the checkpoint holds {} camera corrections for {} training views; resume it on its own data",
                ckpt.display(),
                state.cameras.deltas.len(),
                ds.train.len()
            );
        }
        state.cameras.original = ds.train.iter().map(|v| v.camera.clone()).collect();
    }
    if let Some(model) = cfg.appearance.model_for(ds.kind) {
        state.appearance.free = crate::train::config::AppearanceConfig::free_params(model);
        // One lens per capture: learned by the run that starts from the dataset; a run that
        // starts from another's appearance (the pruned and joint stages) keeps its vignetting,
        // so every scene of a capture is scored through the same lens.
        state.appearance.vignetting_free = cfg.appearance.vignetting && opts.appearance.is_none();
    }
    if state.appearance.params.len() != if cfg.appearance.enabled(ds.kind) { ds.train.len() } else { 0 } {
        bail!(
            "{}: the checkpoint holds {} colour transforms for {} training views; resume it with the configuration it was written with",
            ckpt.display(),
            state.appearance.params.len(),
            ds.train.len()
        );
    }
    Ok((state, rows))
}

/// Densification and the opacity reset due at iteration `it` (plain scenes, never on the last
/// iteration: nothing would train after it, it would only alter the output): the adapted state,
/// loaded into the trainer, or None when neither is due.
fn adapt(
    trainer: &mut Trainer,
    state: &TrainState,
    cfg: &Config,
    it: u64,
    extent: f32,
    final_it: bool,
) -> Result<Option<TrainState>> {
    let d = &cfg.densify;
    let plain = state.layout.is_none();
    let densify_now = plain && !final_it && densifies(d, it);
    let reset_now = plain && !final_it && resets_opacities(d, it);
    if !(densify_now || reset_now) {
        return Ok(None);
    }
    let mut state = trainer.download(it)?;
    if densify_now {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed.wrapping_add(it.wrapping_mul(0x2545_f491)));
        state = densify(&state, cfg, extent, &mut rng).0;
    }
    if reset_now {
        reset_opacity(&mut state);
    }
    state.check_finite().context("training diverged; the last good checkpoint is kept")?;
    if state.scene.is_empty() {
        bail!(
            "densification pruned every splat at iteration {it}: every opacity fell below densify.min_opacity ({}) or every size grew past densify.max_world_scale ({} × the scene extent); lower densify.min_opacity or raise densify.max_world_scale in the --config",
            d.min_opacity,
            d.max_world_scale
        );
    }
    trainer.load(&state)?;
    Ok(Some(state))
}

/// A run's results beside its checkpoint: what it learned of the photos and cameras, the scene,
/// and the curves.
fn write_results(ds: &Dataset, cfg: &Config, opts: &RunOptions, state: &TrainState, rows: &[MetricsRow]) -> Result<()> {
    if !state.appearance.is_empty() {
        write_appearance(&opts.out.join(APPEARANCE_FILE), ds, &state.appearance.learned())?;
    }
    if !state.cameras.is_empty() {
        write_cameras(&opts.out.join(CAMERAS_FILE), ds, &state.cameras)?;
    }
    match state.to_instanced()? {
        Some(inst) => crate::formats::instgs::write(&inst, &opts.out.join("scene.instgs"), opts.offset_dtype)?,
        None => crate::formats::ply::write_ply(&state.scene, &opts.out.join("point_cloud.ply"))?,
    }
    crate::train::plot::write(&curves(rows, cfg, state.layout.is_none(), ds), &opts.out.join("curves.png"))
}

/// Trains `cfg.iterations` iterations on `ds`, writing into `opts.out`: `checkpoint.bin`,
/// `metrics.csv`, `point_cloud.ply` (or `scene.instgs`), `curves.png` and what it learned of the
/// photos and cameras (`appearance.json`, `cameras.json`). With `opts.resume` it continues from the
/// checkpoint (the configuration must match the one it was written with, iterations aside).
pub fn run(gpu: &Arc<Gpu>, k: &Arc<Kernels>, ds: &Dataset, cfg: &Config, opts: &RunOptions) -> Result<RunSummary> {
    let mut fresh = crate::util::NewFolder::create(&opts.out)?;
    if ds.train.is_empty() {
        bail!("the dataset has no training views");
    }
    let extent = ds.camera_extent();
    let ckpt = checkpoint_path(&opts.out);
    let scan = crate::dataset::content::content_identity(ds, &ds.dir, &opts.out)?;
    let dataset = DatasetIdentity { images: Some(scan.id.images.clone()), ..ds.identity() };
    let metrics_path = opts.out.join("metrics.csv");
    let (mut state, mut rows) = start_state(ds, cfg, opts, &ckpt, &dataset, &metrics_path)?;
    for v in &ds.train {
        crate::train::optim::LossBufs::check_size(gpu, v.camera.width, v.camera.height)
            .with_context(|| v.path.display().to_string())?;
    }
    let mut trainer = Trainer::new(gpu, k, &state, cfg.refine_transforms)?;
    scan.save()?;
    let write_metrics = |rows: &[MetricsRow]| -> Result<()> {
        let mut text = String::from(CSV_HEADER);
        text.push('\n');
        for r in rows {
            text.push_str(&r.csv());
            text.push('\n');
        }
        crate::util::write_atomic(&metrics_path, |f| f.write_all(text.as_bytes()))
    };
    let start_it = state.iteration;
    let elapsed0 = rows.last().map_or(0.0, |r| r.elapsed_s);
    let t0 = Instant::now();
    let mode = if opts.progress { ProgressMode::Auto } else { ProgressMode::Tenths };
    let mut progress = Progress::new(&opts.label, "iteration", "it/s", cfg.iterations, start_it, mode);
    let mut test = rows.iter().rev().find_map(|r| r.test_psnr.zip(r.test_ssim));
    let mut interrupted = false;
    let mut pass_times: Vec<(String, Vec<f64>)> = Vec::new();
    for it in start_it + 1..=cfg.iterations {
        if INTERRUPTED.load(Ordering::SeqCst) || opts.stop_after.is_some_and(|n| it > start_it + n) {
            interrupted = true;
            break;
        }
        if it % cfg.sh_increase_interval == 0 && trainer.scene.active_sh_degree < trainer.scene.sh_degree {
            trainer.scene.active_sh_degree += 1;
        }
        let lr = cfg.learning_rates(it, extent);
        if fault_nan_at() == Some(it) {
            // Fault injection for the tests: a NaN in the first Gaussian's colour.
            let mut st = trainer.download(it - 1)?;
            st.scene.sh[0] = f32::NAN;
            trainer.load(&st)?;
        }
        let index = view_index(cfg.seed, it, ds.train.len());
        let view = &ds.train[index];
        let last = trainer.step(view, index, cfg, &lr, it)?;
        for (name, ms) in &trainer.passes {
            match pass_times.iter_mut().find(|(n, _)| n == name) {
                Some(e) => e.1.push(*ms),
                None => pass_times.push((name.clone(), vec![*ms])),
            }
        }
        if !last.loss.is_finite() {
            bail!(
                "the loss became {} at iteration {it} (view {}); stopped without writing a checkpoint — the last good one is {}",
                last.loss,
                view.camera.name,
                ckpt.display()
            );
        }
        // Held-out views after this step's update and before densification and the opacity reset
        // (Inria's training_report order: a reset iteration reports the trained scene).
        let final_it = it == cfg.iterations;
        let mut tested = None;
        if !ds.test.is_empty() && ((cfg.test_interval > 0 && it % cfg.test_interval == 0) || final_it) {
            let vignetting = trainer.vignetting();
            let e =
                evaluate(&mut trainer.raster, &trainer.scene, &ds.test, cfg.background, &vignetting, |_, _, _| Ok(()))?;
            tested = Some((e.psnr, e.ssim));
        }
        if let Some(adapted) = adapt(&mut trainer, &state, cfg, it, extent, final_it)? {
            state = adapted;
        }
        let mut row = MetricsRow {
            iteration: it,
            loss: last.loss,
            l1: last.l1,
            ssim: last.ssim,
            train_psnr: last.psnr,
            splats: trainer.scene.len,
            elapsed_s: elapsed0 + t0.elapsed().as_secs_f64(),
            ..Default::default()
        };
        if let Some((p, q)) = tested {
            row.test_psnr = Some(p);
            row.test_ssim = Some(q);
            test = tested;
        }
        rows.push(row);
        if (cfg.checkpoint_interval > 0 && it % cfg.checkpoint_interval == 0) || final_it {
            state = trainer.download(it)?;
            write_checkpoint(&ckpt, &state, cfg, Some(&dataset))?;
            write_metrics(&rows)?;
        }
        let msg = format!(
            "loss {:.4} PSNR {:.2}{} splats {}",
            last.loss,
            last.psnr,
            test.map(|(p, _)| format!(" test {p:.2}")).unwrap_or_default(),
            trainer.scene.len
        );
        progress.set(it, &msg);
    }
    if let Some(f) = fresh.as_mut() {
        f.keep();
    }
    // The iterations' own time (held-out evaluations included), not the run's end below.
    let loop_secs = t0.elapsed().as_secs_f64();
    progress.finish();
    let done = rows.last().map_or(start_it, |r| r.iteration);
    state = trainer.download(done)?;
    if interrupted || done > start_it {
        write_checkpoint(&ckpt, &state, cfg, Some(&dataset))?;
        write_metrics(&rows)?;
    }
    write_results(ds, cfg, opts, &state, &rows)?;
    let secs = t0.elapsed().as_secs_f64();
    Ok(RunSummary {
        iterations: done,
        splats: trainer.scene.len,
        test_psnr: test.map(|t| t.0),
        test_ssim: test.map(|t| t.1),
        seconds: elapsed0 + secs,
        iterations_per_second: (done - start_it) as f64 / loop_secs.max(1e-9),
        interrupted,
        pass_medians: pass_times
            .into_iter()
            .filter(|(n, _)| n != "setup" && n != "readback")
            .map(|(n, mut v)| {
                v.sort_by(f64::total_cmp);
                (n, v[v.len() / 2])
            })
            .collect(),
    })
}
