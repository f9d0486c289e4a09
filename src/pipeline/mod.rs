//! `instgs-vk train` on a dataset with instance masks: the whole InstGS pipeline in one run
//! folder, stage by stage, each resumable.
//!
//! | stage | reads | writes (in RUN) |
//! |---|---|---|
//! | plain | the dataset (or `--init SCENE.ply`) | `point_cloud.ply`, `checkpoint.bin`, `metrics.csv`, `curves.png` |
//! | segment | `point_cloud.ply`, `masks/train/` | `labels.json`, `segment.json`, `significance.bin` |
//! | instance | `point_cloud.ply`, `labels.json`, `significance.bin` | `init.instgs`, `instance.json` |
//! | joint | `init.instgs` | `scene.instgs`, `joint/{checkpoint.bin, metrics.csv, curves.png}` |
//! | eval | `point_cloud.ply`, `scene.instgs` | `eval.json`, `images/<view>.png` |
//! | bench | `point_cloud.ply`, `scene.instgs` | `bench.json` |
//!
//! `RUN/pipeline.json` records each stage's settings, time and whether it finished;
//! `RUN/report.md` is rewritten after every stage. A re-run skips finished stages, continues
//! the training stages from their checkpoints and redoes an unfinished other stage from its start
//! (they write their results atomically, so a result file is always whole).
pub mod report;
pub mod stage;

pub use stage::{PipelineArgs, Stage, STAGES};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
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
use serde::{Deserialize, Serialize};

/// Whether `data` has instance masks (`masks/train/`): the pipeline runs, else plain training.
pub fn has_masks(data: &Path) -> bool {
    data.join("masks").join("train").is_dir()
}

/// How the masks' ids are meant.
#[derive(Clone, Copy, Debug, PartialEq)]
enum MaskIds {
    /// Ids shared by all views, grouped by `DIR/instances.json`.
    Global,
    /// Ids that mean nothing across frames, with `masks/train/<stem>.json` categories.
    PerFrame,
    /// No masks used: the instances are discovered (`train --discover`).
    Discovered,
}

