//! Training configuration: `configs/default.toml` (embedded; the one place the defaults live)
//! merged with an optional user file holding only the keys it changes. Joint optimisation of an
//! instanced scene merges `configs/instanced.toml` (embedded) over the defaults first.
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};

pub const DEFAULT_TOML: &str = include_str!("../../configs/default.toml");
pub const INSTANCED_TOML: &str = include_str!("../../configs/instanced.toml");
pub const PIPELINE_TOML: &str = include_str!("../../configs/pipeline.toml");

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub iterations: u64,
    pub seed: u64,
    pub sh_degree: u32,
    pub sh_increase_interval: u64,
    pub background: [f32; 3],
    pub ssim_weight: f32,
    /// The frame-cost regulariser's weight (`tile_cost_weight`, configs/default.toml); 0: off.
    pub tile_cost_weight: f32,
    pub test_interval: u64,
    pub checkpoint_interval: u64,
    /// Instanced runs: optimise the instance transforms too (rates `lr.transform_*`).
    pub refine_transforms: bool,
    pub appearance: AppearanceConfig,
    pub cameras: CamerasConfig,
    pub lr: LrConfig,
    pub densify: DensifyConfig,
    pub init: InitConfig,
}

/// `[appearance]`: the per-photo colour transforms (crate::render::appearance).
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AppearanceConfig {
    /// "auto" (COLMAP datasets: [`AppearanceConfig::AUTO`]; others none), "affine", "gain" or
    /// "none".
    pub model: String,
    /// Also learn the lens's vignetting (crate::render::appearance::Vignetting) where the run
    /// learns colour transforms.
    pub vignetting: bool,
    pub lr_init: f64,
    pub lr_final: f64,
    pub from_iter: u64,
}

impl AppearanceConfig {
    /// The model "auto" picks for photos (COLMAP datasets).
    pub const AUTO: &'static str = "affine";

    /// The model a run on a dataset of `kind` ("colmap", "nerf-synthetic") learns, if any.
    pub fn model_for(&self, kind: &str) -> Option<&str> {
        match self.model.as_str() {
            "auto" if kind == "colmap" => Some(Self::AUTO),
            "affine" | "gain" => Some(self.model.as_str()),
            _ => None,
        }
    }

    /// Whether a run on a dataset of `kind` learns transforms.
    pub fn enabled(&self, kind: &str) -> bool {
        self.model_for(kind).is_some()
    }

    /// Which of a transform's 12 parameters (row c: `M[c][0..2]`, `b[c]`) learn under `model`:
    /// all for "affine"; the diagonal gains and the offsets for "gain" (exposure and white
    /// balance, no mixing of channels).
    pub fn free_params(model: &str) -> [bool; 12] {
        match model {
            "gain" => std::array::from_fn(|i| i % 4 == 3 || i % 4 == i / 4),
            _ => [true; 12],
        }
    }

    /// The Adam rate at iteration `it` of a schedule of `max_steps` (the position rate's,
    /// `lr.position_max_steps`, so a run stopped and resumed with another `--iterations` keeps
    /// its rates); 0 before `from_iter`.
    pub fn lr(&self, it: u64, max_steps: u64) -> f64 {
        if it <= self.from_iter {
            return 0.0;
        }
        let t = (it as f64 / max_steps.max(1) as f64).clamp(0.0, 1.0);
        (self.lr_init.ln() * (1.0 - t) + self.lr_final.ln() * t).exp()
    }
}

/// `[cameras]`: the training cameras' refinement (crate::train::cameras).
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CamerasConfig {
    /// Whether the plain training refines its training cameras.
    pub refine: bool,
    /// Adam rates of the rotation (radians) and of the translation (× the cameras' extent),
    /// decaying exponentially from `_init` to `_final` over `lr.position_max_steps`.
    pub lr_rotation_init: f64,
    pub lr_rotation_final: f64,
    pub lr_translation_init: f64,
    pub lr_translation_final: f64,
    /// Iterations before the cameras start to learn (the scene takes shape first).
    pub from_iter: u64,
}

