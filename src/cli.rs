//! The command line's types (clap): every command, its arguments and their documentation.
use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use instgs_vk::formats::instgs;
use instgs_vk::model::camera::UpAxis;
use instgs_vk::pipeline;
use instgs_vk::render::frames::FrameSpec;
use instgs_vk::render::lod::RenderConfig;
use instgs_vk::render::raster::Forward;

/// Instanced 3D Gaussian Splatting on Vulkan compute.
#[derive(Parser)]
#[command(version, about)]
pub(crate) struct Cli {
    /// Vulkan device: index or case-insensitive name substring (default: a real GPU over a CPU
    /// device). Also INSTGS_DEVICE. INSTGS_VALIDATION=1 turns on the validation layers.
    #[arg(long, global = true)]
    pub(crate) device: Option<String>,
    /// How .spz files are framed: `spec` (Niantic's specification: x right, y up, z back, turned
    /// into the PLY frame on reading and back on writing) or `as-stored` (no axis change, as
    /// splat-transform reads and writes .spz).
    #[arg(long, global = true, value_enum, default_value = "spec")]
    pub(crate) spz_frame: instgs_vk::formats::spz::SpzFrame,
    /// Let files name files outside their own folder (a glTF buffer or image, a SOG image, a
    /// dataset's images by `..` or an absolute path, or a symbolic link out). By default only
    /// files in the naming file's folder are read (docs/robustness.md).
    #[arg(long, global = true)]
    pub(crate) allow_outside_paths: bool,
    /// Memory one file may make a reader hold (what it declares: buffers, expanded node
    /// graphs, image texels), e.g. 8GB or 512MiB; refused past it with the figure. Default:
    /// half of this machine's memory.
    #[arg(long, global = true, value_parser = instgs_vk::limits::parse_bytes)]
    pub(crate) max_memory: Option<u64>,
    #[command(subcommand)]
    pub(crate) cmd: Cmd,
}

