//! The GPU forward rasterizer: a scene on the device and the per-frame passes
//! preprocess → scan visible → compact → depth sort → scan tiles → emit → tile sort → ranges →
//! blend, all sized on the GPU (indirect dispatch from GPU-written counts). The command buffer is
//! recorded once per scene, image size and intersection capacity and replayed for every frame.
//! [`Rasterizer::render`] reads the image back; [`Rasterizer::render_resident`] (bench, player)
//! leaves it on the device. Either way the GPU copies its 32-byte counts into host-visible
//! memory, which the host reads after the frame's fence to grow the intersection buffers when a
//! frame needed more than they hold (the tile lists are clamped to capacity, so such a frame is
//! incomplete, never out of bounds, and is rendered again).
use std::sync::Arc;

use anyhow::{bail, Result};
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::{
    bits_for, record_scan, record_sort, scan_blocks_for, sort_hist_for, Counts, Kernels, Scan, SortBuffers,
};
use crate::gpu::{Buffer, CommandBuffer, Gpu, Recorder, Timer};
use crate::model::camera::Camera;
use crate::model::instanced::{InstancedScene, Offsets};
use crate::model::scene::Scene;
use crate::shared::*;

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
        offset_codes: 0,
        num_visible: 0,
        _pad1: 0,
        _pad2: 0,
    }
}

/// The instancing tables of a scene in device memory (instance.glsl). A plain scene has no groups
/// and one-element placeholders (every binding needs a buffer).
pub struct GpuInstancing {
    pub groups: Buffer,
    pub xforms: Buffer,
    /// Offsets per (template Gaussian, instance) pair, pair index = splat − num_background:
    /// Δp (3 f32), Δ SH DC (3 f32), Δ opacity logit (f32).
    pub d_means: Buffer,
    pub d_sh0: Buffer,
    pub d_opacities: Buffer,
    /// Product-quantised offsets (`crate::formats::pq8`; placeholders unless `codes`): 16 bits per
    /// pair, and per group 512 codebook entries (vec4).
    pub d_codes: Buffer,
    pub codebooks: Buffer,
    pub codes: bool,
    pub num_groups: u32,
    /// Offset pairs of level 0 (every template Gaussian × its instances); a scene uploaded with
    /// level of detail holds the coarser levels' pairs after these.
    pub pairs: usize,
    pub instances: usize,
    /// Largest |Δp| of each instance (bounding spheres for culling).
    pub max_offsets: Vec<f32>,
    /// Rendering only: instances are culled and their levels chosen each frame
    /// (`instance_select.comp`). None: every pair is rendered (training, evaluation).
    pub select: Option<SelectArgs>,
    /// Backward also computes the instance-transform gradients (`Grads::xforms`).
    pub xform_grads: bool,
}

/// A scene in device memory: parameter rows (background Gaussians, then every group's template
/// Gaussians; a plain scene is all background) and the instancing tables. Rendering expands
/// `len` splats on the fly.
pub struct GpuScene {
    /// Unique per upload (process-wide): recorded command buffers are keyed by it, not by a
    /// buffer handle, which the driver may hand out again once this scene is dropped.
    id: u64,
    pub means: Buffer,
    pub scales: Buffer,
    pub quats: Buffer,
    pub opacities: Buffer,
    pub sh: Buffer,
    /// Parameter rows.
    pub rows: usize,
    /// Splats rendered: background + Σ template Gaussians × instances.
    pub len: usize,
    pub num_background: usize,
    pub inst: GpuInstancing,
    /// SH degree stored (coefficients per channel: (sh_degree + 1)^2).
    pub sh_degree: u32,
    /// SH degree evaluated (≤ sh_degree; training raises it step by step).
    pub active_sh_degree: u32,
}

/// Refuses a scene whose largest buffer (SH coefficients of its rows, or 16 bytes per splat for
/// the per-frame conics) would pass the device's `maxStorageBufferRange`.
pub fn check_scene_fits(rows: usize, splats: usize, sh_degree: u32, limit: u64) -> Result<()> {
    let sh_bytes = rows as u64 * ((sh_degree + 1) * (sh_degree + 1) * 3 * 4) as u64;
    if sh_bytes > limit {
        bail!(
            "scene too large for this device: {rows} Gaussians at SH degree {sh_degree} need a {sh_bytes}-byte SH buffer, over maxStorageBufferRange ({limit} bytes); splitting a scene is not supported"
        );
    }
    if splats as u64 * 16 > limit {
        bail!(
            "scene too large for this device: {splats} splats need {}-byte per-frame buffers, over maxStorageBufferRange ({limit} bytes)",
            splats as u64 * 16
        );
    }
    Ok(())
}

/// Concatenated offsets of every group (pair order).
pub fn all_offsets(scene: &InstancedScene) -> Offsets {
    let mut o = Offsets::default();
    for g in &scene.groups {
        o.d_means.extend_from_slice(&g.offsets.d_means);
        o.d_sh0.extend_from_slice(&g.offsets.d_sh0);
        o.d_opacities.extend_from_slice(&g.offsets.d_opacities);
    }
    o
}

