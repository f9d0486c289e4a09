//! `instgs-vk view`: the standalone player. A winit window with a Vulkan swapchain; every frame
//! replays the rasterizer's recorded command buffer (the image stays on the device), then
//! `present.comp` packs the image (plus the text overlay) into 8-bit texels that are copied into
//! the acquired swapchain image. Vsync is off by default (immediate, else mailbox, else FIFO).
//!
//! Controls: left drag orbits the target, right drag looks around (fly), middle drag pans, the
//! wheel dollies, W/A/S/D move, Q/E go down/up (Shift: 4× faster), R resets the camera, B cycles
//! the background, L toggles template level of detail (instanced scenes uploaded with it), H
//! hides the overlay, V toggles vsync, P or F12 saves a screenshot (the presented swapchain
//! image), Esc quits.
//!
//! Cameras are OpenCV (x right, y down, z forward), as everywhere in this crate; the player's
//! camera has no roll (its horizon stays level with the up axis).

pub mod controls;
pub mod overlay;

pub use controls::ViewCamera;
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use ash::vk;
use raw_window_handle::{HasDisplayHandle, HasWindowHandle};
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::swapchain::Presenter;
use crate::gpu::{Buffer, Gpu, GpuOptions};
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;

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
}

/// Backgrounds the B key cycles through.
const BACKGROUNDS: [[f32; 3]; 3] = [[0.0; 3], [1.0; 3], [0.5; 3]];

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
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create folder", out.display()))?;
    let gpu = Gpu::new(&GpuOptions::from_env(opts.device.clone()))?;
    eprintln!("device: {}", gpu.describe());
    let k = Kernels::new(&gpu)?;
    let gs = scene.upload_for_rendering(&gpu, &opts.render).with_context(|| opts.scene_path.display().to_string())?;
    let mut r = Rasterizer::new(&gpu, &k)?;
    let mut gpu_ms = Vec::new();
    for i in 0..frames {
        let mut view = start.clone();
        view.orbit(std::f32::consts::TAU * i as f32 / frames as f32, 0.0);
        let f = r.render(&gs, &view.camera(opts.width, opts.height), opts.background)?;
        crate::util::save_png(&out.join(format!("frame_{i:03}.png")), f.width, f.height, &f.image)?;
        gpu_ms.push(f.passes.iter().map(|p| p.1).sum::<f64>());
    }
    report(&gpu, frames, &mut gpu_ms, None)?;
    eprintln!("wrote {frames} frames to {}", out.display());
    Ok(())
}

fn report(gpu: &Gpu, frames: u64, gpu_ms: &mut [f64], wall_fps: Option<f64>) -> Result<()> {
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

/// Opens the window and runs until it is closed (or `frames` frames were shown).
pub fn run_window(opts: PlayerOptions, scene: AnyScene, start: ViewCamera) -> Result<()> {
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow!(
            "cannot open a window ({e}); without a display use --headless --frames N --out DIR, or run under xvfb-run"
        )
    })?;
    let mut app = App {
        opts,
        scene,
        home: start.clone(),
        view: start,
        running: None,
        error: None,
        input: Input::default(),
        background: 0,
        frames: 0,
        screenshots: 0,
        started: None,
        gpu_ms: Vec::new(),
    };
    event_loop.run_app(&mut app).map_err(|e| anyhow!("the window's event loop failed: {e}"))?;
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    let Some(running) = app.running.take() else { bail!("the window never opened") };
    let wall_fps = app.started.map(|t| app.frames.saturating_sub(1) as f64 / t.elapsed().as_secs_f64());
    report(&running.gpu, app.frames, &mut app.gpu_ms, wall_fps)
}

#[derive(Default)]
struct Input {
    held: HashSet<KeyCode>,
    buttons: HashSet<u8>,
    cursor: Option<(f64, f64)>,
    last_tick: Option<Instant>,
}

struct App {
    opts: PlayerOptions,
    scene: AnyScene,
    home: ViewCamera,
    view: ViewCamera,
    running: Option<Running>,
    error: Option<anyhow::Error>,
    input: Input,
    background: usize,
    frames: u64,
    screenshots: u32,
    /// When the first frame was presented.
    started: Option<Instant>,
    gpu_ms: Vec<f64>,
}

