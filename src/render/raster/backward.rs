//! The backward passes of the rasterizer: `blend_backward` (from dL/d pixel to the per-splat
//! projected cotangents) and `preprocess_backward` (to the parameter, offset and transform
//! cotangents and the densification statistics). Cotangents are named `v_*` (dL/dx, as gsplat);
//! the CPU twin is `render::reference::backward`.
use crate::gpu::kernels::Counts;
use anyhow::bail;
use std::sync::Arc;

use anyhow::Result;

use super::Rasterizer;
use crate::gpu::{Buffer, Gpu, Recorder};
use crate::render::upload::GpuScene;
use crate::shared::*;

/// Gradient buffers of one scene: the parameter-row gradients (layouts as [`GpuScene`]), the
/// offset gradients (pair layout), the per-splat projected gradients written by
/// `blend_backward`, and the per-splat densification statistics.
pub struct Grads {
    /// Parameter rows and splats they were made for.
    pub rows: usize,
    pub splats: usize,
    pub v_means: Buffer,
    pub v_scales: Buffer,
    pub v_quats: Buffer,
    pub v_opacities: Buffer,
    pub v_sh: Buffer,
    pub v_d_means: Buffer,
    pub v_d_sh0: Buffer,
    pub v_d_opacities: Buffer,
    /// Gradient terms: an instanced scene's per-pair transform terms (XFORM_GRAD_TERMS floats
    /// each), summed per instance into `v_xforms`, or a plain scene's camera terms summed per
    /// `preprocess_backward` workgroup (CAMERA_GRAD_TERMS each, at most MAX_GROUPS), summed into
    /// `v_camera`; a placeholder when the scene computes neither.
    pub terms: Buffer,
    pub v_xforms: Buffer,
    pub v_camera: Buffer,
    pub v_xys: Buffer,
    pub v_conics: Buffer,
    pub v_colours: Buffer,
    pub v_splat_opacities: Buffer,
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
            v_means: gpu.storage("v_means", r * 12)?,
            v_scales: gpu.storage("v_scales", r * 12)?,
            v_quats: gpu.storage("v_quats", r * 16)?,
            v_opacities: gpu.storage("v_opacities", r * 4)?,
            v_sh: gpu.storage("v_sh", sh)?,
            v_d_means: gpu.storage("v_d_means", pairs * 12)?,
            v_d_sh0: gpu.storage("v_d_sh0", pairs * 12)?,
            v_d_opacities: gpu.storage("v_d_opacities", pairs * 4)?,
            terms: gpu.storage(
                "terms",
                if scene.inst.xform_grads { pairs * XFORM_GRAD_TERMS as u64 } else { 1 }.max(if scene.camera_grads {
                    MAX_GROUPS as u64 * CAMERA_GRAD_TERMS as u64
                } else {
                    1
                }) * 4,
            )?,
            v_xforms: gpu.storage("v_xforms", scene.inst.instances.max(1) as u64 * XFORM_GRAD_TERMS as u64 * 4)?,
            v_camera: gpu.storage("v_camera", CAMERA_GRAD_TERMS as u64 * 4)?,
            v_xys: gpu.storage("v_xys", n * 8)?,
            v_conics: gpu.storage("v_conics", n * 12)?,
            v_colours: gpu.storage("v_colours", n * 12)?,
            v_splat_opacities: gpu.storage("v_splat_opacities", n * 4)?,
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
            &self.v_means,
            &self.v_scales,
            &self.v_quats,
            &self.v_opacities,
            &self.v_sh,
            &self.v_d_means,
            &self.v_d_sh0,
            &self.v_d_opacities,
            &self.terms,
            &self.v_xforms,
            &self.v_camera,
            &self.v_xys,
            &self.v_conics,
            &self.v_colours,
            &self.v_splat_opacities,
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
    /// `preprocess_backward` into the parameter gradients and the densification statistics (and,
    /// when the scene asks, `camera_grad_reduce` into the frame's camera gradients).
    /// The caller submits; the frame's buffers must not be re-rendered in between.
    pub fn record_backward(&self, rec: &mut Recorder, scene: &GpuScene, v_image: &Buffer, g: &Grads) -> Result<()> {
        self.record_blend_backward(rec, scene, v_image, g)?;
        self.record_preprocess_backward(rec, scene, g)
    }

    /// Records `blend_backward` alone: from `v_image` to the per-splat projected gradients
    /// (v_xys, v_conics, v_colours, v_splat_opacities) of the last rendered frame.
    pub fn record_blend_backward(
        &self,
        rec: &mut Recorder,
        scene: &GpuScene,
        v_image: &Buffer,
        g: &Grads,
    ) -> Result<()> {
        let im = self.image.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        self.record_blend_backward_from(rec, scene, v_image, g, &im.last)
    }