/// The parameter rows of an instanced scene: background, then every template.
pub fn scene_rows(scene: &InstancedScene) -> Scene {
    let mut rows = scene.background.clone();
    rows.sh_degree = scene.sh_degree;
    for g in &scene.groups {
        let t = &g.template;
        rows.means.extend_from_slice(&t.means);
        rows.scales.extend_from_slice(&t.scales);
        rows.quats.extend_from_slice(&t.quats);
        rows.opacities.extend_from_slice(&t.opacities);
        rows.sh.extend_from_slice(&t.sh);
    }
    rows
}

/// The GPU group table (level 0 only) and transforms of an instanced scene, and the largest
/// |Δp| of each instance.
pub fn instancing_tables(scene: &InstancedScene) -> (Vec<GroupInfo>, Vec<InstanceXform>, Vec<f32>) {
    let mut groups = Vec::new();
    let mut xforms = Vec::new();
    let mut max_offsets = Vec::new();
    let nb = scene.background.len();
    let mut splat = nb;
    let mut row = nb;
    for g in &scene.groups {
        let (t, k) = (g.template.len(), g.instances.len());
        let one = |v: usize| [v as u32, 0, 0, 0];
        groups.push(GroupInfo {
            splat_first: splat as u32,
            row_first: row as u32,
            rows: t as u32,
            instances: k as u32,
            instance_first: xforms.len() as u32,
            levels: 1,
            level_row_first: one(row),
            level_rows: one(t),
            level_pair_first: one(splat - nb),
            bound: crate::render::lod::bound(&g.template),
            ..Default::default()
        });
        let maxo = crate::render::lod::max_offsets(&g.offsets, t);
        xforms.extend(g.instances.iter().zip(&maxo).map(|(i, &m)| xform(&i.transform, m)));
        max_offsets.extend(maxo);
        splat += t * k;
        row += t;
    }
    (groups, xforms, max_offsets)
}

fn xform(x: &crate::model::instanced::Similarity, max_offset: f32) -> InstanceXform {
    InstanceXform {
        transform: x.render_mat4().to_cols_array_2d(),
        quat: x.quat_wxyz(),
        scale: [x.scale, x.scale.ln(), max_offset, 0.0],
    }
}

/// A storage buffer holding `data` in whole vec4s (size rounded up to 16 bytes, the padding
/// undefined): kernels read SH rows as vec4s, up to 3 floats past a row's end (glsl/sh.glsl).
fn upload_whole_vec4s(gpu: &Arc<Gpu>, name: &str, data: &[f32]) -> Result<Buffer> {
    let buf = gpu.storage(name, (std::mem::size_of_val(data) as u64).next_multiple_of(16))?;
    gpu.write(&buf, data)?;
    Ok(buf)
}

/// Uploads `data`, or one zero element where it is empty (placeholder binding).
fn upload_or_placeholder<T: bytemuck::Pod + Default>(gpu: &Arc<Gpu>, name: &str, data: &[T]) -> Result<Buffer> {
    if data.is_empty() {
        gpu.upload(name, &[T::default()])
    } else {
        gpu.upload(name, data)
    }
}

impl GpuScene {
    /// A plain 3DGS scene.
    pub fn new(gpu: &Arc<Gpu>, scene: &Scene) -> Result<GpuScene> {
        Self::upload(gpu, scene, scene.len(), scene.len(), &[], &[], &Offsets::default(), true)
    }

    /// An instanced scene; nothing is expanded. Every pair is rendered (training, evaluation).
    pub fn instanced(gpu: &Arc<Gpu>, scene: &InstancedScene) -> Result<GpuScene> {
        let (groups, xforms, max_offsets) = instancing_tables(scene);
        let offsets = all_offsets(scene);
        let splats = scene.splats();
        let mut gs =
            Self::upload(gpu, &scene_rows(scene), scene.background.len(), splats, &groups, &xforms, &offsets, true)?;
        gs.inst.max_offsets = max_offsets;
        Ok(gs)
    }

