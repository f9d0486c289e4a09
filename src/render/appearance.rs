//! Per-photo colour transforms ("appearance"): the 3×4 affine `out = M rgb + b` that
//! Hierarchical 3DGS (Kerbl et al. 2024, its exposure compensation, since merged into Inria's
//! 3DGS as `--train_test_exp`) learns for every training photo and applies to the render before
//! the loss, so exposure and white-balance changes from photo to photo are not baked into the
//! scene. A transform is 12 floats, row c = `(M[c][0], M[c][1], M[c][2], b[c])` on linear `[0, 1]`
//! RGB as the images are stored; [`IDENTITY`] leaves a render as it is.
//!
//! With them, the lens's vignetting, one [`Vignetting`] for the whole capture: a radial falloff
//! `v(r) = 1 + k1 r² + k2 r⁴` that multiplies the transformed colour, r² the squared radius of
//! the pixel's centre in normalised image coordinates (((x + 0.5 − cx) / fx)² + ((y + 0.5 −
//! cy) / fy)², OpenCV's convention, as the lens distortion's). A photo is modelled as
//! `v(r) (M rgb + b)`: the scene keeps the light the lens lets through at its centre, so the
//! darker corners of photos are not baked into it, and the held-out metrics render through the
//! same lens ([`vignette`]).
//!
//! The GPU passes are `glsl/appearance.comp` (apply) and `glsl/appearance_backward.comp`
//! (dL/d render, dL/d transform and dL/d vignetting); [`apply_photo`] and [`backward`] are their
//! CPU twins. [`fit`] is the least-squares transform of a render onto a photo over chosen
//! pixels: the evaluation's compensated metrics fit it on a held-out photo's left half and score
//! its right half (H3DGS's protocol).
use std::sync::Arc;

use anyhow::Result;
use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::gpu::kernels::Kernels;
use crate::gpu::{Buffer, Gpu, Recorder};
use crate::model::camera::Camera;
use crate::shared::{AppearanceArgs, APPEARANCE_GRADS, APPEARANCE_PARAMS, APPEARANCE_RUN, WG_SIZE};

/// One photo's colour transform: rows `(M[c][0], M[c][1], M[c][2], b[c])` for c = r, g, b.
pub type ColourTransform = [f32; APPEARANCE_PARAMS as usize];

/// A lens's vignetting `(k1, k2)`: the falloff `1 + k1 r² + k2 r⁴` (module docs).
pub type Vignetting = [f32; 2];

/// The transform that changes nothing.
pub const IDENTITY: ColourTransform = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// A lens without vignetting.
pub const NO_VIGNETTING: Vignetting = [0.0, 0.0];

/// What a run learned of its photos (RUN/appearance.json): each training photo's colour
/// transform, in the dataset's training order, and the lens's vignetting.
#[derive(Clone, Debug, PartialEq)]
pub struct PhotoAppearance {
    pub colours: Vec<ColourTransform>,
    pub vignetting: Vignetting,
}

/// r² of pixel `i`'s centre in `cam`'s normalised image coordinates (twin of
/// `vignetting_radius2` in glsl/vignetting.glsl).
pub fn radius2(cam: &Camera, i: usize) -> f32 {
    let w = cam.width as usize;
    let x = ((i % w) as f32 + 0.5 - cam.cx) * (1.0 / cam.fx);
    let y = ((i / w) as f32 + 0.5 - cam.cy) * (1.0 / cam.fy);
    x * x + y * y
}

/// The falloff `1 + k1 r² + k2 r⁴` at `r2` = r² (twin of `vignetting_falloff`).
pub fn falloff(k: &Vignetting, r2: f32) -> f32 {
    1.0 + r2 * (k[0] + r2 * k[1])
}

/// The push constants of both kernels, for an image of `cam`'s size.
pub fn args(t: &ColourTransform, k: &Vignetting, cam: &Camera) -> AppearanceArgs {
    AppearanceArgs {
        row0: [t[0], t[1], t[2], t[3]],
        row1: [t[4], t[5], t[6], t[7]],
        row2: [t[8], t[9], t[10], t[11]],
        vignetting: [k[0], k[1], 0.0, 0.0],
        pinhole: [cam.cx, cam.cy, 1.0 / cam.fx, 1.0 / cam.fy],
        pixels: cam.width * cam.height,
        width: cam.width,
        ..Default::default()
    }
}

/// `t` applied to every pixel (alpha kept), without vignetting.
pub fn apply(t: &ColourTransform, image: &[[f32; 4]]) -> Vec<[f32; 4]> {
    image
        .iter()
        .map(|p| {
            let row = |c: usize| t[4 * c] * p[0] + t[4 * c + 1] * p[1] + t[4 * c + 2] * p[2] + t[4 * c + 3];
            [row(0), row(1), row(2), p[3]]
        })
        .collect()
}

