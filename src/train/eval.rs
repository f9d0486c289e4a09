//! `instgs-vk eval`: held-out PSNR and SSIM of a scene, per view and mean, with optional
//! comparison pictures.
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::formats::AnyScene;
use crate::gpu::kernels::open_device;
use crate::render::raster::Rasterizer;
use crate::util::{save_png, Progress, ProgressMode};

#[allow(clippy::too_many_arguments)]
/// Prints (or, with `json`, writes to stdout) the PSNR and SSIM of `scene_path` on `data`'s `split`;
/// `out` receives each render and a ground truth | render | error strip.
pub fn eval(
    device: Option<String>,
    scene_path: &Path,
    data: &Path,
    downscale: u32,
    split: &str,
    json: bool,
    out: Option<&Path>,
    background: [f32; 3],
    render: Option<&crate::render::lod::RenderConfig>,
) -> Result<()> {
    let scene = AnyScene::read(scene_path)?;
    let opts = crate::dataset::LoadOptions { downscale, background };
    let ds = crate::dataset::load(data, &opts)?;
    let views = ds.split(split)?;
    if views.is_empty() {
        bail!("{}: the {split} split has no views", data.display());
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
    let e = crate::train::evaluate(&mut r, &gs, views, background, |v, f| {
        done += 1;
        bar.set(done, "");
        let Some(dir) = out else { return Ok(()) };
        save_png(&dir.join(format!("{}.png", v.camera.name)), f.width, f.height, &f.image)?;
        let err = crate::util::error_image(&f.image, &v.image);
        let cmp = crate::util::side_by_side(&[&v.image, &f.image, &err], f.width as usize, f.height as usize);
        save_png(&dir.join(format!("{}_compare.png", v.camera.name)), 3 * f.width, f.height, &cmp)
    })?;
    bar.finish();
    if json {
        let views: Vec<_> =
            e.views.iter().map(|v| serde_json::json!({"name": v.name, "psnr": v.psnr, "ssim": v.ssim})).collect();
        let v = serde_json::json!({
            "scene": scene_path.display().to_string(),
            "data": data.display().to_string(),
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
