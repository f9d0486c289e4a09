//! Frames to files: the cameras of `render` and `bench` (a dataset, a transforms file or an
//! orbit), rendering them to PNGs, and per-pass GPU times.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::{Gpu, GpuOptions};
use crate::math::median;
use crate::model::camera::{self, Camera, UpAxis};
use crate::render::raster::{Forward, Rasterizer};
use crate::util::save_png;

/// What `render` and `bench` draw: a scene from a set of cameras over a background colour.
pub struct FrameSpec {
    /// Scene file (any format `formats::detect` knows).
    pub scene: PathBuf,
    /// A transforms_*.json file, a NeRF-synthetic folder or a COLMAP folder.
    pub cameras: Option<PathBuf>,
    /// Which cameras of a dataset folder: train, test or all.
    pub split: String,
    /// Else N cameras on an orbit around the scene's robust bounds.
    pub orbit: Option<usize>,
    /// The world's up axis, for orbits.
    pub up: UpAxis,
    /// Image size (default: the camera file's; 640×480 for orbits); intrinsics are scaled.
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Linear RGB in [0, 1].
    pub background: [f32; 3],
    /// How the depth-sorted splats become pixels.
    pub forward: Forward,
}

/// The cameras of `view` (checked before any device starts).
pub fn cameras(view: &FrameSpec, scene: &AnyScene) -> Result<Vec<Camera>> {
    if view.width == Some(0) || view.height == Some(0) {
        bail!("--width and --height must be at least 1");
    }
    let cams = match (&view.cameras, view.orbit) {
        (Some(path), _) => {
            let cams = crate::dataset::dataset_cameras(path, &view.split)?;
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
        (None, Some(n)) => camera::scene_orbit(
            &scene.means(),
            n,
            view.up,
            view.width.unwrap_or(640),
            view.height.unwrap_or(480),
            &view.scene.display().to_string(),
        )?,
        (None, None) => bail!("give --cameras FILE or --orbit N"),
    };
    Ok(cams)
}

/// The scene, its cameras (both checked before the device starts) and the device.
pub struct Setup {
    pub gpu: Arc<Gpu>,
    pub k: Arc<Kernels>,
    pub scene: AnyScene,
    pub cams: Vec<Camera>,
}

/// Reads the scene and its cameras, then opens the device.
pub fn setup(device: Option<String>, view: &FrameSpec) -> Result<Setup> {
    let scene = AnyScene::read(&view.scene)?;
    let cams = cameras(view, &scene)?;
    let gpu = Gpu::new(&GpuOptions::from_env(device))?;
    eprintln!("device: {}", gpu.describe());
    let k = Kernels::new(&gpu)?;
    Ok(Setup { gpu, k, scene, cams })
}

/// `instgs-vk render`: one PNG per camera into `out`, a line per frame, per-pass medians.
pub fn render(device: Option<String>, view: &FrameSpec, out: &Path) -> Result<()> {
    let Setup { gpu, k, scene, cams } = setup(device, view)?;
    unique_names(cams.iter().map(|c| c.name.as_str()), view.cameras.as_deref().unwrap_or(&view.scene))?;
    let gs = scene.upload(&gpu).with_context(|| view.scene.display().to_string())?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    r.set_forward(view.forward)?;
    let mut per_pass: Vec<(String, Vec<f64>)> = Vec::new();
    // Into a temporary sibling folder, moved into `out` once every frame is written.
    crate::util::write_dir_atomic(out, None, |tmp| {
        for cam in &cams {
            let f = r.render(&gs, cam, view.background)?;
            save_png(&tmp.join(format!("{}.png", cam.name)), f.width, f.height, &f.image)?;
            let path = out.join(format!("{}.png", cam.name));
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
        Ok(())
    })?;
    print_passes(&per_pass);
    Ok(())
}

/// Appends one frame's pass times to per-pass lists.
pub fn collect(acc: &mut Vec<(String, Vec<f64>)>, passes: &[(String, f64)]) {
    for (name, ms) in passes {
        match acc.iter_mut().find(|(n, _)| n == name) {
            Some(e) => e.1.push(*ms),
            None => acc.push((name.clone(), vec![*ms])),
        }
    }
}

/// Prints the median of every pass.
pub fn print_passes(per_pass: &[(String, Vec<f64>)]) {
    if per_pass.is_empty() {
        println!("(the device has no timestamps on its compute queue)");
        return;
    }
    println!("per-pass GPU time, median over frames (ms):");
    for (name, v) in per_pass {
        println!("  {name:<12} {:>9.3}", median(v));
    }
}

/// Refuses camera names that would write one file twice (`<name>.png` per camera): two frames
/// of `source` with one image basename in different folders, say.
pub fn unique_names<'a>(names: impl Iterator<Item = &'a str>, source: &Path) -> Result<()> {
    let mut seen = std::collections::BTreeSet::new();
    for n in names {
        if !seen.insert(n) {
            bail!(
                "{}: two cameras are named {n:?}; their pictures would overwrite each other (rename one image)",
                source.display()
            );
        }
    }
    Ok(())
}
