//! `instgs-vk bench`: GPU-timestamped frame times (medians, p90), memory and file sizes of a
//! scene, and with a second scene interleaved A B A B ratios and image agreement, as JSON.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{anyhow, bail, Context, Result};

use crate::formats::AnyScene;
use crate::gpu::kernels::Kernels;
use crate::gpu::{Gpu, GpuOptions};
use crate::math::{median, percentile};
use crate::model::camera::Camera;
use crate::render::frames::{collect, print_passes, setup, FrameSpec, Setup};
use crate::render::lod::RenderConfig;
use crate::render::raster::{Forward, Rasterizer};
use crate::render::upload::GpuScene;
use crate::util::{write_json, Progress, ProgressMode};

/// A scene to bench: its file, the scene, how it is rendered (level of detail, forward path).
pub struct BenchInput<'a> {
    pub path: &'a Path,
    pub scene: AnyScene,
    pub render: RenderConfig,
    pub forward: Forward,
}

impl<'a> BenchInput<'a> {
    /// Reads the scene at `path`.
    pub fn read(path: &'a Path, render: RenderConfig, forward: Forward) -> Result<BenchInput<'a>> {
        Ok(BenchInput { path, scene: AnyScene::read(path)?, render, forward })
    }
}

/// One scene of a bench run: its own rasterizer (buffers sized for it) and samples.
struct BenchScene {
    path: PathBuf,
    scene: AnyScene,
    gs: GpuScene,
    r: Rasterizer,
    per_pass: Vec<(String, Vec<f64>)>,
    frame_ms: Vec<f64>,
    /// Wall-clock milliseconds from submission to the frame's fence (host side, a cross-check
    /// of the timestamps: lavapipe's can shift between passes once a context has drawn).
    wall_ms: Vec<f64>,
    isects: Vec<f64>,
    /// An instanced scene's intersections from its background splats (empty for a plain one).
    background_isects: Vec<f64>,
    visible: Vec<f64>,
}

impl BenchScene {
    fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>, input: BenchInput) -> Result<BenchScene> {
        let BenchInput { path, scene, render, forward } = input;
        let gs = scene.upload_for_rendering(gpu, &render).with_context(|| path.display().to_string())?;
        let mut r = Rasterizer::new(gpu, k)?;
        r.set_forward(forward)?;
        Ok(BenchScene {
            path: path.to_path_buf(),
            scene,
            gs,
            r,
            per_pass: Vec::new(),
            frame_ms: Vec::new(),
            wall_ms: Vec::new(),
            isects: Vec::new(),
            background_isects: Vec::new(),
            visible: Vec::new(),
        })
    }