impl CamerasConfig {
    /// The rates [rotation, translation] at iteration `it` (0 until `from_iter`), the
    /// translation's times `extent`.
    pub fn lr(&self, it: u64, max_steps: u64, extent: f32) -> [f64; 2] {
        if it <= self.from_iter {
            return [0.0; 2];
        }
        let t = (it as f64 / max_steps.max(1) as f64).clamp(0.0, 1.0);
        let decay = |a: f64, b: f64| (a.ln() * (1.0 - t) + b.ln() * t).exp();
        [
            decay(self.lr_rotation_init, self.lr_rotation_final),
            decay(self.lr_translation_init, self.lr_translation_final) * extent as f64,
        ]
    }
}

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LrConfig {
    pub position_init: f64,
    pub position_final: f64,
    pub position_max_steps: u64,
    /// Scene scale of the position learning rates: 0 = the training cameras' extent (Inria),
    /// otherwise this fixed value (the InstGS prototype's fine-tuning: 0.1).
    pub spatial_scale: f64,
    pub sh0: f32,
    pub sh_rest: f32,
    pub opacity: f32,
    pub scaling: f32,
    pub rotation: f32,
    /// Instance transforms (refine_transforms): Adam rates of the rotation quaternion, the
    /// translation (scene units) and ln s.
    pub transform_rotation: f32,
    pub transform_translation: f32,
    pub transform_scale: f32,
}

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DensifyConfig {
    pub from_iter: u64,
    pub until_iter: u64,
    pub interval: u64,
    pub grad_threshold: f32,
    pub percent_dense: f32,
    pub opacity_reset_interval: u64,
    pub min_opacity: f32,
    pub max_screen_size: u32,
    pub max_world_scale: f32,
    pub max_splats: usize,
}

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct InitConfig {
    pub random_points: usize,
    pub opacity: f32,
}

/// The tables only a pipeline configuration has (`configs/pipeline.toml`).
const PIPELINE_TABLES: [&str; 5] = ["joint", "segment", "instance", "eval", "bench"];

fn merge(base: &mut toml::Table, over: toml::Table, path: &str) -> Result<()> {
    for (k, v) in over {
        let key = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o, &key)?,
            (Some(toml::Value::Table(_)), _) => bail!("`{key}` must be a table"),
            (Some(slot), v) => *slot = v,
            (None, _) if path.is_empty() && PIPELINE_TABLES.contains(&k.as_str()) => bail!(
                "`[{k}]` is a pipeline table: it applies to a dataset with instance masks (masks/train/), and this run trains one scene (plain 3DGS, or joint optimisation of an --init .instgs); remove the table, or give the dataset masks"
            ),
            (None, _) => bail!("unknown key `{key}`"),
        }
    }
    Ok(())
}

impl Config {
    /// The defaults with `text` (TOML) merged over them; `what` names the source in errors.
    pub fn from_toml(text: &str, what: &str) -> Result<Config> {
        Self::from_layers(&[], text, what)
    }

    /// The defaults, then each embedded layer, then `text`.
    fn from_layers(layers: &[(&str, &str)], text: &str, what: &str) -> Result<Config> {
        let mut base: toml::Table = DEFAULT_TOML.parse().expect("configs/default.toml parses");
        for (layer, name) in layers {
            let t: toml::Table = layer.parse().map_err(|e| anyhow!("{name}: {e}"))?;
            merge(&mut base, t, "").map_err(|e| anyhow!("{name}: {e}"))?;
        }
        let over: toml::Table = text.parse().map_err(|e| anyhow!("{what}: not valid TOML: {e}"))?;
        merge(&mut base, over, "").map_err(|e| anyhow!("{what}: {e}"))?;
        let cfg: Config = toml::Value::Table(base).try_into().map_err(|e| anyhow!("{what}: {e}"))?;
        cfg.validate().map_err(|e| anyhow!("{what}: {e}"))?;
        Ok(cfg)
    }

    /// A configuration saved as JSON (checkpoints) over today's defaults: keys added since it was
    /// written take their default values.
    pub fn from_saved(saved: serde_json::Value) -> Result<Config> {
        let mut base = serde_json::to_value(Config::from_toml("", "configs/default.toml")?)?;
        crate::util::json_overlay(&mut base, &saved);
        Ok(serde_json::from_value(base)?)
    }

    /// The joint-optimisation configuration with `text` (TOML) merged over it.
    pub fn instanced_from_toml(text: &str, what: &str) -> Result<Config> {
        Self::from_layers(&[(INSTANCED_TOML, "configs/instanced.toml")], text, what)
    }