/// `image` (of `cam`'s size) seen through the lens's vignetting `k` (alpha kept).
pub fn vignette(k: &Vignetting, cam: &Camera, image: &[[f32; 4]]) -> Vec<[f32; 4]> {
    if *k == NO_VIGNETTING {
        return image.to_vec();
    }
    image
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let v = falloff(k, radius2(cam, i));
            [v * p[0], v * p[1], v * p[2], p[3]]
        })
        .collect()
}

/// A render as its photo was modelled in training: `t`, then the vignetting `k` (the CPU twin of
/// `appearance.comp`).
pub fn apply_photo(t: &ColourTransform, k: &Vignetting, cam: &Camera, image: &[[f32; 4]]) -> Vec<[f32; 4]> {
    vignette(k, cam, &apply(t, image))
}

/// The CPU twin of `appearance_backward.comp` (in f64): given dL/d out per pixel, dL/d image
/// (`v(r) Mᵀ dL/d out`, alpha 0) and dL/d (t, k) in the parameters' order (the transform's 12,
/// then k1, k2).
pub fn backward(
    t: &ColourTransform,
    k: &Vignetting,
    cam: &Camera,
    image: &[[f32; 4]],
    v_out: &[[f32; 4]],
) -> (Vec<[f32; 4]>, [f64; APPEARANCE_GRADS as usize]) {
    let mut grads = [0.0f64; APPEARANCE_GRADS as usize];
    let p12 = APPEARANCE_PARAMS as usize;
    let v_image = image
        .iter()
        .zip(v_out)
        .enumerate()
        .map(|(i, (p, v))| {
            let r2 = radius2(cam, i) as f64;
            let f = falloff(k, r2 as f32) as f64;
            let x = [p[0] as f64, p[1] as f64, p[2] as f64, 1.0];
            let u = |c: usize| (0..4).map(|j| t[4 * c + j] as f64 * x[j]).sum::<f64>();
            let vu: f64 = (0..3).map(|c| v[c] as f64 * u(c)).sum();
            grads[p12] += r2 * vu;
            grads[p12 + 1] += r2 * r2 * vu;
            for c in 0..3 {
                for j in 0..4 {
                    grads[4 * c + j] += f * v[c] as f64 * x[j];
                }
            }
            let col = |j: usize| (0..3).map(|c| t[4 * c + j] as f64 * f * v[c] as f64).sum::<f64>() as f32;
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
            grads: gpu.storage("appearance_grads", APPEARANCE_GRADS as u64 * 4)?,
            grads_readback: gpu.buffer(
                "appearance_grads_readback",
                APPEARANCE_GRADS as u64 * 4,
                vk::BufferUsageFlags::empty(),
                MemoryLocation::GpuToCpu,
            )?,
        })
    }

    fn groups(&self) -> [u32; 3] {
        [(self.pixels as u32).div_ceil(APPEARANCE_RUN).div_ceil(WG_SIZE), 1, 1]
    }

    /// The push constants for `cam`, whose image must be this size.
    fn args_for(&self, t: &ColourTransform, v: &Vignetting, cam: &Camera) -> Result<AppearanceArgs> {
        if (cam.width * cam.height) as usize != self.pixels {
            anyhow::bail!("a {}x{} camera for appearance buffers of {} pixels", cam.width, cam.height, self.pixels);
        }
        Ok(args(t, v, cam))
    }

    /// Records `image` (a render from `cam`) → `self.adjusted` under `t` and the vignetting `v`.
    pub fn record_apply(
        &self,
        rec: &mut Recorder,
        k: &Kernels,
        image: &Buffer,
        t: &ColourTransform,
        v: &Vignetting,
        cam: &Camera,
    ) -> Result<()> {
        let a = self.args_for(t, v, cam)?;
        rec.dispatch(&k.appearance, &[("image", image), ("adjusted", &self.adjusted)], &a, self.groups())?;
        rec.end_pass("appearance")
    }

    /// Records the backward from dL/d adjusted (`v_adjusted`): `self.v_render` and the gradient
    /// sums, copied for [`AppearanceBufs::read_grads`] in the same submission.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        rec: &mut Recorder,
        k: &Kernels,
        image: &Buffer,
        v_adjusted: &Buffer,
        t: &ColourTransform,
        v: &Vignetting,
        cam: &Camera,
    ) -> Result<()> {
        let a = self.args_for(t, v, cam)?;
        rec.fill(&self.grads, 0);
        rec.dispatch(
            &k.appearance_backward,
            &[("image", image), ("v_adjusted", v_adjusted), ("v_image", &self.v_render), ("grads", &self.grads)],
            &a,
            self.groups(),
        )?;
        rec.end_pass("appearance backward")?;
        rec.copy(&self.grads, &self.grads_readback, APPEARANCE_GRADS as u64 * 4);
        rec.end_pass("readback")
    }

    /// The gradient sums of the last recorded backward, after its submission finished.
    /// The transform's 12, then the vignetting's 2.
    pub fn read_grads(&self) -> Result<[f32; APPEARANCE_GRADS as usize]> {
        let v: Vec<f32> = self.grads_readback.read_mapped(APPEARANCE_GRADS as usize)?;
        Ok(v.try_into().expect("14 gradient sums"))
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
