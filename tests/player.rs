//! The player: `present.comp` against its CPU twin, and the window itself under `xvfb-run` on
//! whatever Vulkan device there is (lavapipe in CI): frames presented, a screenshot taken from
//! the presented swapchain image, equal to the offscreen (headless) render of the same camera.
#![cfg(feature = "player")]
mod common;
use std::path::{Path, PathBuf};
use std::process::Command;

use common::*;
use instgs_vk::player::present_texel;
use instgs_vk::shared::*;

#[test]
fn present_kernel_matches_cpu_twin() {
    let (gpu, k) = gpu();
    let mut rng = Rng::new(7);
    let (w, h) = (37u32, 23u32);
    let (ow, oh) = (11u32, 5u32);
    let image: Vec<[f32; 4]> =
        (0..w * h).map(|_| [rng.f32() * 1.4 - 0.2, rng.f32(), rng.f32() * 1.2, rng.f32()]).collect();
    let overlay: Vec<u32> = (0..ow * oh).map(|_| rng.u32()).collect();
    let image_buf = gpu.upload("image", &image).unwrap();
    let overlay_buf = gpu.upload("overlay", &overlay).unwrap();
    let texels = gpu.storage("texels", (w * h * 4) as u64).unwrap();
    for (bgra, srgb) in [(false, false), (true, false), (true, true)] {
        gpu.submit_and_wait(|rec| {
            rec.fill(&texels, 0x7fc0_0bad);
            let args = PresentArgs {
                width: w,
                height: h,
                overlay_width: ow,
                overlay_height: oh,
                bgra: bgra as u32,
                srgb_decode: srgb as u32,
                ..Default::default()
            };
            rec.dispatch(
                &k.present,
                &[("image", &image_buf), ("overlay", &overlay_buf), ("texels", &texels)],
                &args,
                [2, 1, 1],
            )
        })
        .unwrap();
        let got: Vec<u32> = gpu.read(&texels, (w * h) as usize).unwrap();
        for (i, (&g, p)) in got.iter().zip(&image).enumerate() {
            let (x, y) = (i as u32 % w, i as u32 / w);
            let o = (x < ow && y < oh).then(|| overlay[(y * ow + x) as usize]);
            let want = present_texel([p[0], p[1], p[2]], o, bgra, srgb);
            let (g, e) = (g.to_le_bytes(), want.to_le_bytes());
            // One step of rounding: GLSL's round() may round halves either way.
            assert!(g.iter().zip(&e).all(|(a, b)| a.abs_diff(*b) <= 1), "pixel {i}: {g:?} vs {e:?}");
            assert_eq!(g[3], 255);
        }
    }
    assert_clean(&gpu);
}

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_instgs-vk")
}

fn out_dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("player").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn demo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("demo/guitar.compressed.ply")
}

/// Runs the player under a virtual X server with validation on; returns stderr. The forward path
/// is pinned to compute (the player's `auto` may pick either, which differ by rounding), so
/// screenshots compare exactly with `render` and headless frames.
fn windowed(args: &[&str]) -> String {
    let o = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1024x768x24", bin(), "view", "--forward", "compute"])
        .args(args)
        .env("INSTGS_VALIDATION", "1")
        .output()
        .expect("xvfb-run (Debian package xvfb; tools/install-deps.sh installs it)");
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "player failed: {err}");
    assert!(!err.contains("vulkan validation"), "{err}");
    err
}