    pub fn load(path: Option<&Path>) -> Result<Config> {
        Self::load_layers(&[], path)
    }

    /// The joint-optimisation configuration: defaults, `configs/instanced.toml`, then `path`.
    pub fn load_instanced(path: Option<&Path>) -> Result<Config> {
        Self::load_layers(&[(INSTANCED_TOML, "configs/instanced.toml")], path)
    }

    fn load_layers(layers: &[(&str, &str)], path: Option<&Path>) -> Result<Config> {
        match path {
            None => Config::from_layers(layers, "", "configs/default.toml"),
            Some(p) => {
                let text = std::fs::read_to_string(p).with_context(|| format!("{}: cannot read", p.display()))?;
                Config::from_layers(layers, &text, &p.display().to_string())
            }
        }
    }

    pub fn validate(&self) -> Result<()> {
        check_ranges(&serde_json::to_value(self)?, "", TRAINING_RANGES)?;
        if !matches!(self.appearance.model.as_str(), "auto" | "affine" | "gain" | "none") {
            bail!(
                "appearance.model must be \"auto\", \"affine\", \"gain\" or \"none\", not {:?}",
                self.appearance.model
            );
        }
        Ok(())
    }

    /// The Adam learning rates of every parameter group at `step` (positions decaying as
    /// [`Config::position_lr`], the others constant).
    pub fn learning_rates(&self, step: u64, extent: f32) -> crate::train::optim::LearningRates {
        crate::train::optim::LearningRates {
            means: self.position_lr(step, extent),
            scales: self.lr.scaling,
            quats: self.lr.rotation,
            opacities: self.lr.opacity,
            sh0: self.lr.sh0,
            sh_rest: self.lr.sh_rest,
            cameras: self.cameras.lr(step, self.lr.position_max_steps, extent),
        }
    }

    /// Inria's position learning rate at `step` (get_expon_lr_func without delay), times the
    /// spatial scale (`lr.spatial_scale`, or `extent` when that is 0).
    pub fn position_lr(&self, step: u64, extent: f32) -> f32 {
        let t = (step as f64 / self.lr.position_max_steps.max(1) as f64).clamp(0.0, 1.0);
        let lr = (self.lr.position_init.ln() * (1.0 - t) + self.lr.position_final.ln() * t).exp();
        let scale = if self.lr.spatial_scale > 0.0 { self.lr.spatial_scale } else { extent as f64 };
        (lr * scale) as f32
    }
}

/// `[segment]` of a pipeline configuration (configs/pipeline.toml).
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SegmentStage {
    pub alpha: f32,
}

/// `[instance]`: registration and template initialisation.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct InstanceStage {
    pub init: String,
    pub rigid: bool,
    pub colour: bool,
    pub colour_weight: f64,
    pub seed: u64,
    pub offset_dtype: String,
    /// "auto" (the quality budget, crate::instancing::compact) or a fixed fraction in (0, 1].
    pub background_keep: BackgroundKeep,
    /// The budget: training-view PSNR (dB) the pruned plain scene may lose before the joint
    /// optimisation.
    pub background_budget_db: f64,
    /// Background Gaussians within this fraction of an instance's size rank first.
    pub outline_fraction: f64,
    /// Templates and background under one memory budget (crate::instancing::compact::rebalance).
    pub rebalance: bool,
    /// The rebalance also charges each drawn splat as this many Gaussian rows
    /// (crate::instancing::compact::Spending).
    pub render_weight: f64,
    /// Acceptance of registered poses (crate::instancing::options::Acceptance).
    pub min_fitness: f64,
    pub scale_tolerance: f64,
    pub render_check: bool,
    /// Synchronise the poses of a group's accepted instances (crate::instancing::synchronise).
    pub synchronise: bool,
    /// Edges of the pose graph per instance besides the reference (crate::instancing::synchronise::candidate_edges).
    pub neighbours: usize,
    pub min_render_iou: f64,
    pub min_render_psnr: f64,
    pub min_render_views: usize,
}

/// `[instance] background_keep`: "auto" or a fraction.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(untagged)]
pub enum BackgroundKeep {
    Fraction(f64),
    Auto(String),
}

/// `[eval]`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EvalStage {
    pub images: usize,
}

