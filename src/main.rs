use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use instgs_vk::formats::instgs::{self, AnyScene};
use instgs_vk::gpu::kernels::Kernels;
use instgs_vk::gpu::{Gpu, GpuOptions};
use instgs_vk::model::camera::{self, Camera, UpAxis};
use instgs_vk::model::scene::read_ply;
use instgs_vk::render::raster::Rasterizer;
use instgs_vk::util::{median, percentile, save_png, Progress, ProgressMode};

mod pipeline;
#[path = "pipeline/report.rs"]
mod report;

/// Instanced 3D Gaussian Splatting on Vulkan compute.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// Vulkan device: index or case-insensitive name substring (default: a real GPU over a CPU
    /// device). Also INSTGS_DEVICE. INSTGS_VALIDATION=1 turns on the validation layers.
    #[arg(long, global = true)]
    device: Option<String>,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
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
        #[arg(long, default_value_t = 5)]
        frames: usize,
        /// Untimed frames first.
        #[arg(long, default_value_t = 1)]
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
    },
    /// The main job. On a dataset with instance masks (DIR/masks/train/): the whole InstGS
    /// pipeline, plain → segment → instance → joint → eval → bench, into one run folder with a
    /// report (RUN/report.md); a re-run resumes. Without masks: plain 3DGS training. With
    /// --init SCENE.instgs: joint optimisation of that instanced scene only.
    Train {
        #[command(flatten)]
        data: DataArgs,
        /// Run folder. Plain: checkpoint.bin, metrics.csv, curves.png, point_cloud.ply. Pipeline:
        /// also labels.json, init.instgs, scene.instgs, joint/, eval.json, bench.json, images/,
        /// pipeline.json and report.md (see the README).
        #[arg(long)]
        out: PathBuf,
        /// SCENE.ply: a plain 3DGS scene trained by any 3DGS tool replaces the plain stage.
        /// SCENE.instgs: optimise this instanced scene jointly (configs/instanced.toml applies).
        #[arg(long)]
        init: Option<PathBuf>,
        /// Configuration (TOML, only the keys to change): configs/default.toml's keys for plain
        /// training; a pipeline adds [joint], [segment], [instance], [eval], [bench]
        /// (configs/pipeline.toml).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Iterations of the (plain) training (overrides the configuration's).
        #[arg(long)]
        iterations: Option<u64>,
        /// Continue from OUT/checkpoint.bin (plain or joint-only runs; a pipeline always resumes).
        #[arg(long)]
        resume: bool,
        /// Pipeline: redo this stage and the ones after it (their earlier results are replaced).
        #[arg(long, value_enum)]
        from: Option<pipeline::Stage>,
        /// Pipeline: stop after this stage.
        #[arg(long, value_enum)]
        until: Option<pipeline::Stage>,
        /// Print a line every 10 % instead of a progress bar.
        #[arg(long)]
        quiet: bool,
    },
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
        #[arg(long, default_value = "0,0,0", value_parser = parse_rgb)]
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
        #[arg(long, value_name = "SIGMA")]
        random_offsets: Option<f32>,
        /// Seed of --random-offsets.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Storage type of the offsets in the file.
        #[arg(long, value_enum, default_value = "f32")]
        offset_dtype: OffsetDtype,
        #[arg(long)]
        out: PathBuf,
    },
    /// Convert a scene between formats, chosen by OUT's name: .ply (Inria), .compressed.ply
    /// (SuperSplat, with SH), .spz (version 4), DIR/meta.json (SOG version 2), .splat (no SH),
    /// or .json (an .instgs scene's scene graph). An .instgs scene is expanded first (SH bands rotated per instance).
    Convert {
        /// Any scene we read (PLY, compressed PLY, .spz, SOG, .splat, .instgs).
        scene: PathBuf,
        /// OUT.ply, OUT.compressed.ply, OUT.spz, DIR/meta.json, OUT.splat or OUT.json.
        out: PathBuf,
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
        #[arg(long, default_value_t = 0.8)]
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
    Instance {
        /// The trained plain scene (.ply) that was segmented.
        #[arg(long)]
        scene: PathBuf,
        /// Its per-Gaussian labels (labels.json or labels.bin from `segment`).
        #[arg(long)]
        labels: PathBuf,
        /// Dataset folder: DIR/instances.json groups the instance ids and names the groups; when
        /// it carries ground-truth poses, the recovered transforms are checked against them.
        #[arg(long)]
        data: PathBuf,
        /// Group the ids by this file instead of DIR/instances.json (e.g. the labels.json of
        /// `segment --per-frame-ids`, which carries the associated groups); no ground truth then.
        #[arg(long)]
        groups: Option<PathBuf>,
        /// Template initialisation: max (the largest instance kept whole; measured best), merge
        /// (the paper's merge-and-sample) or first.
        #[arg(long, value_enum, default_value = "max")]
        init: instgs_vk::instancing::template::TemplateInit,
        /// Rigid registration (no per-instance scale).
        #[arg(long)]
        rigid: bool,
        /// Register by shape alone (no colour-aware ICP).
        #[arg(long)]
        geometry_only: bool,
        /// Weight of colour in the colour-aware ICP: a normalised colour difference of 1 counts
        /// as 2 registration voxels × this.
        #[arg(long, default_value_t = 1.0)]
        colour_weight: f64,
        /// Seed of RANSAC.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Storage type of the offsets in the file.
        #[arg(long, value_enum, default_value = "f32")]
        offset_dtype: OffsetDtype,
        /// Also write a JSON report (per instance: registration and, with ground truth, errors).
        #[arg(long)]
        report: Option<PathBuf>,
        /// Downscale factor of the dataset's training images for the render check.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        /// Skip the render check (poses are then checked by geometry alone).
        #[arg(long)]
        no_render_check: bool,
        /// Acceptance: both fitnesses at least this.
        #[arg(long, default_value_t = instgs_vk::instancing::template::Acceptance::default().min_fitness)]
        min_fitness: f64,
        /// Acceptance: scale within this relative distance of the clouds' size ratio.
        #[arg(long, default_value_t = instgs_vk::instancing::template::Acceptance::default().scale_tolerance)]
        scale_tolerance: f64,
        /// Acceptance: the render check's median silhouette IoU at least this.
        #[arg(long, default_value_t = instgs_vk::instancing::template::Acceptance::default().min_render_iou)]
        min_render_iou: f64,
        /// Acceptance: the render check's PSNR (dB) at least this.
        #[arg(long, default_value_t = instgs_vk::instancing::template::Acceptance::default().min_render_psnr)]
        min_render_psnr: f64,
        #[arg(long)]
        out: PathBuf,
    },
    /// The standalone player: a window with the scene, orbit/fly camera and FPS overlay (see
    /// the README for the controls), or with --headless frames saved to PNG files.
    View {
        /// Scene file (.ply: Inria 3DGS or SuperSplat compressed; .instgs).
        scene: PathBuf,
        /// Start from a dataset's camera: a transforms_*.json file, or a NeRF-synthetic or
        /// COLMAP folder. Default: framing the scene's bounds.
        #[arg(long)]
        cameras: Option<PathBuf>,
        /// Which of those cameras.
        #[arg(long, default_value_t = 0, requires = "cameras")]
        camera: usize,
        /// Which cameras of a dataset folder: train, test or all.
        #[arg(long, default_value = "train", requires = "cameras")]
        split: String,
        /// Which world axis is up (orbit and fly moves).
        #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
        up: UpAxis,
        /// Window (or headless frame) width.
        #[arg(long, default_value_t = 1280)]
        width: u32,
        /// Window (or headless frame) height.
        #[arg(long, default_value_t = 720)]
        height: u32,
        /// Background colour r,g,b in [0, 1] (B cycles black, white, grey).
        #[arg(long, default_value = "0,0,0", value_parser = parse_rgb)]
        background: [f32; 3],
        /// Wait for vertical sync (default: off, immediate or mailbox presentation).
        #[arg(long)]
        vsync: bool,
        /// No FPS overlay (H toggles it).
        #[arg(long)]
        no_overlay: bool,
        /// Exit after N frames (windowed: the last one is saved as a screenshot in --out).
        #[arg(long)]
        frames: Option<u64>,
        /// Folder for screenshots (windowed) or frames (headless).
        #[arg(long)]
        out: Option<PathBuf>,
        /// No window: render --frames N turntable frames offscreen into --out DIR.
        #[arg(long, requires_all = ["frames", "out"])]
        headless: bool,
        #[command(flatten)]
        render: RenderArgs,
    },
    /// Time the GPU radix sort against Rust's sort_unstable on the same random keys.
    BenchSort {
        /// Number of keys.
        #[arg(long, default_value_t = 1_000_000)]
        keys: usize,
        /// Key bits to sort (keys are random in 0..2^bits).
        #[arg(long, default_value_t = 32)]
        bits: u32,
        /// Timed GPU repeats (median reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum OffsetDtype {
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
struct DataArgs {
    /// Dataset folder: NeRF-synthetic (transforms_train.json) or COLMAP (sparse/0, images/).
    #[arg(long)]
    data: PathBuf,
    /// Divide the image resolution by this integer factor.
    #[arg(long, default_value_t = 1)]
    downscale: u32,
}

/// How instanced scenes are rendered by `view` and `bench` (configs/render.toml).
#[derive(Args)]
struct RenderArgs {
    /// TOML file with keys of configs/render.toml to change (culling, level of detail).
    #[arg(long)]
    render_config: Option<PathBuf>,
    /// Exact rendering: no template level of detail (instances are still culled, losslessly).
    #[arg(long)]
    exact: bool,
}

impl RenderArgs {
    fn load(&self) -> Result<instgs_vk::render::lod::RenderConfig> {
        let cfg = instgs_vk::render::lod::RenderConfig::load(self.render_config.as_deref())?;
        Ok(if self.exact { cfg.exact() } else { cfg })
    }
}

#[derive(Args)]
struct ViewArgs {
    /// Scene file (.ply: Inria 3DGS or SuperSplat compressed; .instgs).
    #[arg(long)]
    scene: PathBuf,
    /// The cameras: a transforms_*.json file, a NeRF-synthetic folder or a COLMAP folder.
    #[arg(long, conflicts_with = "orbit", required_unless_present = "orbit")]
    cameras: Option<PathBuf>,
    /// Which cameras of a dataset folder: train, test or all.
    #[arg(long, default_value = "train", requires = "cameras")]
    split: String,
    /// N cameras on an orbit around the scene's bounds.
    #[arg(long)]
    orbit: Option<usize>,
    /// Which world axis is up, for orbits.
    #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
    up: UpAxis,
    /// Image width (default: the camera file's, 640 for orbits); intrinsics are scaled.
    #[arg(long)]
    width: Option<u32>,
    /// Image height (default: the camera file's, 480 for orbits).
    #[arg(long)]
    height: Option<u32>,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, default_value = "0,0,0", value_parser = parse_rgb)]
    background: [f32; 3],
}