/// Everything that lives while the window is open. Fields drop in order: the swapchain before
/// the device, the device (and its surface) before the window.
struct Running {
    presenter: Presenter,
    raster: Rasterizer,
    gs: GpuScene,
    _k: Arc<Kernels>,
    gpu: Arc<Gpu>,
    window: Arc<Window>,
    overlay: Option<crate::player::overlay::Overlay>,
    overlay_buf: Buffer,
    overlay_dirty: bool,
    last_title: Instant,
    fps_window: (Instant, u64),
    /// Frames presented per second over the last title period.
    fps: Option<f64>,
    minimised: bool,
    screenshot_next: bool,
}

impl App {
    fn open(&mut self, el: &ActiveEventLoop) -> Result<()> {
        let attrs = Window::default_attributes()
            .with_title("instgs-vk")
            .with_inner_size(winit::dpi::PhysicalSize::new(self.opts.width, self.opts.height));
        let window = Arc::new(el.create_window(attrs).context("cannot create the window")?);
        let display = window.display_handle().map_err(|e| anyhow!("no display handle: {e}"))?.as_raw();
        let handle = window.window_handle().map_err(|e| anyhow!("no window handle: {e}"))?.as_raw();
        let mut gopts = GpuOptions::from_env(self.opts.device.clone());
        gopts.window = Some((display, handle));
        let gpu = Gpu::new(&gopts)?;
        eprintln!("device: {}", gpu.describe());
        let k = Kernels::new(&gpu)?;
        let gs = self
            .scene
            .upload_for_rendering(&gpu, &self.opts.render)
            .with_context(|| self.opts.scene_path.display().to_string())?;
        let raster = Rasterizer::new(&gpu, &k)?;
        let presenter = Presenter::new(&gpu, &k, self.opts.vsync)?;
        let overlay_buf = gpu.storage("overlay", 16)?;
        let now = Instant::now();
        self.running = Some(Running {
            presenter,
            raster,
            gs,
            _k: k,
            gpu,
            window,
            overlay: None,
            overlay_buf,
            overlay_dirty: false,
            last_title: now,
            fps_window: (now, 0),
            fps: None,
            minimised: false,
            screenshot_next: false,
        });
        Ok(())
    }

    /// Applies held keys over the time since the last frame.
    fn tick(&mut self) {
        let now = Instant::now();
        let dt = self.input.last_tick.map_or(0.0, |t| (now - t).as_secs_f32()).min(0.1);
        self.input.last_tick = Some(now);
        let held = |k: KeyCode| self.input.held.contains(&k) as i32 as f32;
        let speed = 0.8 * dt * if held(KeyCode::ShiftLeft) + held(KeyCode::ShiftRight) > 0.0 { 4.0 } else { 1.0 };
        let right = held(KeyCode::KeyD) - held(KeyCode::KeyA);
        let up = held(KeyCode::KeyE) - held(KeyCode::KeyQ);
        let forward = held(KeyCode::KeyW) - held(KeyCode::KeyS);
        if right != 0.0 || up != 0.0 || forward != 0.0 {
            self.view.fly(right * speed, up * speed, forward * speed);
        }
    }

    fn key(&mut self, el: &ActiveEventLoop, code: KeyCode, pressed: bool, repeat: bool) -> Result<()> {
        if !pressed {
            self.input.held.remove(&code);
            return Ok(());
        }
        self.input.held.insert(code);
        if repeat {
            return Ok(());
        }
        let Some(run) = self.running.as_mut() else { return Ok(()) };
        match code {
            KeyCode::Escape => el.exit(),
            KeyCode::KeyR => self.view = self.home.clone(),
            KeyCode::KeyB => self.background = (self.background + 1) % BACKGROUNDS.len(),
            KeyCode::KeyH => {
                self.opts.overlay = !self.opts.overlay;
                run.overlay_dirty = true;
            }
            KeyCode::KeyV => {
                self.opts.vsync = !self.opts.vsync;
                run.presenter.vsync = self.opts.vsync;
                run.presenter.stale = true;
                eprintln!("vsync {}", if self.opts.vsync { "on" } else { "off" });
            }
            KeyCode::KeyP | KeyCode::F12 => run.screenshot_next = true,
            KeyCode::KeyL => {
                // The coarser levels stay uploaded; only the coarsest level allowed changes.
                if let Some(a) = run.gs.inst.select.as_mut() {
                    let levels = self.opts.render.lod.fractions.len() as u32;
                    let on = self.opts.render.lod.enabled && a.max_level == 0;
                    a.max_level = if on { levels } else { 0 };
                    run.overlay_dirty = self.opts.overlay;
                    eprintln!("level of detail {}", if on { "on" } else { "off" });
                }
            }
            _ => {}
        }
        Ok(())
    }

