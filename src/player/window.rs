//! The player's window (winit): the event loop, input (orbit, fly, keys, the instance editor's
//! clicks and drags), redraws and presenting into the swapchain.
use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use ash::vk;
use glam::Vec3;
use raw_window_handle::{HasDisplayHandle, HasWindowHandle};
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

use crate::formats::instgs::Storage;
use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::swapchain::Presenter;
use crate::gpu::{Buffer, Gpu, GpuOptions};
use crate::render::raster::Rasterizer;
use crate::render::upload::GpuScene;

use super::{
    editor, editor_lines, report, save_rgba8, splat_count, PlayerOptions, ViewCamera, BACKGROUNDS, BOX_EDGES, HELP,
    SELECTION,
};

/// Opens the window and runs until it is closed (or `frames` frames were shown). An instanced
/// scene can be edited and is saved as `storage` (the file's).
pub fn run_window(opts: PlayerOptions, scene: AnyScene, storage: Storage, start: ViewCamera) -> Result<()> {
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow!(
            "cannot open a window ({e}); without a display use --headless --frames N --out DIR, or run under xvfb-run"
        )
    })?;
    let editor = match &scene {
        AnyScene::Instanced(s) => Some(editor::Editor::new(s)),
        AnyScene::Plain(_) => {
            eprintln!("view only: editing needs an instanced scene (.instgs)");
            None
        }
    };
    let mut app = App {
        opts,
        scene,
        editor,
        storage,
        drag: None,
        press: None,
        help: false,
        quit_armed: false,
        status: None,
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
    if app.editor.as_ref().is_some_and(|e| e.unsaved()) {
        eprintln!("quit with unsaved edits: {} was not changed", app.opts.scene_path.display());
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

/// A drag of the selected instance: its pose when the drag began and where the cursor's ray met
/// the plane through its centre (or the up axis through it, `vertical`).
struct Drag {
    start: editor::Pose,
    centre: Vec3,
    anchor: Vec3,
    vertical: bool,
}

/// The left button went down: how far the cursor went since (pixels) and the instance picked
/// there (a release after a short way is a click).
struct Press {
    travelled: f64,
    hit: Option<editor::InstanceRef>,
}

struct App {
    opts: PlayerOptions,
    scene: AnyScene,
    /// Editing state (instanced scenes only).
    editor: Option<editor::Editor>,
    storage: Storage,
    drag: Option<Drag>,
    press: Option<Press>,
    /// F1: the overlay lists the keys.
    help: bool,
    /// Esc was pressed once with unsaved edits.
    quit_armed: bool,
    /// The last edit's message, shown in the overlay.
    status: Option<String>,
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
    /// The text part of the overlay, and what is presented (the text, or with a selection a
    /// frame-sized image with the text and the selection's box).
    text: Option<crate::player::overlay::Overlay>,
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
        let mut raster = Rasterizer::new(&gpu, &k)?;
        raster.set_forward(self.opts.forward)?;
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
            text: None,
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
        if held(KeyCode::ControlLeft) + held(KeyCode::ControlRight) > 0.0 {
            return;
        }
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
        if self.running.is_none() {
            return Ok(());
        }
        if code != KeyCode::Escape {
            self.quit_armed = false;
        }
        if self.edit_key(code)? {
            return Ok(());
        }
        let Some(run) = self.running.as_mut() else { return Ok(()) };
        match code {
            KeyCode::Escape => {
                let selected = self.editor.as_ref().and_then(|e| e.selected).is_some();
                let unsaved = self.editor.as_ref().is_some_and(|e| e.unsaved());
                if selected {
                    self.editor.as_mut().unwrap().selected = None;
                    eprintln!("selection cleared");
                } else if unsaved && !self.quit_armed {
                    self.quit_armed = true;
                    self.say("unsaved edits: Ctrl+S saves, Esc again quits without saving".into());
                } else {
                    el.exit();
                }
                if let Some(run) = self.running.as_mut() {
                    run.overlay_dirty = true;
                }
            }
            KeyCode::F1 => {
                self.help = !self.help;
                run.overlay_dirty = true;
            }
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

    /// Prints an editor message and shows it in the overlay.
    fn say(&mut self, message: String) {
        eprintln!("{message}");
        self.status = Some(message);
    }

    fn modifier(&self, left: KeyCode, right: KeyCode) -> bool {
        self.input.held.contains(&left) || self.input.held.contains(&right)
    }

    /// The editing keys; true when `code` was one of them.
    fn edit_key(&mut self, code: KeyCode) -> Result<bool> {
        let ctrl = self.modifier(KeyCode::ControlLeft, KeyCode::ControlRight);
        let shift = self.modifier(KeyCode::ShiftLeft, KeyCode::ShiftRight);
        let up = self.view.up();
        let right = {
            let r = self.view.camera(1, 1).viewmat.inverse().x_axis.truncate();
            (r - up * r.dot(up)).normalize_or_zero()
        };
        let is_edit = matches!(
            (code, ctrl),
            (KeyCode::KeyS | KeyCode::KeyZ | KeyCode::KeyY | KeyCode::KeyD, true)
                | (KeyCode::Delete | KeyCode::Backspace | KeyCode::BracketLeft | KeyCode::BracketRight, _)
                | (KeyCode::Minus | KeyCode::Equal | KeyCode::NumpadSubtract | KeyCode::NumpadAdd, _)
        );
        if !is_edit {
            return Ok(false);
        }
        let (Some(ed), AnyScene::Instanced(scene)) = (self.editor.as_mut(), &mut self.scene) else {
            let path = self.opts.scene_path.display().to_string();
            self.say(format!("editing needs an instanced scene (.instgs); {path} is a plain scene"));
            return Ok(true);
        };
        let step = |fine: f32, coarse: f32| if shift { fine } else { coarse };
        let or_say = |r: Option<(editor::Change, String)>, none: &str| {
            Some(r.map_or((None, none.to_string()), |(c, m)| (Some(c), m)))
        };
        let done: Option<(Option<editor::Change>, String)> = match code {
            KeyCode::KeyS => {
                let path = self.opts.scene_path.clone();
                let message = match ed.save(scene, &path, self.storage) {
                    Ok(backup) => {
                        let kept = backup.map_or(String::new(), |b| format!(" (the original kept as {})", b.display()));
                        let lossy = match self.storage {
                            Storage::F32 => "",
                            _ => "; quantised as the file stores it (shown unquantised until reopened)",
                        };
                        format!("saved {}{kept}{lossy}", path.display())
                    }
                    Err(e) => format!("not saved: {}", crate::util::one_line(&format!("{e:#}"))),
                };
                self.say(message);
                None
            }
            KeyCode::KeyZ if !shift => or_say(ed.undo(scene), "nothing to undo"),
            KeyCode::KeyZ | KeyCode::KeyY => or_say(ed.redo(scene), "nothing to redo"),
            _ if ed.selected.is_none() => {
                self.say("select an instance first (click it)".into());
                None
            }
            KeyCode::KeyD => {
                let (g, k) = ed.selected.unwrap();
                // Beside the original, to the right on screen: its box's extent along that way.
                let along = ed.box_corners(scene, g, k).map(|c| c.dot(right));
                let width = along.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v))
                    - along.iter().fold(f32::INFINITY, |m, &v| m.min(v));
                or_say(ed.duplicate(scene, right * 1.1 * width), "")
            }
            KeyCode::Delete | KeyCode::Backspace => match ed.delete(scene) {
                Ok(r) => or_say(r, ""),
                Err(e) => Some((None, crate::util::one_line(&format!("{e:#}")))),
            },
            KeyCode::BracketLeft => or_say(ed.turn(scene, -step(1.0, 15.0), up), ""),
            KeyCode::BracketRight => or_say(ed.turn(scene, step(1.0, 15.0), up), ""),
            KeyCode::Minus | KeyCode::NumpadSubtract => or_say(ed.scale(scene, 1.0 / step(1.01, 1.05)), ""),
            _ => or_say(ed.scale(scene, step(1.01, 1.05)), ""),
        };
        if let Some((change, message)) = done {
            self.say(message);
            if let Some(change) = change {
                self.upload_change(change)?;
            }
        }
        if let Some(run) = self.running.as_mut() {
            run.overlay_dirty = true;
        }
        Ok(true)
    }

    /// Puts an edit on the device: one instance in place where possible, else the whole scene.
    fn upload_change(&mut self, change: editor::Change) -> Result<()> {
        let (Some(run), AnyScene::Instanced(scene)) = (self.running.as_mut(), &self.scene) else { return Ok(()) };
        if let editor::Change::Instance { group, k, linear } = change {
            let g = &scene.groups[group];
            let t = g.template.len();
            let d_means = &g.offsets.d_means[k * t..(k + 1) * t];
            let device = editor::device_group(scene, group);
            if run.gs.write_instance(&run.gpu, device, k, &g.instances[k].transform, d_means, linear)? {
                return Ok(());
            }
        }
        let level = run.gs.inst.select.map(|a| a.max_level);
        run.gs = crate::render::upload::GpuScene::instanced_for_rendering(
            &run.gpu,
            &editor::renderable(scene),
            &self.opts.render,
        )?;
        if let (Some(a), Some(level)) = (run.gs.inst.select.as_mut(), level) {
            a.max_level = level;
        }
        Ok(())
    }

    /// The camera of the current window size.
    fn camera_now(&self) -> Option<crate::model::camera::Camera> {
        let run = self.running.as_ref()?;
        let size = run.window.inner_size();
        (size.width > 0 && size.height > 0).then(|| self.view.camera(size.width, size.height))
    }

    /// Left button down: a drag of the selection if it is under the cursor, else (on release
    /// close by) a click.
    fn left_pressed(&mut self) -> Result<()> {
        let (Some(cursor), Some(cam)) = (self.input.cursor, self.camera_now()) else { return Ok(()) };
        let (Some(ed), AnyScene::Instanced(scene)) = (self.editor.as_ref(), &self.scene) else { return Ok(()) };
        let (o, d) = cam.ray(cursor.0 as f32, cursor.1 as f32);
        let hit = ed.pick(scene, o, d);
        self.press = Some(Press { travelled: 0.0, hit });
        if let (Some((g, k)), true) = (hit, hit == ed.selected) {
            let centre = ed.centre(scene, g, k);
            let vertical = self.modifier(KeyCode::ShiftLeft, KeyCode::ShiftRight);
            if let Some(anchor) = drag_point(centre, self.view.up(), vertical, o, d) {
                self.drag = Some(Drag { start: ed.pose(scene, g, k), centre, anchor, vertical });
            }
        }
        Ok(())
    }

    fn left_released(&mut self) -> Result<()> {
        let press = self.press.take();
        let (Some(ed), AnyScene::Instanced(scene)) = (self.editor.as_mut(), &self.scene) else { return Ok(()) };
        if let Some(drag) = self.drag.take() {
            if let Some(message) = ed.commit_move(scene, drag.start) {
                self.say(message);
            }
        } else if let Some(Press { hit, .. }) = press.filter(|p| p.travelled < 4.0) {
            ed.selected = hit;
            match hit {
                Some((g, k)) => {
                    let g = &scene.groups[g];
                    let (id, n) = (&g.instances[k].id, g.instances.len());
                    eprintln!("selected instance {id} of group {} ({} of {n})", g.name, k + 1);
                }
                None => eprintln!("selection cleared"),
            }
        }
        if let Some(run) = self.running.as_mut() {
            run.overlay_dirty = true;
        }
        Ok(())
    }

    /// While dragging: the selection follows the cursor's ray.
    fn drag_to(&mut self, x: f64, y: f64) -> Result<()> {
        let (Some(drag), Some(cam)) = (self.drag.as_ref(), self.camera_now()) else { return Ok(()) };
        let (o, d) = cam.ray(x as f32, y as f32);
        let Some(point) = drag_point(drag.centre, self.view.up(), drag.vertical, o, d) else { return Ok(()) };
        let (Some(ed), AnyScene::Instanced(scene)) = (self.editor.as_mut(), &mut self.scene) else { return Ok(()) };
        if let Some(change) = ed.preview_move(scene, &drag.start, point - drag.anchor) {
            self.upload_change(change)?;
        }
        Ok(())
    }

    fn mouse_moved(&mut self, x: f64, y: f64) -> Result<()> {
        if let (Some(p), Some((px, py))) = (self.press.as_mut(), self.input.cursor) {
            p.travelled += ((x - px).powi(2) + (y - py).powi(2)).sqrt();
        }
        if self.drag.is_some() {
            self.input.cursor = Some((x, y));
            return self.drag_to(x, y);
        }
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
        Ok(())
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
        let selected = self.editor.as_ref().and_then(|e| e.selected.map(|s| (e, s)));
        let boxed = self.opts.overlay && selected.is_some();
        if run.overlay_dirty || run.text.is_none() && self.opts.overlay || boxed {
            if run.overlay_dirty || run.text.is_none() {
                run.text = self.opts.overlay.then(|| {
                    let fps = run.fps.map_or("-".into(), |f| format!("{f:.1}"));
                    let mut lines = vec![
                        format!("{fps} FPS | GPU {gpu_ms:.2} MS"),
                        format!(
                            "{} SPLATS | {}X{}{}",
                            splat_count(self.scene.splats()),
                            extent.width,
                            extent.height,
                            lod
                        ),
                    ];
                    if let AnyScene::Instanced(scene) = &self.scene {
                        lines.extend(editor_lines(scene, self.editor.as_ref(), self.status.as_deref()));
                    }
                    if self.help {
                        lines.extend(HELP.iter().map(|l| l.to_string()));
                    }
                    crate::player::overlay::draw(&lines)
                });
            }
            run.overlay = match (selected, &self.scene) {
                (Some((ed, (g, k))), AnyScene::Instanced(scene)) if boxed => {
                    let cam = self.view.camera(extent.width, extent.height);
                    let c = ed.box_corners(scene, g, k).map(|p| cam.project(p));
                    let edges = BOX_EDGES.iter().filter_map(|&(a, b)| Some(((c[a]?), (c[b]?))));
                    let lines: Vec<_> = edges.map(|(a, b)| ([a[0], a[1]], [b[0], b[1]])).collect();
                    let o = crate::player::overlay::frame(
                        extent.width,
                        extent.height,
                        run.text.as_ref(),
                        &lines,
                        SELECTION,
                    );
                    Some(o)
                }
                _ => run.text.clone(),
            };
            if let Some(o) = &run.overlay {
                if run.overlay_buf.size == std::mem::size_of_val(o.texels.as_slice()) as u64 {
                    run.gpu.write(&run.overlay_buf, &o.texels)?;
                } else {
                    run.overlay_buf = run.gpu.upload("overlay", &o.texels)?;
                }
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

/// Where the ray o + t·d meets the horizontal plane through `centre` (normal `up`), or with
/// `vertical` the point of the up axis through `centre` closest to the ray; None when the ray
/// runs (nearly) parallel to it or meets the plane behind the eye.
pub(crate) fn drag_point(centre: Vec3, up: Vec3, vertical: bool, o: Vec3, d: Vec3) -> Option<Vec3> {
    let b = d.dot(up);
    if vertical {
        let denom = 1.0 - b * b;
        let w = centre - o;
        (denom > 1e-6).then(|| centre + up * ((b * d.dot(w) - up.dot(w)) / denom))
    } else {
        let t = (centre - o).dot(up) / b;
        (b.abs() > 1e-6 && t > 0.0).then(|| o + d * t)
    }
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
                match (b, state) {
                    (0, ElementState::Pressed) => self.left_pressed(),
                    (0, ElementState::Released) => self.left_released(),
                    _ => Ok(()),
                }
            }
            WindowEvent::CursorMoved { position, .. } => self.mouse_moved(position.x, position.y),
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
