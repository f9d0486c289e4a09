//! Per-photo colour transforms ("appearance"): the 3×4 affine `out = M rgb + b` that
//! Hierarchical 3DGS (Kerbl et al. 2024, its exposure compensation, since merged into Inria's
//! 3DGS as `--train_test_exp`) learns for every training photo and applies to the render before
//! the loss, so exposure and white-balance changes from photo to photo are not baked into the
//! scene. A transform is 12 floats, row c = `(M[c][0], M[c][1], M[c][2], b[c])` on linear `[0, 1]`
//! RGB as the images are stored; [`IDENTITY`] leaves a render as it is.
//!
//! The GPU passes are `glsl/appearance.comp` (apply) and `glsl/appearance_backward.comp`
//! (dL/d render and dL/d transform); [`apply`] and [`backward`] are their CPU twins. [`fit`] is
//! the least-squares transform of a render onto a photo over chosen pixels: the evaluation's
//! compensated metrics fit it on a held-out photo's left half and score its right half
//! (H3DGS's protocol).
use std::sync::Arc;

use anyhow::Result;
use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::Kernels;
use crate::gpu::{Buffer, Gpu, Recorder};
use crate::shared::{AppearanceArgs, APPEARANCE_PARAMS, APPEARANCE_RUN, WG_SIZE};

/// One photo's colour transform: rows `(M[c][0], M[c][1], M[c][2], b[c])` for c = r, g, b.
pub type ColourTransform = [f32; APPEARANCE_PARAMS as usize];

/// The transform that changes nothing.
pub const IDENTITY: ColourTransform = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// The push constants of both kernels.
pub fn args(t: &ColourTransform, pixels: usize) -> AppearanceArgs {
    AppearanceArgs {
        row0: [t[0], t[1], t[2], t[3]],
        row1: [t[4], t[5], t[6], t[7]],
        row2: [t[8], t[9], t[10], t[11]],
        pixels: pixels as u32,
        ..Default::default()
    }
}

/// `t` applied to every pixel (alpha kept): the CPU twin of `appearance.comp`.
pub fn apply(t: &ColourTransform, image: &[[f32; 4]]) -> Vec<[f32; 4]> {
    image
        .iter()
        .map(|p| {
            let row = |c: usize| t[4 * c] * p[0] + t[4 * c + 1] * p[1] + t[4 * c + 2] * p[2] + t[4 * c + 3];
            [row(0), row(1), row(2), p[3]]
        })
        .collect()
}

/// The CPU twin of `appearance_backward.comp` (in f64): given dL/d out per pixel, dL/d image
/// (`Mᵀ v`, alpha 0) and dL/d t in the parameters' order.
pub fn backward(t: &ColourTransform, image: &[[f32; 4]], v_out: &[[f32; 4]]) -> (Vec<[f32; 4]>, [f64; 12]) {
    let mut grads = [0.0f64; 12];
    let v_image = image
        .iter()
        .zip(v_out)
        .map(|(p, v)| {
            let x = [p[0] as f64, p[1] as f64, p[2] as f64, 1.0];
            for c in 0..3 {
                for j in 0..4 {
                    grads[4 * c + j] += v[c] as f64 * x[j];
                }
            }
            let col = |j: usize| (0..3).map(|c| t[4 * c + j] as f64 * v[c] as f64).sum::<f64>() as f32;
            [col(0), col(1), col(2), 0.0]
        })
        .collect();
    (v_image, grads)
}

/// The transform that maps `render` onto `target` with the least squared error over the pixels
/// `keep` selects (each output channel an ordinary least-squares fit on (r, g, b, 1), solved in
/// f64); the identity when those pixels cannot determine one (fewer than four, or colours
/// that span no volume, as a flat grey half).
pub fn fit(render: &[[f32; 4]], target: &[[f32; 4]], keep: impl Fn(usize) -> bool) -> ColourTransform {
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    let mut atb = nalgebra::Matrix4x3::<f64>::zeros();
    let mut n = 0usize;
    for (i, (p, q)) in render.iter().zip(target).enumerate().filter(|(i, _)| keep(*i)) {
        let _ = i;
        let x = nalgebra::Vector4::new(p[0] as f64, p[1] as f64, p[2] as f64, 1.0);
        ata += x * x.transpose();
        for c in 0..3 {
            for j in 0..4 {
                atb[(j, c)] += x[j] * q[c] as f64;
            }
        }
        n += 1;
    }
    // A light ridge towards the identity keeps an ill-conditioned fit (near-flat colours) sane.
    let ridge = 1e-6 * (n.max(1) as f64);
    let mut prior = nalgebra::Matrix4x3::<f64>::zeros();
    for c in 0..3 {
        prior[(c, c)] = 1.0;
    }
    let lhs = ata + nalgebra::Matrix4::identity() * ridge;
    let rhs = atb + prior * ridge;
    match (n >= 4).then(|| lhs.cholesky()).flatten() {
        Some(ch) => {
            let sol = ch.solve(&rhs);
            let mut t = [0.0f32; 12];
            for c in 0..3 {
                for j in 0..4 {
                    t[4 * c + j] = sol[(j, c)] as f32;
                }
            }
            if t.iter().all(|v| v.is_finite()) {
                t
            } else {
                IDENTITY
            }
        }
        None => IDENTITY,
    }
}

