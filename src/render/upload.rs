//! A scene on the device: parameter rows (background Gaussians, then every group's template
//! Gaussians) and the instancing tables (`glsl/instance.glsl`: groups, per-instance transforms,
//! per-pair offsets as f32, f16 or pq8 codes). Rendering expands the splats on the fly.
use std::sync::Arc;

use anyhow::{bail, Result};

use crate::formats::instgs::Dtype;
use crate::gpu::{Buffer, Gpu};
use crate::model::instanced::{InstancedScene, Offsets};
use crate::model::scene::Scene;
use crate::render::lod::{LodConfig, RenderConfig};
use crate::shared::*;

/// The instancing tables of a scene in device memory (instance.glsl). A plain scene has no groups
/// and one-element placeholders (every binding needs a buffer).
pub struct GpuInstancing {
    pub groups: Buffer,
    /// The group table as uploaded (levels included).
    pub group_infos: Vec<GroupInfo>,
    pub xforms: Buffer,
    /// Offsets per (template Gaussian, instance) pair, pair index = splat − num_background:
    /// Δp (3 f32), Δ SH DC (3 f32), Δ opacity logit (f32).
    pub d_means: Buffer,
    pub d_sh0: Buffer,
    pub d_opacities: Buffer,
    /// Compact offsets (placeholders for `OFFSETS_F32`): product-quantised codes
    /// (`crate::formats::pq8`), 16 bits per pair, with per group 512 codebook entries (vec4); or
    /// `OFFSET_HALVES` halves per pair.
    pub d_codes: Buffer,
    pub codebooks: Buffer,
    /// `OFFSETS_F32`, `OFFSETS_PQ8` or `OFFSETS_F16` (glsl/common.glsl).
    pub storage: u32,
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
    pub(crate) id: u64,
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
    /// Backward also computes the camera gradients (`Grads::v_camera`; plain scenes only:
    /// training's camera refinement; `preprocess_backward`'s CAMERA_GRADS variant).
    pub camera_grads: bool,
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

/// Whether every offset is an f16 value (converting it to f16 and back changes nothing).
pub fn halves_hold(o: &Offsets) -> bool {
    let exact = |v: &f32| half::f16::from_f32(*v).to_f32().to_bits() == v.to_bits();
    o.d_means.iter().flatten().chain(o.d_sh0.iter().flatten()).chain(&o.d_opacities).all(exact)
}

/// Offsets as `OFFSET_HALVES` f16 per pair (Δp xyz, Δ SH DC rgb, Δ opacity logit), two halves per
/// word, low half first, pair after pair without padding (glsl/instance.glsl); values round to
/// the nearest f16.
pub fn pack_halves(o: &Offsets) -> Vec<u32> {
    let halves = o.d_means.iter().zip(&o.d_sh0).zip(&o.d_opacities).flat_map(|((p, c), a)| {
        [p[0], p[1], p[2], c[0], c[1], c[2], *a].map(|v| half::f16::from_f32(v).to_bits() as u32)
    });
    let mut words = vec![0u32; (OFFSET_HALVES as usize * o.len()).div_ceil(2)];
    for (h, v) in halves.enumerate() {
        words[h / 2] |= v << (16 * (h % 2));
    }
    words
}

/// The parameter rows of an instanced scene: background, then every template.
pub fn scene_rows(scene: &InstancedScene) -> Scene {
    let mut rows = scene.background.clone();
    rows.sh_degree = scene.sh_degree;
    for g in &scene.groups {
        rows.append(&g.template);
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

    /// GPU bytes of `scene` as the viewer holds it once written with its offsets stored as
    /// `storage`, levels of detail left out: what a memory budget counts. f32 offsets take 28
    /// bytes per (template Gaussian, instance) pair, f16 ones 14; pq8 is counted as f16 (its
    /// codebooks are fitted when the file is written; its 2-byte codes are smaller still).
    pub fn stored_bytes(gpu: &Arc<Gpu>, scene: &InstancedScene, storage: Dtype) -> Result<u64> {
        if storage == Dtype::F32 {
            return Ok(Self::instanced(gpu, scene)?.gpu_bytes());
        }
        let lod = LodConfig { enabled: false, fractions: Vec::new(), splats_per_pixel: 0.0 };
        let every_pair = RenderConfig { cull: false, cull_margin_px: 0.0, lod };
        Ok(Self::instanced_stored(gpu, scene, &every_pair, None, true)?.gpu_bytes())
    }

    /// An instanced scene for viewing: instances culled per frame and, with `cfg.lod.enabled`,
    /// every template's coarser levels built and uploaded too (`crate::render::lod`).
    pub fn instanced_for_rendering(gpu: &Arc<Gpu>, scene: &InstancedScene, cfg: &RenderConfig) -> Result<GpuScene> {
        // Offsets that are product-quantised already (a pq8 file) stay so on the device, and
        // offsets that f16 holds exactly (an f16 file) stay f16 (the coarser levels' merged
        // offsets are rounded to it); others are f32.
        let books: Option<Vec<crate::formats::pq8::OffsetCodes>> =
            scene.groups.iter().map(|g| crate::formats::pq8::OffsetCodes::exact(&g.offsets)).collect();
        let f16 = scene.groups.iter().all(|g| halves_hold(&g.offsets));
        Self::instanced_stored(gpu, scene, cfg, books, f16)
    }

    /// [`Self::instanced_for_rendering`] with the offsets as pq8 codes (`books`), else as f16
    /// (rounded to the nearest) with `f16`, else as f32.
    fn instanced_stored(
        gpu: &Arc<Gpu>,
        scene: &InstancedScene,
        cfg: &RenderConfig,
        books: Option<Vec<crate::formats::pq8::OffsetCodes>>,
        f16: bool,
    ) -> Result<GpuScene> {
        let (mut groups, xforms, max_offsets) = instancing_tables(scene);
        let mut rows = scene_rows(scene);
        let mut offsets = all_offsets(scene);
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
                rows.append(&t);
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
                gs.inst.storage = OFFSETS_PQ8;
                gs
            }
            None if f16 => {
                let mut gs =
                    Self::upload(gpu, &rows, nb, scene.splats(), &groups, &xforms, &Offsets::default(), !selecting)?;
                gs.inst.d_codes = upload_or_placeholder(gpu, "d_codes", &pack_halves(&offsets))?;
                gs.inst.storage = OFFSETS_F16;
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
                group_infos: groups.to_vec(),
                xforms: upload_or_placeholder(gpu, "xforms", xforms)?,
                d_means: upload_or_placeholder(gpu, "d_means", &offsets.d_means)?,
                d_sh0: upload_or_placeholder(gpu, "d_sh0", &offsets.d_sh0)?,
                d_opacities: upload_or_placeholder(gpu, "d_opacities", &offsets.d_opacities)?,
                d_codes: upload_or_placeholder::<u32>(gpu, "d_codes", &[])?,
                codebooks: upload_or_placeholder::<[f32; 4]>(gpu, "codebooks", &[])?,
                storage: OFFSETS_F32,
                num_groups: groups.len() as u32,
                pairs: offsets.len(),
                instances: xforms.len(),
                max_offsets: Vec::new(),
                select: None,
                xform_grads: false,
            },
            sh_degree: rows.sh_degree,
            active_sh_degree: rows.sh_degree,
            camera_grads: false,
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

    /// Replaces the instance transforms (instance order: groups, then instances).
    pub fn write_transforms(&self, gpu: &Arc<Gpu>, transforms: &[crate::model::instanced::Similarity]) -> Result<()> {
        if transforms.len() != self.inst.instances {
            bail!("{} transforms for {} instances", transforms.len(), self.inst.instances);
        }
        let maxo = |i: usize| self.inst.max_offsets.get(i).copied().unwrap_or(0.0);
        gpu.write(&self.inst.xforms, &transforms.iter().enumerate().map(|(i, x)| xform(x, maxo(i))).collect::<Vec<_>>())
    }

    /// Moves instance `k` of group `group` in place (the player's editor): its transform becomes
    /// `transform` and its level-0 Δp `d_means` (T rows); the coarser levels' merged Δp (weighted
    /// means of level 0's, [`crate::render::lod::merge_clusters`]) are mapped by `linear`, the
    /// linear part of the edit, as level 0's were. Returns false, changing nothing, where the
    /// edit has a linear part and the offsets are compact on the device (pq8 codes share one
    /// codebook per group; mapped Δp are no longer f16 values): the caller uploads the scene
    /// again.
    pub fn write_instance(
        &mut self,
        gpu: &Arc<Gpu>,
        group: usize,
        k: usize,
        transform: &crate::model::instanced::Similarity,
        d_means: &[[f32; 3]],
        linear: glam::Mat3,
    ) -> Result<bool> {
        let i = &mut self.inst;
        let Some(g) = i.group_infos.get(group).copied() else { bail!("no group {group} on the device") };
        if k >= g.instances as usize || d_means.len() != g.rows as usize {
            bail!(
                "instance {k} with {} offsets: the device's group {group} has {} instances of {} rows",
                d_means.len(),
                g.instances,
                g.rows
            );
        }
        if i.storage != OFFSETS_F32 && linear != glam::Mat3::IDENTITY {
            return Ok(false);
        }
        let index = g.instance_first as usize + k;
        let scale = linear.determinant().cbrt();
        if let Some(m) = i.max_offsets.get_mut(index) {
            *m *= scale;
        }
        let maxo = i.max_offsets.get(index).copied().unwrap_or(0.0);
        let stride = std::mem::size_of::<InstanceXform>() as u64;
        gpu.write_at(&i.xforms, index as u64 * stride, &[xform(transform, maxo)])?;
        if linear == glam::Mat3::IDENTITY {
            return Ok(true);
        }
        let row = std::mem::size_of::<[f32; 3]>() as u64;
        for level in 0..g.levels as usize {
            let (first, rows) = (g.level_pair_first[level] as u64, g.level_rows[level] as u64);
            let at = (first + k as u64 * rows) * row;
            if level == 0 {
                gpu.write_at(&i.d_means, at, d_means)?;
            } else {
                let old: Vec<[f32; 3]> = gpu.read_at(&i.d_means, at, rows as usize)?;
                let new: Vec<[f32; 3]> = old.iter().map(|d| (linear * glam::Vec3::from(*d)).to_array()).collect();
                gpu.write_at(&i.d_means, at, &new)?;
            }
        }
        Ok(true)
    }

    /// (name, buffer) bindings of the instancing tables, as instance.glsl names them.
    pub(crate) fn instancing_bindings(&self) -> [(&'static str, &Buffer); 7] {
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

/// Uploading a scene file of either kind (here, so that `formats` stays free of the GPU).
impl crate::formats::AnyScene {
    /// The scene on the device (an instanced scene stays compact).
    pub fn upload(&self, gpu: &Arc<Gpu>) -> Result<GpuScene> {
        match self {
            crate::formats::AnyScene::Plain(s) => GpuScene::new(gpu, s),
            crate::formats::AnyScene::Instanced(s) => GpuScene::instanced(gpu, s),
        }
    }

    /// The scene on the device for viewing: an instanced scene with per-frame culling and level
    /// of detail as `cfg` says (`crate::render::lod`); a plain scene as [`Self::upload`].
    pub fn upload_for_rendering(&self, gpu: &Arc<Gpu>, cfg: &RenderConfig) -> Result<GpuScene> {
        match self {
            crate::formats::AnyScene::Plain(s) => GpuScene::new(gpu, s),
            crate::formats::AnyScene::Instanced(s) => GpuScene::instanced_for_rendering(gpu, s, cfg),
        }
    }
}
