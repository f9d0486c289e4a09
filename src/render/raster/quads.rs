//! The hardware-rasterized forward path: after the compute passes up to the depth sort
//! (preprocess → scan visible → compact → depth sort), the visible splats are drawn front to
//! back as instanced quads (glsl/splat_quads.vert, .frag) through the fixed-function rasterizer
//! and blending, then the background (glsl/splat_background.*), and the image is copied into
//! the same `out_image` buffer as the compute path's blend. No tile lists: the emit, tile sort,
//! ranges and blend passes are skipped.
//!
//! It renders what blend.comp renders: the same alpha per pixel centre (`min(0.99, o e^{-q/2})`,
//! nothing under 1/255) in the same order per pixel (the tile lists keep the depth order), so
//! the two differ by rounding and where a pixel saturates: blend stops before the splat that
//! would take T below 1e-4 (Inria's rule), so at T < 1e-4 / (1 − 0.99) = 0.01; the draw blends
//! it and the rest, which changes that pixel by less than T. Forward only: training and `last`
//! (the backward pass's start per pixel) stay with the compute path, the reference.
use anyhow::Result;

use crate::gpu::draw::{RenderTarget, SplatDraw, SplatDrawCall};
use crate::gpu::kernels::Kernels;
use crate::gpu::{Buffer, Gpu, Recorder};

/// How the forward rasterizer turns depth-sorted splats into pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Forward {
    /// Tile lists and the blend kernel (the reference, and the training path).
    #[default]
    Compute,
    /// Instanced quads, fixed-function rasterization and blending.
    Quads,
    /// Whichever of the two renders the first frame faster on this device (three frames each,
    /// alternating, by the wall clock); compute where the device cannot draw.
    Auto,
}

/// The draw path's pipelines, its target (one image size) and its indirect draw arguments.
pub(super) struct QuadBufs {
    draw: SplatDraw,
    target: Option<RenderTarget>,
    /// VkDrawIndirectCommand: QUAD_VERTICES vertices, COUNT_VISIBLE instances (draw_args.comp).
    args: Buffer,
}

impl QuadBufs {
    pub fn new(gpu: &std::sync::Arc<Gpu>) -> Result<QuadBufs> {
        Ok(QuadBufs { draw: SplatDraw::new(gpu)?, target: None, args: gpu.storage("draw_args", 16)? })
    }

    /// A target of `width` × `height` (kept while the size stays).
    pub fn ensure_target(&mut self, gpu: &std::sync::Arc<Gpu>, width: u32, height: u32) -> Result<()> {
        if self.target.as_ref().is_none_or(|t| t.width != width || t.height != height) {
            self.target = None;
            self.target = Some(RenderTarget::new(gpu, &self.draw, width, height)?);
        }
        Ok(())
    }

    pub fn bytes(&self) -> u64 {
        self.args.size + self.target.as_ref().map_or(0, |t| t.bytes())
    }

    /// Records the draw of the COUNT_VISIBLE splats in `depth_ids` order into `out_image`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        rec: &mut Recorder,
        k: &Kernels,
        counts: &Buffer,
        frame: &Buffer,
        splats: [(&str, &Buffer); 4],
        out_image: &Buffer,
    ) -> Result<()> {
        rec.dispatch(&k.draw_args, &[("counts", counts), ("draw_args", &self.args)], &(), [1, 1, 1])?;
        let [a, b, c, d] = splats;
        let target = self.target.as_ref().expect("ensure_target before record");
        rec.draw_splats(
            &self.draw,
            target,
            &SplatDrawCall {
                splats: &[("frame_texels", frame), a, b, c, d],
                args: &self.args,
                args_offset: 0,
                background: &[("frame_texels", frame)],
                out: out_image,
            },
        )
    }
}
