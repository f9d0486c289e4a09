//! The instance stage's settings ([`InstanceOptions`]: template initialisation, registration,
//! the checks a pose must pass) and what became of each instance ([`Status`]).
use nalgebra::Vector3;

use std::collections::BTreeMap;

use crate::register::{RegisterOptions, Sim3};

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TemplateInit {
    /// Merge all aligned instances, farthest-point sample to the mean count, re-initialise all
    /// but positions and SH DC (paper).
    Merge,
    /// The instance with the most Gaussians, kept whole (the default: measured 0.2–0.5 dB better
    /// than `Merge` on the shared scenes, BENCHMARKS.md).
    Max,
    /// The group's first instance.
    First,
}

#[derive(Clone, Debug)]
pub struct InstanceOptions {
    pub init: TemplateInit,
    /// Estimate a uniform scale per instance (registration and ICP).
    pub with_scale: bool,
    /// Register with the Gaussians' base colours too ([`crate::register::register_coloured`]),
    /// for symmetric shapes.
    pub use_colour: bool,
    /// [`RegisterOptions::colour_weight`].
    pub colour_weight: f64,
    /// Gaussians below this opacity take no part in registration and merging.
    pub min_opacity: f32,
    /// Registration voxel = this fraction of the reference instance's size ([`object_size`](crate::register::object_size)).
    pub voxel_fraction: f64,
    pub seed: u64,
    /// What a pose must pass before its instance is instanced.
    pub accept: Acceptance,
    /// Starting poses (instance id → a common frame, e.g. `discover`'s `to_reference`): where
    /// an instance and its group's reference both have one, the pose they imply is tried first.
    pub starts: BTreeMap<u32, Sim3>,
    /// With a render check and three or more accepted instances besides a group's reference,
    /// register them onto each other too and keep the synchronised poses
    /// ([`crate::instancing::synchronise`]).
    pub synchronise: bool,
    /// The pose graph's edges per instance ([`candidate_edges`](crate::instancing::synchronise::candidate_edges)):
    /// each accepted instance is registered onto this many others of its group, the nearest by
    /// size signature, besides the reference.
    pub neighbours: usize,
    /// Only these instances are registered (the others stay background): a subset for timing
    /// the stage at a smaller scale (`tools/instance-scaling.sh`) or for debugging. None: all.
    pub only: Option<std::collections::BTreeSet<u32>>,
    /// The scene's up axis (a unit normal of the floor the objects stand on; its sign does not
    /// matter): shape-ambiguous instances also try their best hypothesis turned about it
    /// ([`UP_TURNS_DEG`](crate::instancing::pose::UP_TURNS_DEG)). `None`: [`instantiate`](crate::instancing::template::instantiate) finds it from the background ([`up_axis`](crate::instancing::pose::up_axis)).
    pub up: Option<Vector3<f64>>,
}

impl InstanceOptions {
    /// Registration settings for a reference object of `size` ([`object_size`](crate::register::object_size)).
    pub fn register_options(&self, size: f64) -> RegisterOptions {
        RegisterOptions {
            voxel: size * self.voxel_fraction,
            with_scale: self.with_scale,
            scale_tolerance: self.accept.scale_tolerance,
            colour_weight: self.colour_weight,
            seed: self.seed,
            ..RegisterOptions::for_size(size)
        }
    }
}

impl Default for InstanceOptions {
    fn default() -> Self {
        InstanceOptions {
            init: TemplateInit::Max,
            with_scale: true,
            use_colour: true,
            colour_weight: 1.0,
            min_opacity: 0.05,
            voxel_fraction: 0.04,
            seed: 0,
            accept: Acceptance::default(),
            starts: BTreeMap::new(),
            synchronise: true,
            neighbours: 2,
            only: None,
            up: None,
        }
    }
}

/// What became of one instance.
#[derive(Clone, Debug, PartialEq)]
pub enum Status {
    /// The group's reference: the instance the others are registered onto (the one with the
    /// most opaque Gaussians); its frame is the template's.
    Reference,
    /// Registered; every check passed.
    Accepted,
    /// No pose passed the checks; the instance stays plain (background Gaussians).
    Refused(String),
    /// Its group kept fewer than two instances, so the whole group stays plain.
    Plain(String),
}

impl Status {
    pub fn instanced(&self) -> bool {
        matches!(self, Status::Reference | Status::Accepted)
    }

    /// "reference", "accepted", "refused" or "plain".
    pub fn name(&self) -> &'static str {
        match self {
            Status::Reference => "reference",
            Status::Accepted => "accepted",
            Status::Refused(_) => "refused",
            Status::Plain(_) => "plain",
        }
    }

    pub fn reason(&self) -> Option<&str> {
        match self {
            Status::Refused(r) | Status::Plain(r) => Some(r),
            _ => None,
        }
    }
}

/// The checks a registered pose must pass before its instance shares the group's template
/// (configuration `[instance]`, configs/pipeline.toml). A pose that fails them all leaves the
/// instance plain: its Gaussians stay in the scene as background.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Acceptance {
    /// Both fitnesses ([`PoseCheck`](crate::instancing::pose::PoseCheck)) at least this: the instance's Gaussians lie on the
    /// reference's and the reference's on the instance's.
    pub min_fitness: f64,
    /// The pose's scale within this relative distance of the two clouds' size ratio.
    pub scale_tolerance: f64,
    /// Render check ([`RenderCheck`](crate::instancing::pose::RenderCheck)): the placed silhouette's IoU with the
    /// mask at least this share of the instance's own silhouette's (median over views,
    /// [`RenderScore::relative_iou`](crate::instancing::pose::RenderScore::relative_iou)).
    pub min_render_iou: f64,
    /// Render check: PSNR (dB, after a non-negative colour mix for the instance's tint) at least
    /// this.
    pub min_render_psnr: f64,
    /// Render check: compared in at least this many views (each showing the instance on at
    /// least `verify::MIN_VIEW_PIXELS` pixels). A repetition worth instancing is an object seen
    /// from several sides; a check that one view passes proves little (on a capture's plain
    /// scene, `discover --auto` once paired two floor fragments on a single view).
    pub min_render_views: usize,
    /// Pose hypotheses tried per instance, the most plausible first, over two RANSAC seeds.
    pub max_candidates: usize,
}

impl Default for Acceptance {
    fn default() -> Self {
        Acceptance {
            min_fitness: 0.5,
            scale_tolerance: 0.25,
            min_render_iou: 0.85,
            min_render_psnr: 17.0,
            min_render_views: 3,
            max_candidates: 6,
        }
    }
}
