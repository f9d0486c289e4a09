//! The training loss and Adam on the GPU: recording of the `loss_*` and `adam` kernels and the
//! buffers they use. CPU twins in [`crate::render::reference::backward`].
use std::sync::Arc;

use anyhow::{bail, Result};
use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::Kernels;
use crate::gpu::{Buffer, Gpu, Recorder};
use crate::render::raster::backward::Grads;
use crate::render::upload::GpuScene;
use crate::shared::*;

/// Inria's weight of the D-SSIM term: L = (1 − λ) L1 + λ (1 − SSIM).
pub const SSIM_WEIGHT: f32 = 0.2;

/// Buffers of the loss at one image size.
pub struct LossBufs {
    pub width: u32,
    pub height: u32,
    /// Ground truth, RGBA f32 per pixel (alpha unused).
    pub target: Buffer,
    moments: Buffer,
    cotangents: Buffer,
    filtered: Buffer,
    /// dL/d rgb per pixel (RGBA f32, a = 0).
    pub v_image: Buffer,
    /// LOSS_SLOTS floats: sums of |x − y| and of SSIM over pixels and channels.
    pub sums: Buffer,
    /// Host-visible: the next target, copied into `target` inside the training step's own
    /// submission ([`LossBufs::record_target_upload`]).
    pub target_upload: Buffer,
    /// Host-visible: `sums` copied back inside the same submission ([`LossBufs::record_sums_readback`]).
    pub sums_readback: Buffer,
}

impl LossBufs {
    /// Refuses an image the loss's largest buffer (the SSIM moments, 60 bytes a pixel) cannot
    /// hold on `gpu`, with the `--downscale` that would fit.
    pub fn check_size(gpu: &Gpu, width: u32, height: u32) -> Result<()> {
        let px = width as u64 * height as u64;
        let planes = (SSIM_MOMENTS * 3) as u64 * px * 4;
        let limit = gpu.info.max_storage_buffer_range;
        if planes > limit {
            let factor = ((planes as f64 / limit as f64).sqrt().ceil() as u32).max(2);
            bail!(
                "image {width}x{height} is too large for the training loss's buffers on this device ({planes} bytes, over maxStorageBufferRange {limit}); train with --downscale {factor} or more"
            );
        }
        Ok(())
    }

    pub fn new(gpu: &Arc<Gpu>, width: u32, height: u32) -> Result<LossBufs> {
        LossBufs::check_size(gpu, width, height)?;
        let px = width as u64 * height as u64;
        let planes = (SSIM_MOMENTS * 3) as u64 * px * 4;
        Ok(LossBufs {
            width,
            height,
            target: gpu.storage("loss_target", px * 16)?,
            moments: gpu.storage("loss_moments", planes)?,
            cotangents: gpu.storage("loss_cotangents", (SSIM_COTANGENTS * 3) as u64 * px * 4)?,
            filtered: gpu.storage("loss_filtered", (SSIM_COTANGENTS * 3) as u64 * px * 4)?,
            v_image: gpu.storage("v_image", px * 16)?,
            sums: gpu.storage("loss_sums", LOSS_SLOTS as u64 * 4)?,
            target_upload: gpu.buffer(
                "loss_target_upload",
                px * 16,
                vk::BufferUsageFlags::empty(),
                MemoryLocation::CpuToGpu,
            )?,
            sums_readback: gpu.buffer(
                "loss_sums_readback",
                LOSS_SLOTS as u64 * 4,
                vk::BufferUsageFlags::empty(),
                MemoryLocation::GpuToCpu,
            )?,
        })
    }

    /// Records the copy of `target_upload` (written with `write_mapped`) into `target`.
    pub fn record_target_upload(&self, rec: &mut Recorder) -> Result<()> {
        rec.copy(&self.target_upload, &self.target, self.target.size);
        rec.end_pass("setup")
    }

    /// Records the copy of `sums` into `sums_readback` (read with `read_mapped` after the wait).
    pub fn record_sums_readback(&self, rec: &mut Recorder) -> Result<()> {
        rec.copy(&self.sums, &self.sums_readback, LOSS_SLOTS as u64 * 4);
        rec.end_pass("readback")
    }

    /// (mean L1, mean SSIM) from the read-back sums.
    pub fn means(&self, sums: &[f32]) -> (f64, f64) {
        let count = 3.0 * self.width as f64 * self.height as f64;
        (sums[LOSS_L1 as usize] as f64 / count, sums[LOSS_SSIM as usize] as f64 / count)
    }
}