#[derive(Subcommand)]
pub(crate) enum Cmd {
    /// Print a scene's Gaussian count, SH degree, bounds and file size; for an .instgs scene
    /// also its groups, instances (template→world transforms) and the bytes of every part.
    Info {
        /// Scene file (.ply: Inria 3DGS or SuperSplat compressed; .instgs).
        scene: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Render a scene from a camera file or an orbit to PNG files and print per-pass GPU times.
    Render {
        #[command(flatten)]
        view: ViewArgs,
        /// Output folder: <basename of file_path>.png per camera, view_000.png… for orbits.
        #[arg(long)]
        out: PathBuf,
    },
    /// Render frames offscreen and report per-pass GPU times (medians), splats and memory.
    Bench {
        #[command(flatten)]
        view: ViewArgs,
        /// Timed frames per camera.
        #[arg(long, allow_negative_numbers = true, value_parser = positive_usize, default_value_t = 5)]
        frames: usize,
        /// Untimed frames first.
        #[arg(long, allow_negative_numbers = true, value_parser = natural_usize, default_value_t = 1)]
        warmup: usize,
        /// A second scene (.ply or .instgs) rendered interleaved with the first (A B A B …)
        /// from the same cameras; ratios are A over B.
        #[arg(long)]
        compare: Option<PathBuf>,
        /// Also write the results as JSON to this file.
        #[arg(long)]
        json: Option<PathBuf>,
        #[command(flatten)]
        render: RenderArgs,
        /// Render the --compare scene exactly (no level of detail) whatever the render config
        /// says: with the same file as --compare, this measures level of detail against exact
        /// rendering (frame time ratios and the PSNR of A's frames against B's).
        #[arg(long, requires = "compare")]
        compare_exact: bool,
        /// B's forward path (default: A's, --forward). Without --compare, B is A's scene: this
        /// times the two forward paths against each other on the same frames.
        #[arg(long, value_enum)]
        compare_forward: Option<Forward>,
    },
    /// The main job. On a dataset with instance masks (DIR/masks/train/): the whole InstGS
    /// pipeline, plain → segment → instance → joint → pruned → eval → bench, into one run folder with a
    /// report (RUN/report.md); a re-run resumes. Without masks: plain 3DGS training, or with
    /// --discover the pipeline with the instances found without masks. With --init
    /// SCENE.instgs: joint optimisation of that instanced scene only.
    Train(TrainArgs),
    /// The memory–quality curve of a finished `train` run: InstGS at each memory budget
    /// against the plain scene pruned to the same GPU memory, both fine-tuned as long as the
    /// joint stage; RUN/rate_distortion.json and .png, and the report shows them. Resumes.
    Curve(CurveArgs),
    /// PSNR and SSIM of a scene on a dataset's held-out (or training) views.
    Eval {
        /// Scene file (.ply or .instgs).
        #[arg(long)]
        scene: PathBuf,
        #[command(flatten)]
        data: DataArgs,
        /// Which views: test or train.
        #[arg(long, default_value = "test")]
        split: String,
        /// Print JSON: psnr_mean, ssim_mean and a views list.
        #[arg(long)]
        json: bool,
        /// Also write <view>.png renders and <view>_compare.png (ground truth | render | error ×4).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Background colour r,g,b in [0, 1] (as in training).
        #[arg(long, allow_hyphen_values = true, default_value = "0,0,0", value_parser = parse_rgb)]
        background: [f32; 3],
        /// Render as the player does (configs/render.toml: culling and template level of
        /// detail) instead of exactly, to measure what level of detail costs.
        #[arg(long)]
        lod: bool,
        /// With --lod: a TOML file with keys of configs/render.toml to change.
        #[arg(long, requires = "lod")]
        render_config: Option<PathBuf>,
    },
    /// Build an instanced scene (.instgs) from template PLYs and a scene graph.
    Compose {
        /// NAME=FILE.ply: the template of the scene graph's template_id NAME, in template space
        /// (the frame of the group's first instance). Repeat per group.
        #[arg(long = "template", required = true)]
        templates: Vec<String>,
        /// The prototype's scene_graph.json: [{template_id, instances: [{instance_id,
        /// transform}]}], transform = 4×4 row-major world→template (instance 1: identity).
        #[arg(long)]
        scene_graph: PathBuf,
        /// Plain Gaussians around the instances.
        #[arg(long)]
        background: Option<PathBuf>,
        /// Draw every offset (Δp, Δ SH DC, Δ opacity logit) from N(0, SIGMA²).
        #[arg(long, allow_negative_numbers = true, value_parser = non_negative_f32, value_name = "SIGMA")]
        random_offsets: Option<f32>,
        /// Seed of --random-offsets.
        #[arg(long, allow_negative_numbers = true, value_parser = natural_u64, default_value_t = 0)]
        seed: u64,
        /// Storage type of the offsets in the file.
        #[arg(long, value_enum, default_value = "f32")]
        offset_dtype: OffsetDtype,
        #[arg(long)]
        out: PathBuf,
    },
    /// Convert a scene between formats, chosen by OUT's name: .ply (Inria), .compressed.ply
    /// (SuperSplat, with SH), .spz (version 4), DIR/meta.json (SOG version 2), OUT.sog (the same
    /// in one zip), .glb/.gltf (KHR_gaussian_splatting), DIR/tileset.json (3D Tiles 1.1 for
    /// CesiumJS: SPZ-compressed glTF tiles beside it, a tile per instance), .splat (no SH),
    /// .json (an instanced scene's scene graph) or .instgs (an instanced scene; --compress). An
    /// instanced scene (.instgs, or a .glb we wrote from one) is expanded first (SH bands rotated
    /// per instance), except to .glb/.gltf, which share its templates (a node per instance)
    /// unless --expand, and to .instgs.
    Convert {
        /// Any scene we read (PLY, compressed PLY, .spz, SOG, .splat, .glb/.gltf, tileset.json,
        /// .instgs).
        scene: PathBuf,
        /// OUT.ply, OUT.compressed.ply, OUT.spz, DIR/meta.json, OUT.sog, OUT.glb, OUT.gltf,
        /// DIR/tileset.json, OUT.splat, OUT.json or (an instanced scene) OUT.instgs.
        out: PathBuf,
        /// Write an instanced scene to .glb/.gltf expanded (one plain splat primitive).
        #[arg(long)]
        expand: bool,
        /// .glb/.gltf only: 16-bit positions (KHR_mesh_quantization, dequantised by the node's
        /// translation and scale) and rotations; scales, opacities and SH stay float
        /// (docs/formats.md).
        #[arg(long)]
        quantize: bool,
        /// .instgs only: a compressed file, lossy — background and templates as one SOG
        /// bundle (16-bit positions, 8-bit rotations and opacities, codebooks for scales,
        /// colours and SH), offsets as q8 (8-bit multiples of a step, zstd). Without it, f32
        /// throughout.
        #[arg(long)]
        compress: bool,
    },
    /// Export a dataset's cameras (NeRF-synthetic or COLMAP folder) as a NeRF-synthetic
    /// transforms JSON: OpenGL camera-to-world matrices, per-frame intrinsics, image paths.
    Cameras {
        /// The dataset folder (or a transforms JSON).
        data: PathBuf,
        /// train, test or all.
        #[arg(long, default_value = "all")]
        split: String,
        #[arg(long)]
        out: PathBuf,
    },
    /// Gradient-driven instance segmentation of a trained plain scene with the dataset's
    /// instance masks (masks/<split>/<image>.png, ids grouped by DIR/instances.json).
    Segment {
        /// The trained plain scene (.ply).
        #[arg(long)]
        scene: PathBuf,
        /// Dataset folder (NeRF-synthetic layout with masks/ and instances.json).
        #[arg(long)]
        data: PathBuf,
        /// Views whose masks drive the segmentation.
        #[arg(long, default_value = "train")]
        split: String,
        /// Weight of the background-removal term (paper: 0.8).
        #[arg(long, allow_negative_numbers = true, default_value_t = 0.8, value_parser = non_negative_f32)]
        alpha: f32,
        /// labels.json ({ids, labels}) or labels.bin (u32 little-endian per Gaussian; 0 = background).
        #[arg(long)]
        out: PathBuf,
        /// Also write one PLY per instance and background.ply here.
        #[arg(long)]
        export_dir: Option<PathBuf>,
        /// The masks' ids mean nothing across frames (e.g. from SAM): each frame's ids are
        /// associated across views first (view consensus); masks/<split>/<stem>.json gives each
        /// mask id's category. Needs a .json output, which then carries the associated groups.
        #[arg(long)]
        per_frame_ids: bool,
    },
    /// Registration and template initialisation (paper §4.2): a segmented plain scene becomes an
    /// instanced scene (.instgs) ready for joint optimisation (`train --init`).
    Instance(InstanceArgs),
    /// Find repeated objects in a plain scene without per-instance masks: the copies of one
    /// example (--example, --box) or, with --auto, groups of objects standing on the scene's
    /// support plane. Writes a labels file and a groups file for `instance` (every copy checked
    /// as the instance stage checks a pose, the render check against the training views).
    Discover(DiscoverArgs),
    #[cfg(feature = "player")]
    /// The standalone player: a window with the scene, orbit/fly camera and FPS overlay (see
    /// docs/usage.md for the controls), or with --headless frames saved to PNG files.
    View(PlayerArgs),
    /// Time the GPU radix sort against Rust's sort_unstable on the same random keys.
    BenchSort {
        /// Number of keys.
        #[arg(long, allow_negative_numbers = true, value_parser = positive_usize, default_value_t = 1_000_000)]
        keys: usize,
        /// Key bits to sort (keys are random in 0..2^bits).
        #[arg(long, allow_negative_numbers = true, value_parser = key_bits, default_value_t = 32)]
        bits: u32,
        /// Timed GPU repeats (median reported).
        #[arg(long, allow_negative_numbers = true, value_parser = positive_usize, default_value_t = 5)]
        repeats: usize,
    },
}

// `train`'s arguments (Cmd::Train).
#[derive(Args)]
pub(crate) struct TrainArgs {
    #[command(flatten)]
    pub(crate) data: DataArgs,
    /// Run folder. Plain: checkpoint.bin, metrics.csv, curves.png, point_cloud.ply. Pipeline:
    /// also labels.json, init.instgs, scene.instgs, joint/, eval.json, bench.json, images/,
    /// pipeline.json and report.md (docs/pipeline.md).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// SCENE.ply: a plain 3DGS scene trained by any 3DGS tool replaces the plain stage.
    /// SCENE.instgs: optimise this instanced scene jointly (configs/instanced.toml applies).
    #[arg(long)]
    pub(crate) init: Option<PathBuf>,
    /// Configuration (TOML, only the keys to change): configs/default.toml's keys for plain
    /// training; a pipeline adds [joint], [segment], [instance], [eval], [bench]
    /// (configs/pipeline.toml).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Iterations of the (plain) training (overrides the configuration's).
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u64)]
    pub(crate) iterations: Option<u64>,
    /// Continue from OUT/checkpoint.bin (plain or joint-only runs; a pipeline always resumes).
    #[arg(long)]
    pub(crate) resume: bool,
    /// Pipeline: redo this stage and the ones after it (their earlier results are replaced).
    #[arg(long, value_enum)]
    pub(crate) from: Option<pipeline::Stage>,
    /// Pipeline: stop after this stage.
    #[arg(long, value_enum)]
    pub(crate) until: Option<pipeline::Stage>,
    /// Pipeline without instance masks: find the instances with `discover` instead of
    /// segmenting by masks — `auto`, a box `xmin,ymin,zmin,xmax,ymax,zmax`, or one
    /// training view's mask of one instance (MASK.png, named like the view's image).
    /// Masks the dataset has are then not used for finding instances.
    #[arg(long, value_name = "auto|BOX|MASK.png", value_parser = parse_discover)]
    pub(crate) discover: Option<instgs_vk::discover::run::ExampleSpec>,
    /// Pipeline: skip the "plain, pruned" baseline (the plain scene pruned to InstGS's GPU
    /// memory and fine-tuned as long as the joint stage), which shows what instancing adds
    /// over pruning alone.
    #[arg(long)]
    pub(crate) no_pruned_baseline: bool,
    /// Print a line every 10 % instead of a progress bar.
    #[arg(long)]
    pub(crate) quiet: bool,
}