fn parse_rgb(s: &str) -> std::result::Result<[f32; 3], String> {
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

fn main() -> ExitCode {
    // Output piped into a reader that stops early (`| head`) ends the process quietly, as
    // Unix tools do, instead of a panic in println!.
    #[cfg(unix)]
    // SAFETY: setting a signal disposition to SIG_DFL before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Info { scene, json } => info(&scene, json),
        Cmd::Render { view, out } => render(cli.device, &view, &out),
        Cmd::Bench { view, frames, warmup, compare, json, render, compare_exact } => {
            let cfg = render.load()?;
            let b = compare.as_deref().map(|p| (p, if compare_exact { cfg.clone().exact() } else { cfg.clone() }));
            bench(cli.device, &view, frames, warmup, &cfg, b, json.as_deref())
        }
        Cmd::Compose { templates, scene_graph, background, random_offsets, seed, offset_dtype, out } => compose(
            &templates,
            &scene_graph,
            background.as_deref(),
            random_offsets.map(|s| (s, seed)),
            offset_dtype,
            &out,
        ),
        Cmd::Convert { scene, out } => convert(&scene, &out),
        Cmd::Cameras { data, split, out } => export_cameras(&data, &split, &out),
        Cmd::Segment { scene, data, split, alpha, out, export_dir, per_frame_ids } => {
            segment(cli.device, &scene, &data, &split, alpha, &out, export_dir.as_deref(), per_frame_ids)
        }
        Cmd::Instance {
            scene,
            labels,
            data,
            groups,
            init,
            rigid,
            geometry_only,
            colour_weight,
            seed,
            offset_dtype,
            report,
            downscale,
            no_render_check,
            min_fitness,
            scale_tolerance,
            min_render_iou,
            min_render_psnr,
            out,
        } => {
            let groups_file = groups.clone().unwrap_or_else(|| data.join("instances.json"));
            let truth = groups.is_none().then_some(groups_file.as_path());
            let accept = instgs_vk::instancing::template::Acceptance {
                min_fitness,
                scale_tolerance,
                min_render_iou,
                min_render_psnr,
                ..Default::default()
            };
            let opts = instgs_vk::instancing::template::InstanceOptions {
                init,
                with_scale: !rigid,
                use_colour: !geometry_only,
                colour_weight,
                seed,
                accept,
                ..Default::default()
            };
            let has_views = data.join("transforms_train.json").exists() || data.join("sparse").is_dir();
            let mut check = if no_render_check || !has_views {
                None
            } else {
                let load = instgs_vk::dataset::LoadOptions { downscale, background: [0.0; 3] };
                let ds = instgs_vk::dataset::load(&data, &load)?;
                let masks = match groups {
                    None if data.join("masks").join("train").is_dir() => {
                        Some(instgs_vk::segment::load_masks(&data, "train", &ds.train)?)
                    }
                    _ => None,
                };
                let (gpu, k) = open_device(cli.device.clone())?;
                let cams = ds.train.iter().map(|v| v.camera.clone()).collect();
                Some(instgs_vk::instancing::verify::ImageCheck::new(&gpu, &k, cams, masks)?)
            };
            let check = check.as_mut().map(|c| c as &mut dyn instgs_vk::instancing::template::RenderCheck);
            instance(
                &scene,
                &labels,
                &groups_file,
                truth,
                &opts,
                offset_dtype.into(),
                None,
                check,
                report.as_deref(),
                &out,
            )
            .map(|_| {
                if !no_render_check && !has_views {
                    eprintln!(
                        "note: {} holds no training views (transforms_train.json or sparse/): the poses were checked by geometry alone",
                        data.display()
                    );
                }
            })
        }
        Cmd::View {
            scene,
            cameras,
            camera,
            split,
            up,
            width,
            height,
            background,
            vsync,
            no_overlay,
            frames,
            out,
            headless,
            render,
        } => {
            let opts = instgs_vk::player::PlayerOptions {
                render: render.load()?,
                scene_path: scene,
                device: cli.device,
                width,
                height,
                background,
                vsync,
                overlay: !no_overlay,
                frames,
                out,
            };
            view(opts, cameras.as_deref(), (camera, &split), up, headless)
        }
        Cmd::BenchSort { keys, bits, repeats } => bench_sort(cli.device, keys, bits, repeats),
        Cmd::Train { data, out, init, config, iterations, resume, quiet, from, until } => {
            let is_instgs = match init.as_deref() {
                Some(p) => instgs_vk::formats::detect(p)? == instgs_vk::formats::Format::Instgs,
                None => false,
            };
            let masks = pipeline::has_masks(&data.data);
            if masks && !is_instgs {
                let init_ply = init.clone();
                return pipeline::run(pipeline::PipelineArgs {
                    data: data.data.clone(),
                    downscale: data.downscale,
                    out,
                    init_ply,
                    config,
                    iterations,
                    from,
                    until,
                    progress: !quiet,
                    device: cli.device,
                });
            }
            if from.is_some() || until.is_some() {
                bail!(
                    "--from and --until choose pipeline stages, and {} has no instance masks (masks/train/)",
                    data.data.display()
                );
            }
            if init.is_some() && !is_instgs {
                bail!(
                    "--init with a plain scene starts the InstGS pipeline, which needs instance masks: {} has no masks/train/ (see the README, 'Bringing your own masks')",
                    data.data.display()
                );
            }
            if init.is_none() {
                eprintln!("{}: no instance masks (masks/train/): training plain 3DGS only", data.data.display());
            }
            train(cli.device, &data, &out, init.as_deref(), config.as_deref(), iterations, resume, quiet)
        }
        Cmd::Eval { scene, data, split, json, out, background, lod, render_config } => {
            let render =
                lod.then(|| instgs_vk::render::lod::RenderConfig::load(render_config.as_deref())).transpose()?;
            eval(cli.device, &scene, &data, &split, json, out.as_deref(), background, render.as_ref())
        }
    }
}