    fn mouse_moved(&mut self, x: f64, y: f64) {
        if let Some((px, py)) = self.input.cursor {
            let (dx, dy) = ((x - px) as f32 * 0.005, (y - py) as f32 * 0.005);
            let b = &self.input.buttons;
            if b.contains(&0) {
                self.view.orbit(-dx, dy);
            } else if b.contains(&1) {
                self.view.look(-dx, dy);
            } else if b.contains(&2) {
                self.view.fly(-dx * 0.3, dy * 0.3, 0.0);
            }
        }
        self.input.cursor = Some((x, y));
    }

    fn redraw(&mut self, el: &ActiveEventLoop) -> Result<()> {
        self.tick();
        let background = if self.background == 0 { self.opts.background } else { BACKGROUNDS[self.background] };
        let Some(run) = self.running.as_mut() else { return Ok(()) };
        if run.minimised {
            return Ok(());
        }
        if run.presenter.stale || run.presenter.swapchain.is_none() {
            let size = run.window.inner_size();
            if !run.presenter.recreate(vk::Extent2D { width: size.width, height: size.height })? {
                run.minimised = true;
                return Ok(());
            }
        }
        let extent = run.presenter.swapchain.as_ref().unwrap().extent;
        let last = self.opts.frames.is_some_and(|n| self.frames + 1 >= n);
        let screenshot = run.screenshot_next || (last && self.opts.out.is_some());
        let Some(image) = run.presenter.acquire()? else { return Ok(()) };
        let stats = run.raster.render_resident(&run.gs, &self.view.camera(extent.width, extent.height), background)?;
        let gpu_ms: f64 = stats.passes.iter().map(|p| p.1).sum();
        let lod = match run.gs.inst.select {
            Some(a) if a.max_level > 0 => " | LOD",
            Some(_) => " | EXACT",
            None => "",
        };
        if run.overlay_dirty || run.overlay.is_none() && self.opts.overlay {
            run.overlay = self.opts.overlay.then(|| {
                let fps = run.fps.map_or("-".into(), |f| format!("{f:.1}"));
                crate::player::overlay::draw(&[
                    format!("{fps} FPS | GPU {gpu_ms:.2} MS"),
                    format!("{} SPLATS | {}X{}{}", splat_count(self.scene.splats()), extent.width, extent.height, lod),
                ])
            });
            if let Some(o) = &run.overlay {
                run.overlay_buf = run.gpu.upload("overlay", &o.texels)?;
            }
            run.overlay_dirty = false;
        }
        let overlay = run.overlay.as_ref().map(|o| ((o.width, o.height), &run.overlay_buf));
        let image_buf = run.raster.image_buffer().ok_or_else(|| anyhow!("the rasterizer has no image"))?;
        let shot = run.presenter.present(image, image_buf, overlay, screenshot)?;
        self.frames += 1;
        self.gpu_ms.push(gpu_ms);
        run.fps_window.1 += 1;
        if self.started.is_none() {
            self.started = Some(Instant::now());
        }
        if let Some((w, h, rgba)) = shot {
            run.screenshot_next = false;
            let dir = self.opts.out.clone().unwrap_or_else(|| PathBuf::from("."));
            std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create folder", dir.display()))?;
            let path = dir.join(format!("screenshot_{:03}.png", self.screenshots));
            save_rgba8(&path, w, h, rgba)?;
            self.screenshots += 1;
            eprintln!("screenshot {}", path.display());
        }
        if run.last_title.elapsed().as_secs_f64() >= 0.5 {
            let (t, n) = run.fps_window;
            let fps = n as f64 / t.elapsed().as_secs_f64();
            run.fps = Some(fps);
            let name = self.opts.scene_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            run.window.set_title(&format!("instgs-vk — {name} — {fps:.1} FPS, GPU {gpu_ms:.2} ms"));
            run.last_title = Instant::now();
            run.fps_window = (Instant::now(), 0);
            run.overlay_dirty = self.opts.overlay;
        }
        if last {
            el.exit();
        }
        Ok(())
    }

