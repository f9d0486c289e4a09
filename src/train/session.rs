//! One training session as `instgs-vk train` runs it without instance masks: the config, the
//! dataset, the device, Ctrl-C, the run and its one-line summary.
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::formats::instgs;
use crate::gpu::kernels::open_device;

#[allow(clippy::too_many_arguments)]
/// Trains `data` into `out` (plain 3DGS, or joint InstGS optimisation from an `.instgs` `init`);
/// `resume` continues from the checkpoint in `out`.
pub fn train(
    device: Option<String>,
    data: &Path,
    downscale: u32,
    out: &Path,
    init: Option<&Path>,
    config: Option<&Path>,
    iterations: Option<u64>,
    resume: bool,
    quiet: bool,
) -> Result<()> {
    use crate::train;
    let init = init.map(instgs::read).transpose()?;
    let ckpt = train::checkpoint_path(out);
    let instanced =
        init.is_some() || (resume && train::read_checkpoint(&ckpt).is_ok_and(|(st, _)| st.layout.is_some()));
    let mut cfg = if instanced {
        crate::train::config::Config::load_instanced(config)?
    } else {
        crate::train::config::Config::load(config)?
    };
    if let Some(n) = iterations {
        cfg.iterations = n;
    }
    let opts = crate::dataset::LoadOptions { downscale, background: cfg.background };
    let ds = crate::dataset::load(data, &opts)?;
    let what = ds.describe(data)?;
    let (gpu, k) = open_device(device)?;
    eprintln!("{}: {what}; {}", data.display(), gpu.describe());
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