/// Records the loss of `image` (RGBA f32, the rasterizer's output) against `lb.target`: the
/// sums into `lb.sums` and dL/d image into `lb.v_image`.
pub fn record_loss(rec: &mut Recorder, k: &Kernels, image: &Buffer, lb: &LossBufs, ssim_weight: f32) -> Result<()> {
    let px = lb.width * lb.height;
    let args = LossArgs { width: lb.width, height: lb.height, ssim_weight, inv_count: 1.0 / (3.0 * px as f32) };
    let runs_h = lb.width.div_ceil(LOSS_RUN) * lb.height;
    let runs_v = lb.height.div_ceil(LOSS_RUN) * lb.width;
    let (groups_h, groups_v) = ([runs_h.div_ceil(WG_SIZE), 1, 1], [runs_v.div_ceil(WG_SIZE), 1, 1]);
    rec.fill(&lb.sums, 0);
    rec.dispatch(
        &k.loss_moments_h,
        &[("image", image), ("target", &lb.target), ("moments", &lb.moments)],
        &args,
        groups_h,
    )?;
    rec.dispatch(
        &k.loss_ssim_v,
        &[
            ("image", image),
            ("target", &lb.target),
            ("moments", &lb.moments),
            ("cotangents", &lb.cotangents),
            ("loss", &lb.sums),
        ],
        &args,
        groups_v,
    )?;
    rec.dispatch(&k.loss_cotangents_h, &[("cotangents", &lb.cotangents), ("filtered", &lb.filtered)], &args, groups_h)?;
    rec.dispatch(
        &k.loss_grad_v,
        &[("image", image), ("target", &lb.target), ("filtered", &lb.filtered), ("v_image", &lb.v_image)],
        &args,
        groups_v,
    )?;
    rec.end_pass("loss")
}

/// Learning rates of the parameter groups (Inria's names: xyz, scaling, rotation, opacity,
/// f_dc, f_rest).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    pub means: f32,
    pub scales: f32,
    pub quats: f32,
    pub opacities: f32,
    pub sh0: f32,
    pub sh_rest: f32,
    /// The training cameras' corrections (crate::train::cameras): rotation (radians),
    /// translation (world units); 0 until `cameras.from_iter`.
    pub cameras: [f64; 2],
}

/// Adam's first and second moments of every parameter buffer (layouts as [`GpuScene`]) and of
/// the offset buffers (d_means, d_sh0, d_opacities; one-element placeholders without offsets).
pub struct AdamState {
    pub exp_avg: [Buffer; 5],
    pub exp_avg_sq: [Buffer; 5],
    pub offset_exp_avg: [Buffer; 3],
    pub offset_exp_avg_sq: [Buffer; 3],
}

impl AdamState {
    /// Zeroed moments.
    pub fn new(gpu: &Arc<Gpu>, scene: &GpuScene) -> Result<AdamState> {
        let sizes = param_buffers(scene).map(|b| b.size);
        let mk = |name: &str, i: usize| gpu.storage(&format!("{name}{i}"), sizes[i]);
        let offset_sizes = offset_buffers(scene).map(|b| b.size);
        let mk_off = |name: &str, i: usize| gpu.storage(&format!("{name}{i}"), offset_sizes[i]);
        let st = AdamState {
            exp_avg: [mk("exp_avg", 0)?, mk("exp_avg", 1)?, mk("exp_avg", 2)?, mk("exp_avg", 3)?, mk("exp_avg", 4)?],
            exp_avg_sq: [
                mk("exp_avg_sq", 0)?,
                mk("exp_avg_sq", 1)?,
                mk("exp_avg_sq", 2)?,
                mk("exp_avg_sq", 3)?,
                mk("exp_avg_sq", 4)?,
            ],
            offset_exp_avg: [mk_off("offset_exp_avg", 0)?, mk_off("offset_exp_avg", 1)?, mk_off("offset_exp_avg", 2)?],
            offset_exp_avg_sq: [
                mk_off("offset_exp_avg_sq", 0)?,
                mk_off("offset_exp_avg_sq", 1)?,
                mk_off("offset_exp_avg_sq", 2)?,
            ],
        };
        gpu.submit_and_wait(|rec| {
            for b in st.exp_avg.iter().chain(&st.exp_avg_sq).chain(&st.offset_exp_avg).chain(&st.offset_exp_avg_sq) {
                rec.fill(b, 0);
            }
            Ok(())
        })?;
        Ok(st)
    }

    pub fn gpu_bytes(&self) -> u64 {
        self.exp_avg
            .iter()
            .chain(&self.exp_avg_sq)
            .chain(&self.offset_exp_avg)
            .chain(&self.offset_exp_avg_sq)
            .map(|b| b.size)
            .sum()
    }
}

/// The scene's offset buffers in a fixed order: d_means, d_sh0, d_opacities.
pub fn offset_buffers(s: &GpuScene) -> [&Buffer; 3] {
    [&s.inst.d_means, &s.inst.d_sh0, &s.inst.d_opacities]
}

/// The offset gradient buffers in the order of [`offset_buffers`].
pub fn offset_grad_buffers(g: &Grads) -> [&Buffer; 3] {
    [&g.v_d_means, &g.v_d_sh0, &g.v_d_opacities]
}

/// The scene's parameter buffers in a fixed order: means, scales, quats, opacities, sh.
pub fn param_buffers(s: &GpuScene) -> [&Buffer; 5] {
    [&s.means, &s.scales, &s.quats, &s.opacities, &s.sh]
}