/// Runs the binary with `args` and `--out out`, validation on; it must succeed.
fn validated(args: &[&str], out: &Path) {
    let o = Command::new(bin()).args(args).arg("--out").arg(out).env("INSTGS_VALIDATION", "1").output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// The largest difference of two equally sized images, in 1/255 steps.
fn worst_difference(a: &image::RgbImage, b: &image::RgbImage) -> u8 {
    assert_eq!(a.dimensions(), b.dimensions());
    a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
}

fn rgb(path: &Path) -> image::RgbImage {
    image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgb8()
}

#[test]
fn window_screenshot_equals_offscreen_render() {
    let scene = demo();
    let scene = scene.to_str().unwrap();
    let win = out_dir("window");
    let err = windowed(&[
        scene,
        "--width",
        "320",
        "--height",
        "240",
        "--frames",
        "4",
        "--no-overlay",
        "--out",
        win.to_str().unwrap(),
    ]);
    assert!(err.contains("swapchain 320x240"), "{err}");
    assert!(err.contains("4 frames: GPU"), "{err}");
    let head = out_dir("headless");
    validated(
        &["view", scene, "--forward", "compute", "--width", "320", "--height", "240", "--headless", "--frames", "1"],
        &head,
    );
    let (shot, frame) = (rgb(&win.join("screenshot_000.png")), rgb(&head.join("frame_000.png")));
    let worst = worst_difference(&shot, &frame);
    assert!(worst <= 1, "screenshot differs from the offscreen render by up to {worst}/255");
    let lit = frame.as_raw().iter().filter(|&&v| v > 20).count();
    assert!(lit > 1000, "the frame is nearly empty ({lit} lit values)");

    // With the overlay: its text is white over the top-left corner; the rest is unchanged.
    let ov = out_dir("overlay");
    windowed(&[scene, "--width", "320", "--height", "240", "--frames", "2", "--out", ov.to_str().unwrap()]);
    let shot = rgb(&ov.join("screenshot_000.png"));
    let white =
        (0..40).flat_map(|y| (0..200).map(move |x| (x, y))).filter(|&(x, y)| shot.get_pixel(x, y).0 == [255; 3]);
    assert!(white.count() > 100, "no overlay text");
    for y in 60..240 {
        for x in 0..320 {
            let (a, b) = (shot.get_pixel(x, y).0, frame.get_pixel(x, y).0);
            assert!(a.iter().zip(&b).all(|(p, q)| p.abs_diff(*q) <= 1), "({x}, {y}): {a:?} vs {b:?}");
        }
    }
}

#[test]
fn no_display_is_a_clear_error() {
    let o = Command::new(bin())
        .args(["view", demo().to_str().unwrap(), "--frames", "1"])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("error: cannot open a window") && err.contains("--headless"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// Runs a bash `script` under a virtual X server with validation on; the player's stderr is
/// redirected by the script to `dir/err`, which is returned after checking success and the
/// absence of validation messages.
fn scripted(dir: &Path, script: &str) -> String {
    let o = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1024x768x24", "bash", "-c", script])
        .env("INSTGS_VALIDATION", "1")
        .output()
        .expect("xvfb-run and xdotool (tools/install-deps.sh installs them)");
    let err = std::fs::read_to_string(dir.join("err")).unwrap_or_default();
    assert!(o.status.success(), "{err}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(!err.contains("vulkan validation"), "{err}");
    err
}

/// A shell function call that waits (up to 120 s) until the player's stderr in `dir/err`
/// contains its argument. The scripts wait on what the player says, never on frame counts, so
/// they hold on fast and slow machines alike.
fn wait_for(dir: &Path) -> String {
    format!(
        "w8() {{ for i in $(seq 1200); do grep -q \"$1\" {}/err && return 0; sleep 0.1; done; return 1; }}; w8",
        dir.display()
    )
}

#[test]
fn window_resize_recreates_the_swapchain() {
    let dir = out_dir("resize");
    // Resize the window (xdotool; no window manager under Xvfb) once the first swapchain
    // exists; the player goes on at the new size; P saves a screenshot of that size; `]` (turn
    // the selection) on a plain scene says editing needs an instanced scene; Esc quits.
    let script = format!(
        "timeout 300 {bin} view {scene} --width 320 --height 240 --no-overlay --out {out} 2> {out}/err & \
         {wait_for} 'swapchain 320x240'; \
         w=$(xdotool search --sync --name instgs-vk | head -1); xdotool windowsize --sync $w 200 150; \
         {wait_for} 'swapchain 200x150'; xdotool windowfocus --sync $w; xdotool key p; \
         {wait_for} screenshot; xdotool key bracketright; {wait_for} 'editing needs'; \
         xdotool key Escape; wait $!",
        bin = bin(),
        scene = demo().display(),
        out = dir.display(),
        wait_for = wait_for(&dir),
    );
    let err = scripted(&dir, &script);
    assert!(err.contains("swapchain 200x150"), "{err}");
    // A plain scene is viewed, not edited: an editing key says why.
    assert!(err.contains("view only: editing needs an instanced scene (.instgs)"), "{err}");
    assert!(err.contains("editing needs an instanced scene (.instgs);"), "{err}");
    assert_eq!(rgb(&dir.join("screenshot_000.png")).dimensions(), (200, 150));
}

#[test]
fn keys_toggle_level_of_detail_and_vsync() {
    // An instanced scene (level of detail on by default): L turns it off, V turns vsync on
    // (the swapchain is recreated with FIFO). Keys go to the focused window (xdotool).
    let dir = out_dir("keys");
    let scene = dir.join("two.instgs");
    let graph = dir.join("graph.json");
    std::fs::write(
        &graph,
        r#"[{"template_id": "g", "instances": [
            {"instance_id": "1", "transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
            {"instance_id": "2", "transform": [[1,0,0,-3],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}]"#,
    )
    .unwrap();
    let o = Command::new(bin())
        .args(["compose", "--template", &format!("g={}", demo().display()), "--scene-graph"])
        .args([graph.to_str().unwrap(), "--out", scene.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let script = format!(
        "timeout 300 {bin} view {scene} --width 200 --height 150 --out {out} 2> {out}/err & \
         {wait_for} 'swapchain 200x150'; \
         w=$(xdotool search --sync --name instgs-vk | head -1); xdotool windowfocus --sync $w; \
         xdotool key l; {wait_for} 'level of detail'; xdotool key v; {wait_for} 'vsync'; \
         {wait_for} FIFO; xdotool key Escape; wait $!",
        bin = bin(),
        scene = scene.display(),
        out = dir.display(),
        wait_for = wait_for(&dir),
    );
    let err = scripted(&dir, &script);
    assert!(err.contains("level of detail off"), "{err}");
    assert!(err.contains("vsync on") && err.contains("FIFO"), "{err}");
}

/// Three guitars side by side (x = −2.5, 0, 2.5) as an instanced scene with random offsets,
/// and one level camera on an orbit about them (+z up) as a transforms file.
fn guitar_row(dir: &Path, width: u32, height: u32) -> (PathBuf, PathBuf, instgs_vk::model::camera::Camera) {
    use instgs_vk::model::camera::{transforms_json, Orbit, UpAxis};
    let scene = dir.join("row.instgs");
    let graph = dir.join("graph.json");
    let instance = |id: &str, x: f32| {
        format!(r#"{{"instance_id": "{id}", "transform": [[1,0,0,{}],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}"#, -x)
    };
    let text = format!(
        r#"[{{"template_id": "guitar", "instances": [{}, {}, {}]}}]"#,
        instance("1", 0.0),
        instance("2", 2.5),
        instance("3", -2.5)
    );
    std::fs::write(&graph, text).unwrap();
    let o = Command::new(bin())
        .args(["compose", "--template", &format!("guitar={}", demo().display()), "--scene-graph"])
        .args([graph.to_str().unwrap(), "--random-offsets", "0.002", "--out", scene.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cam = Orbit {
        center: glam::Vec3::new(0.0, -2.0, 0.2),
        distance: 9.0,
        up: UpAxis::PosZ,
        elevation_deg: 35.0,
        fov_x_deg: 60.0,
    }
    .cameras(1, width, height)
    .remove(0);
    let cams = dir.join("transforms_edit.json");
    std::fs::write(&cams, transforms_json(std::slice::from_ref(&cam), &["view".into()]).to_string()).unwrap();
    (scene, cams, cam)
}

#[test]
fn editing_moves_turns_duplicates_deletes_undoes_and_saves() {
    use glam::{Quat, Vec3};
    let dir = out_dir("edit");
    let (w, h) = (320u32, 240u32);
    let (scene_path, cams, cam) = guitar_row(&dir, w, h);
    let original_bytes = std::fs::read(&scene_path).unwrap();
    let original = instgs_vk::formats::instgs::read(&scene_path).unwrap();
    // Instance 1's centre (its template box centre) on screen, and where the drag ends.
    let t = &original.groups[0].template;
    let (lo, hi) = t
        .means
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), m| (lo.min(Vec3::from(*m)), hi.max(Vec3::from(*m))));
    let centre = 0.5 * (lo + hi);
    let [u, v, _] = cam.project(centre).unwrap();
    let (x0, y0) = (u.round() as i32, v.round() as i32);
    let (x1, y1) = (x0 + 30, y0 + 12);
    // Where the drag puts the centre (the plane z = centre.z under the cursor), on screen: a
    // Shift-drag from there 25 pixels up lifts the instance along +z.
    let plane = |x: i32, y: i32| {
        let (o, d) = cam.ray(x as f32, y as f32);
        o + d * ((centre.z - o.z) / d.z)
    };
    let moved_centre = centre + (plane(x1, y1) - plane(x0, y0));
    let [u3, v3, _] = cam.project(moved_centre).unwrap();
    let (x3, y3) = (u3.round() as i32, v3.round() as i32);
    // The point of the vertical through the moved centre nearest the cursor's ray: its height.
    let height = |x: i32, y: i32| {
        let (o, d) = cam.ray(x as f32, y as f32);
        let (b, w) = (d.z, moved_centre - o);
        (b * d.dot(w) - w.z) / (1.0 - b * b)
    };
    let lift = height(x3, y3 - 25) - height(x3, y3);
    // Instance 2 on screen (clicked to check that a click picks the instance under it).
    let [u2, v2, _] = cam.project(centre + Vec3::new(2.5, 0.0, 0.0)).unwrap();
    let script = format!(
        "timeout 300 {bin} view {scene} --forward compute --cameras {cams} --up +z --exact --width {w} --height {h} --out {out} 2> {out}/err & \
         {wait_for} 'swapchain {w}x{h}'; \
         win=$(xdotool search --sync --name instgs-vk | head -1); xdotool windowfocus --sync $win; \
         xdotool mousemove --window $win {x2} {y2} click 1; {wait_for} 'selected instance 2'; \
         xdotool mousemove --window $win {x0} {y0} click 1; {wait_for} 'selected instance 1 '; \
         xdotool key p; {wait_for} 'screenshot_000'; \
         xdotool mousemove --window $win {x0} {y0} mousedown 1; sleep 0.3; \
         xdotool mousemove --window $win {xm} {ym}; sleep 0.3; xdotool mousemove --window $win {x1} {y1}; sleep 0.3; \
         xdotool mouseup 1; {wait_for} 'moved instance 1'; \
         xdotool keydown shift mousemove --window $win {x3} {y3} mousedown 1; sleep 0.3; \
         xdotool mousemove --window $win {x3} {y4}; sleep 0.3; xdotool mouseup 1 keyup shift; \
         {wait_for} 'moved instance 1 by (0.0000, 0.0000'; \
         xdotool key bracketright; {wait_for} 'turned by 15'; \
         xdotool key ctrl+d; {wait_for} 'duplicated instance 1 as 1-copy'; \
         xdotool key Delete; {wait_for} 'deleted instance 1-copy'; \
         xdotool key ctrl+z; {wait_for} 'undo: instance back: 1-copy'; \
         xdotool key ctrl+s; {wait_for} 'saved '; \
         xdotool key Escape; {wait_for} 'selection cleared'; xdotool key h; \
         xdotool key p; {wait_for} 'screenshot_001'; xdotool key Escape; wait $!",
        bin = bin(),
        scene = scene_path.display(),
        cams = cams.display(),
        out = dir.display(),
        wait_for = wait_for(&dir),
        x2 = u2.round() as i32,
        y2 = v2.round() as i32,
        xm = (x0 + x1) / 2,
        y4 = y3 - 25,
        ym = (y0 + y1) / 2,
    );
    let err = scripted(&dir, &script);
    assert!(!err.contains("unsaved"), "{err}");
    // The selection is boxed in the overlay.
    let boxed = rgb(&dir.join("screenshot_000.png"));
    let outline = boxed.pixels().filter(|p| p.0 == [255, 200, 0]).count();
    assert!(outline > 100, "no selection outline ({outline} pixels)");

    // The saved file: instance 1 moved on the plane z = centre.z to under the cursor, lifted
    // along +z, then turned 15° about +z through its centre; 1-copy beside it with zero offsets; 2 and 3 as
    // they were; the original kept as .bak.
    assert_eq!(std::fs::read(dir.join("row.instgs.bak")).unwrap(), original_bytes);
    let saved = instgs_vk::formats::instgs::read(&scene_path).unwrap();
    let g = &saved.groups[0];
    let ids: Vec<&str> = g.instances.iter().map(|i| i.id.as_str()).collect();
    assert_eq!(ids, ["1", "1-copy", "2", "3"]);
    let turn = Quat::from_rotation_z(15f32.to_radians());
    let x = g.instances[0].transform;
    // Moved by δ on the plane and lifted by l, then turned about its centre c = centre + t:
    // t' = c + R·(t − c) = c − R·centre.
    assert!(lift > 0.05, "the Shift-drag lifts ({lift})");
    let want_t = moved_centre + Vec3::Z * lift - turn * centre;
    assert!((x.translation - want_t).length() < 1e-3, "{} vs {want_t}", x.translation);
    assert!(x.rotation.angle_between(turn) < 1e-4 && (x.scale - 1.0).abs() < 1e-5);
    let tl = t.len();
    let turned: Vec<[f32; 3]> =
        original.groups[0].offsets.d_means[..tl].iter().map(|d| (turn * Vec3::from(*d)).to_array()).collect();
    let worst = g.offsets.d_means[..tl].iter().zip(&turned).map(|(a, b)| (Vec3::from(*a) - Vec3::from(*b)).length());
    assert!(worst.fold(0.0f32, f32::max) < 1e-6, "Δp turned with the instance");
    assert!(g.offsets.d_means[tl..2 * tl].iter().all(|d| *d == [0.0; 3]), "the duplicate has zero offsets");
    let copy = g.instances[1].transform;
    assert!(copy.rotation.angle_between(turn) < 1e-4 && (copy.translation.z - x.translation.z).abs() < 1e-5);
    assert!((copy.translation - x.translation).length() > 0.5, "the duplicate stands beside");
    for (k, inst) in g.instances[2..].iter().enumerate() {
        assert_eq!(inst, &original.groups[0].instances[k + 1]);
        let r = (k + 2) * tl..(k + 3) * tl;
        assert_eq!(g.offsets.d_means[r.clone()], original.groups[0].offsets.d_means[r.start - tl..r.end - tl]);
    }

    // The last screenshot (selection cleared, overlay hidden) is `render` of the saved file.
    let rendered = dir.join("rendered");
    validated(&["render", "--scene", scene_path.to_str().unwrap(), "--cameras", cams.to_str().unwrap()], &rendered);
    let (shot, frame) = (rgb(&dir.join("screenshot_001.png")), rgb(&rendered.join("view.png")));
    let worst = worst_difference(&shot, &frame);
    assert!(worst <= 1, "screenshot differs from `render` of the saved file by up to {worst}/255");
}

#[test]
fn the_draw_path_shows_the_same_picture() {
    // The player's forward paths (`--forward quads`: fixed-function quads; `auto`: the faster of
    // the two on this device) against compute, headless, validation on. They differ only where
    // a pixel saturates (T < 0.01, see render::raster::quads).
    let scene = demo();
    let scene = scene.to_str().unwrap();
    let mut frames = Vec::new();
    for forward in ["compute", "quads", "auto"] {
        let out = out_dir(&format!("forward-{forward}"));
        validated(
            &["view", scene, "--forward", forward, "--width", "320", "--height", "240", "--headless", "--frames", "1"],
            &out,
        );
        frames.push(rgb(&out.join("frame_000.png")));
    }
    for (f, name) in frames[1..].iter().zip(["quads", "auto"]) {
        let worst = worst_difference(&frames[0], f);
        assert!(worst <= 3, "{name} differs from compute by up to {worst}/255");
    }
}
