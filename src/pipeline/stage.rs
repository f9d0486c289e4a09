//! The pipeline's stages, in order, and the arguments of one run: what the stages and the
//! report share.
use std::path::PathBuf;

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, clap::ValueEnum)]
pub enum Stage {
    /// Plain 3DGS training (or the --init PLY).
    Plain,
    /// Gradient-driven instance segmentation.
    Segment,
    /// Registration and template initialisation.
    Instance,
    /// Joint optimisation of templates, offsets and background.
    Joint,
    /// The "plain, pruned" baseline: the plain scene pruned to InstGS's GPU memory and
    /// fine-tuned as long as the joint stage (skipped with --no-pruned-baseline).
    Pruned,
    /// Held-out PSNR/SSIM of plain, plain pruned and InstGS, side-by-side images.
    Eval,
    /// Frame times and memory, InstGS against plain and plain pruned.
    Bench,
}

pub const STAGES: [Stage; 7] =
    [Stage::Plain, Stage::Segment, Stage::Instance, Stage::Joint, Stage::Pruned, Stage::Eval, Stage::Bench];

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Plain => "plain",
            Stage::Segment => "segment",
            Stage::Instance => "instance",
            Stage::Joint => "joint",
            Stage::Pruned => "pruned",
            Stage::Eval => "eval",
            Stage::Bench => "bench",
        }
    }

    /// 1-based position in [`STAGES`].
    pub fn number(self) -> usize {
        STAGES.iter().position(|&s| s == self).unwrap_or(0) + 1
    }

    /// The progress prefix, e.g. `[2/6 segment] `.
    pub fn label(self) -> String {
        format!("[{}/{} {}] ", self.number(), STAGES.len(), self.name())
    }
}

pub struct PipelineArgs {
    pub data: PathBuf,
    pub downscale: u32,
    pub out: PathBuf,
    /// A scene to start from: a plain scene trained elsewhere (any format we read) replaces the
    /// plain stage; an `.instgs` makes `train` optimise it jointly, without the pipeline.
    pub init: Option<PathBuf>,
    pub config: Option<PathBuf>,
    pub iterations: Option<u64>,
    pub from: Option<Stage>,
    pub until: Option<Stage>,
    /// Find the instances without masks (`crate::discover`) in the segment stage.
    pub discover: Option<crate::discover::run::ExampleSpec>,
    /// Run the "plain, pruned" baseline stage (`--no-pruned-baseline`: false).
    pub pruned_baseline: bool,
    pub progress: bool,
    pub device: Option<String>,
}