fn view(
    opts: instgs_vk::player::PlayerOptions,
    cameras: Option<&Path>,
    (camera, split): (usize, &str),
    up: UpAxis,
    headless: bool,
) -> Result<()> {
    use instgs_vk::player::{run_headless, run_window, ViewCamera};
    if opts.width == 0 || opts.height == 0 {
        bail!("--width and --height must be at least 1");
    }
    if opts.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    let scene = AnyScene::read(&opts.scene_path)?;
    let means = scene.means();
    let (lo, hi) = instgs_vk::model::scene::robust_bounds(&means, 0.02);
    let centre = 0.5 * (lo + hi);
    let start = match cameras {
        Some(path) => {
            let cams = instgs_vk::dataset::dataset_cameras(path, split)?;
            let n = cams.len();
            cams.into_iter()
                .nth(camera)
                .ok_or_else(|| anyhow::anyhow!("{}: --camera {camera} is out of range ({n} cameras)", path.display()))?
        }
        None => instgs_vk::model::camera::orbit_around_points(&means, 1, up, opts.width, opts.height).remove(0),
    };
    let start = ViewCamera::from_camera(&start, centre, up.vector());
    drop(means);
    if headless {
        run_headless(&opts, &scene, start)
    } else {
        run_window(opts, scene, start)
    }
}

fn open_device(device: Option<String>) -> Result<(Arc<Gpu>, Arc<Kernels>)> {
    let gpu = Gpu::new(&GpuOptions::from_env(device))?;
    let k = Kernels::new(&gpu)?;
    Ok((gpu, k))
}

