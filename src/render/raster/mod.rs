//! The GPU forward rasterizer: a scene on the device and the per-frame passes
//! preprocess → scan visible → compact → depth sort → scan tiles → emit → tile sort → ranges →
//! blend, all sized on the GPU (indirect dispatch from GPU-written counts), or with
//! [`Forward::Quads`] the depth-sorted splats drawn as quads after the depth sort ([`quads`]). The command buffer is
//! recorded once per scene, image size and intersection capacity and replayed for every frame.
//! [`Rasterizer::render`] reads the image back; [`Rasterizer::render_resident`] (bench, player)
//! leaves it on the device. Either way the GPU copies its 32-byte counts into host-visible
//! memory, which the host reads after the frame's fence to grow the intersection buffers when a
//! frame needed more than they hold (the tile lists are clamped to capacity, so such a frame is
//! incomplete, never out of bounds, and is rendered again).
use std::sync::Arc;

use anyhow::{bail, Result};
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::{scan_blocks_for, sort_hist_for, Counts, Kernels};
use crate::gpu::{Buffer, CommandBuffer, Gpu, Timer};
use crate::model::camera::Camera;
use crate::shared::*;

pub mod backward;
pub mod quads;
mod record;

pub use quads::Forward;
use quads::QuadBufs;

use crate::render::upload::GpuScene;

/// Near and far planes (camera z) used for culling, as gsplat's defaults.
pub const NEAR_PLANE: f32 = 0.01;
pub const FAR_PLANE: f32 = 1e10;

/// The per-frame uniform block for a camera.
pub fn frame_params(
    num_gaussians: usize,
    sh_degree: u32,
    cam: &Camera,
    background: [f32; 3],
    isect_capacity: u32,
) -> FrameParams {
    let pos = cam.position();
    FrameParams {
        viewmat: cam.viewmat.to_cols_array_2d(),
        intrinsics: [cam.fx, cam.fy, cam.cx, cam.cy],
        campos: [pos.x, pos.y, pos.z, 1.0],
        background: [background[0], background[1], background[2], 1.0],
        width: cam.width,
        height: cam.height,
        tiles_x: cam.width.div_ceil(TILE_SIZE),
        tiles_y: cam.height.div_ceil(TILE_SIZE),
        num_gaussians: num_gaussians as u32,
        sh_degree,
        sh_coeffs: (sh_degree + 1) * (sh_degree + 1),
        isect_capacity,
        near_plane: NEAR_PLANE,
        far_plane: FAR_PLANE,
        num_background: num_gaussians as u32,
        num_groups: 0,
        num_rows: num_gaussians as u32,
        xform_grads: 0,
        select: 0,
        num_instances: 0,
        offset_storage: OFFSETS_F32,
        num_visible: 0,
        tile_cost_weight: 0.0,
        _pad2: 0,
    }
}

impl GpuScene {
    /// The frame parameters for this scene.
    pub(crate) fn frame_params(&self, cam: &Camera, background: [f32; 3], isect_capacity: u32) -> FrameParams {
        let mut fp = frame_params(self.len, self.sh_degree, cam, background, isect_capacity);
        fp.sh_degree = self.active_sh_degree;
        fp.num_background = self.num_background as u32;
        fp.num_groups = self.inst.num_groups;
        fp.num_rows = self.rows as u32;
        fp.xform_grads = self.inst.xform_grads as u32;
        fp.select = self.inst.select.is_some() as u32;
        fp.num_instances = self.inst.instances as u32;
        fp.offset_storage = self.inst.storage;
        fp
    }
}

/// Per-Gaussian frame buffers (capacity `n`).
struct GaussBufs {
    n: usize,
    xys: Buffer,
    conics: Buffer,
    colours: Buffer,
    depths: Buffer,
    radii: Buffer,
    tiles_touched: Buffer,
    vis_offsets: Buffer,
    depth_keys: [Buffer; 2],
    depth_ids: [Buffer; 2],
    isect_offsets: Buffer,
}

