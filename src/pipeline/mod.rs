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
pub mod curve;
pub mod report;
pub mod stage;
mod stages;

pub use stage::{PipelineArgs, Stage, STAGES};
use stages::Ctx;
pub use stages::PRUNED_FILE;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Instant;

use crate::dataset::Dataset;
use crate::train::config::PipelineConfig;
use crate::train::{self, INTERRUPTED};
use anyhow::{bail, Context, Result};
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
            "{}: there are masks but neither {} (instance ids shared by all views) nor {} (per-frame ids with categories); see docs/data.md, 'Bringing your own masks'",
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

/// The pipeline: checks every input and what earlier runs left in RUN before any stage runs,
/// then runs the stages from the first unfinished one to `--until`.
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
    let mut ds = crate::dataset::load(&a.data, &load)?;
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
    let from = redo_changed(&state, &a, &content, a.from);
    check_settings(&state, &a, &cfg, until, from, run)?;
    if let Some(from) = from {
        forget_from(&mut state, run, from)?;
    }
    if state.done(Stage::Plain) {
        correct_cameras(run, &mut ds)?;
    }
    check_checkpoints(&state, run, until, &ds)?;
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
    let env = StageEnv { a: &a, cfg: &cfg, gpu: &gpu, k: &k, mask_ids };
    run_stages(&env, &mut ds, &mut state, &mut fresh, &content, until, hook.as_deref())?;
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

/// The first stage whose images or masks changed in place since it ran (it and what follows are
/// redone), or `from` when that comes first.
fn redo_changed(
    state: &State,
    a: &PipelineArgs,
    content: &crate::dataset::content::ContentIdentity,
    mut from: Option<Stage>,
) -> Option<Stage> {
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
    from
}

/// Refuses a stage already run (or begun) with other settings than this run's.
fn check_settings(
    state: &State,
    a: &PipelineArgs,
    cfg: &PipelineConfig,
    until: Stage,
    from: Option<Stage>,
    run: &Path,
) -> Result<()> {
    // A stage already run (or begun) with other settings is not silently reused. Keys added to
    // the configuration since it ran count as their defaults.
    let defaults = PipelineConfig::load(None)?;
    // Checked before --from changes anything; the stages --from redoes are not checked.
    for s in STAGES.iter().copied().filter(|&s| s <= until && from.is_none_or(|f| s < f)) {
        if let Some(r) = state.stages.get(s.name()) {
            let mut recorded = settings(s, a, &defaults)?;
            crate::util::json_overlay(&mut recorded, &r.settings);
            if recorded != settings(s, a, cfg)? {
                bail!(
                    "{}: stage {} was run with other settings (data, --downscale, --init or its configuration); redo it and what follows with --from {}, or choose another --out",
                    State::path(run).display(),
                    s.name(),
                    s.name()
                );
            }
        }
    }
    Ok(())
}

/// Forgets stage `from` and the stages after it, with their training checkpoints.
fn forget_from(state: &mut State, run: &Path, from: Stage) -> Result<()> {
    for s in STAGES.iter().copied().filter(|&s| s >= from) {
        state.stages.remove(s.name());
        let cameras = run.join(train::CAMERAS_FILE);
        if s == Stage::Plain && cameras.exists() {
            std::fs::remove_file(&cameras).with_context(|| format!("{}: cannot remove", cameras.display()))?;
        }
        if let Some(c) = stage_checkpoint(run, s) {
            if c.exists() {
                std::fs::remove_file(&c).with_context(|| format!("{}: cannot remove", c.display()))?;
            }
        }
    }
    state.write(run)?;
    Ok(())
}

/// Corrects `ds`'s training cameras as the plain stage of `run` did (RUN/cameras.json, when it
/// refined them).
fn correct_cameras(run: &Path, ds: &mut Dataset) -> Result<()> {
    let path = run.join(train::CAMERAS_FILE);
    if path.exists() {
        train::apply_cameras(&path, ds)?;
        eprintln!("{}: the training cameras as the plain stage corrected them", path.display());
    }
    Ok(())
}

/// Refuses a damaged training checkpoint, or one trained on other data, before anything runs.
fn check_checkpoints(state: &State, run: &Path, until: Stage, ds: &Dataset) -> Result<()> {
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
    Ok(())
}

/// What every stage reads besides the dataset (which the plain stage's camera corrections change).
struct StageEnv<'a> {
    a: &'a PipelineArgs,
    cfg: &'a PipelineConfig,
    gpu: &'a std::sync::Arc<crate::gpu::Gpu>,
    k: &'a std::sync::Arc<crate::gpu::kernels::Kernels>,
    mask_ids: MaskIds,
}

/// Runs the unfinished stages up to `until`, recording each in `RUN/pipeline.json` and
/// rewriting the report after each; an interrupted stage stops the run (resumable).
fn run_stages(
    env: &StageEnv,
    ds: &mut Dataset,
    state: &mut State,
    fresh: &mut Option<crate::util::NewFolder>,
    content: &crate::dataset::content::ContentIdentity,
    until: Stage,
    hook: Option<&str>,
) -> Result<()> {
    let (a, run) = (env.a, env.a.out.as_path());
    let (cfg, gpu, k, mask_ids) = (env.cfg, env.gpu, env.k, env.mask_ids);
    for s in STAGES.iter().copied().filter(|&s| s <= until) {
        // The stages after the plain one see the training cameras as it corrected them.
        let ctx = Ctx { a, cfg, ds: &*ds, gpu, k, mask_ids };
        if state.done(s) {
            eprintln!("{}done earlier", s.label());
            continue;
        }
        eprintln!("{}started", s.label());
        let rec = state.stages.entry(s.name().into()).or_default();
        rec.settings = settings(s, a, ctx.cfg)?;
        rec.content = Some(content.clone());
        rec.attempts += 1;
        state.write(run)?;
        let hooked = hook == Some(s.name());
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
                if s == Stage::Plain {
                    correct_cameras(run, ds)?;
                }
                report::write(run, a, &State::read(run)?.summary())?;
            }
            Ok(false) => {
                if let Some(f) = fresh.as_mut() {
                    f.keep();
                }
                state.write(run)?;
                report::write(run, a, &state.summary())?;
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
    Ok(())
}

impl State {
    /// Per stage (in order): done, seconds.
    fn summary(&self) -> Vec<(Stage, bool, f64)> {
        STAGES.iter().filter_map(|&s| self.stages.get(s.name()).map(|r| (s, r.done, r.seconds))).collect()
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
            "--init with a plain scene starts the InstGS pipeline, which needs instance masks: {} has no masks/train/ (see docs/data.md, 'Bringing your own masks')",
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