    fn frame(&mut self, cam: &Camera, background: [f32; 3], timed: bool) -> Result<()> {
        let t0 = std::time::Instant::now();
        let f = self.r.render_resident(&self.gs, cam, background)?;
        let wall = t0.elapsed().as_secs_f64() * 1e3;
        if timed {
            self.frame_ms.push(f.passes.iter().map(|p| p.1).sum::<f64>());
            self.wall_ms.push(wall);
            collect(&mut self.per_pass, &f.passes);
            self.isects.push(f.intersections as f64);
            if self.gs.num_background < self.gs.len {
                self.background_isects.push(self.r.intersections_of_first(self.gs.num_background)? as f64);
            }
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
        println!("scene            {} ({} forward path)", self.path.display(), forward_name(self.r.forward()));
        println!("splats           {}", self.scene.splats());
        println!("visible (median) {}", median(&self.visible));
        println!("intersections    {}", median(&self.isects));
        let parts = self.intersection_parts();
        if let Some((background, instanced)) = parts {
            println!("  background     {background}");
            println!("  instanced      {instanced}");
        }
        println!("frame (median)   {fm:.3} ms  ({:.1} FPS); p90 {p90:.3} ms", 1000.0 / fm);
        println!("wall (median)    {:.3} ms  (submission to fence, host clock)", median(&self.wall_ms));
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
        let mut json = serde_json::json!({
            "scene": self.path.display().to_string(),
            "forward": self.r.forward(),
            "splats": self.scene.splats(),
            "visible": median(&self.visible),
            "intersections": median(&self.isects),
            "frame_ms_median": fm,
            "frame_ms_p90": p90,
            "fps_median": 1000.0 / fm,
            "wall_ms_median": median(&self.wall_ms),
            "scene_gpu_bytes": self.gs.gpu_bytes(),
            "frame_gpu_bytes": self.r.frame_gpu_bytes(),
            "file_bytes": file_bytes,
            "passes": passes,
            "sorts": sorts.iter().map(|c| serde_json::json!({
                "name": c.name, "keys": c.keys, "gpu_ms": c.gpu_ms, "sort_unstable_ms": c.cpu_ms,
                "ratio": c.gpu_ms / c.cpu_ms,
            })).collect::<Vec<_>>(),
        });
        if let Some((background, instanced)) = parts {
            json["background_intersections"] = background.into();
            json["instanced_intersections"] = instanced.into();
        }
        Ok(json)
    }

    /// An instanced scene's intersections by part, medians over the timed frames: (background,
    /// instanced splats).
    fn intersection_parts(&self) -> Option<(f64, f64)> {
        if self.background_isects.is_empty() {
            return None;
        }
        let instanced: Vec<f64> = self.isects.iter().zip(&self.background_isects).map(|(t, b)| t - b).collect();
        Some((median(&self.background_isects), median(&instanced)))
    }
}

fn forward_name(f: Forward) -> &'static str {
    match f {
        Forward::Compute => "compute",
        Forward::Quads => "quads",
        Forward::Auto => "auto",
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

/// `instgs-vk bench`: renders `view`'s scene (and `compare`, interleaved) `frames` times per
/// camera after `warmup` untimed frames; prints the tables and writes `json`.
pub fn bench(
    device: Option<String>,
    view: &FrameSpec,
    (frames, warmup): (usize, usize),
    render: &RenderConfig,
    compare: Option<(&Path, RenderConfig, Forward)>,
    json: Option<&Path>,
) -> Result<()> {
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    let Setup { gpu, k, scene, cams } = setup(device, view)?;
    let a = BenchInput { path: &view.scene, scene, render: render.clone(), forward: view.forward };
    let b: Vec<BenchInput> = compare.map(|(p, c, f)| BenchInput::read(p, c, f)).into_iter().collect::<Result<_>>()?;
    let v = bench_scenes(&gpu, &k, a, b, &cams, (frames, warmup), view.background, ("bench: ", ProgressMode::Auto))?;
    if let Some(path) = json {
        write_json(path, &v, true)?;
    }
    Ok(())
}

/// Renders scene A (and the `others`, interleaved A B C A B C …) from `cams`, prints the tables
/// and returns the JSON report: A's numbers; with others also `compare` (B's), `ratios` (A over
/// B) and image agreement of A and B, and for every further scene an entry of `compare_more`
/// (its numbers with its own `ratios`, A over it).
#[allow(clippy::too_many_arguments)]
pub fn bench_scenes(
    gpu: &Arc<Gpu>,
    k: &Arc<Kernels>,
    a: BenchInput,
    others: Vec<BenchInput>,
    cams: &[Camera],
    (frames, warmup): (usize, usize),
    background: [f32; 3],
    progress: (&str, ProgressMode),
) -> Result<serde_json::Value> {
    let render = serde_json::to_value(&a.render)?;
    let mut runs = vec![BenchScene::new(gpu, k, a)?];
    for b in others {
        runs.push(BenchScene::new(gpu, k, b)?);
    }
    // Interleaved (A B A B …) so that clock and thermal drift hit every scene alike.
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
    v["driver"] = gpu.info.driver.clone().into();
    v["width"] = cams[0].width.into();
    v["height"] = cams[0].height.into();
    v["views"] = cams.len().into();
    v["frames"] = frames.into();
    v["allocated_gpu_bytes"] = gpu.allocated_bytes().into();
    v["cpu_rss_bytes"] = rss.into();
    let mut more = Vec::new();
    for (j, b) in reports.iter().enumerate().skip(1) {
        let ratio = |key: &str| {
            let (x, y) = (reports[0][key].as_f64().unwrap_or(f64::NAN), b[key].as_f64().unwrap_or(f64::NAN));
            x / y
        };
        let ratios = serde_json::json!({
            // Timing ratios pair each frame of A with the frame of the other scene rendered
            // right after it (same camera, same machine state) and take the median of those ratios.
            "fps": paired_median(&runs[j].frame_ms, &runs[0].frame_ms),
            "frame_ms": paired_median(&runs[0].frame_ms, &runs[j].frame_ms),
            "wall_ms": paired_median(&runs[0].wall_ms, &runs[j].wall_ms),
            "scene_gpu_bytes": ratio("scene_gpu_bytes"),
            "frame_gpu_bytes": ratio("frame_gpu_bytes"),
            "file_bytes": ratio("file_bytes"),
            "intersections": ratio("intersections"),
        });
        println!(
            "A over {}: FPS {:.3}x (median of paired frames; wall-clock frame time {:.3}x), scene GPU bytes {:.3}x, file bytes {:.3}x, frame GPU bytes {:.3}x ({} interleaved frames each)",
            (b'A' + j as u8) as char,
            ratios["fps"].as_f64().unwrap_or(f64::NAN),
            ratios["wall_ms"].as_f64().unwrap_or(f64::NAN),
            ratios["scene_gpu_bytes"].as_f64().unwrap_or(f64::NAN),
            ratios["file_bytes"].as_f64().unwrap_or(f64::NAN),
            ratios["frame_gpu_bytes"].as_f64().unwrap_or(f64::NAN),
            runs[0].frame_ms.len()
        );
        if j == 1 {
            v["compare"] = b.clone();
            v["ratios"] = ratios;
        } else {
            let mut entry = b.clone();
            entry["ratios"] = ratios;
            more.push(entry);
        }
    }
    if !more.is_empty() {
        v["compare_more"] = more.into();
    }
    if runs.len() > 1 {
        // Image agreement, outside the timed frames: A's frames against B's, and both against
        // an antialiased reference, B rendered at twice the resolution and box-filtered 2×2.
        // Identical images count as 100 dB.
        let db = |a: &[[f32; 4]], b: &[[f32; 4]]| crate::util::psnr(a, b).min(100.0);
        let (mut ab, mut a_ref, mut b_ref) = (Vec::new(), Vec::new(), Vec::new());
        if let [a, b, ..] = &mut runs[..] {
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
    v["render"] = render;
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
    use crate::render::reference;
    let st = r.read_state()?;
    let proj = st.projected;
    let depth_ids: Vec<u32> = (0..proj.depths.len() as u32).filter(|&i| proj.tiles_touched[i as usize] > 0).collect();
    let depth_keys: Vec<u32> = depth_ids.iter().map(|&i| proj.depths[i as usize].to_bits()).collect();
    let fp = r.last_frame_params().ok_or_else(|| anyhow!("no frame rendered"))?;
    let gpu = |name: &str| per_pass.iter().find(|(n, _)| n == name).map(|(_, v)| median(v));
    let mut out = Vec::new();
    if let Some(gpu_ms) = gpu("depth_sort") {
        let cpu_ms = time_sort_unstable(&depth_keys, &depth_ids, 5);
        out.push(SortComparison { name: "depth_sort", keys: depth_keys.len(), gpu_ms, cpu_ms });
    }
    // The tile lists exist on the compute forward path only.
    if let Some(gpu_ms) = gpu("tile_sort") {
        let (tile_keys, tile_ids) = reference::forward::emit(&fp, &proj, &st.depth_ids);
        let cpu_ms = time_sort_unstable(&tile_keys, &tile_ids, 5);
        out.push(SortComparison { name: "tile_sort", keys: tile_keys.len(), gpu_ms, cpu_ms });
    }
    Ok(out)
}

/// `instgs-vk bench-sort`: the GPU radix sort against `sort_unstable` on `n` fixed pseudo-random
/// keys of `bits` bits.
pub fn bench_sort(device: Option<String>, n: usize, bits: u32, repeats: usize) -> Result<()> {
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
    let mut sorter = crate::render::sort::GpuSort::new(&gpu, &k, n)?;
    let sorted = sorter.sort(&keys, &vals, bits, repeats)?;
    let gpu_ms = sorted.gpu_ms.ok_or_else(|| anyhow!("the device has no timestamps"))?;
    let cpu_ms = time_sort_unstable(&keys, &vals, repeats);
    println!("keys {n}, bits {bits}: GPU radix sort {gpu_ms:.2} ms, sort_unstable (key,value) {cpu_ms:.2} ms, GPU/CPU {:.2}x", gpu_ms / cpu_ms);
    Ok(())
}