// `curve`'s arguments (Cmd::Curve).
#[derive(Args)]
pub(crate) struct CurveArgs {
    /// The run's dataset (as given to `train`).
    #[command(flatten)]
    pub(crate) data: DataArgs,
    /// The run folder of a finished `train` (through its eval stage).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// The run's configuration (as given to `train`): the points are fine-tuned with its [joint].
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Memory budgets as fractions of the plain scene's GPU memory, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [0.05, 0.1, 0.2, 0.4])]
    pub(crate) budgets: Vec<f64>,
    /// Print a line every 10 % instead of a progress bar.
    #[arg(long)]
    pub(crate) quiet: bool,
}

// `instance`'s arguments (Cmd::Instance).
#[derive(Args)]
pub(crate) struct InstanceArgs {
    /// The trained plain scene (.ply) that was segmented.
    #[arg(long)]
    pub(crate) scene: PathBuf,
    /// Its per-Gaussian labels (labels.json or labels.bin from `segment`).
    #[arg(long)]
    pub(crate) labels: PathBuf,
    /// Dataset folder: DIR/instances.json groups the instance ids and names the groups; when
    /// it carries ground-truth poses, the recovered transforms are checked against them.
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// Group the ids by this file instead of DIR/instances.json (e.g. the labels.json of
    /// `segment --per-frame-ids`, which carries the associated groups); no ground truth then.
    #[arg(long)]
    pub(crate) groups: Option<PathBuf>,
    /// Template initialisation: max (the largest instance kept whole; measured best), merge
    /// (the paper's merge-and-sample) or first.
    #[arg(long, value_enum, default_value = "max")]
    pub(crate) init: instgs_vk::instancing::options::TemplateInit,
    /// Rigid registration (no per-instance scale).
    #[arg(long)]
    pub(crate) rigid: bool,
    /// Register by shape alone (no colour-aware ICP).
    #[arg(long)]
    pub(crate) geometry_only: bool,
    /// Weight of colour in the colour-aware ICP: a normalised colour difference of 1 counts
    /// as 2 registration voxels × this.
    #[arg(long, allow_negative_numbers = true, value_parser = non_negative_f64, default_value_t = 1.0)]
    pub(crate) colour_weight: f64,
    /// Seed of RANSAC.
    #[arg(long, allow_negative_numbers = true, value_parser = natural_u64, default_value_t = 0)]
    pub(crate) seed: u64,
    /// Storage type of the offsets in the file.
    #[arg(long, value_enum, default_value = "f32")]
    pub(crate) offset_dtype: OffsetDtype,
    /// Also write a JSON report (per instance: registration and, with ground truth, errors).
    #[arg(long)]
    pub(crate) report: Option<PathBuf>,
    /// Downscale factor of the dataset's training images for the render check.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32, default_value_t = 1)]
    pub(crate) downscale: u32,
    /// Skip the render check (poses are then checked by geometry alone).
    #[arg(long)]
    pub(crate) no_render_check: bool,
    /// Keep each pose registered onto the reference alone: no synchronisation over the
    /// group's pose graph (it needs the render check).
    #[arg(long)]
    pub(crate) no_synchronise: bool,
    /// Register only these instance ids (comma-separated; the others stay background): the
    /// stage at a smaller scale, e.g. for timing it (tools/instance-scaling.sh).
    #[arg(long, value_delimiter = ',')]
    pub(crate) instances: Option<Vec<u32>>,
    /// The pose graph: each accepted instance is registered onto this many others of its
    /// group (the nearest by size signature) besides the reference.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_usize, default_value_t = instgs_vk::instancing::options::InstanceOptions::default().neighbours)]
    pub(crate) neighbours: usize,
    /// Acceptance: both fitnesses at least this.
    #[arg(long, allow_negative_numbers = true, value_parser = unit_f64, default_value_t = instgs_vk::instancing::options::Acceptance::default().min_fitness)]
    pub(crate) min_fitness: f64,
    /// Acceptance: scale within this relative distance of the clouds' size ratio.
    #[arg(long, allow_negative_numbers = true, value_parser = non_negative_f64, default_value_t = instgs_vk::instancing::options::Acceptance::default().scale_tolerance)]
    pub(crate) scale_tolerance: f64,
    /// Acceptance: the render check's silhouette IoU with the masks at least this share of the instance's own silhouette's (median over views).
    #[arg(long, allow_negative_numbers = true, value_parser = unit_f64, default_value_t = instgs_vk::instancing::options::Acceptance::default().min_render_iou)]
    pub(crate) min_render_iou: f64,
    /// Acceptance: the render check's PSNR (dB) at least this.
    #[arg(long, allow_negative_numbers = true, value_parser = finite_f64, default_value_t = instgs_vk::instancing::options::Acceptance::default().min_render_psnr)]
    pub(crate) min_render_psnr: f64,
    /// Acceptance: the render check compares at least this many views that show the instance.
    #[arg(long, default_value_t = instgs_vk::instancing::options::Acceptance::default().min_render_views)]
    pub(crate) min_render_views: usize,
    #[arg(long)]
    pub(crate) out: PathBuf,
}