impl GaussBufs {
    /// The per-splat buffers (the depth keys and ids aside).
    fn per_splat(&self) -> [&Buffer; 8] {
        [
            &self.xys,
            &self.conics,
            &self.colours,
            &self.depths,
            &self.radii,
            &self.tiles_touched,
            &self.vis_offsets,
            &self.isect_offsets,
        ]
    }
}

/// Intersection buffers (capacity `cap`), the scan and sort scratch and the image.
struct IsectBufs {
    cap: usize,
    keys: [Buffer; 2],
    ids: [Buffer; 2],
    hist: Buffer,
    block_sums: Buffer,
}

/// Per-instance buffers of `instance_select` (capacity `n` instances).
struct SelectBufs {
    n: usize,
    inst_count: Buffer,
    inst_level: Buffer,
    inst_offsets: Buffer,
    block_sums: Buffer,
}

struct ImageBufs {
    width: u32,
    height: u32,
    ranges: Buffer,
    /// Per tile: the most loop iterations its splats can cost a blend invocation (emit).
    tile_costs: Buffer,
    out_image: Buffer,
    last: Buffer,
    /// Allocated on the first frame that reads its image back.
    readback_image: Option<Buffer>,
}

/// Counts and timings of one frame.
#[derive(Clone, Debug, Default)]
pub struct FrameStats {
    pub visible: u32,
    pub intersections: u32,
    /// GPU milliseconds per pass, in execution order (empty without timestamps).
    pub passes: Vec<(String, f64)>,
}

/// The result of one frame.
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Row-major RGBA: rgb = C + T·background, a = final transmittance T.
    pub image: Vec<[f32; 4]>,
    pub visible: u32,
    pub intersections: u32,
    /// GPU milliseconds per pass, in execution order (empty without timestamps).
    pub passes: Vec<(String, f64)>,
}

/// Everything a test needs to check each pass against its CPU twin.
pub struct FrameState {
    /// The preprocess pass's per-Gaussian output.
    pub projected: crate::render::reference::forward::Projected,
    pub depth_keys: Vec<u32>,
    pub depth_ids: Vec<u32>,
    pub isect_offsets: Vec<u32>,
    pub isect_keys: Vec<u32>,
    pub isect_ids: Vec<u32>,
    pub ranges: Vec<[u32; 2]>,
    /// emit's per-tile blend loop costs.
    pub tile_costs: Vec<u32>,
    pub counts: Vec<u32>,
    /// With per-frame instance selection: each instance's splat count, level and scanned offset.
    pub selection: Option<Selection>,
}

/// What `instance_select` chose for every instance in a frame.
pub struct Selection {
    pub inst_count: Vec<u32>,
    pub inst_level: Vec<u32>,
    pub inst_offsets: Vec<u32>,
}

pub struct Rasterizer {
    gpu: Arc<Gpu>,
    k: Arc<Kernels>,
    frame_ub: Buffer,
    counts: Counts,
    readback_counts: Buffer,
    gauss: Option<GaussBufs>,
    isect: Option<IsectBufs>,
    image: Option<ImageBufs>,
    select: Option<SelectBufs>,
    /// Bound where a kernel's instance-selection buffers are unused (exact rendering).
    placeholder: Buffer,
    /// How sorted splats become pixels ([`Rasterizer::set_forward`]): never `Auto` here.
    forward: Forward,
    /// `Auto` was asked for and the first frame has not chosen yet.
    choose_forward: bool,
    /// The draw path's pipelines and target (with [`Forward::Quads`]).
    quads: Option<QuadBufs>,
    cmd: CommandBuffer,
    timer: Option<Timer>,
    /// (scene buffer handle, N, width, height, capacity, image read back) the command buffer
    /// was recorded for.
    recorded: Option<RecordKey>,
    /// Buffer indices holding the sorted depth and tile lists.
    depth_result: usize,
    isect_result: usize,
    /// The frame parameters of the last rendered frame.
    last_params: Option<FrameParams>,
    /// Tests: fill every output buffer with [`POISON`] before the kernels run, so elements a
    /// kernel fails to write show up.
    pub poison: bool,
    /// Training's frame-cost regulariser, written into every frame's parameters
    /// (`FrameParams::tile_cost_weight`, read by the backward pass only); 0: off.
    pub tile_cost_weight: f32,
}

