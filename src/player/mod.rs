//! `instgs-vk view`: the standalone player. A winit window with a Vulkan swapchain; every frame
//! replays the rasterizer's recorded command buffer (the image stays on the device), then
//! `present.comp` packs the image (plus the text overlay) into 8-bit texels that are copied into
//! the acquired swapchain image. Vsync is off by default (immediate, else mailbox, else FIFO).
//!
//! Controls: left drag orbits the target, right drag looks around (fly), middle drag pans, the
//! wheel dollies, W/A/S/D move, Q/E go down/up (Shift: 4× faster), R resets the camera, B cycles
//! the background, L toggles template level of detail (instanced scenes uploaded with it), H
//! hides the overlay, V toggles vsync, P or F12 saves a screenshot (the presented swapchain
//! image), F1 lists the keys, Esc quits.
//!
//! Editing an instanced scene ([`editor`]): a click selects the instance under the cursor (boxed
//! in the overlay; a click on the background clears the selection), dragging the selection moves
//! it on the horizontal plane through its centre (Shift when the drag starts: along the up
//! axis), `[` / `]` turn it by 15° about the up axis (Shift: 1°), `-` / `=` scale it by 1/1.05 /
//! 1.05 (Shift: 1.01), Ctrl+D duplicates it, Delete removes it, Ctrl+Z / Ctrl+Y (or
//! Ctrl+Shift+Z) undo / redo, Ctrl+S saves the `.instgs` (atomically; the first save keeps the
//! file as it was as `SCENE.instgs.bak`), Esc clears the selection (with unsaved edits, a second
//! Esc quits). Moves, turns and scales rewrite only the instance's transform and Δp on the
//! device; duplicate and delete upload the scene again.
//!
//! Cameras are OpenCV (x right, y down, z forward), as everywhere in this crate; the player's
//! camera has no roll (its horizon stays level with the up axis).

pub mod controls;
pub mod editor;
pub mod overlay;
pub mod window;

pub use controls::ViewCamera;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

use crate::formats::instgs::Storage;
use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::{Gpu, GpuOptions};
use crate::render::raster::Rasterizer;

/// What the player shows and how.
pub struct PlayerOptions {
    pub scene_path: PathBuf,
    pub device: Option<String>,
    pub width: u32,
    pub height: u32,
    pub background: [f32; 3],
    pub vsync: bool,
    pub overlay: bool,
    /// Exit after this many frames (the last one is saved as a screenshot when `out` is set).
    pub frames: Option<u64>,
    /// Where screenshots (windowed) or frames (headless) go.
    pub out: Option<PathBuf>,
    /// Culling and level of detail of instanced scenes.
    pub render: crate::render::lod::RenderConfig,
    /// How the depth-sorted splats become pixels.
    pub forward: crate::render::raster::Forward,
}

/// The selection's box outline colour (RGBA8).
pub(crate) const SELECTION: [u8; 4] = [255, 200, 0, 255];

/// Corner pairs of a box's 12 edges (corner i: bit 0 x, bit 1 y, bit 2 z).
pub(crate) const BOX_EDGES: [(usize, usize); 12] =
    [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)];

/// What F1 lists.
pub(crate) const HELP: [&str; 8] = [
    "LEFT DRAG: ORBIT | RIGHT: LOOK | MIDDLE: PAN | WHEEL: DOLLY",
    "WASD QE: FLY (SHIFT: FASTER) | R: RESET VIEW | B: BACKGROUND",
    "L: LEVEL OF DETAIL | V: VSYNC | H: OVERLAY | P: SCREENSHOT",
    "CLICK: SELECT INSTANCE | DRAG IT: MOVE (SHIFT: UP/DOWN)",
    "[ ]: TURN 15 DEG (SHIFT: 1) | - =: SCALE 1.05 (SHIFT: 1.01)",
    "CTRL+D: DUPLICATE | DELETE: REMOVE",
    "CTRL+Z: UNDO | CTRL+Y: REDO | CTRL+S: SAVE",
    "ESC: CLEAR SELECTION / QUIT | F1: THESE KEYS",
];

