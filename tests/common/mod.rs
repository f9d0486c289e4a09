//! Test helpers: one validated device per test binary, a seeded generator, random scenes.
#![allow(dead_code)]
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use glam::{Mat4, Vec3};
use instgs_vk::gpu::kernels::{KernelPolicy, Kernels};
use instgs_vk::gpu::{Gpu, GpuOptions};
use instgs_vk::model::camera::Camera;
use instgs_vk::model::scene::Scene;

/// The device with validation layers (synchronization validation included) on: `INSTGS_DEVICE`
/// where set (as the CLI), else the default choice (a real GPU over a CPU device).
pub fn gpu() -> (Arc<Gpu>, Arc<Kernels>) {
    static G: OnceLock<(Arc<Gpu>, Arc<Kernels>)> = OnceLock::new();
    G.get_or_init(|| {
        let opts = GpuOptions { validation: true, ..GpuOptions::from_env(None) };
        let gpu = Gpu::new(&opts).expect("a Vulkan device with validation layers");
        let k = Kernels::new(&gpu).expect("kernels");
        (gpu, k)
    })
    .clone()
}

/// Kernels built with both device policies (GPU and CPU), so each path is tested on any device.
pub fn both_policies() -> [Arc<Kernels>; 2] {
    static K: OnceLock<[Arc<Kernels>; 2]> = OnceLock::new();
    K.get_or_init(|| {
        let (gpu, _) = gpu();
        [KernelPolicy::GPU, KernelPolicy::CPU].map(|p| Kernels::with_policy(&gpu, p).expect("kernels"))
    })
    .clone()
}

/// Fails the test on any validation message so far.
pub fn assert_clean(gpu: &Gpu) {
    let m = gpu.take_validation_messages();
    assert!(m.is_empty(), "{} validation message(s):\n{}", m.len(), m.join("\n"));
}

/// `../shared/data/<rel>` next to the checkout.
pub fn shared_data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data").join(rel)
}

/// xorshift64*: deterministic, seedable.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1)
    }
    pub fn u64(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    pub fn u32(&mut self) -> u32 {
        (self.u64() >> 32) as u32
    }
    /// Uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        (self.u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, a: f32, b: f32) -> f32 {
        a + (b - a) * self.f32()
    }
    pub fn normal(&mut self) -> f32 {
        let u = self.f32().max(1e-7);
        let v = self.f32();
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}

/// A camera at `eye` looking at `target` (OpenCV axes), `up` the world up.
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, width: u32, height: u32, fx: f32) -> Camera {
    let z = (target - eye).normalize();
    let x = z.cross(up).normalize();
    let y = z.cross(x);
    let c2w = Mat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), eye.extend(1.0));
    Camera {
        name: "test".into(),
        width,
        height,
        fx,
        fy: fx * 1.05,
        cx: 0.5 * width as f32 + 3.0,
        cy: 0.5 * height as f32 - 2.0,
        viewmat: c2w.inverse(),
        lens: Default::default(),
    }
}

/// N random Gaussians around the origin: small and huge ones (straddling many tiles), nearly
/// transparent and fully opaque ones (the T < 1e-4 cut-off), some behind the camera.
pub fn random_scene(rng: &mut Rng, n: usize, sh_degree: u32) -> Scene {
    let coeffs = ((sh_degree + 1) * (sh_degree + 1)) as usize;
    let mut s = Scene { sh_degree, ..Default::default() };
    for _ in 0..n {
        s.means.push([rng.range(-1.5, 1.5), rng.range(-1.2, 1.2), rng.range(-1.5, 1.5)]);
        let big = rng.f32() < 0.05;
        let base = if big { rng.range(-1.5, -0.5) } else { rng.range(-5.0, -2.5) };
        s.scales.push([base + rng.range(-0.5, 0.5), base + rng.range(-0.5, 0.5), base + rng.range(-1.5, 0.5)]);
        s.quats.push([rng.normal(), rng.normal(), rng.normal(), rng.normal()]);
        s.opacities.push(if rng.f32() < 0.3 { rng.range(3.0, 8.0) } else { rng.range(-4.0, 3.0) });
        for k in 0..coeffs {
            for _ in 0..3 {
                s.sh.push(if k == 0 { rng.range(-1.6, 1.6) } else { rng.range(-0.4, 0.4) });
            }
        }
    }
    s
}

/// `n` splats a few pixels wide crowded into the tiles around the centre of the returned 64 x 48
/// view: with a whole tile column per invocation (the CPU policy) their loop costs exceed
/// BLEND_LOOP_ITERATIONS, with one pixel per invocation (the GPU policy) they do not, so the two
/// policies run both the crowded-tile and the row-loop pipelines of blend and blend_backward.
#[allow(dead_code)]
pub fn crowded_scene(rng: &mut Rng, n: usize) -> (Scene, Camera) {
    let mut s = random_scene(rng, n, 1);
    for i in 0..n {
        s.means[i] = [rng.range(-0.1, 0.1), rng.range(-0.1, 0.1), rng.range(-0.5, 0.5)];
        s.scales[i] = [rng.range(-2.8, -2.2), rng.range(-2.8, -2.2), rng.range(-2.8, -2.2)];
        s.opacities[i] = rng.range(-6.0, -2.0);
    }
    (s, look_at(Vec3::new(0.0, 0.0, -5.0), Vec3::ZERO, -Vec3::Y, 64, 48, 60.0))
}

