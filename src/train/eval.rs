//! `instgs-vk eval`: held-out PSNR and SSIM of a scene, per view and mean, with optional
//! comparison pictures.
use crate::dataset::View;
use crate::render::upload::GpuScene;
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
    // A run's scene renders the light at the lens's centre; its photos went through the lens.
    let vignetting = crate::train::appearance::vignetting_beside(scene_path)?;
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
    if out.is_some() {
        crate::render::frames::unique_names(views.iter().map(|v| v.camera.name.as_str()), data)?;
    }
    let mut bar = Progress::new("eval: ", "view", "views/s", views.len() as u64, 0, ProgressMode::Auto);
    let mut done = 0;
    let mut score = |dir: Option<&Path>| {
        evaluate(&mut r, &gs, views, background, &vignetting, |v, f, _| {
            done += 1;
            bar.set(done, "");
            let Some(dir) = dir else { return Ok(()) };
            save_png(&dir.join(format!("{}.png", v.camera.name)), f.width, f.height, &f.image)?;
            let err = crate::util::error_image(&f.image, &v.image);
            let cmp = crate::util::side_by_side(&[&v.image, &f.image, &err], f.width as usize, f.height as usize);
            save_png(&dir.join(format!("{}_compare.png", v.camera.name)), 3 * f.width, f.height, &cmp)
        })
    };
    // Pictures into a temporary sibling folder, moved into `out` when all are written.
    let e = match out {
        Some(dir) => {
            let mut e = None;
            crate::util::write_dir_atomic(dir, None, |tmp| {
                e = Some(score(Some(tmp))?);
                Ok(())
            })?;
            e.expect("evaluated")
        }
        None => score(None)?,
    };
    bar.finish();
    if json {
        let views: Vec<_> = e.views.iter().map(ViewScore::json).collect();
        let v = serde_json::json!({
            "scene": scene_path.display().to_string(),
            "data": data.display().to_string(),
            "split": split,
            "psnr_mean": e.psnr,
            "ssim_mean": e.ssim,
            "psnr_compensated_mean": e.psnr_compensated,
            "ssim_compensated_mean": e.ssim_compensated,
            "compensated": COMPENSATED_NOTE,
            "vignetting": {"k1": vignetting[0], "k2": vignetting[1]},
            "views": views,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        if vignetting != crate::render::appearance::NO_VIGNETTING {
            println!(
                "renders seen through the lens's vignetting the run learned (k1 = {:.4}, k2 = {:.4}; {} beside the scene)",
                vignetting[0],
                vignetting[1],
                crate::train::appearance::APPEARANCE_FILE
            );
        }
        println!("{:<24} {:>22}  {:>22}", "", "raw (whole image)", "compensated (right half)");
        for v in &e.views {
            println!(
                "{:<24} PSNR {:7.3} dB SSIM {:.4}  PSNR {:7.3} dB SSIM {:.4}",
                v.name, v.psnr, v.ssim, v.psnr_compensated, v.ssim_compensated
            );
        }
        println!(
            "{:<24} PSNR {:7.3} dB SSIM {:.4}  PSNR {:7.3} dB SSIM {:.4}  ({} views)",
            "mean",
            e.psnr,
            e.ssim,
            e.psnr_compensated,
            e.ssim_compensated,
            e.views.len()
        );
    }
    Ok(())
}

/// What the compensated scores are, in the JSON outputs.
pub const COMPENSATED_NOTE: &str =
    "the photo's colour transform (3x4 affine) fitted on its left half, PSNR/SSIM on its right half (Hierarchical 3DGS's protocol)";

/// PSNR and SSIM of one view: raw (the render as it is, the whole image) and compensated (the
/// photo's colour transform fitted on its left half, both measured on its right half:
/// crate::render::appearance::compensated_scores).
#[derive(Clone, Debug, PartialEq)]
pub struct ViewScore {
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
    pub psnr_compensated: f64,
    pub ssim_compensated: f64,
}

/// Mean scores over views, and each view's.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub psnr: f64,
    pub ssim: f64,
    pub psnr_compensated: f64,
    pub ssim_compensated: f64,
    pub views: Vec<ViewScore>,
}

impl ViewScore {
    /// The view's entry of an `eval.json` / `eval --json`.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "name": self.name, "psnr": self.psnr, "ssim": self.ssim,
            "psnr_compensated": self.psnr_compensated, "ssim_compensated": self.ssim_compensated,
        })
    }
}

/// Renders `views` from `scene` and scores them against their images, each render seen through
/// the lens's `vignetting` (crate::render::appearance; none for renders); `each` sees every
/// rendered frame as rendered (for writing pictures) and the image scored (through the lens).
pub fn evaluate(
    raster: &mut Rasterizer,
    scene: &GpuScene,
    views: &[View],
    background: [f32; 3],
    vignetting: &crate::render::appearance::Vignetting,
    mut each: impl FnMut(&View, &crate::render::raster::Frame, &[[f32; 4]]) -> Result<()>,
) -> Result<Evaluation> {
    let mut per = Vec::new();
    for v in views {
        let f = raster.render(scene, &v.camera, background)?;
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let photo = crate::render::appearance::vignette(vignetting, &v.camera, &f.image);
        let a: Vec<[f64; 3]> = photo.iter().map(|p| [0, 1, 2].map(|c| p[c].clamp(0.0, 1.0) as f64)).collect();
        let b: Vec<[f64; 3]> = v.image.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        let (psnr_compensated, ssim_compensated) =
            crate::render::appearance::compensated_scores(&photo, &v.image, w, h);
        per.push(ViewScore {
            name: v.camera.name.clone(),
            psnr: crate::util::psnr(&photo, &v.image),
            ssim: crate::render::reference::backward::ssim(&a, &b, w, h),
            psnr_compensated,
            ssim_compensated,
        });
        each(v, &f, &photo)?;
    }
    let n = per.len().max(1) as f64;
    let mean = |f: fn(&ViewScore) -> f64| per.iter().map(f).sum::<f64>() / n;
    Ok(Evaluation {
        psnr: mean(|p| p.psnr),
        ssim: mean(|p| p.ssim),
        psnr_compensated: mean(|p| p.psnr_compensated),
        ssim_compensated: mean(|p| p.ssim_compensated),
        views: per,
    })
}