/// The gradient buffers in the order of [`param_buffers`].
pub fn grad_buffers(g: &Grads) -> [&Buffer; 5] {
    [&g.v_means, &g.v_scales, &g.v_quats, &g.v_opacities, &g.v_sh]
}

/// Adam's constants (Inria: betas (0.9, 0.999), eps 1e-15).
pub const BETA1: f64 = 0.9;
pub const BETA2: f64 = 0.999;
pub const EPS: f32 = 1e-15;

/// One Adam dispatch over part of a parameter group (fields as [`AdamArgs`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AdamPart {
    /// adam_vec4.comp (counts in vec4s) rather than adam.comp (counts in floats).
    pub vec4: bool,
    pub first: u32,
    pub count: u32,
    pub stride: u32,
    pub head: u32,
}

/// How a group of `total` floats in rows of `stride`, the first `head` of each row at lr_head,
/// is split between the kernels: rows of whole vec4s go to adam_vec4.comp; a group with one
/// learning rate (head >= stride) is one run of vec4s plus at most 3 floats for adam.comp; other
/// rows (SH degree 2's 27 coefficients) go to adam.comp whole.
pub fn adam_parts(total: u32, stride: u32, head: u32) -> Vec<AdamPart> {
    let part = |vec4, first, count, stride, head| AdamPart { vec4, first, count, stride, head };
    if head >= stride {
        let quads = total / 4;
        [part(true, 0, quads, 1, 4), part(false, 4 * quads, total % 4, 1, 1)]
            .into_iter()
            .filter(|p| p.count > 0)
            .collect()
    } else if stride.is_multiple_of(4) {
        vec![part(true, 0, total / 4, stride / 4, head)]
    } else {
        vec![part(false, 0, total, stride, head)]
    }
}

/// Records one Adam step (`step` counted from 1) over every parameter buffer and, for an
/// instanced scene, every offset buffer (Δp at the position rate, Δc at sh0's, Δo at opacity's).
pub fn record_adam(
    rec: &mut Recorder,
    k: &Kernels,
    scene: &GpuScene,
    grads: &Grads,
    st: &AdamState,
    lr: &LearningRates,
    step: u64,
) -> Result<()> {
    let n = scene.rows as u32;
    let coeffs = (scene.sh_degree + 1) * (scene.sh_degree + 1);
    let inv_bias1 = (1.0 / (1.0 - BETA1.powi(step as i32))) as f32;
    let inv_sqrt_bias2 = (1.0 / (1.0 - BETA2.powi(step as i32)).sqrt()) as f32;
    // (stride, head, lr_head, lr_tail) per buffer.
    let groups = [
        (3, 3, lr.means, lr.means),
        (3, 3, lr.scales, lr.scales),
        (4, 4, lr.quats, lr.quats),
        (1, 1, lr.opacities, lr.opacities),
        (coeffs * 3, 3, lr.sh0, lr.sh_rest),
    ];
    let pairs = scene.inst.pairs as u32;
    let offset_groups = [(3, lr.means), (3, lr.sh0), (1, lr.opacities)];
    // (rows, stride, head, lr_head, lr_tail, parameters, gradients, exp_avg, exp_avg_sq)
    let mut jobs = Vec::new();
    for (i, &(stride, head, lr_head, lr_tail)) in groups.iter().enumerate() {
        let bufs = (param_buffers(scene)[i], grad_buffers(grads)[i], &st.exp_avg[i], &st.exp_avg_sq[i]);
        jobs.push((n, stride, head, lr_head, lr_tail, bufs));
    }
    for (i, &(stride, lr)) in offset_groups.iter().enumerate().filter(|_| pairs > 0) {
        let bufs =
            (offset_buffers(scene)[i], offset_grad_buffers(grads)[i], &st.offset_exp_avg[i], &st.offset_exp_avg_sq[i]);
        jobs.push((pairs, stride, stride, lr, lr, bufs));
    }
    for (n, stride, head, lr_head, lr_tail, (param, grad, m, v)) in jobs {
        for part in adam_parts(n * stride, stride, head) {
            let args = AdamArgs {
                count: part.count,
                stride: part.stride,
                head: part.head,
                lr_head,
                lr_tail,
                beta1: BETA1 as f32,
                beta2: BETA2 as f32,
                eps: EPS,
                inv_bias1,
                inv_sqrt_bias2,
                first: part.first,
                ..Default::default()
            };
            let kernel = if part.vec4 { &k.adam_vec4 } else { &k.adam };
            let rows = part.count / part.stride;
            let binds = [("params", param), ("grads", grad), ("exp_avg", m), ("exp_avg_sq", v)];
            rec.dispatch(kernel, &binds, &args, [rows.div_ceil(WG_SIZE).min(MAX_GROUPS), 1, 1])?;
        }
    }
    rec.end_pass("adam")
}