/// The editor's overlay lines: the selection (id, group, translation, rotation angle, scale),
/// unsaved edits and the last edit's message.
pub(crate) fn editor_lines(
    scene: &crate::model::instanced::InstancedScene,
    ed: Option<&editor::Editor>,
    status: Option<&str>,
) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some((g, k)) = ed.and_then(|e| e.selected) {
        let (group, x) = (&scene.groups[g], &scene.groups[g].instances[k].transform);
        let t = x.translation;
        lines.push(format!(
            "INSTANCE {} ({} OF {}) | GROUP {}",
            group.instances[k].id,
            k + 1,
            group.instances.len(),
            group.name
        ));
        let angle = x.rotation.to_axis_angle().1.to_degrees();
        lines.push(format!("T {:.2} {:.2} {:.2} | R {angle:.1} | S {:.3}", t.x, t.y, t.z, x.scale));
    }
    let unsaved = ed.filter(|e| e.unsaved()).map_or(String::new(), |e| format!("UNSAVED: {} | ", e.edits()));
    let last: String = status.unwrap_or("F1: KEYS").chars().take(40).collect();
    lines.push(format!("{unsaved}{last}"));
    lines
}

/// Backgrounds the B key cycles through.
pub(crate) const BACKGROUNDS: [[f32; 3]; 3] = [[0.0; 3], [1.0; 3], [0.5; 3]];

/// Packs one pixel as present.comp does (CPU twin): clamp, blend the overlay texel (RGBA8,
/// straight alpha), decode sRGB for an _SRGB swapchain, swap to BGRA, round to 8 bits.
pub fn present_texel(rgb: [f32; 3], overlay: Option<u32>, bgra: bool, srgb_decode: bool) -> u32 {
    let mut c = rgb.map(|v| v.clamp(0.0, 1.0));
    if let Some(o) = overlay {
        let o = o.to_le_bytes().map(|b| b as f32 / 255.0);
        c = [0, 1, 2].map(|i| c[i] * (1.0 - o[3]) + o[i] * o[3]);
    }
    if srgb_decode {
        c = c.map(|v| if v > 0.04045 { ((v + 0.055) / 1.055).powf(2.4) } else { v / 12.92 });
    }
    if bgra {
        c = [c[2], c[1], c[0]];
    }
    let q = c.map(|v| (v * 255.0).round() as u8);
    u32::from_le_bytes([q[0], q[1], q[2], 255])
}

/// Renders `frames` frames offscreen on a turntable that starts at `start` (one turn about the
/// up axis) and saves them as `out/frame_NNN.png`; prints the median GPU time per frame.
pub fn run_headless(opts: &PlayerOptions, scene: &AnyScene, start: ViewCamera) -> Result<()> {
    let frames = opts.frames.ok_or_else(|| anyhow!("--headless needs --frames N"))?;
    let out = opts.out.as_deref().ok_or_else(|| anyhow!("--headless needs --out DIR"))?;
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    let gpu = Gpu::new(&GpuOptions::from_env(opts.device.clone()))?;
    eprintln!("device: {}", gpu.describe());
    let k = Kernels::new(&gpu)?;
    let gs = scene.upload_for_rendering(&gpu, &opts.render).with_context(|| opts.scene_path.display().to_string())?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    r.set_forward(opts.forward)?;
    let mut gpu_ms = Vec::new();
    // Into a temporary sibling folder, moved into `out` once every frame is written.
    crate::util::write_dir_atomic(out, None, |tmp| {
        for i in 0..frames {
            let mut view = start.clone();
            view.orbit(std::f32::consts::TAU * i as f32 / frames as f32, 0.0);
            let f = r.render(&gs, &view.camera(opts.width, opts.height), opts.background)?;
            crate::util::save_png(&tmp.join(format!("frame_{i:03}.png")), f.width, f.height, &f.image)?;
            gpu_ms.push(f.passes.iter().map(|p| p.1).sum::<f64>());
        }
        Ok(())
    })?;
    report(&gpu, frames, &mut gpu_ms, None)?;
    eprintln!("wrote {frames} frames to {}", out.display());
    Ok(())
}

pub(crate) fn report(gpu: &Gpu, frames: u64, gpu_ms: &mut [f64], wall_fps: Option<f64>) -> Result<()> {
    gpu_ms.sort_by(f64::total_cmp);
    if let Some(m) = gpu_ms.get(gpu_ms.len() / 2) {
        let wall = wall_fps.map_or(String::new(), |f| format!(", {f:.1} frames/s presented"));
        eprintln!("{frames} frames: GPU {m:.3} ms per frame (median; {:.1} FPS){wall}", 1000.0 / m);
    }
    let m = gpu.take_validation_messages();
    if !m.is_empty() {
        bail!("{} Vulkan validation message(s), first: {}", m.len(), m[0]);
    }
    Ok(())
}

/// "1.23M" style splat counts.
pub(crate) fn splat_count(n: usize) -> String {
    match n {
        0..1_000 => n.to_string(),
        1_000..1_000_000 => format!("{:.1}K", n as f64 / 1e3),
        _ => format!("{:.2}M", n as f64 / 1e6),
    }
}

