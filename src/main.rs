//! The `instgs-vk` command line: argument parsing and dispatch only; every command's work is in
//! the library (`instgs_vk`), in the module of its stage.
use std::process::ExitCode;

use anyhow::Result;
use clap::error::ErrorKind;
use clap::Parser;

mod cli;
use cli::{Cli, Cmd};
#[cfg(feature = "player")]
use instgs_vk::player;
use instgs_vk::render::lod::RenderConfig;
use instgs_vk::{bench, dataset, formats, instancing, pipeline, render, segment, train};

fn main() -> ExitCode {
    // Output piped into a reader that stops early (`| head`) ends the process quietly, as
    // Unix tools do, instead of a panic in println!.
    #[cfg(unix)]
    // SAFETY: setting a signal disposition to SIG_DFL before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        // A value out of its range is bad input like any other: exit status 1, as the checks
        // after parsing give. Usage errors (an unknown flag, a missing argument) keep clap's 2;
        // --help and --version print and exit 0.
        Err(e) if matches!(e.kind(), ErrorKind::ValueValidation | ErrorKind::InvalidValue) => {
            let _ = e.print();
            return ExitCode::FAILURE;
        }
        Err(e) => e.exit(),
    };
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", instgs_vk::util::one_line(&format!("{e:#}")));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let device = cli.device;
    formats::spz::set_frame(cli.spz_frame);
    instgs_vk::limits::set(instgs_vk::limits::Limits {
        allow_outside: cli.allow_outside_paths,
        max_memory: cli.max_memory.unwrap_or_else(instgs_vk::limits::default_budget),
    });
    match cli.cmd {
        Cmd::Info { scene, json } => formats::info::info(&scene, json),
        Cmd::Render { view, out } => render::frames::render(device, &view.spec(), &out),
        Cmd::Bench { view, frames, warmup, compare, json, render, compare_exact, compare_forward } => {
            let cfg = render.load()?;
            let spec = view.spec();
            let b_cfg = if compare_exact { cfg.clone().exact() } else { cfg.clone() };
            let b = match (compare.as_deref(), compare_forward) {
                (Some(p), f) => Some((p, b_cfg, f.unwrap_or(spec.forward))),
                (None, Some(f)) => Some((spec.scene.as_path(), b_cfg, f)),
                (None, None) => None,
            };
            bench::bench(device, &spec, (frames, warmup), &cfg, b, json.as_deref())
        }
        Cmd::Compose { templates, scene_graph, background, random_offsets, seed, offset_dtype, out } => {
            instancing::build::compose(
                &templates,
                &scene_graph,
                background.as_deref(),
                random_offsets.map(|s| (s, seed)),
                offset_dtype.into(),
                &out,
            )
        }
        Cmd::Convert { scene, out, expand, quantize, compress } => {
            let accessors =
                if quantize { formats::gltf::Accessors::Quantized } else { formats::gltf::Accessors::Float };
            formats::convert(&scene, &out, expand, accessors, compress)
        }
        Cmd::Cameras { data, split, out } => dataset::export_cameras(&data, &split, &out),
        Cmd::Segment { scene, data, split, alpha, out, export_dir, per_frame_ids } => {
            segment::run::segment(device, &scene, &data, &split, alpha, &out, export_dir.as_deref(), per_frame_ids)
        }
        Cmd::Instance(args) => instance(device, args),
        Cmd::Discover(args) => discover(device, args),
        #[cfg(feature = "player")]
        Cmd::View(args) => view(device, args),
        Cmd::BenchSort { keys, bits, repeats } => bench::bench_sort(device, keys, bits, repeats),
        Cmd::Train(args) => train(device, args),
        Cmd::Curve(args) => curve(device, args),
        Cmd::Eval { scene, data, split, json, out, background, lod, render_config } => {
            let render = lod.then(|| RenderConfig::load(render_config.as_deref())).transpose()?;
            train::eval::eval(
                device,
                &scene,
                &data.data,
                data.downscale,
                &split,
                json,
                out.as_deref(),
                background,
                render.as_ref(),
            )
        }
    }
}