/// PSNR and SSIM of `render` against `target` (`width`×`height`) with the photo's colour
/// transform compensated (H3DGS's protocol): the transform is fitted on the left half
/// (x < width / 2) and both metrics are measured on the right half alone.
pub fn compensated_scores(render: &[[f32; 4]], target: &[[f32; 4]], width: usize, height: usize) -> (f64, f64) {
    let half = width / 2;
    let t = fit(render, target, |i| i % width < half);
    let adjusted = apply(&t, render);
    let crop = |img: &[[f32; 4]]| -> Vec<[f32; 4]> {
        (0..height).flat_map(|y| img[y * width + half..(y + 1) * width].iter().copied()).collect()
    };
    let (a, b) = (crop(&adjusted), crop(target));
    let rgb = |img: &[[f32; 4]]| -> Vec<[f64; 3]> {
        img.iter().map(|p| [0, 1, 2].map(|c| p[c].clamp(0.0, 1.0) as f64)).collect()
    };
    let w = width - half;
    (crate::util::psnr(&a, &b), crate::render::reference::backward::ssim(&rgb(&a), &rgb(&b), w, height))
}

/// The device buffers of the transform at one image size: the transformed render, dL/d render
/// and the gradient sums (with their host-visible copy).
pub struct AppearanceBufs {
    pub pixels: usize,
    /// The render after the transform (RGBA f32), what the loss sees.
    pub adjusted: Buffer,
    /// dL/d render (RGBA f32, a = 0), what the rasterizer's backward takes.
    pub v_render: Buffer,
    grads: Buffer,
    grads_readback: Buffer,
}

impl AppearanceBufs {
    pub fn new(gpu: &Arc<Gpu>, pixels: usize) -> Result<AppearanceBufs> {
        let px = pixels as u64;
        Ok(AppearanceBufs {
            pixels,
            adjusted: gpu.storage("appearance_adjusted", px * 16)?,
            v_render: gpu.storage("appearance_v_render", px * 16)?,
            grads: gpu.storage("appearance_grads", APPEARANCE_PARAMS as u64 * 4)?,
            grads_readback: gpu.buffer(
                "appearance_grads_readback",
                APPEARANCE_PARAMS as u64 * 4,
                vk::BufferUsageFlags::empty(),
                MemoryLocation::GpuToCpu,
            )?,
        })
    }

    fn groups(&self) -> [u32; 3] {
        [(self.pixels as u32).div_ceil(APPEARANCE_RUN).div_ceil(WG_SIZE), 1, 1]
    }

    /// Records `image` → `self.adjusted` under `t`.
    pub fn record_apply(&self, rec: &mut Recorder, k: &Kernels, image: &Buffer, t: &ColourTransform) -> Result<()> {
        let a = args(t, self.pixels);
        rec.dispatch(&k.appearance, &[("image", image), ("adjusted", &self.adjusted)], &a, self.groups())?;
        rec.end_pass("appearance")
    }

    /// Records the backward from dL/d adjusted (`v_adjusted`): `self.v_render` and the gradient
    /// sums, copied for [`AppearanceBufs::read_grads`] in the same submission.
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        k: &Kernels,
        image: &Buffer,
        v_adjusted: &Buffer,
        t: &ColourTransform,
    ) -> Result<()> {
        let a = args(t, self.pixels);
        rec.fill(&self.grads, 0);
        rec.dispatch(
            &k.appearance_backward,
            &[("image", image), ("v_adjusted", v_adjusted), ("v_image", &self.v_render), ("grads", &self.grads)],
            &a,
            self.groups(),
        )?;
        rec.end_pass("appearance backward")?;
        rec.copy(&self.grads, &self.grads_readback, APPEARANCE_PARAMS as u64 * 4);
        rec.end_pass("readback")
    }

    /// The gradient sums of the last recorded backward, after its submission finished.
    pub fn read_grads(&self) -> Result<[f32; 12]> {
        let v: Vec<f32> = self.grads_readback.read_mapped(APPEARANCE_PARAMS as usize)?;
        Ok(v.try_into().expect("12 gradient sums"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_recovers_a_known_transform() {
        let t: ColourTransform = [1.1, 0.05, 0.0, 0.02, 0.0, 0.95, 0.03, -0.01, 0.02, 0.0, 1.05, 0.0];
        let render: Vec<[f32; 4]> = (0..500)
            .map(|i| {
                let f = |k: u32| ((i * 7919 + k * 104_729) % 1000) as f32 / 1000.0;
                [f(1), f(2), f(3), 1.0]
            })
            .collect();
        let target = apply(&t, &render);
        let got = fit(&render, &target, |_| true);
        for (a, b) in got.iter().zip(&t) {
            assert!((a - b).abs() < 1e-3, "{got:?} vs {t:?}");
        }
        // Nothing to fit on: the identity.
        assert_eq!(fit(&render, &target, |_| false), IDENTITY);
        let grey = vec![[0.5, 0.5, 0.5, 1.0]; 100];
        let f = fit(&grey, &grey, |_| true);
        assert!(apply(&f, &grey).iter().all(|p| (p[0] - 0.5).abs() < 1e-3));
    }
}