// `discover`'s arguments (Cmd::Discover).
#[derive(Args)]
pub(crate) struct DiscoverArgs {
    /// The trained plain scene (any format `info` reads).
    #[arg(long)]
    pub(crate) scene: PathBuf,
    /// Dataset folder: its training views drive the render check and a mask example; where
    /// its instances.json carries ground-truth poses, the result is compared with them
    /// (never used in the search).
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// The example: a label id of --labels, or one instance's mask in one training view
    /// (a grey PNG named like the view's image, or with --view).
    #[arg(long, conflicts_with_all = ["auto", "bbox"])]
    pub(crate) example: Option<String>,
    /// The example: the Gaussians in xmin,ymin,zmin,xmax,ymax,zmax (world units).
    #[arg(long = "box", value_name = "XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX", conflicts_with = "auto")]
    pub(crate) bbox: Option<String>,
    /// No example: propose the groups (support plane, clusters on it, registered together).
    #[arg(long)]
    pub(crate) auto: bool,
    /// The labels file of --example ID.
    #[arg(long)]
    pub(crate) labels: Option<PathBuf>,
    /// The training view of --example MASK.png (default: the view whose image has its name).
    #[arg(long)]
    pub(crate) view: Option<String>,
    /// The id in --example MASK.png to take (default: its only non-zero id).
    #[arg(long)]
    pub(crate) mask_id: Option<u16>,
    /// Downscale factor of the training images.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32, default_value_t = 1)]
    pub(crate) downscale: u32,
    /// Skip the render check (copies are then checked by geometry alone).
    #[arg(long)]
    pub(crate) no_render_check: bool,
    /// Seed of RANSAC.
    #[arg(long, allow_negative_numbers = true, value_parser = natural_u64, default_value_t = 0)]
    pub(crate) seed: u64,
    /// The labels file written ({ids, labels}).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// The groups file written (default: groups.json beside --out).
    #[arg(long)]
    pub(crate) groups: Option<PathBuf>,
}