/// What a recorded frame depends on: scene id, per-splat capacity, width, height,
/// intersection capacity, image read back, instance-selection push constants (as bits), the
/// forward path.
type RecordKey = (u64, usize, u32, u32, usize, bool, Option<[u32; 3]>, Forward);

/// A quiet-NaN bit pattern that no kernel writes.
pub const POISON: u32 = 0x7fc0_0bad;

// glsl/frame.glsl reads the frame parameters as 12 RGBA32UI texels.
const _: () = assert!(std::mem::size_of::<FrameParams>() == 12 * 16);

impl Rasterizer {
    pub fn new(gpu: &Arc<Gpu>, k: &Arc<Kernels>) -> Result<Rasterizer> {
        Ok(Rasterizer {
            gpu: gpu.clone(),
            k: k.clone(),
            frame_ub: gpu.buffer(
                "frame",
                std::mem::size_of::<FrameParams>() as u64,
                ash::vk::BufferUsageFlags::STORAGE_BUFFER,
                MemoryLocation::CpuToGpu,
            )?,
            counts: Counts::new(gpu)?,
            readback_counts: gpu.buffer(
                "readback-counts",
                COUNT_SLOTS as u64 * 4,
                Default::default(),
                MemoryLocation::GpuToCpu,
            )?,
            gauss: None,
            isect: None,
            image: None,
            select: None,
            placeholder: gpu.storage("placeholder", 16)?,
            forward: Forward::Compute,
            choose_forward: false,
            quads: None,
            cmd: CommandBuffer::new(gpu)?,
            timer: Timer::new(gpu, 32)?,
            recorded: None,
            depth_result: 0,
            isect_result: 0,
            last_params: None,
            poison: false,
            tile_cost_weight: 0.0,
        })
    }

    /// Chooses the forward path (default [`Forward::Compute`]); [`Forward::Quads`] builds the
    /// draw pipelines and fails on a device that cannot draw them; [`Forward::Auto`] times both
    /// on the first frame (where the device can draw; else compute).
    pub fn set_forward(&mut self, forward: Forward) -> Result<()> {
        let usable = self.gpu.info.draws;
        if (forward == Forward::Quads || (forward == Forward::Auto && usable)) && self.quads.is_none() {
            self.quads = Some(QuadBufs::new(&self.gpu)?);
        }
        self.choose_forward = forward == Forward::Auto && usable;
        self.forward = if forward == Forward::Quads { Forward::Quads } else { Forward::Compute };
        Ok(())
    }

    /// The forward path in use (with `Auto`, the chosen one once a frame was rendered).
    pub fn forward(&self) -> Forward {
        self.forward
    }

    /// `Auto`'s choice: three frames of each path, alternating, from the first camera; the
    /// lower median wall-clock frame time (submission to fence) wins, ties to compute (the
    /// reference). Not GPU timestamps: lavapipe's shift between passes once a context has drawn.
    fn choose_forward(&mut self, scene: &GpuScene, cam: &Camera, background: [f32; 3]) -> Result<()> {
        self.choose_forward = false;
        let mut ms = [Vec::new(), Vec::new()];
        for _ in 0..3 {
            for (i, f) in [Forward::Compute, Forward::Quads].into_iter().enumerate() {
                self.forward = f;
                let t0 = std::time::Instant::now();
                self.render_frame(scene, cam, background, false)?;
                ms[i].push(t0.elapsed().as_secs_f64() * 1e3);
            }
        }
        let (compute, quads) = (crate::math::median(&ms[0]), crate::math::median(&ms[1]));
        self.forward = if quads < compute { Forward::Quads } else { Forward::Compute };
        eprintln!(
            "forward path: {} (first frame: compute {compute:.2} ms, quads {quads:.2} ms)",
            if self.forward == Forward::Quads { "quads" } else { "compute" }
        );
        Ok(())
    }