#[allow(clippy::too_many_arguments)]
fn train(
    device: Option<String>,
    data: &DataArgs,
    out: &Path,
    init: Option<&Path>,
    config: Option<&Path>,
    iterations: Option<u64>,
    resume: bool,
    quiet: bool,
) -> Result<()> {
    use instgs_vk::train;
    let init = init.map(instgs::read).transpose()?;
    let ckpt = train::checkpoint_path(out);
    let instanced =
        init.is_some() || (resume && train::read_checkpoint(&ckpt).is_ok_and(|(st, _)| st.layout.is_some()));
    let mut cfg = if instanced {
        instgs_vk::train::config::Config::load_instanced(config)?
    } else {
        instgs_vk::train::config::Config::load(config)?
    };
    if let Some(n) = iterations {
        cfg.iterations = n;
    }
    let opts = instgs_vk::dataset::LoadOptions { downscale: data.downscale, background: cfg.background };
    let ds = instgs_vk::dataset::load(&data.data, &opts)?;
    let what = ds.describe(&data.data)?;
    let (gpu, k) = open_device(device)?;
    eprintln!("{}: {what}; {}", data.data.display(), gpu.describe());
    ctrlc::set_handler(|| train::INTERRUPTED.store(true, std::sync::atomic::Ordering::SeqCst))
        .context("cannot install the Ctrl-C handler")?;
    let opts = train::RunOptions { init, ..train::RunOptions::new(out.to_path_buf(), resume, !quiet) };
    let r = train::run(&gpu, &k, &ds, &cfg, &opts)?;
    let test = match (r.test_psnr, r.test_ssim) {
        (Some(p), Some(s)) => format!(", test PSNR {p:.2} dB SSIM {s:.4}"),
        _ => String::new(),
    };
    eprintln!(
        "{} iterations, {} splats{test}, {:.1} s ({:.2} it/s this session)",
        r.iterations, r.splats, r.seconds, r.iterations_per_second
    );
    if !r.pass_medians.is_empty() {
        let total: f64 = r.pass_medians.iter().map(|p| p.1).sum();
        let list: Vec<String> = r.pass_medians.iter().map(|(n, ms)| format!("{n} {ms:.2}")).collect();
        eprintln!("GPU ms per iteration (medians): {} = {total:.2}", list.join(", "));
    }
    let m = gpu.take_validation_messages();
    if !m.is_empty() {
        bail!("{} Vulkan validation message(s), first: {}", m.len(), m[0]);
    }
    if r.interrupted {
        bail!(
            "interrupted at iteration {}; checkpoint written to {}, continue with --resume",
            r.iterations,
            train::checkpoint_path(out).display()
        );
    }
    let result = if instanced { "scene.instgs" } else { "point_cloud.ply" };
    eprintln!("wrote {}", out.join(result).display());
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn eval(
    device: Option<String>,
    scene_path: &Path,
    data: &DataArgs,
    split: &str,
    json: bool,
    out: Option<&Path>,
    background: [f32; 3],
    render: Option<&instgs_vk::render::lod::RenderConfig>,
) -> Result<()> {
    let scene = AnyScene::read(scene_path)?;
    let opts = instgs_vk::dataset::LoadOptions { downscale: data.downscale, background };
    let ds = instgs_vk::dataset::load(&data.data, &opts)?;
    let views = ds.split(split)?;
    if views.is_empty() {
        bail!("{}: the {split} split has no views", data.data.display());
    }
    let (gpu, k) = open_device(device)?;
    let gs = match render {
        Some(cfg) => scene.upload_for_rendering(&gpu, cfg),
        None => scene.upload(&gpu),
    }
    .with_context(|| scene_path.display().to_string())?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    if let Some(dir) = out {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    let mut bar = Progress::new("eval: ", "view", "views/s", views.len() as u64, 0, ProgressMode::Auto);
    let mut done = 0;
    let e = instgs_vk::train::evaluate(&mut r, &gs, views, background, |v, f| {
        done += 1;
        bar.set(done, "");
        let Some(dir) = out else { return Ok(()) };
        save_png(&dir.join(format!("{}.png", v.camera.name)), f.width, f.height, &f.image)?;
        let err = instgs_vk::util::error_image(&f.image, &v.image);
        let cmp = instgs_vk::util::side_by_side(&[&v.image, &f.image, &err], f.width as usize, f.height as usize);
        save_png(&dir.join(format!("{}_compare.png", v.camera.name)), 3 * f.width, f.height, &cmp)
    })?;
    bar.finish();
    if json {
        let views: Vec<_> =
            e.views.iter().map(|v| serde_json::json!({"name": v.name, "psnr": v.psnr, "ssim": v.ssim})).collect();
        let v = serde_json::json!({
            "scene": scene_path.display().to_string(),
            "data": data.data.display().to_string(),
            "split": split,
            "psnr_mean": e.psnr,
            "ssim_mean": e.ssim,
            "views": views,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for v in &e.views {
            println!("{:<24} PSNR {:7.3} dB  SSIM {:.4}", v.name, v.psnr, v.ssim);
        }
        println!("{:<24} PSNR {:7.3} dB  SSIM {:.4}  ({} views)", "mean", e.psnr, e.ssim, e.views.len());
    }
    Ok(())
}

fn info(path: &Path, json: bool) -> Result<()> {
    let format = instgs_vk::formats::detect(path)?;
    if format == instgs_vk::formats::Format::Instgs {
        return info_instgs(path, json);
    }
    let scene = instgs_vk::formats::read_scene(path)?;
    let file_bytes = instgs_vk::formats::file_bytes(path)?;
    let (lo, hi) = scene.bounds();
    let (rlo, rhi) = scene.robust_bounds(0.02);
    if json {
        let v = serde_json::json!({
            "file": path.display().to_string(),
            "kind": "plain",
            "format": format.name(),
            "gaussians": scene.len(),
            "sh_degree": scene.sh_degree,
            "bounds_min": lo.to_array(),
            "bounds_max": hi.to_array(),
            "bounds_min_p2": rlo.to_array(),
            "bounds_max_p98": rhi.to_array(),
            "file_bytes": file_bytes,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("file        {}", path.display());
        println!("format      {}", format.name());
        println!("gaussians   {}", scene.len());
        println!("sh degree   {}", scene.sh_degree);
        println!("bounds      [{:.4}, {:.4}, {:.4}] .. [{:.4}, {:.4}, {:.4}]", lo.x, lo.y, lo.z, hi.x, hi.y, hi.z);
        println!(
            "p2..p98     [{:.4}, {:.4}, {:.4}] .. [{:.4}, {:.4}, {:.4}]",
            rlo.x, rlo.y, rlo.z, rhi.x, rhi.y, rhi.z
        );
        println!("file size   {file_bytes} bytes");
    }
    Ok(())
}

fn info_instgs(path: &Path, json: bool) -> Result<()> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let scene = instgs::from_bytes(&bytes, &path.display().to_string())?;
    let parts = instgs::part_bytes(&bytes)?;
    let splats = scene.splats();
    // A plain PLY of the expanded scene: 62 floats per splat at degree 3 (x y z, nx ny nz,
    // 3 f_dc, 45 f_rest, opacity, 3 scales, 4 rot), fewer at lower degrees; header excluded.
    let floats = 17 + 3 * (scene.background.sh_coeffs() - 1);
    let expanded_ply_bytes = (splats * floats * 4) as u64;
    if json {
        let groups: Vec<_> = scene
            .groups
            .iter()
            .map(|g| {
                serde_json::json!({
                    "name": g.name,
                    "template_gaussians": g.template.len(),
                    "instances": g.instances.iter().map(|i| serde_json::json!({
                        "id": i.id,
                        "transform": instgs_vk::model::instanced::mat4_to_rows(i.transform.to_mat4()),
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        let v = serde_json::json!({
            "file": path.display().to_string(),
            "kind": "instanced",
            "sh_degree": scene.sh_degree,
            "background_gaussians": scene.background.len(),
            "parameter_rows": scene.rows(),
            "splats": splats,
            "groups": groups,
            "parts": parts,
            "file_bytes": bytes.len(),
            "expanded_ply_vertex_bytes": expanded_ply_bytes,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("file          {}", path.display());
        println!("sh degree     {}", scene.sh_degree);
        println!("background    {} Gaussians", scene.background.len());
        for g in &scene.groups {
            println!("group {:?}: {} template Gaussians x {} instances", g.name, g.template.len(), g.instances.len());
            for i in &g.instances {
                let t = i.transform;
                println!(
                    "  instance {:?}: scale {:.4}, translation {}, rotation (w,x,y,z) {:?}",
                    i.id,
                    t.scale,
                    t.translation,
                    t.quat_wxyz()
                );
            }
        }
        println!("splats        {splats} expanded ({} parameter rows)", scene.rows());
        for p in &parts {
            println!("  {:<22} {} bytes", p.name, p.bytes);
        }
        println!("file size     {} bytes (expanded plain PLY: {expanded_ply_bytes} bytes of vertex data)", bytes.len());
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn segment(
    device: Option<String>,
    scene_path: &Path,
    data: &Path,
    split: &str,
    alpha: f32,
    out: &Path,
    export_dir: Option<&Path>,
    per_frame_ids: bool,
) -> Result<()> {
    let is_json = out.extension().and_then(|e| e.to_str()) == Some("json");
    if per_frame_ids && !is_json {
        bail!("{}: with --per-frame-ids the output must be .json (it carries the associated groups)", out.display());
    }
    if !is_json && out.extension().and_then(|e| e.to_str()) != Some("bin") {
        bail!("{}: the output must end in .json or .bin", out.display());
    }
    let scene = instgs_vk::formats::read_scene(scene_path)?;
    let opts = instgs_vk::dataset::LoadOptions { downscale: 1, background: [0.0; 3] };
    let ds = instgs_vk::dataset::load(data, &opts)?;
    let (gpu, k) = open_device(device)?;
    let seg = segment_scene(
        &gpu,
        &k,
        &scene,
        data,
        &ds,
        split,
        alpha,
        per_frame_ids,
        ("segmentation: ", ProgressMode::Auto),
    )?;
    if is_json {
        write_json(out, &seg.doc, false)?;
    } else {
        instgs_vk::util::write_atomic(out, |f| {
            use std::io::Write;
            f.write_all(bytemuck::cast_slice(&seg.labels))
        })?;
    }
    if let Some(dir) = export_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        for id in seg.ids.iter().copied().chain([0]) {
            let part = instgs_vk::segment::subset(&scene, &seg.labels, id);
            let name = if id == 0 { "background.ply".to_string() } else { format!("instance_{id}.ply") };
            if !part.is_empty() {
                instgs_vk::model::scene::write_ply(&part, &dir.join(name))?;
            }
        }
    }
    Ok(())
}

/// Writes `v` as JSON, atomically.
fn write_json(path: &Path, v: &serde_json::Value, pretty: bool) -> Result<()> {
    let text = if pretty { serde_json::to_string_pretty(v)? } else { serde_json::to_string(v)? };
    instgs_vk::util::write_atomic(path, |f| {
        use std::io::Write;
        f.write_all(text.as_bytes())
    })
}

/// A segmentation and what `segment` reports of it.
struct SegmentOutcome {
    /// Instance ids in group order.
    ids: Vec<u32>,
    labels: Vec<u32>,
    /// labels.json: {ids, labels} (and, with per-frame ids, the associated groups).
    doc: serde_json::Value,
    /// {instances: [{group, id, gaussians, test_iou, test_views}], background}.
    summary: serde_json::Value,
    /// Per Gaussian: blending weight summed over the views (`Segmentation::weight`).
    significance: Vec<f32>,
}

/// Segments `scene` with the masks of `ds`'s `split` views (`DIR/masks/<split>/`); prints one
/// line per instance (with the held-out IoU where test masks with global ids exist).
#[allow(clippy::too_many_arguments)]
fn segment_scene(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    scene: &instgs_vk::model::scene::Scene,
    data: &Path,
    ds: &instgs_vk::dataset::Dataset,
    split: &str,
    alpha: f32,
    per_frame_ids: bool,
    progress: (&str, ProgressMode),
) -> Result<SegmentOutcome> {
    use instgs_vk::segment;
    let views = ds.split(split)?;
    let mut masks = segment::load_masks(data, split, views)?;
    let mut members_json = serde_json::Map::new();
    let groups = if per_frame_ids {
        let cats = segment::load_frame_categories(data, split, views, &masks)?;
        let o = segment::AssociateOptions { alpha, ..Default::default() };
        let a = segment::associate(gpu, k, scene, views, &masks, &cats, &o)?;
        let total: usize = a.members.values().map(Vec::len).sum::<usize>() + a.dropped.len();
        println!(
            "association: {} masks of {} views → {} instances in {} groups ({} masks in no instance of ≥ {} views)",
            total,
            views.len(),
            a.members.len(),
            a.groups.len(),
            a.dropped.len(),
            o.min_views
        );
        for (id, ms) in &a.members {
            let list: Vec<serde_json::Value> = ms
                .iter()
                .map(|(v, m)| {
                    let name = views[*v].path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                    serde_json::json!([name, m])
                })
                .collect();
            members_json.insert(id.to_string(), list.into());
        }
        masks = a.masks;
        a.groups
    } else {
        segment::read_groups(&data.join("instances.json"))?
    };
    let ids: Vec<u32> = groups.iter().flat_map(|g| g.ids.iter().copied()).collect();
    let mut bar = Progress::new(progress.0, "view", "views/s", views.len() as u64, 0, progress.1);
    let seg = segment::segment_with_progress(gpu, k, scene, views, &masks, &ids, alpha, |i, _| bar.set(i as u64, ""))?;
    bar.finish();
    if !seg.unknown_ids.is_empty() {
        eprintln!(
            "warning: mask ids {:?} are not in {}; their pixels count as background",
            seg.unknown_ids,
            data.join("instances.json").display()
        );
    }
    let mut doc = serde_json::json!({"ids": seg.ids, "labels": seg.labels});
    if per_frame_ids {
        // A groups file too (`instance --groups`): groups → instances with their masks.
        doc["groups"] = groups
            .iter()
            .map(|g| {
                let inst: Vec<serde_json::Value> = g
                    .ids
                    .iter()
                    .map(|id| serde_json::json!({"id": id, "masks": members_json[&id.to_string()]}))
                    .collect();
                serde_json::json!({"name": g.name, "instances": inst})
            })
            .collect();
    }
    // Held-out views with masks (ids meaningful across frames): the IoU of every instance's
    // rendered visible region.
    let test_masks =
        if ds.test.is_empty() || per_frame_ids { None } else { segment::load_masks(data, "test", &ds.test).ok() };
    let mut rows = Vec::new();
    for g in &groups {
        for &id in &g.ids {
            let n = seg.labels.iter().filter(|&&l| l == id).count();
            let mut row = serde_json::json!({"group": g.name, "id": id, "gaussians": n});
            let iou = match &test_masks {
                Some(m) if !m.is_empty() => {
                    let v = segment::instance_iou(gpu, k, scene, &seg.labels, &ds.test, m, id)?;
                    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
                    row["test_iou"] = mean.into();
                    row["test_views"] = v.len().into();
                    format!("  test IoU {mean:.3} ({} views)", v.len())
                }
                _ => String::new(),
            };
            println!("{} {id}: {n} Gaussians{iou}", g.name);
            rows.push(row);
        }
    }
    let background = seg.labels.iter().filter(|&&l| l == 0).count();
    println!("background: {background} Gaussians");
    let summary = serde_json::json!({"instances": rows, "background": background, "alpha": alpha});
    Ok(SegmentOutcome { ids, labels: seg.labels, doc, summary, significance: seg.weight })
}

/// Chooses the kept background fraction: (scene, labels, significance) → (fraction, ranking
/// per Gaussian, what was decided as JSON).
type KeepRule<'a> =
    dyn FnMut(&instgs_vk::model::scene::Scene, &[u32], &[f32]) -> Result<(f64, Vec<f32>, serde_json::Value)> + 'a;

#[allow(clippy::too_many_arguments)]
fn instance(
    scene_path: &Path,
    labels: &Path,
    groups_path: &Path,
    truth_path: Option<&Path>,
    opts: &instgs_vk::instancing::template::InstanceOptions,
    dtype: instgs::Dtype,
    prune: Option<(&Path, &mut KeepRule)>,
    check: Option<&mut dyn instgs_vk::instancing::template::RenderCheck>,
    report: Option<&Path>,
    out: &Path,
) -> Result<serde_json::Value> {
    use instgs_vk::instancing::template;
    let scene = instgs_vk::formats::read_scene(scene_path)?;
    let labels = template::read_labels(labels, scene.len())?;
    let groups = instgs_vk::segment::read_groups(groups_path)?;
    // Background pruning (the pipeline's `instance.background_keep`): the background Gaussians
    // ranked by `rule` from significance.bin (f32 per Gaussian, written by `segment`) stay.
    let mut pruned = serde_json::Value::Null;
    let (scene, labels) = match prune {
        Some((sig_path, rule)) => {
            let bytes = std::fs::read(sig_path).with_context(|| format!("{}: cannot read", sig_path.display()))?;
            if bytes.len() != 4 * scene.len() {
                bail!("{}: {} bytes, expected 4 per Gaussian ({})", sig_path.display(), bytes.len(), scene.len());
            }
            let sig: Vec<f32> = bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
            let before = labels.iter().filter(|&&l| l == 0).count();
            let (keep, ranking, how) = rule(&scene, &labels, &sig)?;
            let (s, l, dropped) = template::prune_background(&scene, &labels, &ranking, keep)?;
            eprintln!("background: kept {} of {before} Gaussians ({:.1} %)", before - dropped, 100.0 * keep);
            pruned = serde_json::json!({"keep": keep, "before": before, "dropped": dropped, "rule": how});
            (s, l)
        }
        None => (scene, labels),
    };
    let check_ran = check.is_some();
    let (inst, reports) = template::instantiate(&scene, &labels, &groups, opts, check, |line| eprintln!("{line}"))?;
    if instgs_vk::train::INTERRUPTED.load(std::sync::atomic::Ordering::SeqCst) {
        bail!("interrupted before {} was written", out.display());
    }
    instgs::write(&inst, out, dtype)?;
    let truth = match truth_path {
        Some(p) => template::read_ground_truth(p)?,
        None => None,
    };
    let mut rows = Vec::new();
    for r in &reports {
        let mut row = serde_json::json!({
            "group": r.group, "id": r.id, "reference": r.reference, "gaussians": r.gaussians,
            "status": r.status.name(), "reason": r.status.reason(),
            "fitness": r.check.fitness, "fitness_reverse": r.check.fitness_reverse,
            "scale": r.relative.scale, "scale_ratio": r.check.scale_ratio,
            "poses_tried": r.tried, "shape_ambiguous": r.shape_ambiguous,
        });
        let mut line = format!(
            "{} {} ({}): {} Gaussians, fitness {:.2} / {:.2}, scale {:.4}",
            r.group,
            r.id,
            r.status.name(),
            r.gaussians,
            r.check.fitness,
            r.check.fitness_reverse,
            r.relative.scale
        );
        if let Some(s) = &r.render {
            row["render_iou"] = s.iou.into();
            row["render_psnr"] = s.psnr.into();
            row["render_views"] = s.views.into();
            line += &format!(", render IoU {:.2} PSNR {:.1} dB ({} views)", s.iou, s.psnr, s.views);
        }
        if let Some(t) = &truth {
            if let (Some(a), Some(b)) = (t.get(&r.reference), t.get(&r.id)) {
                let (rot, trans, scale) = template::pose_error(&r.relative, a, b);
                line += &format!(
                    "; against {}: rotation {rot:.3}°, translation {:.3} % of the size, scale {:+.3} %",
                    groups_path.display(),
                    100.0 * trans,
                    100.0 * scale
                );
                row["rotation_error_deg"] = rot.into();
                row["translation_error_fraction"] = trans.into();
                row["scale_error_fraction"] = scale.into();
            }
        }
        if let Some(why) = r.status.reason() {
            line += &format!("\n    {}: {why}", r.status.name());
        }
        println!("{line}");
        rows.push(row);
    }
    println!(
        "{}: {} groups, {} template Gaussians, {} background, {} splats ({:?} templates)",
        out.display(),
        inst.groups.len(),
        inst.groups.iter().map(|g| g.template.len()).sum::<usize>(),
        inst.background.len(),
        inst.splats(),
        opts.init
    );
    let v = serde_json::json!({
        "init": format!("{:?}", opts.init).to_lowercase(),
        "colour": opts.use_colour,
        "acceptance": serde_json::to_value(&opts.accept)?,
        "render_check": check_ran,
        "template_gaussians": inst.groups.iter().map(|g| g.template.len()).sum::<usize>(),
        "background_gaussians": inst.background.len(),
        "splats": inst.splats(),
        "background_pruning": pruned,
        "instances": rows,
    });
    if let Some(path) = report {
        write_json(path, &v, true)?;
    }
    Ok(v)
}

fn compose(
    templates: &[String],
    graph: &Path,
    background: Option<&Path>,
    random_offsets: Option<(f32, u64)>,
    dtype: OffsetDtype,
    out: &Path,
) -> Result<()> {
    let mut loaded = Vec::new();
    for t in templates {
        let Some((name, file)) = t.split_once('=') else {
            bail!("--template {t:?}: expected NAME=FILE.ply");
        };
        loaded.push((name.to_string(), instgs_vk::formats::read_scene(Path::new(file))?));
    }
    let graph = instgs_vk::model::instanced::read_scene_graph(graph)?;
    let background = background.map(read_ply).transpose()?;
    let scene = instgs_vk::model::instanced::compose(loaded, graph, background, random_offsets)?;
    instgs::write(&scene, out, dtype.into())?;
    eprintln!(
        "wrote {}: {} groups, {} splats from {} parameter rows",
        out.display(),
        scene.groups.len(),
        scene.splats(),
        scene.rows()
    );
    Ok(())
}

fn convert(path: &Path, out: &Path) -> Result<()> {
    let scene = AnyScene::read(path)?;
    let name = out.file_name().map(|n| n.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    match (&scene, name.ends_with(".json") && !name.ends_with("meta.json")) {
        (AnyScene::Instanced(s), true) => {
            let text = serde_json::to_string_pretty(&instgs_vk::model::instanced::scene_graph(s))?;
            instgs_vk::util::write_atomic(out, |f| {
                use std::io::Write;
                f.write_all(text.as_bytes())
            })?;
        }
        (AnyScene::Plain(_), true) => {
            bail!("{}: a scene graph (.json) comes from an instanced scene; {} is plain", out.display(), path.display())
        }
        (AnyScene::Plain(s), false) => instgs_vk::formats::write_scene(s, out)?,
        (AnyScene::Instanced(s), false) => instgs_vk::formats::write_scene(&s.expand(), out)?,
    }
    eprintln!("wrote {}", out.display());
    Ok(())
}

fn export_cameras(data: &Path, split: &str, out: &Path) -> Result<()> {
    let cams = instgs_vk::dataset::dataset_cameras_with_images(data, split)?;
    if cams.is_empty() {
        bail!("{}: the {split} split has no cameras", data.display());
    }
    let images: Vec<String> = cams
        .iter()
        .map(|(_, p)| std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()).display().to_string())
        .collect();
    let cams: Vec<Camera> = cams.into_iter().map(|(c, _)| c).collect();
    write_json(out, &camera::transforms_json(&cams, &images), true)?;
    eprintln!("wrote {} ({} cameras)", out.display(), cams.len());
    Ok(())
}

fn cameras(view: &ViewArgs, scene: &AnyScene) -> Result<Vec<Camera>> {
    if view.width == Some(0) || view.height == Some(0) {
        bail!("--width and --height must be at least 1");
    }
    let cams = match (&view.cameras, view.orbit) {
        (Some(path), _) => {
            let cams = instgs_vk::dataset::dataset_cameras(path, &view.split)?;
            match (view.width, view.height) {
                (None, None) => cams,
                (w, h) => cams
                    .into_iter()
                    .map(|c| {
                        let (w, h) = (w.unwrap_or(c.width), h.unwrap_or(c.height));
                        c.resized(w, h)
                    })
                    .collect(),
            }
        }
        (None, Some(0)) => bail!("--orbit needs at least 1 camera"),
        (None, Some(n)) => camera::orbit_around_points(
            &scene.means(),
            n,
            view.up,
            view.width.unwrap_or(640),
            view.height.unwrap_or(480),
        ),
        (None, None) => bail!("give --cameras FILE or --orbit N"),
    };
    Ok(cams)
}

/// The scene, its cameras (both checked before the device starts) and the device.
struct Setup {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    scene: AnyScene,
    cams: Vec<Camera>,
}

fn setup(device: Option<String>, view: &ViewArgs) -> Result<Setup> {
    let scene = AnyScene::read(&view.scene)?;
    let cams = cameras(view, &scene)?;
    let gpu = Gpu::new(&GpuOptions::from_env(device))?;
    eprintln!("device: {}", gpu.describe());
    let k = Kernels::new(&gpu)?;
    Ok(Setup { gpu, k, scene, cams })
}

fn render(device: Option<String>, view: &ViewArgs, out: &Path) -> Result<()> {
    let Setup { gpu, k, scene, cams } = setup(device, view)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create folder", out.display()))?;
    let gs = scene.upload(&gpu).with_context(|| view.scene.display().to_string())?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    let mut per_pass: Vec<(String, Vec<f64>)> = Vec::new();
    for cam in &cams {
        let f = r.render(&gs, cam, view.background)?;
        let path = out.join(format!("{}.png", cam.name));
        save_png(&path, f.width, f.height, &f.image)?;
        let total: f64 = f.passes.iter().map(|p| p.1).sum();
        println!(
            "{}  {}x{}  visible {}  intersections {}  gpu {:.2} ms",
            path.display(),
            f.width,
            f.height,
            f.visible,
            f.intersections,
            total
        );
        collect(&mut per_pass, &f.passes);
    }
    print_passes(&per_pass);
    Ok(())
}

fn collect(acc: &mut Vec<(String, Vec<f64>)>, passes: &[(String, f64)]) {
    for (name, ms) in passes {
        match acc.iter_mut().find(|(n, _)| n == name) {
            Some(e) => e.1.push(*ms),
            None => acc.push((name.clone(), vec![*ms])),
        }
    }
}

fn print_passes(per_pass: &[(String, Vec<f64>)]) {
    if per_pass.is_empty() {
        println!("(the device has no timestamps on its compute queue)");
        return;
    }
    println!("per-pass GPU time, median over frames (ms):");
    for (name, v) in per_pass {
        println!("  {name:<12} {:>9.3}", median(v));
    }
}

/// One scene of a bench run: its own rasterizer (buffers sized for it) and samples.
struct BenchScene {
    path: PathBuf,
    scene: AnyScene,
    gs: instgs_vk::render::raster::GpuScene,
    r: Rasterizer,
    per_pass: Vec<(String, Vec<f64>)>,
    frame_ms: Vec<f64>,
    isects: Vec<f64>,
    visible: Vec<f64>,
}

impl BenchScene {
    fn new(
        gpu: &Arc<Gpu>,
        k: &Arc<Kernels>,
        path: &Path,
        scene: AnyScene,
        cfg: &instgs_vk::render::lod::RenderConfig,
    ) -> Result<BenchScene> {
        let gs = scene.upload_for_rendering(gpu, cfg).with_context(|| path.display().to_string())?;
        let r = Rasterizer::new(gpu, k)?;
        Ok(BenchScene {
            path: path.to_path_buf(),
            scene,
            gs,
            r,
            per_pass: Vec::new(),
            frame_ms: Vec::new(),
            isects: Vec::new(),
            visible: Vec::new(),
        })
    }

    fn frame(&mut self, cam: &Camera, background: [f32; 3], timed: bool) -> Result<()> {
        let f = self.r.render_resident(&self.gs, cam, background)?;
        if timed {
            self.frame_ms.push(f.passes.iter().map(|p| p.1).sum::<f64>());
            collect(&mut self.per_pass, &f.passes);
            self.isects.push(f.intersections as f64);
            self.visible.push(f.visible as f64);
        }
        Ok(())
    }

    /// Prints the table and returns the JSON object of this scene.
    fn report(&self) -> Result<serde_json::Value> {
        let fm = median(&self.frame_ms);
        let p90 = percentile(&self.frame_ms, 0.9);
        let file_bytes = std::fs::metadata(&self.path)?.len();
        let sorts = sort_comparison(&self.r, &self.per_pass)?;
        println!("scene            {}", self.path.display());
        println!("splats           {}", self.scene.splats());
        println!("visible (median) {}", median(&self.visible));
        println!("intersections    {}", median(&self.isects));
        println!("frame (median)   {fm:.3} ms  ({:.1} FPS); p90 {p90:.3} ms", 1000.0 / fm);
        println!("scene GPU bytes  {}", self.gs.gpu_bytes());
        println!("frame GPU bytes  {}", self.r.frame_gpu_bytes());
        println!("file bytes       {file_bytes}");
        print_passes(&self.per_pass);
        println!("GPU sort vs sort_unstable on the last frame's own keys (ms):");
        for c in &sorts {
            println!(
                "  {:<11} {:>8} keys  GPU {:>8.2}  sort_unstable {:>7.2}  ratio {:.2}x",
                c.name,
                c.keys,
                c.gpu_ms,
                c.cpu_ms,
                c.gpu_ms / c.cpu_ms
            );
        }
        let passes: serde_json::Map<String, serde_json::Value> =
            self.per_pass.iter().map(|(n, v)| (n.clone(), serde_json::json!(median(v)))).collect();
        Ok(serde_json::json!({
            "scene": self.path.display().to_string(),
            "splats": self.scene.splats(),
            "visible": median(&self.visible),
            "intersections": median(&self.isects),
            "frame_ms_median": fm,
            "frame_ms_p90": p90,
            "fps_median": 1000.0 / fm,
            "scene_gpu_bytes": self.gs.gpu_bytes(),
            "frame_gpu_bytes": self.r.frame_gpu_bytes(),
            "file_bytes": file_bytes,
            "passes": passes,
            "sorts": sorts.iter().map(|c| serde_json::json!({
                "name": c.name, "keys": c.keys, "gpu_ms": c.gpu_ms, "sort_unstable_ms": c.cpu_ms,
                "ratio": c.gpu_ms / c.cpu_ms,
            })).collect::<Vec<_>>(),
        }))
    }
}

/// Median over i of a[i] / b[i].
fn paired_median(a: &[f64], b: &[f64]) -> f64 {
    median(&a.iter().zip(b).map(|(x, y)| x / y).collect::<Vec<_>>())
}

/// 2×2 box filter of a (2w)×(2h) image.
fn box_down2(img: &[[f32; 4]], w: usize, h: usize) -> Vec<[f32; 4]> {
    let mut out = vec![[0.0f32; 4]; w * h];
    for y in 0..h {
        for x in 0..w {
            let px = |dx: usize, dy: usize| img[(2 * y + dy) * 2 * w + 2 * x + dx];
            let s = [px(0, 0), px(1, 0), px(0, 1), px(1, 1)];
            out[y * w + x] = std::array::from_fn(|c| 0.25 * s.iter().map(|p| p[c]).sum::<f32>());
        }
    }
    out
}

/// The process's resident set (Linux /proc/self/status VmRSS), if known.
fn cpu_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

#[allow(clippy::too_many_arguments)]
fn bench(
    device: Option<String>,
    view: &ViewArgs,
    frames: usize,
    warmup: usize,
    cfg: &instgs_vk::render::lod::RenderConfig,
    compare: Option<(&Path, instgs_vk::render::lod::RenderConfig)>,
    json: Option<&Path>,
) -> Result<()> {
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    let Setup { gpu, k, scene, cams } = setup(device, view)?;
    let b = compare.map(|(p, c)| AnyScene::read(p).map(|s| (p, s, c))).transpose()?;
    let v = bench_scenes(
        &gpu,
        &k,
        (&view.scene, scene, cfg),
        b,
        &cams,
        (frames, warmup),
        view.background,
        ("bench: ", ProgressMode::Auto),
    )?;
    if let Some(path) = json {
        write_json(path, &v, true)?;
    }
    Ok(())
}

/// Renders scene A (and B, interleaved A B A B …) from `cams`, prints the tables and returns
/// the JSON report (A's numbers; with B also `compare`, `ratios` A over B and image agreement).
#[allow(clippy::too_many_arguments)]
fn bench_scenes(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    a: (&Path, AnyScene, &instgs_vk::render::lod::RenderConfig),
    b: Option<(&Path, AnyScene, instgs_vk::render::lod::RenderConfig)>,
    cams: &[Camera],
    (frames, warmup): (usize, usize),
    background: [f32; 3],
    progress: (&str, ProgressMode),
) -> Result<serde_json::Value> {
    let cfg = a.2;
    let mut runs = vec![BenchScene::new(gpu, k, a.0, a.1, cfg)?];
    if let Some((p, scene, bcfg)) = b {
        runs.push(BenchScene::new(gpu, k, p, scene, &bcfg)?);
    }
    // Interleaved (A B A B …) so that clock and thermal drift hit both scenes alike.
    let mut bar = Progress::new(progress.0, "view", "views/s", cams.len() as u64, 0, progress.1);
    for (i, cam) in cams.iter().enumerate() {
        for _ in 0..warmup {
            for run in runs.iter_mut() {
                run.frame(cam, background, false)?;
            }
        }
        for _ in 0..frames {
            for run in runs.iter_mut() {
                run.frame(cam, background, true)?;
            }
        }
        bar.set(i as u64 + 1, "");
    }
    bar.finish();
    let mut reports = Vec::new();
    for (i, run) in runs.iter().enumerate() {
        if i > 0 {
            println!();
        }
        reports.push(run.report()?);
    }
    let rss = cpu_rss_bytes();
    println!();
    println!("allocator bytes  {} (everything the allocator holds)", gpu.allocated_bytes());
    if let Some(rss) = rss {
        println!("CPU RSS          {rss} bytes (the process)");
    }
    let mut v = reports[0].clone();
    v["device"] = gpu.info.name.clone().into();
    v["width"] = cams[0].width.into();
    v["height"] = cams[0].height.into();
    v["views"] = cams.len().into();
    v["frames"] = frames.into();
    v["allocated_gpu_bytes"] = gpu.allocated_bytes().into();
    v["cpu_rss_bytes"] = rss.into();
    if let Some(b) = reports.get(1) {
        let ratio = |key: &str| {
            let (x, y) = (reports[0][key].as_f64().unwrap_or(f64::NAN), b[key].as_f64().unwrap_or(f64::NAN));
            x / y
        };
        let ratios = serde_json::json!({
            // Timing ratios pair each frame of A with the frame of B rendered right after it
            // (same camera, same machine state) and take the median of those ratios.
            "fps": paired_median(&runs[1].frame_ms, &runs[0].frame_ms),
            "frame_ms": paired_median(&runs[0].frame_ms, &runs[1].frame_ms),
            "scene_gpu_bytes": ratio("scene_gpu_bytes"),
            "frame_gpu_bytes": ratio("frame_gpu_bytes"),
            "file_bytes": ratio("file_bytes"),
            "intersections": ratio("intersections"),
        });
        println!(
            "A over B: FPS {:.3}x (median of paired frames), scene GPU bytes {:.3}x, file bytes {:.3}x, frame GPU bytes {:.3}x ({} interleaved frames each)",
            ratios["fps"].as_f64().unwrap_or(f64::NAN),
            ratios["scene_gpu_bytes"].as_f64().unwrap_or(f64::NAN),
            ratios["file_bytes"].as_f64().unwrap_or(f64::NAN),
            ratios["frame_gpu_bytes"].as_f64().unwrap_or(f64::NAN),
            runs[0].frame_ms.len()
        );
        v["compare"] = b.clone();
        v["ratios"] = ratios;
        // Image agreement, outside the timed frames: A's frames against B's, and both against
        // an antialiased reference, B rendered at twice the resolution and box-filtered 2×2.
        // Identical images count as 100 dB.
        let db = |a: &[[f32; 4]], b: &[[f32; 4]]| instgs_vk::util::psnr(a, b).min(100.0);
        let (mut ab, mut a_ref, mut b_ref) = (Vec::new(), Vec::new(), Vec::new());
        if let [a, b] = &mut runs[..] {
            for cam in cams {
                let fa = a.r.render(&a.gs, cam, background)?;
                let fb = b.r.render(&b.gs, cam, background)?;
                let big = b.r.render(&b.gs, &cam.resized(2 * cam.width, 2 * cam.height), background)?;
                let reference = box_down2(&big.image, cam.width as usize, cam.height as usize);
                ab.push(db(&fa.image, &fb.image));
                a_ref.push(db(&fa.image, &reference));
                b_ref.push(db(&fb.image, &reference));
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let worst = ab.iter().copied().fold(f64::INFINITY, f64::min);
        println!("A against B: PSNR {:.2} dB mean, {worst:.2} dB worst view", mean(&ab));
        println!(
            "against B at 2x resolution, box-filtered: A {:.2} dB, B {:.2} dB (A - B {:+.2} dB)",
            mean(&a_ref),
            mean(&b_ref),
            mean(&a_ref) - mean(&b_ref)
        );
        v["psnr_a_vs_b"] = serde_json::json!({ "mean": mean(&ab), "min": worst, "views": ab });
        v["psnr_vs_reference"] = serde_json::json!({ "a": mean(&a_ref), "b": mean(&b_ref) });
    }
    v["render"] = serde_json::to_value(cfg)?;
    Ok(v)
}

/// Median milliseconds of Rust's sort_unstable on (key, value) pairs, by key.
fn time_sort_unstable(keys: &[u32], vals: &[u32], repeats: usize) -> f64 {
    let mut times = Vec::new();
    for _ in 0..repeats.max(1) {
        let mut pairs: Vec<(u32, u32)> = keys.iter().copied().zip(vals.iter().copied()).collect();
        let t = std::time::Instant::now();
        pairs.sort_unstable_by_key(|p| p.0);
        times.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(&pairs);
    }
    median(&times)
}

struct SortComparison {
    name: &'static str,
    keys: usize,
    gpu_ms: f64,
    cpu_ms: f64,
}

/// The GPU's depth and tile sorts (median pass times) against Rust's sort_unstable of the same
/// (key, value) pairs, rebuilt from the last frame's GPU state in the order the GPU sorted them.
fn sort_comparison(r: &Rasterizer, per_pass: &[(String, Vec<f64>)]) -> Result<Vec<SortComparison>> {
    use instgs_vk::render::reference;
    let st = r.read_state()?;
    let proj = st.projected;
    let depth_ids: Vec<u32> = (0..proj.depths.len() as u32).filter(|&i| proj.tiles_touched[i as usize] > 0).collect();
    let depth_keys: Vec<u32> = depth_ids.iter().map(|&i| proj.depths[i as usize].to_bits()).collect();
    let fp = r.last_frame_params().ok_or_else(|| anyhow!("no frame rendered"))?;
    let (tile_keys, tile_ids) = reference::forward::emit(&fp, &proj, &st.depth_ids);
    let gpu = |name: &str| per_pass.iter().find(|(n, _)| n == name).map_or(f64::NAN, |(_, v)| median(v));
    Ok(vec![
        SortComparison {
            name: "depth_sort",
            keys: depth_keys.len(),
            gpu_ms: gpu("depth_sort"),
            cpu_ms: time_sort_unstable(&depth_keys, &depth_ids, 5),
        },
        SortComparison {
            name: "tile_sort",
            keys: tile_keys.len(),
            gpu_ms: gpu("tile_sort"),
            cpu_ms: time_sort_unstable(&tile_keys, &tile_ids, 5),
        },
    ])
}

fn bench_sort(device: Option<String>, n: usize, bits: u32, repeats: usize) -> Result<()> {
    if n == 0 || !(1..=32).contains(&bits) {
        bail!("--keys must be at least 1 and --bits in 1..32");
    }
    let gpu = Gpu::new(&GpuOptions::from_env(device))?;
    eprintln!("device: {}", gpu.describe());
    let k = Kernels::new(&gpu)?;
    // A fixed xorshift stream: the same keys every run.
    let mut s = 0x9e37_79b9_7f4a_7c15u64;
    let mask = if bits == 32 { u32::MAX } else { (1u32 << bits) - 1 };
    let keys: Vec<u32> = (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 32) as u32 & mask
        })
        .collect();
    let vals: Vec<u32> = (0..n as u32).collect();
    let mut sorter = instgs_vk::render::sort::GpuSort::new(&gpu, &k, n)?;
    let sorted = sorter.sort(&keys, &vals, bits, repeats)?;
    let gpu_ms = sorted.gpu_ms.ok_or_else(|| anyhow!("the device has no timestamps"))?;
    let cpu_ms = time_sort_unstable(&keys, &vals, repeats);
    println!("keys {n}, bits {bits}: GPU radix sort {gpu_ms:.2} ms, sort_unstable (key,value) {cpu_ms:.2} ms, GPU/CPU {:.2}x", gpu_ms / cpu_ms);
    Ok(())
}