// `view`'s arguments (Cmd::View).
#[cfg(feature = "player")]
#[derive(Args)]
pub(crate) struct PlayerArgs {
    /// Scene file (.ply: Inria 3DGS or SuperSplat compressed; .instgs).
    pub(crate) scene: PathBuf,
    /// Start from a dataset's camera: a transforms_*.json file, or a NeRF-synthetic or
    /// COLMAP folder. Default: framing the scene's bounds.
    #[arg(long)]
    pub(crate) cameras: Option<PathBuf>,
    /// Which of those cameras.
    #[arg(long, allow_negative_numbers = true, value_parser = natural_usize, default_value_t = 0, requires = "cameras")]
    pub(crate) camera: usize,
    /// Which cameras of a dataset folder: train, test or all.
    #[arg(long, default_value = "train", requires = "cameras")]
    pub(crate) split: String,
    /// Which world axis is up (orbit and fly moves).
    #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
    pub(crate) up: UpAxis,
    /// Window (or headless frame) width.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32, default_value_t = 1280)]
    pub(crate) width: u32,
    /// Window (or headless frame) height.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32, default_value_t = 720)]
    pub(crate) height: u32,
    /// Background colour r,g,b in [0, 1] (B cycles black, white, grey).
    #[arg(long, allow_hyphen_values = true, default_value = "0,0,0", value_parser = parse_rgb)]
    pub(crate) background: [f32; 3],
    /// Wait for vertical sync (default: off, immediate or mailbox presentation).
    #[arg(long)]
    pub(crate) vsync: bool,
    /// No FPS overlay (H toggles it).
    #[arg(long)]
    pub(crate) no_overlay: bool,
    /// Exit after N frames (windowed: the last one is saved as a screenshot in --out).
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u64)]
    pub(crate) frames: Option<u64>,
    /// Folder for screenshots (windowed) or frames (headless).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// No window: render --frames N turntable frames offscreen into --out DIR.
    #[arg(long, requires_all = ["frames", "out"])]
    pub(crate) headless: bool,
    #[command(flatten)]
    pub(crate) render: RenderArgs,
    /// How the depth-sorted splats become pixels: compute (the blend kernel), quads (the
    /// fixed-function rasterizer) or auto (whichever renders the first frame faster).
    #[arg(long, value_enum, default_value = "auto")]
    pub(crate) forward: Forward,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum OffsetDtype {
    F32,
    F16,
    /// Product-quantised: two 8-bit codes per pair into 256-entry codebooks (lossy once).
    Pq8,
}