    /// Bytes of the per-frame device buffers.
    pub fn frame_gpu_bytes(&self) -> u64 {
        let mut b =
            self.frame_ub.size + self.counts.counts.size + self.counts.indirect.size + self.readback_counts.size;
        if let Some(g) = &self.gauss {
            b += g.per_splat().iter().map(|x| x.size).sum::<u64>();
            b += g.depth_keys.iter().chain(&g.depth_ids).map(|x| x.size).sum::<u64>();
        }
        if let Some(i) = &self.isect {
            b += i.keys.iter().chain(&i.ids).map(|x| x.size).sum::<u64>() + i.hist.size + i.block_sums.size;
        }
        if let Some(s) = &self.select {
            b += s.inst_count.size + s.inst_level.size + s.inst_offsets.size + s.block_sums.size;
        }
        if let Some(im) = &self.image {
            b += im.ranges.size + im.out_image.size + im.last.size + im.readback_image.as_ref().map_or(0, |r| r.size);
        }
        b + self.quads.as_ref().map_or(0, |q| q.bytes())
    }

    fn ensure_buffers(
        &mut self,
        n: usize,
        instances: usize,
        width: u32,
        height: u32,
        cap: usize,
        readback: bool,
    ) -> Result<()> {
        let gpu = self.gpu.clone();
        if instances > 0 && self.select.as_ref().is_none_or(|s| s.n < instances) {
            let b = instances as u64 * 4;
            self.select = Some(SelectBufs {
                n: instances,
                inst_count: gpu.storage("inst_count", b)?,
                inst_level: gpu.storage("inst_level", b)?,
                inst_offsets: gpu.storage("inst_offsets", b)?,
                block_sums: gpu.storage("inst_block_sums", scan_blocks_for(&self.k, instances as u64) * 4)?,
            });
        }
        let limit = gpu.info.max_storage_buffer_range;
        if (cap as u64) * 4 > limit {
            bail!(
                "the frame needs {cap} tile intersections, more than one storage buffer can hold on this device (maxStorageBufferRange {limit} bytes); lower the resolution"
            );
        }
        if n as u64 * 16 > limit {
            bail!(
                "the frame needs {n} splats, more than this device's storage buffers hold at 16 bytes each (maxStorageBufferRange {limit} bytes); use level of detail (configs/render.toml) or fewer instances"
            );
        }
        let pixels = width as u64 * height as u64;
        if pixels * 16 > limit {
            bail!("image {width}x{height} is too large for one storage buffer on this device (maxStorageBufferRange {limit} bytes)");
        }
        if self.gauss.as_ref().is_none_or(|g| g.n < n) {
            let b = n as u64 * 4;
            self.gauss = Some(GaussBufs {
                n,
                xys: gpu.storage("xys", b * 2)?,
                conics: gpu.storage("conics", b * 4)?,
                colours: gpu.storage("colours", b * 4)?,
                depths: gpu.storage("depths", b)?,
                radii: gpu.storage("radii", b * 2)?,
                tiles_touched: gpu.storage("tiles_touched", b)?,
                vis_offsets: gpu.storage("vis_offsets", b)?,
                depth_keys: [gpu.storage("depth_keys_a", b)?, gpu.storage("depth_keys_b", b)?],
                depth_ids: [gpu.storage("depth_ids_a", b)?, gpu.storage("depth_ids_b", b)?],
                isect_offsets: gpu.storage("isect_offsets", b)?,
            });
            self.isect = None;
        }
        if self.isect.as_ref().is_none_or(|i| i.cap < cap) {
            let b = cap as u64 * 4;
            let most = (cap.max(n)) as u64;
            self.isect = Some(IsectBufs {
                cap,
                keys: [gpu.storage("isect_keys_a", b)?, gpu.storage("isect_keys_b", b)?],
                ids: [gpu.storage("isect_ids_a", b)?, gpu.storage("isect_ids_b", b)?],
                hist: gpu.storage("sort_hist", sort_hist_for(&self.k, most) * 4)?,
                block_sums: gpu.storage("scan_block_sums", scan_blocks_for(&self.k, n as u64) * 4)?,
            });
        }
        if self.image.as_ref().is_none_or(|im| im.width != width || im.height != height) {
            let tiles = (width.div_ceil(TILE_SIZE) * height.div_ceil(TILE_SIZE)) as u64;
            self.image = Some(ImageBufs {
                width,
                height,
                ranges: gpu.storage("ranges", tiles * 8)?,
                tile_costs: gpu.storage("tile_costs", tiles * 4)?,
                out_image: gpu.storage("out_image", pixels * 16)?,
                last: gpu.storage("last", pixels * 4)?,
                readback_image: None,
            });
        }
        if self.forward == Forward::Quads {
            self.quads.as_mut().unwrap().ensure_target(&gpu, width, height)?;
        }
        let im = self.image.as_mut().unwrap();
        if readback && im.readback_image.is_none() {
            im.readback_image =
                Some(gpu.buffer("readback-image", pixels * 16, Default::default(), MemoryLocation::GpuToCpu)?);
        }
        Ok(())
    }