    /// An instanced scene for viewing: instances culled per frame and, with `cfg.lod.enabled`,
    /// every template's coarser levels built and uploaded too (`crate::render::lod`).
    pub fn instanced_for_rendering(
        gpu: &Arc<Gpu>,
        scene: &InstancedScene,
        cfg: &crate::render::lod::RenderConfig,
    ) -> Result<GpuScene> {
        let (mut groups, xforms, max_offsets) = instancing_tables(scene);
        let mut rows = scene_rows(scene);
        let mut offsets = all_offsets(scene);
        // Offsets that are product-quantised already (a pq8 file) stay so on the device.
        let books: Option<Vec<crate::formats::pq8::OffsetCodes>> =
            scene.groups.iter().map(|g| crate::formats::pq8::OffsetCodes::exact(&g.offsets)).collect();
        let mut codes: Vec<[u8; 2]> = books.iter().flatten().flat_map(|b| b.codes.iter().copied()).collect();
        let fractions: &[f32] = if cfg.lod.enabled { &cfg.lod.fractions } else { &[] };
        for (gi, (info, g)) in groups.iter_mut().zip(&scene.groups).enumerate() {
            let levels = crate::render::lod::build_levels(&g.template, &g.offsets, g.instances.len(), fractions);
            for (l, (t, o)) in levels.into_iter().enumerate() {
                if let Some(b) = &books {
                    // Coarser levels' merged offsets take their nearest codes.
                    codes.extend(b[gi].assign(&o));
                }
                info.level_row_first[l + 1] = rows.len() as u32;
                info.level_rows[l + 1] = t.len() as u32;
                info.level_pair_first[l + 1] = offsets.len() as u32;
                rows.means.extend_from_slice(&t.means);
                rows.scales.extend_from_slice(&t.scales);
                rows.quats.extend_from_slice(&t.quats);
                rows.opacities.extend_from_slice(&t.opacities);
                rows.sh.extend_from_slice(&t.sh);
                offsets.d_means.extend_from_slice(&o.d_means);
                offsets.d_sh0.extend_from_slice(&o.d_sh0);
                offsets.d_opacities.extend_from_slice(&o.d_opacities);
                info.levels = l as u32 + 2;
            }
        }
        let nb = scene.background.len();
        let selecting = !groups.is_empty() && (cfg.cull || cfg.lod.enabled);
        let mut gs = match &books {
            Some(b) => {
                let pairs = offsets.len();
                let mut gs =
                    Self::upload(gpu, &rows, nb, scene.splats(), &groups, &xforms, &Offsets::default(), !selecting)?;
                let mut words = vec![0u32; pairs.div_ceil(2)];
                for (p, c) in codes.iter().enumerate() {
                    words[p / 2] |= (c[0] as u32 | (c[1] as u32) << 8) << (16 * (p % 2));
                }
                let table: Vec<[f32; 4]> = b
                    .iter()
                    .flat_map(|b| b.dp.iter().map(|p| [p[0], p[1], p[2], 0.0]).chain(b.dc.iter().copied()))
                    .collect();
                gs.inst.d_codes = upload_or_placeholder(gpu, "d_codes", &words)?;
                gs.inst.codebooks = upload_or_placeholder(gpu, "codebooks", &table)?;
                gs.inst.codes = true;
                gs
            }
            None => Self::upload(gpu, &rows, nb, scene.splats(), &groups, &xforms, &offsets, !selecting)?,
        };
        gs.inst.pairs = scene.splats() - nb;
        gs.inst.max_offsets = max_offsets;
        if selecting {
            gs.inst.select = Some(SelectArgs {
                max_level: fractions.len() as u32,
                splats_per_pixel: cfg.lod.splats_per_pixel,
                margin_px: if cfg.cull { cfg.cull_margin_px } else { f32::NEG_INFINITY },
                _pad0: 0,
            });
        }
        Ok(gs)
    }

    #[allow(clippy::too_many_arguments)]
    fn upload(
        gpu: &Arc<Gpu>,
        rows: &Scene,
        num_background: usize,
        splats: usize,
        groups: &[GroupInfo],
        xforms: &[InstanceXform],
        offsets: &Offsets,
        frames_expand_all: bool,
    ) -> Result<GpuScene> {
        let n = rows.len();
        if n == 0 {
            bail!("the scene has no Gaussians");
        }
        // Frames of a scene rendered with per-frame selection size their buffers by what they
        // select (checked per frame), the others by every splat.
        let frame_splats = if frames_expand_all { splats } else { 0 };
        check_scene_fits(n, frame_splats, rows.sh_degree, gpu.info.max_storage_buffer_range)?;
        static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        Ok(GpuScene {
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            means: gpu.upload("means", &rows.means)?,
            scales: gpu.upload("scales", &rows.scales)?,
            quats: gpu.upload("quats", &rows.quats)?,
            opacities: gpu.upload("opacities", &rows.opacities)?,
            sh: upload_whole_vec4s(gpu, "sh", &rows.sh)?,
            rows: n,
            len: splats,
            num_background,
            inst: GpuInstancing {
                groups: upload_or_placeholder(gpu, "groups", groups)?,
                xforms: upload_or_placeholder(gpu, "xforms", xforms)?,
                d_means: upload_or_placeholder(gpu, "d_means", &offsets.d_means)?,
                d_sh0: upload_or_placeholder(gpu, "d_sh0", &offsets.d_sh0)?,
                d_opacities: upload_or_placeholder(gpu, "d_opacities", &offsets.d_opacities)?,
                d_codes: upload_or_placeholder::<u32>(gpu, "d_codes", &[])?,
                codebooks: upload_or_placeholder::<[f32; 4]>(gpu, "codebooks", &[])?,
                codes: false,
                num_groups: groups.len() as u32,
                pairs: offsets.len(),
                instances: xforms.len(),
                max_offsets: Vec::new(),
                select: None,
                xform_grads: false,
            },
            sh_degree: rows.sh_degree,
            active_sh_degree: rows.sh_degree,
        })
    }