impl From<OffsetDtype> for instgs::Dtype {
    fn from(d: OffsetDtype) -> instgs::Dtype {
        match d {
            OffsetDtype::F32 => instgs::Dtype::F32,
            OffsetDtype::F16 => instgs::Dtype::F16,
            OffsetDtype::Pq8 => instgs::Dtype::Pq8,
        }
    }
}

#[derive(Args)]
pub(crate) struct DataArgs {
    /// Dataset folder: NeRF-synthetic (transforms_train.json) or COLMAP (sparse/0, images/).
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// Divide the image resolution by this integer factor.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32, default_value_t = 1)]
    pub(crate) downscale: u32,
}

/// How instanced scenes are rendered by `view` and `bench` (configs/render.toml).
#[derive(Args)]
pub(crate) struct RenderArgs {
    /// TOML file with keys of configs/render.toml to change (culling, level of detail).
    #[arg(long)]
    pub(crate) render_config: Option<PathBuf>,
    /// Exact rendering: no template level of detail (instances are still culled, losslessly).
    #[arg(long)]
    pub(crate) exact: bool,
}

impl RenderArgs {
    pub(crate) fn load(&self) -> Result<RenderConfig> {
        let cfg = RenderConfig::load(self.render_config.as_deref())?;
        Ok(if self.exact { cfg.exact() } else { cfg })
    }
}