    /// Renders one frame of `scene` seen by `cam` over `background` (linear RGB in [0, 1]) and
    /// reads the image back.
    pub fn render(&mut self, scene: &GpuScene, cam: &Camera, background: [f32; 3]) -> Result<Frame> {
        if self.choose_forward {
            self.choose_forward(scene, cam, background)?;
        }
        let stats = self.render_frame(scene, cam, background, true)?;
        let im = self.image.as_ref().unwrap();
        let image = im.readback_image.as_ref().unwrap().read_mapped((cam.width * cam.height) as usize)?;
        Ok(Frame {
            width: cam.width,
            height: cam.height,
            image,
            visible: stats.visible,
            intersections: stats.intersections,
            passes: stats.passes,
        })
    }

    /// Renders one frame and leaves the image on the device ([`Rasterizer::image_buffer`]):
    /// the steady state of the bench and the player, where nothing but the counts is read.
    pub fn render_resident(&mut self, scene: &GpuScene, cam: &Camera, background: [f32; 3]) -> Result<FrameStats> {
        if self.choose_forward {
            self.choose_forward(scene, cam, background)?;
        }
        self.render_frame(scene, cam, background, false)
    }

    fn render_frame(
        &mut self,
        scene: &GpuScene,
        cam: &Camera,
        background: [f32; 3],
        readback: bool,
    ) -> Result<FrameStats> {
        cam.validate()?;
        // Per-splat capacity: every splat, or with per-frame selection what frames needed so
        // far (grown below when a frame needs more).
        let selecting = scene.inst.select.is_some();
        let first = (scene.len / 4).max(1024).min(scene.len);
        let mut n = if selecting { self.gauss.as_ref().map_or(first, |g| g.n) } else { scene.len };
        let mut cap = self.isect.as_ref().map_or(n.max(1 << 16), |i| i.cap);
        loop {
            self.ensure_buffers(n, scene.inst.instances, cam.width, cam.height, cap, readback)?;
            n = self.gauss.as_ref().unwrap().n;
            cap = self.isect.as_ref().unwrap().cap;
            let mut fp = scene.frame_params(cam, background, cap as u32);
            fp.tile_cost_weight = self.tile_cost_weight;
            self.frame_ub.write_mapped(&[fp])?;
            let select = scene.inst.select.map(|a| [a.max_level, a.splats_per_pixel.to_bits(), a.margin_px.to_bits()]);
            let key = (scene.id, n, cam.width, cam.height, cap, readback, select, self.forward);
            if self.recorded != Some(key) || self.poison {
                self.record(scene, &fp, readback)?;
                self.recorded = Some(key);
            }
            self.cmd.submit_and_wait()?;
            self.last_params = Some(fp);
            let counts: Vec<u32> = self.readback_counts.read_mapped(COUNT_SLOTS as usize)?;
            let splats = counts[COUNT_SPLATS_NEEDED as usize] as usize;
            if selecting && splats > n {
                n = (splats + splats / 4).min(scene.len);
                continue;
            }
            let needed = counts[COUNT_ISECT_NEEDED as usize] as usize;
            if needed > cap {
                // Grow with headroom and render the frame again.
                cap = needed + needed / 4;
                continue;
            }
            let passes = match &self.timer {
                Some(t) => t.results()?.into_iter().filter(|(n, _)| n != "setup" && n != "readback").collect(),
                None => Vec::new(),
            };
            return Ok(FrameStats {
                visible: counts[COUNT_VISIBLE as usize],
                intersections: counts[COUNT_ISECT as usize],
                passes,
            });
        }
    }