    /// [`Rasterizer::record_blend_backward`] with `last` (per pixel, u32) in place of the
    /// frame's own counts ([`Rasterizer::read_last`]). A pixel whose count is 0 walks no splat:
    /// where `v_image` is zero outside some pixels, the frame's counts with every other pixel
    /// set to 0 give the same gradients and spare the rest of the frame (the segmentation's
    /// per-mask passes).
    pub fn record_blend_backward_from(
        &self,
        rec: &mut Recorder,
        scene: &GpuScene,
        v_image: &Buffer,
        g: &Grads,
        last: &Buffer,
    ) -> Result<()> {
        let fp = self.last_params.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        let gb = self.gauss.as_ref().unwrap();
        let is = self.isect.as_ref().unwrap();
        let im = self.image.as_ref().unwrap();
        let pixels = (im.width * im.height) as u64 * 4;
        if last.size < pixels {
            bail!("the `last` counts hold {} bytes, the frame needs {pixels}", last.size);
        }
        if g.rows != scene.rows || g.splats != scene.len {
            bail!(
                "gradient buffers hold {} rows and {} splats, the scene {} and {}",
                g.rows,
                g.splats,
                scene.rows,
                scene.len
            );
        }
        for b in [&g.v_xys, &g.v_conics, &g.v_colours, &g.v_splat_opacities] {
            rec.fill(b, 0);
        }
        for blend_backward in &self.k.blend_backward {
            rec.dispatch(
                blend_backward,
                &[
                    ("frame_texels", &self.frame_ub),
                    ("ranges", &im.ranges),
                    ("isect_ids", &is.ids[self.isect_result]),
                    ("xys", &gb.xys),
                    ("conics", &gb.conics),
                    ("colours", &gb.colours),
                    ("out_image", &im.out_image),
                    ("last", last),
                    ("v_image", v_image),
                    ("v_xys", &g.v_xys),
                    ("v_conics", &g.v_conics),
                    ("v_colours", &g.v_colours),
                    ("v_splat_opacities", &g.v_splat_opacities),
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
            ("frame_texels", &self.frame_ub),
            ("means", &scene.means),
            ("scales", &scene.scales),
            ("quats", &scene.quats),
            ("opacities", &scene.opacities),
            ("sh", &scene.sh),
            ("radii", &gb.radii),
            ("tiles_touched", &gb.tiles_touched),
            ("v_xys", &g.v_xys),
            ("v_conics", &g.v_conics),
            ("v_colours", &g.v_colours),
            ("v_splat_opacities", &g.v_splat_opacities),
            ("v_means", &g.v_means),
            ("v_scales", &g.v_scales),
            ("v_quats", &g.v_quats),
            ("v_opacities", &g.v_opacities),
            ("v_sh", &g.v_sh),
            ("grad2d_accum", &g.grad2d_accum),
            ("grad2d_count", &g.grad2d_count),
            ("max_radii", &g.max_radii),
            ("v_d_means", &g.v_d_means),
            ("v_d_sh0", &g.v_d_sh0),
            ("v_d_opacities", &g.v_d_opacities),
            ("terms", &g.terms),
            ("visible_ids", &gb.depth_ids[self.depth_result]),
        ]
        .into_iter()
        .chain(scene.instancing_bindings())
        .collect();
        if scene.camera_grads
            && (scene.inst.instances > 0 || g.terms.size < (MAX_GROUPS * CAMERA_GRAD_TERMS * 4) as u64)
        {
            bail!("camera gradients need a plain scene and gradient buffers made for them");
        }
        if scene.inst.instances == 0 {
            // Plain: only the visible Gaussians' rows; the culled ones' gradients are zero.
            for b in [&g.v_means, &g.v_scales, &g.v_quats, &g.v_opacities, &g.v_sh] {
                rec.fill(b, 0);
            }
            let num_visible = std::mem::offset_of!(FrameParams, num_visible) as u64;
            rec.copy_region(&self.counts.counts, COUNT_VISIBLE as u64 * 4, &self.frame_ub, num_visible, 4);
            rec.dispatch_indirect(
                &self.k.preprocess_backward[if scene.camera_grads { 2 } else { 1 }],
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
        if scene.camera_grads {
            rec.dispatch(
                &self.k.camera_grad_reduce,
                &[("frame_texels", &self.frame_ub), ("terms", &g.terms), ("v_camera", &g.v_camera)],
                &(),
                [1, 1, 1],
            )?;
            rec.end_pass("camera_grad_reduce")?;
        }
        if scene.inst.xform_grads && scene.inst.instances > 0 {
            if g.terms.size < (scene.inst.pairs * XFORM_GRAD_TERMS as usize * 4) as u64 {
                bail!("gradient buffers were made without transform gradients");
            }
            rec.dispatch(
                &self.k.xform_grad_reduce,
                &[
                    ("frame_texels", &self.frame_ub),
                    ("groups", &scene.inst.groups),
                    ("terms", &g.terms),
                    ("v_xforms", &g.v_xforms),
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

    /// The last frame's per-pixel `last` counts: the number of the tile's splats up to and
    /// including the pixel's last blended one.
    pub fn read_last(&self) -> Result<Vec<u32>> {
        let im = self.image.as_ref().ok_or_else(|| anyhow::anyhow!("no frame rendered"))?;
        self.gpu.read(&im.last, (im.width * im.height) as usize)
    }

    /// The frame parameters of the last rendered frame.
    pub fn last_frame_params(&self) -> Option<FrameParams> {
        self.last_params
    }
}