#[derive(Args)]
pub(crate) struct ViewArgs {
    /// Scene file (.ply: Inria 3DGS or SuperSplat compressed; .instgs).
    #[arg(long)]
    pub(crate) scene: PathBuf,
    /// The cameras: a transforms_*.json file, a NeRF-synthetic folder or a COLMAP folder.
    #[arg(long, conflicts_with = "orbit", required_unless_present = "orbit")]
    pub(crate) cameras: Option<PathBuf>,
    /// Which cameras of a dataset folder: train, test or all.
    #[arg(long, default_value = "train", requires = "cameras")]
    pub(crate) split: String,
    /// N cameras on an orbit around the scene's bounds.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_usize)]
    pub(crate) orbit: Option<usize>,
    /// Which world axis is up, for orbits.
    #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
    pub(crate) up: UpAxis,
    /// Image width (default: the camera file's, 640 for orbits); intrinsics are scaled.
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32)]
    pub(crate) width: Option<u32>,
    /// Image height (default: the camera file's, 480 for orbits).
    #[arg(long, allow_negative_numbers = true, value_parser = positive_u32)]
    pub(crate) height: Option<u32>,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, allow_hyphen_values = true, default_value = "0,0,0", value_parser = parse_rgb)]
    pub(crate) background: [f32; 3],
    /// How the depth-sorted splats become pixels: compute (tile lists and the blend kernel, the
    /// reference), quads (instanced quads through the fixed-function rasterizer and blending;
    /// a device with a graphics queue) or auto (whichever renders the first frame faster).
    #[arg(long, value_enum, default_value = "compute")]
    pub(crate) forward: Forward,
}

impl ViewArgs {
    pub(crate) fn spec(self) -> FrameSpec {
        FrameSpec {
            scene: self.scene,
            cameras: self.cameras,
            split: self.split,
            orbit: self.orbit,
            up: self.up,
            width: self.width,
            height: self.height,
            background: self.background,
            forward: self.forward,
        }
    }
}