/// One 16 x 16 tile holding more splats than lavapipe's 65 535 loop iterations per invocation:
/// `near` sub-pixel splats over columns 0-1 (depth 3.5-4.5) in front of 2 000 over columns
/// 13-15 (depth 6), so the right columns' invocations pass every near splat before they reach
/// the ones they blend (and blend_backward, back to front, the other way round).
#[allow(dead_code)]
pub fn overfull_tile_scene(rng: &mut Rng, near: usize) -> (Scene, Camera) {
    let cam = look_at(Vec3::new(0.0, 0.0, -5.0), Vec3::ZERO, -Vec3::Y, 16, 16, 20.0);
    let to_world = cam.viewmat.inverse();
    let mut s = random_scene(rng, near + 2000, 0);
    for i in 0..s.len() {
        let (u, z) = if i < near { (rng.range(0.3, 1.7), rng.range(3.5, 4.5)) } else { (rng.range(13.0, 15.7), 6.0) };
        let v = rng.range(0.3, 15.7);
        let c = Vec3::new((u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z);
        s.means[i] = to_world.transform_point3(c).to_array();
        let sigma = (0.35 * z / cam.fx).ln();
        s.scales[i] = [sigma; 3];
        s.opacities[i] = rng.range(-1.0, 1.0);
    }
    (s, cam)
}

/// A fresh folder under cargo's per-test temporary directory.
#[allow(dead_code)]
pub fn tempdir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

pub fn random_quat(rng: &mut Rng) -> glam::Quat {
    glam::Quat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize()
}

/// A small template around the origin (radius ~0.4).
pub fn template(rng: &mut Rng, n: usize, deg: u32) -> instgs_vk::model::scene::Scene {
    let mut t = random_scene(rng, n, deg);
    for m in &mut t.means {
        *m = m.map(|v| 0.3 * v);
    }
    for s in &mut t.scales {
        *s = s.map(|v| v - 0.5);
    }
    t
}

/// Groups of (template Gaussians, instances) with random similarity transforms (scale
/// 0.6–1.5) and offsets, and `background` plain Gaussians.
pub fn random_instanced(
    rng: &mut Rng,
    deg: u32,
    background: usize,
    groups: &[(usize, usize)],
) -> instgs_vk::model::instanced::InstancedScene {
    let mut bg = random_scene(rng, background, deg);
    bg.sh_degree = deg;
    let groups = groups
        .iter()
        .enumerate()
        .map(|(g, &(t, k))| {
            let template = template(rng, t, deg);
            let instances = (0..k)
                .map(|i| instgs_vk::model::instanced::Instance {
                    id: format!("{}", i + 1),
                    transform: instgs_vk::model::instanced::Similarity::from_parts(
                        random_quat(rng),
                        rng.range(0.6, 1.5),
                        Vec3::new(rng.range(-1.0, 1.0), rng.range(-0.8, 0.8), rng.range(-1.0, 1.0)),
                    ),
                })
                .collect::<Vec<_>>();
            let n = t * k;
            let mut offsets = instgs_vk::model::instanced::Offsets::zeros(n);
            for p in 0..n {
                offsets.d_means[p] = [0.0; 3].map(|_| 0.03 * rng.normal());
                offsets.d_sh0[p] = [0.0; 3].map(|_| 0.2 * rng.normal());
                offsets.d_opacities[p] = 0.5 * rng.normal();
            }
            instgs_vk::model::instanced::Group { name: format!("group{g}"), template, instances, offsets }
        })
        .collect();
    instgs_vk::model::instanced::InstancedScene { sh_degree: deg, background: bg, groups }
}

/// Environment that pins a spawned `instgs-vk` to lavapipe with one thread, where the machine
/// has lavapipe: its float atomics then add in a fixed order and runs repeat bit for bit. None on
/// a machine without it (a GPU's float atomics add in whatever order the threads arrive).
pub fn lavapipe_one_thread_env() -> Option<[(&'static str, &'static str); 2]> {
    let opts = GpuOptions { device: Some("llvmpipe".into()), ..Default::default() };
    Gpu::new(&opts).ok().map(|_| [("INSTGS_DEVICE", "llvmpipe"), ("LP_NUM_THREADS", "1")])
}

/// What a run of the binary left: its exit status and standard error.
pub struct BinOut {
    pub ok: bool,
    /// The exit status (None: killed by a signal).
    #[allow(dead_code)]
    pub code: Option<i32>,
    pub stderr: String,
}

/// Starts `instgs-vk` with validation layers on (stdout discarded, stderr piped).
pub fn spawn_bin(args: &[&str], env: &[(&str, &str)]) -> std::process::Child {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_instgs-vk"));
    c.args(args).env("INSTGS_VALIDATION", "1").stdout(std::process::Stdio::null()).stderr(std::process::Stdio::piped());
    for (k, v) in env {
        c.env(k, v);
    }
    c.spawn().unwrap()
}

/// Waits for a spawned binary (900 s guard), collects stderr, and fails on a panic.
pub fn finish_bin(mut child: std::process::Child, what: &str) -> BinOut {
    let stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        for l in std::io::BufRead::lines(std::io::BufReader::new(stderr)) {
            s.push_str(&l.unwrap_or_default());
            s.push('\n');
        }
        s
    });
    let start = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > std::time::Duration::from_secs(900) {
            child.kill().unwrap();
            panic!("{what} hung");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let status = child.wait().unwrap();
    let stderr = reader.join().unwrap();
    assert!(!stderr.contains("panicked"), "{what} panicked:\n{stderr}");
    BinOut { ok: status.success(), code: status.code(), stderr }
}

/// Runs `instgs-vk` to the end.
pub fn run_bin(args: &[&str], env: &[(&str, &str)]) -> BinOut {
    finish_bin(spawn_bin(args, env), &format!("instgs-vk {args:?}"))
}