    /// Bytes of the scene's device buffers (parameters and instancing tables).
    pub fn gpu_bytes(&self) -> u64 {
        let i = &self.inst;
        [&self.means, &self.scales, &self.quats, &self.opacities, &self.sh]
            .into_iter()
            .chain([&i.groups, &i.xforms, &i.d_means, &i.d_sh0, &i.d_opacities, &i.d_codes, &i.codebooks])
            .map(|b| b.size)
            .sum()
    }

    /// The frame parameters for this scene.
    fn frame_params(&self, cam: &Camera, background: [f32; 3], isect_capacity: u32) -> FrameParams {
        let mut fp = frame_params(self.len, self.sh_degree, cam, background, isect_capacity);
        fp.sh_degree = self.active_sh_degree;
        fp.num_background = self.num_background as u32;
        fp.num_groups = self.inst.num_groups;
        fp.num_rows = self.rows as u32;
        fp.xform_grads = self.inst.xform_grads as u32;
        fp.select = self.inst.select.is_some() as u32;
        fp.num_instances = self.inst.instances as u32;
        fp.offset_codes = self.inst.codes as u32;
        fp
    }

    /// Replaces the instance transforms (instance order: groups, then instances).
    pub fn write_transforms(&self, gpu: &Arc<Gpu>, transforms: &[crate::model::instanced::Similarity]) -> Result<()> {
        if transforms.len() != self.inst.instances {
            bail!("{} transforms for {} instances", transforms.len(), self.inst.instances);
        }
        let maxo = |i: usize| self.inst.max_offsets.get(i).copied().unwrap_or(0.0);
        gpu.write(&self.inst.xforms, &transforms.iter().enumerate().map(|(i, x)| xform(x, maxo(i))).collect::<Vec<_>>())
    }