/// A whole number in `min..=max`; clap names the flag before the message.
fn whole(s: &str, min: u64, max: u64) -> std::result::Result<u64, String> {
    s.trim().parse::<u64>().ok().filter(|v| (min..=max).contains(v)).ok_or_else(|| match max >= u32::MAX as u64 {
        true => format!("'{s}' is not a whole number ≥ {min}"),
        false => format!("'{s}' is not a whole number from {min} to {max}"),
    })
}

fn positive_u32(s: &str) -> std::result::Result<u32, String> {
    whole(s, 1, u32::MAX as u64).map(|v| v as u32)
}

fn positive_u64(s: &str) -> std::result::Result<u64, String> {
    whole(s, 1, u64::MAX)
}

fn positive_usize(s: &str) -> std::result::Result<usize, String> {
    whole(s, 1, usize::MAX as u64).map(|v| v as usize)
}

fn natural_u64(s: &str) -> std::result::Result<u64, String> {
    whole(s, 0, u64::MAX)
}

fn natural_usize(s: &str) -> std::result::Result<usize, String> {
    whole(s, 0, usize::MAX as u64).map(|v| v as usize)
}

/// `bench-sort --bits`: 1 to 32.
fn key_bits(s: &str) -> std::result::Result<u32, String> {
    whole(s, 1, 32).map(|v| v as u32)
}

/// A finite number accepted by `ok`, `range` saying which in the message.
fn number(s: &str, ok: fn(f64) -> bool, range: &str) -> std::result::Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && ok(v) => Ok(v),
        _ => Err(format!("'{s}' is not {range}")),
    }
}

fn non_negative_f64(s: &str) -> std::result::Result<f64, String> {
    number(s, |v| v >= 0.0, "a finite number ≥ 0")
}

fn non_negative_f32(s: &str) -> std::result::Result<f32, String> {
    non_negative_f64(s).map(|v| v as f32)
}

fn unit_f64(s: &str) -> std::result::Result<f64, String> {
    number(s, |v| (0.0..=1.0).contains(&v), "a number in [0, 1]")
}

fn finite_f64(s: &str) -> std::result::Result<f64, String> {
    number(s, |_| true, "a finite number")
}

pub(crate) fn parse_rgb(s: &str) -> std::result::Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>().map_err(|_| format!("'{p}' is not a number")))
        .collect::<std::result::Result<_, _>>()?;
    match v[..] {
        [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok([r, g, b]),
        [_, _, _] => Err("components must be in [0, 1]".into()),
        _ => Err("expected r,g,b".into()),
    }
}

/// `train --discover`: auto, a box or a mask path.
fn parse_discover(s: &str) -> std::result::Result<instgs_vk::discover::run::ExampleSpec, String> {
    use instgs_vk::discover::run::ExampleSpec;
    if s == "auto" {
        return Ok(ExampleSpec::Auto);
    }
    if s.ends_with(".png") {
        return Ok(ExampleSpec::Mask { path: s.into(), view: None, id: None });
    }
    parse_box(s).map(ExampleSpec::Box).map_err(|e| format!("{e} (or auto, or MASK.png)"))
}

/// `--box xmin,ymin,zmin,xmax,ymax,zmax`.
pub(crate) fn parse_box(s: &str) -> std::result::Result<[f64; 6], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| format!("--box {s:?}: {e}"))?;
    let Ok(b) = <[f64; 6]>::try_from(v.as_slice()) else {
        return Err(format!("--box {s:?}: six numbers, xmin,ymin,zmin,xmax,ymax,zmax"));
    };
    if !b.iter().all(|x| x.is_finite()) || (0..3).any(|a| b[a] >= b[a + 3]) {
        return Err(format!("--box {s:?}: finite, each min below its max"));
    }
    Ok(b)
}