/// `[bench]`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BenchStage {
    pub frames: usize,
    pub warmup: usize,
}

#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub(crate) struct PipelineTables {
    segment: SegmentStage,
    instance: InstanceStage,
    eval: EvalStage,
    bench: BenchStage,
}

/// Every stage's settings of `instgs-vk train` on a dataset with masks: one file, the plain
/// stage's keys at the top, `[joint]` for the joint optimisation, `[segment]` `[instance]`
/// `[eval]` `[bench]` for the others (configs/pipeline.toml).
#[derive(Clone, Debug, PartialEq)]
pub struct PipelineConfig {
    pub plain: Config,
    pub joint: Config,
    pub segment: SegmentStage,
    pub instance: InstanceStage,
    pub eval: EvalStage,
    pub bench: BenchStage,
}

impl PipelineConfig {
    /// The defaults with `text` merged over them; `what` names the source in errors.
    pub fn from_toml(text: &str, what: &str) -> Result<PipelineConfig> {
        let mut user: toml::Table = text.parse().map_err(|e| anyhow!("{what}: not valid TOML: {e}"))?;
        let mut take = |key: &str| -> Result<toml::Table> {
            match user.remove(key) {
                None => Ok(toml::Table::new()),
                Some(toml::Value::Table(t)) => Ok(t),
                Some(_) => bail!("{what}: `{key}` must be a table"),
            }
        };
        let joint = take("joint")?;
        let mut tables = toml::Table::new();
        for key in ["segment", "instance", "eval", "bench"] {
            tables.insert(key.into(), toml::Value::Table(take(key)?));
        }
        let plain = Config::from_toml(&toml::to_string(&user)?, what)?;
        let joint = Config::instanced_from_toml(&toml::to_string(&joint)?, &format!("{what} [joint]"))?;
        let mut base: toml::Table = PIPELINE_TOML.parse().expect("configs/pipeline.toml parses");
        merge(&mut base, tables, "").map_err(|e| anyhow!("{what}: {e}"))?;
        let t: PipelineTables = toml::Value::Table(base).try_into().map_err(|e| anyhow!("{what}: {e}"))?;
        if !matches!(t.instance.init.as_str(), "merge" | "max" | "first") {
            bail!("{what}: instance.init must be \"merge\", \"max\" or \"first\"");
        }
        crate::formats::instgs::Dtype::offsets(&t.instance.offset_dtype)
            .map_err(|e| anyhow!("{what}: instance.offset_dtype: {e}"))?;
        match &t.instance.background_keep {
            BackgroundKeep::Fraction(f) if *f > 0.0 && *f <= 1.0 => {}
            BackgroundKeep::Auto(a) if a == "auto" => {}
            _ => bail!("{what}: instance.background_keep must be \"auto\" or a fraction in (0, 1]"),
        }
        check_ranges(&serde_json::to_value(&t)?, "", PIPELINE_RANGES).map_err(|e| anyhow!("{what}: {e}"))?;
        Ok(PipelineConfig { plain, joint, segment: t.segment, instance: t.instance, eval: t.eval, bench: t.bench })
    }

    pub fn load(path: Option<&Path>) -> Result<PipelineConfig> {
        match path {
            None => Self::from_toml("", "configs/pipeline.toml"),
            Some(p) => {
                let text = std::fs::read_to_string(p).with_context(|| format!("{}: cannot read", p.display()))?;
                Self::from_toml(&text, &p.display().to_string())
            }
        }
    }
}

/// Where a configuration value must lie.
#[derive(Clone, Copy, Debug)]
pub enum Bound {
    /// lo ≤ v ≤ hi.
    In(f64, f64),
    /// lo < v < hi.
    Inside(f64, f64),
    /// v ≥ lo.
    AtLeast(f64),
    /// v > lo.
    Above(f64),
}

impl Bound {
    fn holds(self, v: f64) -> bool {
        v.is_finite()
            && match self {
                Bound::In(lo, hi) => v >= lo && v <= hi,
                Bound::Inside(lo, hi) => v > lo && v < hi,
                Bound::AtLeast(lo) => v >= lo,
                Bound::Above(lo) => v > lo,
            }
    }