    fn fail(&mut self, el: &ActiveEventLoop, e: anyhow::Error) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        el.exit();
    }
}

/// "1.23M" style splat counts.
fn splat_count(n: usize) -> String {
    match n {
        0..1_000 => n.to_string(),
        1_000..1_000_000 => format!("{:.1}K", n as f64 / 1e3),
        _ => format!("{:.2}M", n as f64 / 1e6),
    }
}

fn save_rgba8(path: &Path, width: u32, height: u32, rgba: Vec<u8>) -> Result<()> {
    let img = image::RgbaImage::from_raw(width, height, rgba).ok_or_else(|| anyhow!("screenshot size mismatch"))?;
    crate::util::write_atomic(path, |f| {
        img.write_to(&mut std::io::BufWriter::new(f), image::ImageFormat::Png).map_err(std::io::Error::other)
    })
}

impl ApplicationHandler for App {
    fn resumed(&mut self, el: &ActiveEventLoop) {
        if self.running.is_none() {
            if let Err(e) = self.open(el) {
                self.fail(el, e);
            }
        }
    }

    fn window_event(&mut self, el: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let r = match event {
            WindowEvent::CloseRequested => {
                el.exit();
                Ok(())
            }
            WindowEvent::Resized(size) => {
                if let Some(run) = self.running.as_mut() {
                    run.minimised = size.width == 0 || size.height == 0;
                    run.presenter.stale = true;
                }
                Ok(())
            }
            WindowEvent::KeyboardInput { event, .. } => match event.physical_key {
                PhysicalKey::Code(code) => self.key(el, code, event.state == ElementState::Pressed, event.repeat),
                PhysicalKey::Unidentified(_) => Ok(()),
            },
            WindowEvent::MouseInput { state, button, .. } => {
                let b = match button {
                    MouseButton::Left => 0,
                    MouseButton::Right => 1,
                    MouseButton::Middle => 2,
                    _ => 3,
                };
                if state == ElementState::Pressed {
                    self.input.buttons.insert(b);
                } else {
                    self.input.buttons.remove(&b);
                }
                Ok(())
            }
            WindowEvent::CursorMoved { position, .. } => {
                self.mouse_moved(position.x, position.y);
                Ok(())
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let lines = match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => p.y as f32 / 50.0,
                };
                self.view.dolly(0.85f32.powf(lines));
                Ok(())
            }
            WindowEvent::RedrawRequested => self.redraw(el),
            _ => Ok(()),
        };
        if let Err(e) = r {
            self.fail(el, e);
        }
    }

    fn about_to_wait(&mut self, el: &ActiveEventLoop) {
        match &self.running {
            Some(run) if !run.minimised => {
                el.set_control_flow(ControlFlow::Poll);
                run.window.request_redraw();
            }
            _ => el.set_control_flow(ControlFlow::Wait),
        }
    }
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
    use crate::player::{run_headless, run_window, ViewCamera};
    if opts.width == 0 || opts.height == 0 {
        bail!("--width and --height must be at least 1");
    }
    if opts.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    let scene = AnyScene::read(&opts.scene_path)?;
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
        None => crate::model::camera::orbit_around_points(&means, 1, up, opts.width, opts.height).remove(0),
    };
    let start = ViewCamera::from_camera(&start, centre, up.vector());
    drop(means);
    if headless {
        run_headless(&opts, &scene, start)
    } else {
        run_window(opts, scene, start)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