/// Checks the masks against the training views before any long work: every view has its
/// mask, of its size (or an integer multiple with --downscale), and every instance of
/// `instances.json` shows in some mask.
fn check_masks(data: &Path, ds: &Dataset) -> Result<MaskIds> {
    let dir = data.join("masks").join("train");
    let groups_file = data.join("instances.json");
    let first_stem = ds.train.first().and_then(|v| v.path.file_stem()).map(|s| s.to_string_lossy().into_owned());
    let ids = if groups_file.exists() {
        MaskIds::Global
    } else if first_stem.is_some_and(|s| dir.join(format!("{s}.json")).exists()) {
        MaskIds::PerFrame
    } else {
        bail!(
            "{}: there are masks but neither {} (instance ids shared by all views) nor {} (per-frame ids with categories); see the README, 'Bringing your own masks'",
            data.display(),
            groups_file.display(),
            dir.join("<image>.json").display()
        );
    };
    let missing: Vec<String> = ds
        .train
        .iter()
        .filter(|v| crate::dataset::masks::mask_path(data, "train", &v.path).is_err())
        .filter_map(|v| Some(v.path.file_name()?.to_string_lossy().into_owned()))
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: {} of {} training views have no mask (first: {}); masks/train/ must hold one PNG per training image, named as the image or as its stem with .png (img_001.jpg: img_001.jpg or img_001.png)",
            dir.display(),
            missing.len(),
            ds.train.len(),
            missing[..missing.len().min(3)].join(", ")
        );
    }
    let masks = crate::dataset::masks::load_masks(data, "train", &ds.train)?;
    if ids == MaskIds::Global {
        let groups = crate::dataset::masks::read_groups(&groups_file)?;
        let mut seen = std::collections::BTreeSet::new();
        for m in &masks {
            seen.extend(m.iter().copied());
        }
        for g in &groups {
            for &id in &g.ids {
                if id > u16::MAX as u32 || !seen.contains(&(id as u16)) {
                    bail!(
                        "{}: instance {id} ({}) appears in no training mask of {}",
                        groups_file.display(),
                        g.name,
                        dir.display()
                    );
                }
            }
        }
        if groups.iter().all(|g| g.ids.len() < 2) {
            eprintln!(
                "warning: {}: no group has two instances; every template will have a single instance",
                groups_file.display()
            );
        }
    }
    Ok(ids)
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct StageRecord {
    /// The settings the stage ran with (its result is reused only with the same).
    settings: serde_json::Value,
    done: bool,
    /// Wall seconds over all attempts (a killed attempt's time is lost).
    seconds: f64,
    attempts: u32,
    /// What the dataset's images and masks held when the stage ran (runs from before this was
    /// recorded have none).
    #[serde(default)]
    content: Option<crate::dataset::content::ContentIdentity>,
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct State {
    stages: BTreeMap<String, StageRecord>,
}

impl State {
    fn path(run: &Path) -> PathBuf {
        run.join("pipeline.json")
    }

    fn read(run: &Path) -> Result<State> {
        let p = State::path(run);
        if !p.exists() {
            return Ok(State::default());
        }
        let text = std::fs::read_to_string(&p).with_context(|| format!("{}: cannot read", p.display()))?;
        serde_json::from_str(&text)
            .with_context(|| format!("{}: damaged pipeline state (remove it to start the run afresh)", p.display()))
    }

    fn write(&self, run: &Path) -> Result<()> {
        crate::util::write_json(&State::path(run), &serde_json::to_value(self)?, true)
    }

    fn done(&self, s: Stage) -> bool {
        self.stages.get(s.name()).is_some_and(|r| r.done)
    }
}

/// `INSTGS_INTERRUPT_IN=<stage>` (tests): the run behaves as if Ctrl-C arrived in that stage —
/// a training stage after half of this session's iterations, any other stage during its work.
fn interrupt_hook() -> Option<String> {
    std::env::var("INSTGS_INTERRUPT_IN").ok()
}

fn interrupted() -> bool {
    INTERRUPTED.load(Ordering::SeqCst)
}

/// What a stage's result depends on besides earlier stages.
fn settings(s: Stage, a: &PipelineArgs, cfg: &PipelineConfig) -> Result<serde_json::Value> {
    let data = std::fs::canonicalize(&a.data).unwrap_or_else(|_| a.data.clone());
    let mut v = serde_json::json!({"data": data.display().to_string(), "downscale": a.downscale});
    let own = match s {
        Stage::Plain => match &a.init {
            Some(p) => serde_json::json!({"init": std::fs::canonicalize(p).unwrap_or_else(|_| p.clone())}),
            None => serde_json::to_value(&cfg.plain)?,
        },
        Stage::Segment => match &a.discover {
            Some(spec) => {
                serde_json::json!({"discover": format!("{spec:?}"), "instance": serde_json::to_value(&cfg.instance)?})
            }
            None => serde_json::to_value(&cfg.segment)?,
        },
        Stage::Instance => serde_json::to_value(&cfg.instance)?,
        Stage::Joint => serde_json::to_value(&cfg.joint)?,
        Stage::Pruned => serde_json::json!({"baseline": a.pruned_baseline, "joint": serde_json::to_value(&cfg.joint)?}),
        Stage::Eval => serde_json::to_value(&cfg.eval)?,
        Stage::Bench => serde_json::to_value(&cfg.bench)?,
    };
    v[s.name()] = own;
    Ok(v)
}

/// Files a stage starts from that `--from` must remove (training checkpoints).
fn stage_checkpoint(run: &Path, s: Stage) -> Option<PathBuf> {
    match s {
        Stage::Plain => Some(train::checkpoint_path(run)),
        Stage::Joint => Some(train::checkpoint_path(&run.join("joint"))),
        Stage::Pruned => Some(train::checkpoint_path(&run.join("pruned"))),
        _ => None,
    }
}

pub fn run(a: PipelineArgs) -> Result<()> {
    let mut cfg = PipelineConfig::load(a.config.as_deref())?;
    if let Some(n) = a.iterations {
        cfg.plain.iterations = n;
    }
    if let (Some(f), Some(u)) = (a.from, a.until) {
        if f > u {
            bail!("--from {} comes after --until {}", f.name(), u.name());
        }
    }
    let until = a.until.unwrap_or(Stage::Bench);
    let load = crate::dataset::LoadOptions { downscale: a.downscale, background: cfg.plain.background };
    let ds = crate::dataset::load(&a.data, &load)?;
    let what = ds.describe(&a.data)?;
    let mask_ids = match &a.discover {
        Some(_) => MaskIds::Discovered,
        None => check_masks(&a.data, &ds)?,
    };
    if let Some(p) = &a.init {
        // Read now: a bad file is refused before anything runs.
        crate::formats::read_scene(p)?;
    }
    let mut fresh = crate::util::NewFolder::create(&a.out)?;
    let run = a.out.as_path();
    let mut state = State::read(run)?;
    // Images or masks edited in place since a stage ran: that stage and what follows are redone.
    let scan = crate::dataset::content::content_identity(&ds, &a.data, run)?;
    let content = scan.id.clone();
    let mut from = a.from;
    if let Some((s, what)) = STAGES.iter().copied().find_map(|s| {
        let was = state.stages.get(s.name())?.content.as_ref()?;
        let images = was.images != content.images && !(s == Stage::Plain && a.init.is_some());
        let masks = was.masks != content.masks && s != Stage::Plain;
        (images || masks).then_some((s, if images { "images" } else { "masks" }))
    }) {
        if from.is_none_or(|f| f > s) {
            eprintln!(
                "note: the {what} of {} changed since stage {} ran (same names, other contents): it and the stages after it are redone",
                a.data.display(),
                s.name()
            );
            from = Some(s);
        }
    }
    // A stage already run (or begun) with other settings is not silently reused. Keys added to
    // the configuration since it ran count as their defaults.
    let defaults = PipelineConfig::load(None)?;
    // Checked before --from changes anything; the stages --from redoes are not checked.
    for s in STAGES.iter().copied().filter(|&s| s <= until && from.is_none_or(|f| s < f)) {
        if let Some(r) = state.stages.get(s.name()) {
            let mut recorded = settings(s, &a, &defaults)?;
            crate::util::json_overlay(&mut recorded, &r.settings);
            if recorded != settings(s, &a, &cfg)? {
                bail!(
                    "{}: stage {} was run with other settings (data, --downscale, --init or its configuration); redo it and what follows with --from {}, or choose another --out",
                    State::path(run).display(),
                    s.name(),
                    s.name()
                );
            }
        }
    }
    if let Some(from) = from {
        for s in STAGES.iter().copied().filter(|&s| s >= from) {
            state.stages.remove(s.name());
            if let Some(c) = stage_checkpoint(run, s) {
                if c.exists() {
                    std::fs::remove_file(&c).with_context(|| format!("{}: cannot remove", c.display()))?;
                }
            }
        }
        state.write(run)?;
    }
    // A training checkpoint in a stage's folder that this run has not finished is resumed; one
    // trained on other data (a plain run of another dataset, say) is refused before anything runs.
    for s in STAGES.iter().copied().filter(|&s| s <= until && !state.done(s)) {
        if let Some(c) = stage_checkpoint(run, s).filter(|c| c.exists()) {
            if !train::checkpoint_is_whole(&c)? {
                bail!(
                    "{} is damaged: its checksum does not match its contents (a byte changed after it was written); redo stage {} with --from {}",
                    c.display(),
                    s.name(),
                    s.name()
                );
            }
            if let Some(why) = train::checkpoint_dataset(&c)?.and_then(|was| was.mismatch(&ds.identity())) {
                bail!(
                    "{}: the checkpoint of stage {} was trained on other data: {why}; choose another --out",
                    c.display(),
                    s.name()
                );
            }
        }
    }
    let (gpu, k) = crate::gpu::kernels::open_device(a.device.clone())?;
    scan.save()?;
    eprintln!(
        "{}: {what}, {}; {}",
        a.data.display(),
        match mask_ids {
            MaskIds::Global => "instance masks (ids grouped by instances.json)",
            MaskIds::PerFrame => "instance masks (per-frame ids)",
            MaskIds::Discovered => "instances discovered without masks",
        },
        gpu.describe()
    );
    ctrlc::set_handler(|| INTERRUPTED.store(true, Ordering::SeqCst)).context("cannot install the Ctrl-C handler")?;
    let hook = interrupt_hook();
    let ctx = Ctx { a: &a, cfg: &cfg, ds: &ds, gpu: &gpu, k: &k, mask_ids };
    for s in STAGES.iter().copied().filter(|&s| s <= until) {
        if state.done(s) {
            eprintln!("{}done earlier", s.label());
            continue;
        }
        eprintln!("{}started", s.label());
        let rec = state.stages.entry(s.name().into()).or_default();
        rec.settings = settings(s, &a, &cfg)?;
        rec.content = Some(content.clone());
        rec.attempts += 1;
        state.write(run)?;
        let hooked = hook.as_deref() == Some(s.name());
        let t0 = Instant::now();
        let result = ctx.stage(s, hooked);
        let rec = state.stages.entry(s.name().into()).or_default();
        rec.seconds += t0.elapsed().as_secs_f64();
        match result {
            Ok(true) => {
                rec.done = true;
                if let Some(f) = fresh.as_mut() {
                    f.keep();
                }
                state.write(run)?;
                eprintln!("{}finished in {:.1} s", s.label(), t0.elapsed().as_secs_f64());
                report::write(run, &a, &State::read(run)?.summary())?;
            }
            Ok(false) => {
                if let Some(f) = fresh.as_mut() {
                    f.keep();
                }
                state.write(run)?;
                report::write(run, &a, &state.summary())?;
                bail!(
                    "interrupted in stage {} (results of earlier stages and training checkpoints are kept); run the same command again to resume",
                    s.name()
                );
            }
            Err(e) => {
                state.write(run)?;
                if interrupted() {
                    if let Some(f) = fresh.as_mut() {
                        f.keep();
                    }
                    bail!("interrupted in stage {} ({e:#}); run the same command again to resume", s.name());
                }
                return Err(e.context(format!("stage {}", s.name())));
            }
        }
    }
    let m = gpu.take_validation_messages();
    if !m.is_empty() {
        bail!("{} Vulkan validation message(s), first: {}", m.len(), m[0]);
    }
    if until == Stage::Bench {
        eprintln!("report: {}", run.join("report.md").display());
        eprintln!("open the result in the player: instgs-vk view {}", run.join("scene.instgs").display());
    } else {
        eprintln!("stopped after stage {} (--until); run without --until to go on", until.name());
    }
    Ok(())
}

impl State {
    /// Per stage (in order): done, seconds.
    fn summary(&self) -> Vec<(Stage, bool, f64)> {
        STAGES.iter().filter_map(|&s| self.stages.get(s.name()).map(|r| (s, r.done, r.seconds))).collect()
    }
}

/// Registration and acceptance as `[instance]` sets them (the instance stage's, and the
/// discovery's in the segment stage).
fn instance_options(c: &crate::train::config::InstanceStage) -> Result<crate::instancing::template::InstanceOptions> {
    Ok(crate::instancing::template::InstanceOptions {
        init: clap::ValueEnum::from_str(&c.init, true).map_err(|e| anyhow!("instance.init: {e}"))?,
        with_scale: !c.rigid,
        use_colour: c.colour,
        colour_weight: c.colour_weight,
        seed: c.seed,
        accept: crate::instancing::template::Acceptance {
            min_fitness: c.min_fitness,
            scale_tolerance: c.scale_tolerance,
            min_render_iou: c.min_render_iou,
            min_render_psnr: c.min_render_psnr,
            min_render_views: c.min_render_views,
            ..Default::default()
        },
        synchronise: c.synchronise && c.render_check,
        ..Default::default()
    })
}

/// The "plain, pruned" baseline's scene in a run folder.
pub const PRUNED_FILE: &str = "pruned.ply";

/// What a training stage starts from.
enum Init {
    /// The dataset (plain 3DGS).
    Dataset,
    /// A plain scene, fine-tuned without densification (the pruned baseline).
    Plain(crate::model::scene::Scene),
    /// An instanced scene (joint optimisation).
    Instanced(crate::model::instanced::InstancedScene),
}

struct Ctx<'a> {
    a: &'a PipelineArgs,
    cfg: &'a PipelineConfig,
    ds: &'a Dataset,
    gpu: &'a Arc<Gpu>,
    k: &'a Arc<Kernels>,
    mask_ids: MaskIds,
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
    fn stage(&self, s: Stage, hooked: bool) -> Result<bool> {
        if hooked && !matches!(s, Stage::Plain | Stage::Joint) {
            INTERRUPTED.store(true, Ordering::SeqCst);
        }
        let run = self.run_dir();
        match s {
            Stage::Plain => {
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
            Stage::Segment if self.mask_ids == MaskIds::Discovered => self.discover(),
            Stage::Segment => {
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
            Stage::Instance => {
                let c = &self.cfg.instance;
                let opts = instance_options(c)?;
                let dtype = match c.offset_dtype.as_str() {
                    "f16" => crate::formats::instgs::Dtype::F16,
                    "pq8" => crate::formats::instgs::Dtype::Pq8,
                    _ => crate::formats::instgs::Dtype::F32,
                };
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
                        MaskIds::Global => {
                            Some(crate::dataset::masks::load_masks(&self.a.data, "train", &self.ds.train)?)
                        }
                        MaskIds::PerFrame | MaskIds::Discovered => None,
                    };
                    let cams = self.ds.train.iter().map(|v| v.camera.clone()).collect();
                    Some(crate::instancing::verify::ImageCheck::new(self.gpu, self.k, cams, masks)?)
                } else {
                    None
                };
                let views = &self.ds.train;
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
                let r = crate::instancing::build::instance(
                    &run.join("point_cloud.ply"),
                    &run.join("labels.json"),
                    &groups,
                    truth.as_ref().map(|(p, ids)| (p.as_path(), *ids)),
                    &opts,
                    dtype,
                    Some((&run.join("significance.bin"), &mut rule)),
                    check.as_mut().map(|c| c as &mut dyn crate::instancing::template::RenderCheck),
                    None,
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
            Stage::Joint => {
                let init = crate::formats::instgs::read(&run.join("init.instgs"))?;
                let dir = run.join("joint");
                if !self.train(&dir, Init::Instanced(init), &self.cfg.joint, s, hooked)? {
                    return Ok(false);
                }
                std::fs::rename(dir.join("scene.instgs"), run.join("scene.instgs"))
                    .with_context(|| format!("{}: cannot move the result", dir.join("scene.instgs").display()))?;
                Ok(true)
            }
            Stage::Pruned => self.pruned(hooked),
            Stage::Eval => self.eval(),
            Stage::Bench => {
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
        }
    }

    /// The held-out views (the training views when the dataset holds none out).
    fn views(&self) -> &[crate::dataset::View] {
        if self.ds.test.is_empty() {
            &self.ds.train
        } else {
            &self.ds.test
        }
    }

    fn train(
        &self,
        out: &Path,
        init: Init,
        cfg: &crate::train::config::Config,
        s: Stage,
        hooked: bool,
    ) -> Result<bool> {
        let resume = train::checkpoint_path(out).exists();
        // The later stages start from the photos' colour transforms the plain stage learned.
        let colours = self.run_dir().join(train::APPEARANCE_FILE);
        let appearance = match init {
            Init::Dataset => None,
            _ if colours.exists() && cfg.appearance.enabled(self.ds.kind) => {
                Some(train::read_appearance(&colours, self.ds)?)
            }
            _ => None,
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
            let e = train::evaluate(&mut r, &gs, views, bg, |v, f| {
                if interrupted() {
                    bail!("interrupted");
                }
                progress.set(index as u64 + 1, "");
                if let Some(m) = &masks {
                    let m = &m[index];
                    for (k, object) in [true, false].into_iter().enumerate() {
                        if let Some(db) = crate::util::psnr_where(&f.image, &v.image, |i| (m[i] != 0) == object) {
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
        });
        for (name, r) in results {
            v[name] = r;
        }
        v["images"] = pick.iter().map(|&i| format!("images/{}.png", views[i].camera.name)).collect();
        crate::util::write_json(&run.join("eval.json"), &v, true)?;
        Ok(true)
    }
}

/// `instgs-vk train`: the whole InstGS pipeline where the dataset has instance masks (and `init`
/// is not already instanced); else one training session — plain 3DGS, or joint optimisation
/// from an `.instgs` `init` — which `resume` continues (a pipeline always resumes).
pub fn train(a: PipelineArgs, resume: bool) -> Result<()> {
    crate::dataset::layout(&a.data)?;
    let is_instgs = match a.init.as_deref() {
        Some(p) => crate::formats::detect(p)? == crate::formats::Format::Instgs,
        None => false,
    };
    if (has_masks(&a.data) || a.discover.is_some()) && !is_instgs {
        return run(a);
    }
    if a.from.is_some() || a.until.is_some() {
        bail!(
            "--from and --until choose pipeline stages, and {} has no instance masks (masks/train/)",
            a.data.display()
        );
    }
    if a.init.is_some() && !is_instgs {
        bail!(
            "--init with a plain scene starts the InstGS pipeline, which needs instance masks: {} has no masks/train/ (see the README, 'Bringing your own masks')",
            a.data.display()
        );
    }
    if a.init.is_none() {
        eprintln!("{}: no instance masks (masks/train/): training plain 3DGS only", a.data.display());
    }
    crate::train::session::train(
        a.device,
        &a.data,
        a.downscale,
        &a.out,
        a.init.as_deref(),
        a.config.as_deref(),
        a.iterations,
        resume,
        !a.progress,
    )
}