fn instance(device: Option<String>, args: cli::InstanceArgs) -> Result<()> {
    let cli::InstanceArgs {
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
        no_synchronise,
        instances,
        neighbours,
        min_fitness,
        scale_tolerance,
        min_render_iou,
        min_render_psnr,
        min_render_views,
        out,
    } = args;
    let accept = instgs_vk::instancing::options::Acceptance {
        min_fitness,
        scale_tolerance,
        min_render_iou,
        min_render_psnr,
        min_render_views,
        ..Default::default()
    };
    let opts = instgs_vk::instancing::options::InstanceOptions {
        init,
        with_scale: !rigid,
        use_colour: !geometry_only,
        colour_weight,
        seed,
        accept,
        synchronise: !no_synchronise,
        neighbours,
        only: instances.map(|v| v.into_iter().collect()),
        ..Default::default()
    };
    let req = instancing::build::InstanceRequest {
        scene,
        labels,
        data,
        groups,
        opts,
        offset_dtype: offset_dtype.into(),
        report,
        downscale,
        render_check: !no_render_check,
        out,
    };
    instancing::build::instance_command(device, &req)
}

fn discover(device: Option<String>, args: cli::DiscoverArgs) -> Result<()> {
    let cli::DiscoverArgs {
        scene,
        data,
        example,
        bbox,
        auto,
        labels,
        view,
        mask_id,
        downscale,
        no_render_check,
        seed,
        out,
        groups,
    } = args;
    use instgs_vk::discover::run::{discover_command, DiscoverRequest, ExampleSpec};
    let example = match (example, bbox, auto) {
        (_, _, true) => ExampleSpec::Auto,
        (_, Some(b), _) => ExampleSpec::Box(cli::parse_box(&b).map_err(anyhow::Error::msg)?),
        (Some(e), None, false) => match (e.parse::<u32>(), labels) {
            (Ok(id), Some(labels)) => ExampleSpec::Label { labels, id },
            (Ok(_), None) => anyhow::bail!("--example {e}: a label id needs --labels FILE"),
            (Err(_), _) => ExampleSpec::Mask { path: e.into(), view, id: mask_id },
        },
        (None, None, false) => anyhow::bail!("discover needs --example, --box or --auto"),
    };
    let mut opts = instgs_vk::discover::DiscoverOptions::default();
    opts.instance.seed = seed;
    let groups = groups.unwrap_or_else(|| out.with_file_name("groups.json"));
    let req = DiscoverRequest { scene, data, example, opts, render_check: !no_render_check, downscale, out, groups };
    discover_command(device, &req).map(|_| ())
}

#[cfg(feature = "player")]
fn view(device: Option<String>, args: cli::PlayerArgs) -> Result<()> {
    let cli::PlayerArgs {
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
        forward,
    } = args;
    let opts = player::PlayerOptions {
        render: render.load()?,
        forward,
        scene_path: scene,
        device,
        width,
        height,
        background,
        vsync,
        overlay: !no_overlay,
        frames,
        out,
    };
    player::view(opts, cameras.as_deref(), (camera, &split), up, headless)
}

fn curve(device: Option<String>, args: cli::CurveArgs) -> Result<()> {
    let cli::CurveArgs { data, out, config, budgets, quiet } = args;
    let run = pipeline::PipelineArgs {
        data: data.data,
        downscale: data.downscale,
        out,
        init: None,
        config,
        iterations: None,
        from: None,
        until: None,
        discover: None,
        pruned_baseline: true,
        progress: !quiet,
        device,
    };
    pipeline::curve::curve(pipeline::curve::CurveArgs { run, budgets })
}

fn train(device: Option<String>, args: cli::TrainArgs) -> Result<()> {
    let cli::TrainArgs {
        data,
        out,
        init,
        config,
        iterations,
        resume,
        quiet,
        from,
        until,
        discover,
        no_pruned_baseline,
    } = args;
    let args = pipeline::PipelineArgs {
        data: data.data,
        downscale: data.downscale,
        out,
        init,
        config,
        iterations,
        from,
        until,
        discover,
        pruned_baseline: !no_pruned_baseline,
        progress: !quiet,
        device,
    };
    pipeline::train(args, resume)
}