pub(crate) fn save_rgba8(path: &Path, width: u32, height: u32, rgba: Vec<u8>) -> Result<()> {
    let img = image::RgbaImage::from_raw(width, height, rgba).ok_or_else(|| anyhow!("screenshot size mismatch"))?;
    crate::util::write_atomic(path, |f| {
        img.write_to(&mut std::io::BufWriter::new(f), image::ImageFormat::Png).map_err(std::io::Error::other)
    })
}

/// `instgs-vk view`: the player, in a window or headless (`frames` frames to `out`), starting from
/// camera `camera` of the `cameras` dataset or file (`split`), else an orbit camera.
pub fn view(
    opts: crate::player::PlayerOptions,
    cameras: Option<&Path>,
    (camera, split): (usize, &str),
    up: crate::model::camera::UpAxis,
    headless: bool,
) -> Result<()> {
    use crate::player::window::run_window;
    use crate::player::{run_headless, ViewCamera};
    if opts.width == 0 || opts.height == 0 {
        bail!("--width and --height must be at least 1");
    }
    if opts.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    let (scene, storage) = if crate::formats::detect(&opts.scene_path)? == crate::formats::Format::Instgs {
        let (s, storage) = crate::formats::instgs::read_with_storage(&opts.scene_path)?;
        (AnyScene::Instanced(s), storage)
    } else {
        (AnyScene::read(&opts.scene_path)?, Storage::F32)
    };
    let means = scene.means();
    let (lo, hi) = crate::model::scene::robust_bounds(&means, 0.02);
    let centre = 0.5 * (lo + hi);
    let start = match cameras {
        Some(path) => {
            let cams = crate::dataset::dataset_cameras(path, split)?;
            let n = cams.len();
            cams.into_iter()
                .nth(camera)
                .ok_or_else(|| anyhow::anyhow!("{}: --camera {camera} is out of range ({n} cameras)", path.display()))?
        }
        None => crate::model::camera::scene_orbit(
            &means,
            1,
            up,
            opts.width,
            opts.height,
            &opts.scene_path.display().to_string(),
        )?
        .remove(0),
    };
    let start = ViewCamera::from_camera(&start, centre, up.vector());
    drop(means);
    if headless {
        run_headless(&opts, &scene, start)
    } else {
        run_window(opts, scene, storage, start)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::player::window::drag_point;
    use glam::Vec3;

    #[test]
    fn drag_points_lie_on_the_plane_or_the_up_axis() {
        let (centre, up) = (Vec3::new(1.0, 2.0, 0.5), Vec3::Z);
        let o = Vec3::new(0.0, -3.0, 4.0);
        let d = (Vec3::new(2.0, 2.5, 0.0) - o).normalize();
        let p = drag_point(centre, up, false, o, d).unwrap();
        assert!((p.z - 0.5).abs() < 1e-5 && (p - o).cross(d).length() < 1e-4);
        // The up axis through the centre, at the point nearest a ray aimed at (1, 2, 1.5).
        let d = (Vec3::new(1.0, 2.0, 1.5) - o).normalize();
        let p = drag_point(centre, up, true, o, d).unwrap();
        assert!((p - Vec3::new(1.0, 2.0, 1.5)).length() < 1e-4, "{p}");
        assert!(drag_point(centre, up, false, o, Vec3::X).is_none(), "parallel to the plane");
        assert!(drag_point(centre, up, true, o, Vec3::Z).is_none(), "parallel to the axis");
    }

    #[test]
    fn splat_counts_read_short() {
        assert_eq!(splat_count(1_234_567), "1.23M");
        assert_eq!(splat_count(45_600), "45.6K");
    }

    #[test]
    fn present_texel_rounds_blends_and_swaps() {
        assert_eq!(present_texel([1.0, 0.5, 0.0], None, false, false).to_le_bytes(), [255, 128, 0, 255]);
        assert_eq!(present_texel([1.0, 0.5, 0.0], None, true, false).to_le_bytes(), [0, 128, 255, 255]);
        assert_eq!(present_texel([2.0, -1.0, 0.0], None, false, false).to_le_bytes(), [255, 0, 0, 255]);
        let white = u32::from_le_bytes([255, 255, 255, 255]);
        assert_eq!(present_texel([0.0; 3], Some(white), false, false).to_le_bytes(), [255, 255, 255, 255]);
        assert_eq!(present_texel([0.5; 3], None, false, true).to_le_bytes()[0], 55);
    }
}