    /// (name, buffer) bindings of the instancing tables, as instance.glsl names them.
    fn instancing_bindings(&self) -> [(&'static str, &Buffer); 7] {
        let i = &self.inst;
        [
            ("groups", &i.groups),
            ("xforms", &i.xforms),
            ("d_means", &i.d_means),
            ("d_sh0", &i.d_sh0),
            ("d_opacities", &i.d_opacities),
            ("d_codes", &i.d_codes),
            ("codebooks", &i.codebooks),
        ]
    }
}

/// Per-Gaussian frame buffers (capacity `n`).
struct GaussBufs {
    n: usize,
    xys: Buffer,
    conics: Buffer,
    colors: Buffer,
    depths: Buffer,
    radii: Buffer,
    tiles_touched: Buffer,
    vis_offsets: Buffer,
    depth_keys: [Buffer; 2],
    depth_ids: [Buffer; 2],
    isect_offsets: Buffer,
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
}

/// What a recorded frame depends on: scene id, per-splat capacity, width, height,
/// intersection capacity, image read back, instance-selection push constants (as bits).
type RecordKey = (u64, usize, u32, u32, usize, bool, Option<[u32; 3]>);

/// A quiet-NaN bit pattern that no kernel writes.
pub const POISON: u32 = 0x7fc0_0bad;

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
            cmd: CommandBuffer::new(gpu)?,
            timer: Timer::new(gpu, 32)?,
            recorded: None,
            depth_result: 0,
            isect_result: 0,
            last_params: None,
            poison: false,
        })
    }

    /// Bytes of the per-frame device buffers.
    pub fn frame_gpu_bytes(&self) -> u64 {
        let mut b =
            self.frame_ub.size + self.counts.counts.size + self.counts.indirect.size + self.readback_counts.size;
        if let Some(g) = &self.gauss {
            b +=
                [&g.xys, &g.conics, &g.colors, &g.depths, &g.radii, &g.tiles_touched, &g.vis_offsets, &g.isect_offsets]
                    .iter()
                    .map(|x| x.size)
                    .sum::<u64>();
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
        b
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
                block_sums: gpu.storage("inst_block_sums", scan_blocks_for(instances as u64) * 4)?,
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
                colors: gpu.storage("colors", b * 4)?,
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
                block_sums: gpu.storage("scan_block_sums", scan_blocks_for(n as u64) * 4)?,
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
        let im = self.image.as_mut().unwrap();
        if readback && im.readback_image.is_none() {
            im.readback_image =
                Some(gpu.buffer("readback-image", pixels * 16, Default::default(), MemoryLocation::GpuToCpu)?);
        }
        Ok(())
    }

    fn record(&mut self, scene: &GpuScene, fp: &FrameParams, readback: bool) -> Result<()> {
        let k = self.k.clone();
        let g = self.gauss.as_ref().unwrap();
        let is = self.isect.as_ref().unwrap();
        let im = self.image.as_ref().unwrap();
        let c = &self.counts;
        let n = scene.len as u32;
        let select = scene.inst.select.map(|a| (a, self.select.as_ref().unwrap()));
        let placeholder = &self.placeholder;
        let tile_bits = bits_for(fp.tiles_x * fp.tiles_y);
        let cap = is.cap as u32;
        let frame = &self.frame_ub;
        let mut depth_result = 0;
        let mut isect_result = 0;
        let readback_counts = &self.readback_counts;
        let poison = self.poison;
        self.cmd.record_timed(self.timer.as_mut(), |rec| {
            if poison {
                for b in [
                    &g.xys,
                    &g.conics,
                    &g.colors,
                    &g.depths,
                    &g.radii,
                    &g.tiles_touched,
                    &g.vis_offsets,
                    &g.isect_offsets,
                ]
                .into_iter()
                .chain(&g.depth_keys)
                .chain(&g.depth_ids)
                .chain(&is.keys)
                .chain(&is.ids)
                .chain([&im.out_image, &im.last])
                {
                    rec.fill(b, POISON);
                }
            }
            let mut init = [0u32; COUNT_SLOTS as usize];
            init[COUNT_GAUSSIANS as usize] = n;
            init[COUNT_INSTANCES as usize] = scene.inst.instances as u32;
            rec.update(&c.counts, &init);
            rec.fill(&im.ranges, 0);
            rec.fill(&im.tile_costs, 0);
            c.record_args(rec, &k, COUNT_GAUSSIANS)?;
            rec.end_pass("setup")?;
            if let Some((args, sel)) = select {
                if poison {
                    for b in [&sel.inst_count, &sel.inst_level, &sel.inst_offsets] {
                        rec.fill(b, POISON);
                    }
                }
                c.record_args(rec, &k, COUNT_INSTANCES)?;
                rec.dispatch(
                    &k.instance_select,
                    &[
                        ("frame", frame),
                        ("groups", &scene.inst.groups),
                        ("xforms", &scene.inst.xforms),
                        ("inst_count", &sel.inst_count),
                        ("inst_level", &sel.inst_level),
                    ],
                    &args,
                    [(scene.inst.instances as u32).div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
                )?;
                // The frame's splats: background + the selected instances' Gaussians, clamped to
                // the per-splat buffers (the host grows them when more were needed).
                record_scan(
                    rec,
                    &k,
                    c,
                    &Scan {
                        count_slot: COUNT_INSTANCES,
                        mode: SCAN_MODE_VALUE,
                        input: &sel.inst_count,
                        gather: None,
                        block_sums: &sel.block_sums,
                        output: &sel.inst_offsets,
                        out_slot: COUNT_SPLATS_NEEDED,
                        clamp_slot: COUNT_GAUSSIANS,
                        capacity: g.n as u32,
                        out_bias: scene.num_background as u32,
                    },
                )?;
                c.record_args(rec, &k, COUNT_GAUSSIANS)?;
                rec.end_pass("select")?;
            }
            let (inst_offsets, inst_level) =
                select.map_or((placeholder, placeholder), |(_, s)| (&s.inst_offsets, &s.inst_level));
            let bindings: Vec<(&str, &Buffer)> = [
                ("frame", frame),
                ("means", &scene.means),
                ("scales", &scene.scales),
                ("quats", &scene.quats),
                ("opacities", &scene.opacities),
                ("sh", &scene.sh),
                ("xys", &g.xys),
                ("conics", &g.conics),
                ("colors", &g.colors),
                ("depths", &g.depths),
                ("radii", &g.radii),
                ("tiles_touched", &g.tiles_touched),
            ]
            .into_iter()
            .chain(scene.instancing_bindings())
            .chain([("counts", &c.counts), ("inst_offsets", inst_offsets), ("inst_level", inst_level)])
            .collect();
            let items = Counts::args_offset(COUNT_GAUSSIANS, ARGS_ITEMS);
            rec.dispatch_indirect(&k.preprocess, &bindings, &(), &c.indirect, items)?;
            rec.end_pass("preprocess")?;
            record_scan(
                rec,
                &k,
                c,
                &Scan {
                    count_slot: COUNT_GAUSSIANS,
                    mode: SCAN_MODE_NONZERO,
                    input: &g.tiles_touched,
                    gather: None,
                    block_sums: &is.block_sums,
                    output: &g.vis_offsets,
                    out_slot: COUNT_VISIBLE,
                    clamp_slot: NO_SLOT,
                    capacity: 0,
                    out_bias: 0,
                },
            )?;
            rec.dispatch_indirect(
                &k.compact,
                &[
                    ("counts", &c.counts),
                    ("tiles_touched", &g.tiles_touched),
                    ("vis_offsets", &g.vis_offsets),
                    ("depths", &g.depths),
                    ("depth_keys", &g.depth_keys[0]),
                    ("depth_ids", &g.depth_ids[0]),
                ],
                &(),
                &c.indirect,
                items,
            )?;
            c.record_args(rec, &k, COUNT_VISIBLE)?;
            rec.end_pass("scan")?;
            // Depths are positive floats: the sign bit is 0, so 31 bits order them.
            let depth_bufs = SortBuffers {
                keys: [&g.depth_keys[0], &g.depth_keys[1]],
                vals: [&g.depth_ids[0], &g.depth_ids[1]],
                hist: &is.hist,
            };
            depth_result = record_sort(rec, &k, c, COUNT_VISIBLE, 31, &depth_bufs)?;
            rec.end_pass("depth_sort")?;
            let depth_ids = &g.depth_ids[depth_result];
            record_scan(
                rec,
                &k,
                c,
                &Scan {
                    count_slot: COUNT_VISIBLE,
                    mode: SCAN_MODE_GATHER,
                    input: &g.tiles_touched,
                    gather: Some(depth_ids),
                    block_sums: &is.block_sums,
                    output: &g.isect_offsets,
                    out_slot: COUNT_ISECT_NEEDED,
                    clamp_slot: COUNT_ISECT,
                    capacity: cap,
                    out_bias: 0,
                },
            )?;
            rec.end_pass("scan")?;
            rec.dispatch_indirect(
                &k.emit,
                &[
                    ("frame", frame),
                    ("counts", &c.counts),
                    ("depth_ids", depth_ids),
                    ("isect_offsets", &g.isect_offsets),
                    ("xys", &g.xys),
                    ("radii", &g.radii),
                    ("isect_keys", &is.keys[0]),
                    ("isect_ids", &is.ids[0]),
                    ("conics", &g.conics),
                    ("tile_costs", &im.tile_costs),
                ],
                &(),
                &c.indirect,
                Counts::args_offset(COUNT_VISIBLE, ARGS_ITEMS),
            )?;
            c.record_args(rec, &k, COUNT_ISECT)?;
            rec.end_pass("emit")?;
            let tile_bufs =
                SortBuffers { keys: [&is.keys[0], &is.keys[1]], vals: [&is.ids[0], &is.ids[1]], hist: &is.hist };
            isect_result = record_sort(rec, &k, c, COUNT_ISECT, tile_bits, &tile_bufs)?;
            rec.end_pass("tile_sort")?;
            rec.dispatch_indirect(
                &k.ranges,
                &[("counts", &c.counts), ("isect_keys", &is.keys[isect_result]), ("ranges", &im.ranges)],
                &(),
                &c.indirect,
                Counts::args_offset(COUNT_ISECT, ARGS_ITEMS),
            )?;
            rec.end_pass("ranges")?;
            for blend in &k.blend {
                rec.dispatch(
                    blend,
                    &[
                        ("frame", frame),
                        ("ranges", &im.ranges),
                        ("isect_ids", &is.ids[isect_result]),
                        ("xys", &g.xys),
                        ("conics", &g.conics),
                        ("colors", &g.colors),
                        ("out_image", &im.out_image),
                        ("last", &im.last),
                        ("tile_costs", &im.tile_costs),
                    ],
                    &(),
                    [fp.tiles_x, fp.tiles_y, 1],
                )?;
            }
            rec.end_pass("blend")?;
            if readback {
                rec.copy(&im.out_image, im.readback_image.as_ref().unwrap(), im.out_image.size);
            }
            rec.copy(&c.counts, readback_counts, c.counts.size);
            rec.end_pass("readback")
        })?;
        self.depth_result = depth_result;
        self.isect_result = isect_result;
        Ok(())
    }

    /// Renders one frame of `scene` seen by `cam` over `background` (linear RGB in [0, 1]) and
    /// reads the image back.
    pub fn render(&mut self, scene: &GpuScene, cam: &Camera, background: [f32; 3]) -> Result<Frame> {
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
            let fp = scene.frame_params(cam, background, cap as u32);
            self.frame_ub.write_mapped(&[fp])?;
            let select = scene.inst.select.map(|a| [a.max_level, a.splats_per_pixel.to_bits(), a.margin_px.to_bits()]);
            let key = (scene.id, n, cam.width, cam.height, cap, readback, select);
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
                colors: gpu.read(&g.colors, n)?,
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

/// Gradient buffers of one scene: the parameter-row gradients (layouts as [`GpuScene`]), the
/// offset gradients (pair layout), the per-splat projected gradients written by
/// `blend_backward`, and the per-splat densification statistics.
pub struct Grads {
    /// Parameter rows and splats they were made for.
    pub rows: usize,
    pub splats: usize,
    pub means: Buffer,
    pub scales: Buffer,
    pub quats: Buffer,
    pub opacities: Buffer,
    pub sh: Buffer,
    pub d_means: Buffer,
    pub d_sh0: Buffer,
    pub d_opacities: Buffer,
    /// Per-pair transform-gradient terms and their per-instance sums (XFORM_GRAD_TERMS floats
    /// each; placeholders unless the scene computes transform gradients).
    pub xform_terms: Buffer,
    pub xforms: Buffer,
    pub v_xys: Buffer,
    pub v_conics: Buffer,
    pub v_colors: Buffer,
    pub v_opacities: Buffer,
    /// Sum over views of |dL/d mean2d| in Inria's NDC units (f32 per Gaussian).
    pub grad2d_accum: Buffer,
    /// Views in which the Gaussian was visible (u32 per Gaussian).
    pub grad2d_count: Buffer,
    /// Largest screen radius in pixels seen (u32 per Gaussian).
    pub max_radii: Buffer,
}

impl Grads {
    pub fn new(gpu: &Arc<Gpu>, scene: &GpuScene) -> Result<Grads> {
        let r = scene.rows as u64;
        let n = scene.len as u64;
        let pairs = scene.inst.pairs.max(1) as u64;
        let sh = scene.sh.size;
        Ok(Grads {
            rows: scene.rows,
            splats: scene.len,
            means: gpu.storage("grad_means", r * 12)?,
            scales: gpu.storage("grad_scales", r * 12)?,
            quats: gpu.storage("grad_quats", r * 16)?,
            opacities: gpu.storage("grad_opacities", r * 4)?,
            sh: gpu.storage("grad_sh", sh)?,
            d_means: gpu.storage("grad_d_means", pairs * 12)?,
            d_sh0: gpu.storage("grad_d_sh0", pairs * 12)?,
            d_opacities: gpu.storage("grad_d_opacities", pairs * 4)?,
            xform_terms: gpu
                .storage("xform_terms", if scene.inst.xform_grads { pairs } else { 1 } * XFORM_GRAD_TERMS as u64 * 4)?,
            xforms: gpu.storage("grad_xforms", scene.inst.instances.max(1) as u64 * XFORM_GRAD_TERMS as u64 * 4)?,
            v_xys: gpu.storage("v_xys", n * 8)?,
            v_conics: gpu.storage("v_conics", n * 12)?,
            v_colors: gpu.storage("v_colors", n * 12)?,
            v_opacities: gpu.storage("v_opacities", n * 4)?,
            grad2d_accum: gpu.storage("grad2d_accum", n * 4)?,
            grad2d_count: gpu.storage("grad2d_count", n * 4)?,
            max_radii: gpu.storage("max_radii", n * 4)?,
        })
    }

    /// Zeroes the densification statistics.
    pub fn record_reset_stats(&self, rec: &mut Recorder) {
        rec.fill(&self.grad2d_accum, 0);
        rec.fill(&self.grad2d_count, 0);
        rec.fill(&self.max_radii, 0);
    }

    pub fn gpu_bytes(&self) -> u64 {
        [
            &self.means,
            &self.scales,
            &self.quats,
            &self.opacities,
            &self.sh,
            &self.d_means,
            &self.d_sh0,
            &self.d_opacities,
            &self.xform_terms,
            &self.xforms,
            &self.v_xys,
            &self.v_conics,
            &self.v_colors,
            &self.v_opacities,
            &self.grad2d_accum,
            &self.grad2d_count,
            &self.max_radii,
        ]
        .iter()
        .map(|b| b.size)
        .sum()
    }
}

impl Rasterizer {
    /// Records the backward passes of the last rendered frame: `blend_backward` from `v_image`
    /// (dL/d rgb per pixel, RGBA f32) into the projected-splat gradients, then
    /// `preprocess_backward` into the parameter gradients and the densification statistics.
    /// The caller submits; the frame's buffers must not be re-rendered in between.
    pub fn record_backward(&self, rec: &mut Recorder, scene: &GpuScene, v_image: &Buffer, g: &Grads) -> Result<()> {
        self.record_blend_backward(rec, scene, v_image, g)?;
        self.record_preprocess_backward(rec, scene, g)
    }

    /// Records `blend_backward` alone: from `v_image` to the per-splat projected gradients
    /// (v_xys, v_conics, v_colors, v_opacities) of the last rendered frame.
    pub fn record_blend_backward(
        &self,
        rec: &mut Recorder,
        scene: &GpuScene,
        v_image: &Buffer,
        g: &Grads,
    ) -> Result<()> {
        let fp = self.last_params.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        let gb = self.gauss.as_ref().unwrap();
        let is = self.isect.as_ref().unwrap();
        let im = self.image.as_ref().unwrap();
        if g.rows != scene.rows || g.splats != scene.len {
            bail!(
                "gradient buffers hold {} rows and {} splats, the scene {} and {}",
                g.rows,
                g.splats,
                scene.rows,
                scene.len
            );
        }
        for b in [&g.v_xys, &g.v_conics, &g.v_colors, &g.v_opacities] {
            rec.fill(b, 0);
        }
        for blend_backward in &self.k.blend_backward {
            rec.dispatch(
                blend_backward,
                &[
                    ("frame", &self.frame_ub),
                    ("ranges", &im.ranges),
                    ("isect_ids", &is.ids[self.isect_result]),
                    ("xys", &gb.xys),
                    ("conics", &gb.conics),
                    ("colors", &gb.colors),
                    ("out_image", &im.out_image),
                    ("last", &im.last),
                    ("v_image", v_image),
                    ("v_xys", &g.v_xys),
                    ("v_conics", &g.v_conics),
                    ("v_colors", &g.v_colors),
                    ("v_opacities", &g.v_opacities),
                    ("tile_costs", &im.tile_costs),
                ],
                &(),
                [fp.tiles_x, fp.tiles_y, 1],
            )?;
        }
        rec.end_pass("blend_backward")
    }

    fn record_preprocess_backward(&self, rec: &mut Recorder, scene: &GpuScene, g: &Grads) -> Result<()> {
        let gb = self.gauss.as_ref().unwrap();
        let bindings: Vec<(&str, &Buffer)> = [
            ("frame", &self.frame_ub),
            ("means", &scene.means),
            ("scales", &scene.scales),
            ("quats", &scene.quats),
            ("opacities", &scene.opacities),
            ("sh", &scene.sh),
            ("radii", &gb.radii),
            ("tiles_touched", &gb.tiles_touched),
            ("v_xys", &g.v_xys),
            ("v_conics", &g.v_conics),
            ("v_colors", &g.v_colors),
            ("v_opacities", &g.v_opacities),
            ("grad_means", &g.means),
            ("grad_scales", &g.scales),
            ("grad_quats", &g.quats),
            ("grad_opacities", &g.opacities),
            ("grad_sh", &g.sh),
            ("grad2d_accum", &g.grad2d_accum),
            ("grad2d_count", &g.grad2d_count),
            ("max_radii", &g.max_radii),
            ("grad_d_means", &g.d_means),
            ("grad_d_sh0", &g.d_sh0),
            ("grad_d_opacities", &g.d_opacities),
            ("xform_terms", &g.xform_terms),
            ("visible_ids", &gb.depth_ids[self.depth_result]),
        ]
        .into_iter()
        .chain(scene.instancing_bindings())
        .collect();
        if scene.inst.instances == 0 {
            // Plain: only the visible Gaussians' rows; the culled ones' gradients are zero.
            for b in [&g.means, &g.scales, &g.quats, &g.opacities, &g.sh] {
                rec.fill(b, 0);
            }
            let num_visible = std::mem::offset_of!(FrameParams, num_visible) as u64;
            rec.copy_region(&self.counts.counts, COUNT_VISIBLE as u64 * 4, &self.frame_ub, num_visible, 4);
            rec.dispatch_indirect(
                &self.k.preprocess_backward[1],
                &bindings,
                &(),
                &self.counts.indirect,
                Counts::args_offset(COUNT_VISIBLE, ARGS_ITEMS),
            )?;
        } else {
            rec.dispatch(
                &self.k.preprocess_backward[0],
                &bindings,
                &(),
                [(scene.rows as u32).div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1],
            )?;
        }
        rec.end_pass("preprocess_backward")?;
        if scene.inst.xform_grads && scene.inst.instances > 0 {
            if g.xform_terms.size < (scene.inst.pairs * XFORM_GRAD_TERMS as usize * 4) as u64 {
                bail!("gradient buffers were made without transform gradients");
            }
            rec.dispatch(
                &self.k.xform_grad_reduce,
                &[
                    ("frame", &self.frame_ub),
                    ("groups", &scene.inst.groups),
                    ("xform_terms", &g.xform_terms),
                    ("grad_xforms", &g.xforms),
                ],
                &(),
                [scene.inst.instances as u32, 1, 1],
            )?;
            rec.end_pass("xform_grad_reduce")?;
        }
        Ok(())
    }

    /// The last frame's rendered image buffer (row-major RGBA f32, rgb = C + T·background,
    /// a = T) on the device.
    pub fn image_buffer(&self) -> Option<&Buffer> {
        self.image.as_ref().map(|im| &im.out_image)
    }

    /// The last frame's per-pixel `last` counts (for tests).
    pub fn read_last(&self) -> Result<Vec<u32>> {
        let im = self.image.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        self.gpu.read(&im.last, (im.width * im.height) as usize)
    }

    /// The frame parameters of the last rendered frame.
    pub fn last_frame_params(&self) -> Option<FrameParams> {
        self.last_params
    }
}

/// Uploading a scene file of either kind (here, so that `formats` stays free of the GPU).
impl crate::formats::AnyScene {
    /// The scene on the device (an instanced scene stays compact).
    pub fn upload(&self, gpu: &std::sync::Arc<crate::gpu::Gpu>) -> Result<GpuScene> {
        match self {
            crate::formats::AnyScene::Plain(s) => GpuScene::new(gpu, s),
            crate::formats::AnyScene::Instanced(s) => GpuScene::instanced(gpu, s),
        }
    }

    /// The scene on the device for viewing: an instanced scene with per-frame culling and level
    /// of detail as `cfg` says (`crate::render::lod`); a plain scene as [`Self::upload`].
    pub fn upload_for_rendering(
        &self,
        gpu: &std::sync::Arc<crate::gpu::Gpu>,
        cfg: &crate::render::lod::RenderConfig,
    ) -> Result<GpuScene> {
        match self {
            crate::formats::AnyScene::Plain(s) => GpuScene::new(gpu, s),
            crate::formats::AnyScene::Instanced(s) => GpuScene::instanced_for_rendering(gpu, s, cfg),
        }
    }
}