    fn describe(self) -> String {
        match self {
            Bound::In(lo, hi) => format!("in [{lo}, {hi}]"),
            Bound::Inside(lo, hi) => format!("in ({lo}, {hi})"),
            Bound::AtLeast(lo) => format!("at least {lo}"),
            Bound::Above(lo) => format!("above {lo}"),
        }
    }
}

/// The range of every training value that has one (plain and joint configurations): the one
/// table of ranges, checked after the files are merged. Arrays: every element.
pub const TRAINING_RANGES: &[(&str, Bound)] = &[
    ("iterations", Bound::AtLeast(1.0)),
    ("sh_degree", Bound::In(0.0, 3.0)),
    ("sh_increase_interval", Bound::AtLeast(1.0)),
    ("background", Bound::In(0.0, 1.0)),
    ("ssim_weight", Bound::In(0.0, 1.0)),
    ("tile_cost_weight", Bound::In(0.0, 1.0)),
    ("lr.position_init", Bound::Above(0.0)),
    ("lr.position_final", Bound::Above(0.0)),
    ("lr.position_max_steps", Bound::AtLeast(1.0)),
    ("lr.spatial_scale", Bound::AtLeast(0.0)),
    ("lr.sh0", Bound::AtLeast(0.0)),
    ("lr.sh_rest", Bound::AtLeast(0.0)),
    ("lr.opacity", Bound::AtLeast(0.0)),
    ("lr.scaling", Bound::AtLeast(0.0)),
    ("lr.rotation", Bound::AtLeast(0.0)),
    ("lr.transform_rotation", Bound::AtLeast(0.0)),
    ("lr.transform_translation", Bound::AtLeast(0.0)),
    ("lr.transform_scale", Bound::AtLeast(0.0)),
    ("densify.interval", Bound::AtLeast(1.0)),
    ("densify.grad_threshold", Bound::Above(0.0)),
    ("densify.percent_dense", Bound::In(0.0, 1.0)),
    ("densify.min_opacity", Bound::In(0.0, 1.0)),
    ("densify.max_world_scale", Bound::Above(0.0)),
    ("densify.max_splats", Bound::AtLeast(1.0)),
    ("init.opacity", Bound::Inside(0.0, 1.0)),
    ("appearance.lr_init", Bound::Above(0.0)),
    ("appearance.lr_final", Bound::Above(0.0)),
    ("cameras.lr_rotation_init", Bound::Above(0.0)),
    ("cameras.lr_rotation_final", Bound::Above(0.0)),
    ("cameras.lr_translation_init", Bound::Above(0.0)),
    ("cameras.lr_translation_final", Bound::Above(0.0)),
];

/// The ranges of the pipeline's own tables (`[segment]`, `[instance]`, `[eval]`, `[bench]`).
pub const PIPELINE_RANGES: &[(&str, Bound)] = &[
    ("segment.alpha", Bound::AtLeast(0.0)),
    ("instance.colour_weight", Bound::AtLeast(0.0)),
    ("instance.min_fitness", Bound::In(0.0, 1.0)),
    ("instance.scale_tolerance", Bound::In(0.0, 10.0)),
    ("instance.min_render_iou", Bound::In(0.0, 1.0)),
    ("instance.min_render_psnr", Bound::In(0.0, 100.0)),
    ("instance.min_render_views", Bound::AtLeast(1.0)),
    ("instance.background_budget_db", Bound::In(0.0, 100.0)),
    ("instance.outline_fraction", Bound::In(0.0, 10.0)),
    ("instance.render_weight", Bound::In(0.0, 100.0)),
    ("bench.frames", Bound::AtLeast(1.0)),
];

/// Checks every key of `table` that `v` holds (numbers; arrays element by element) against its
/// bound; the error names the key (`prefix` + key) and the value.
pub fn check_ranges(v: &serde_json::Value, prefix: &str, table: &[(&str, Bound)]) -> Result<()> {
    for (key, bound) in table {
        let Some(x) = key.split('.').try_fold(v, |v, k| v.get(k)) else { continue };
        let values: Vec<&serde_json::Value> = match x {
            serde_json::Value::Array(a) => a.iter().collect(),
            other => vec![other],
        };
        for y in values {
            if let Some(n) = y.as_f64() {
                if !bound.holds(n) {
                    bail!("{prefix}{key} must be {}, not {n}", bound.describe());
                }
            }
        }
    }
    Ok(())
}