    /// The last frame's intersections from its first `splats` splats (at most the frame's splat
    /// count, which instance selection makes GPU-written): an instanced scene's background is
    /// splats 0 .. num_background with or without selection.
    pub fn intersections_of_first(&self, splats: usize) -> Result<u64> {
        let g = self.gauss.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        let counts: Vec<u32> = self.gpu.read(&self.counts.counts, COUNT_SLOTS as usize)?;
        let n = (counts[COUNT_GAUSSIANS as usize] as usize).min(splats);
        let touched: Vec<u32> = self.gpu.read(&g.tiles_touched, n)?;
        Ok(touched.iter().map(|&t| t as u64).sum())
    }

    /// Reads every intermediate buffer of the last frame (for tests).
    pub fn read_state(&self) -> Result<FrameState> {
        let gpu = &self.gpu;
        let g = self.gauss.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        let is = self.isect.as_ref().unwrap();
        let im = self.image.as_ref().unwrap();
        let counts: Vec<u32> = gpu.read(&self.counts.counts, COUNT_SLOTS as usize)?;
        let n = self.recorded.unwrap().1;
        let vis = counts[COUNT_VISIBLE as usize] as usize;
        let m = counts[COUNT_ISECT as usize] as usize;
        let tiles = (im.width.div_ceil(TILE_SIZE) * im.height.div_ceil(TILE_SIZE)) as usize;
        Ok(FrameState {
            projected: crate::render::reference::forward::Projected {
                xys: gpu.read(&g.xys, n)?,
                conics: gpu.read(&g.conics, n)?,
                colours: gpu.read(&g.colours, n)?,
                depths: gpu.read(&g.depths, n)?,
                radii: gpu.read(&g.radii, n)?,
                tiles_touched: gpu.read(&g.tiles_touched, n)?,
            },
            depth_keys: gpu.read(&g.depth_keys[self.depth_result], vis)?,
            depth_ids: gpu.read(&g.depth_ids[self.depth_result], vis)?,
            isect_offsets: gpu.read(&g.isect_offsets, vis)?,
            isect_keys: gpu.read(&is.keys[self.isect_result], m)?,
            isect_ids: gpu.read(&is.ids[self.isect_result], m)?,
            ranges: gpu.read(&im.ranges, tiles)?,
            tile_costs: gpu.read(&im.tile_costs, tiles)?,
            selection: match (&self.select, self.last_params.is_some_and(|p| p.select != 0)) {
                (Some(s), true) => {
                    let ni = self.last_params.unwrap().num_instances as usize;
                    Some(Selection {
                        inst_count: gpu.read(&s.inst_count, ni)?,
                        inst_level: gpu.read(&s.inst_level, ni)?,
                        inst_offsets: gpu.read(&s.inst_offsets, ni)?,
                    })
                }
                _ => None,
            },
            counts,
        })
    }
}
