//! Photos taken through a distorting lens, undistorted on load (what nerfstudio's splatfacto and
//! gsplat's COLMAP parser do): the rasterizer draws pinhole images, so a dataset whose cameras
//! carry distortion is remapped, each photo (bilinear) and each mask (nearest), onto a pinhole
//! camera with the same image size and principal point whose focal length is chosen so that
//! every output pixel sees the photo (no blank border, as OpenCV's `getOptimalNewCameraMatrix`
//! with alpha = 0 and COLMAP's `image_undistorter` with `blank_pixels = 0`).
//!
//! The distortion models are in [`crate::model::camera::Lens`] (normalised image coordinates
//! x = (u − cx) / fx, y = (v − cy) / fy, pixel (0, 0)'s centre at (0.5, 0.5)).
use anyhow::{bail, Result};

use crate::model::camera::{Camera, Lens};

/// The remap of one photo: for every output (pinhole) pixel, where it lies in the photo.
#[derive(Clone, Debug, PartialEq)]
pub struct Undistort {
    /// The photo's camera as the camera file gives it (size, intrinsics, lens).
    pub source: Camera,
    /// The undistorted camera (same size, principal point and pose; focal lengths scaled; a
    /// pinhole).
    pub target: Camera,
}

impl Undistort {
    /// The remap of `source` through its lens; refused where the distortion folds over inside
    /// the image (not invertible there), with `what` (file, frame) and the model named.
    pub fn new(source: &Camera, what: &str) -> Result<Undistort> {
        let lens = source.lens;
        let (w, h) = (source.width as f64, source.height as f64);
        let (fx, fy, cx, cy) = (source.fx as f64, source.fy as f64, source.cx as f64, source.cy as f64);
        // The distortion must be one-to-one over the whole image and a margin past it (the remap
        // may reach past the border before it shrinks): the determinant of its Jacobian, on a
        // grid over 1.5 × the image's extent about the principal point, stays positive (tangential
        // terms included; a fold has it change sign).
        let (x0, x1) = (1.5 * (0.0 - cx) / fx, 1.5 * (w - cx) / fx);
        let (y0, y1) = (1.5 * (0.0 - cy) / fy, 1.5 * (h - cy) / fy);
        const GRID: usize = 96;
        let e = 1e-4 * (x1 - x0).abs().max((y1 - y0).abs()).max(1e-9);
        for i in 0..=GRID {
            for j in 0..=GRID {
                let x = x0 + (x1 - x0) * i as f64 / GRID as f64;
                let y = y0 + (y1 - y0) * j as f64 / GRID as f64;
                let (ax, ay) = lens.distort(x + e, y);
                let (bx, by) = lens.distort(x - e, y);
                let (cx_, cy_) = lens.distort(x, y + e);
                let (dx, dy) = lens.distort(x, y - e);
                let det = (ax - bx) * (cy_ - dy) - (ay - by) * (cx_ - dx);
                if det.is_nan() || det <= 0.0 {
                    bail!(
                        "{what}: the {} distortion folds over near pixel ({:.0}, {:.0}) (the Jacobian's determinant there is {:.2e}, not positive); it cannot be undistorted (are its parameters for this image size?)",
                        lens.name(),
                        cx + fx * x,
                        cy + fy * y,
                        det / (4.0 * e * e)
                    );
                }
            }
        }
        // The smallest focal scale whose border pixels all land inside the photo.
        let inside = |m: f64| {
            let target = scaled(source, m);
            let border = (0..source.width)
                .flat_map(|i| [(i, 0), (i, source.height - 1)])
                .chain((0..source.height).flat_map(|j| [(0, j), (source.width - 1, j)]));
            border.into_iter().all(|(i, j)| {
                let (u, v) = source_point(source, &target, i, j);
                (0.0..=w).contains(&u) && (0.0..=h).contains(&v)
            })
        };
        let (mut lo, mut hi) = (0.05f64, 20.0f64);
        if !inside(hi) {
            bail!("{what}: the {} distortion leaves no pinhole view without blank pixels", lens.name());
        }
        for _ in 0..50 {
            let mid = (lo * hi).sqrt();
            if inside(mid) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Ok(Undistort { source: source.clone(), target: scaled(source, hi) })
    }

    /// The photo (`source` size, RGBA) remapped onto the target camera, bilinearly.
    pub fn image(&self, rgba: &[[f32; 4]]) -> Vec<[f32; 4]> {
        let (w, h) = (self.source.width as usize, self.source.height as usize);
        self.map()
            .map(|(u, v)| {
                // Pixel centres at half-integers: index space is shifted by half a pixel.
                let (x, y) = ((u - 0.5).clamp(0.0, (w - 1) as f64), (v - 0.5).clamp(0.0, (h - 1) as f64));
                let (x0, y0) = (x.floor() as usize, y.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
                let at = |xx: usize, yy: usize| rgba[yy * w + xx];
                std::array::from_fn(|c| {
                    let top = at(x0, y0)[c] * (1.0 - fx) + at(x1, y0)[c] * fx;
                    let bottom = at(x0, y1)[c] * (1.0 - fx) + at(x1, y1)[c] * fx;
                    top * (1.0 - fy) + bottom * fy
                })
            })
            .collect()
    }

    /// An id mask (`source` size) remapped onto the target camera: nearest pixel, so ids stay ids.
    pub fn ids(&self, ids: &[u16]) -> Vec<u16> {
        let (w, h) = (self.source.width as usize, self.source.height as usize);
        self.map().map(|(u, v)| ids[(v.floor() as usize).min(h - 1) * w + (u.floor() as usize).min(w - 1)]).collect()
    }

    /// Every target pixel's position in the photo (continuous pixel coordinates), row by row.
    fn map(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        let (tw, th) = (self.target.width, self.target.height);
        (0..th).flat_map(move |j| (0..tw).map(move |i| source_point(&self.source, &self.target, i, j)))
    }
}

/// `source` as a pinhole with its focal lengths scaled by `m`.
fn scaled(source: &Camera, m: f64) -> Camera {
    Camera {
        fx: (source.fx as f64 * m) as f32,
        fy: (source.fy as f64 * m) as f32,
        lens: Lens::Pinhole,
        ..source.clone()
    }
}

/// Where target pixel (i, j)'s centre lies in the photo.
fn source_point(source: &Camera, target: &Camera, i: u32, j: u32) -> (f64, f64) {
    let x = (i as f64 + 0.5 - target.cx as f64) / target.fx as f64;
    let y = (j as f64 + 0.5 - target.cy as f64) / target.fy as f64;
    let (xd, yd) = source.lens.distort(x, y);
    (source.fx as f64 * xd + source.cx as f64, source.fy as f64 * yd + source.cy as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth picture defined on the undistorted image plane (normalised coordinates).
    fn pattern(x: f64, y: f64) -> [f32; 4] {
        let v = |a: f64| (0.5 + 0.4 * a.sin()) as f32;
        [v(7.0 * x), v(5.0 * y + 1.0), v(4.0 * (x + y)), 1.0]
    }

    /// The distorted photo of [`pattern`]: each photo pixel's undistorted point found by
    /// inverting the lens (Newton), as a camera would have recorded it.
    fn photo(lens: &Lens, cam: &Camera) -> Vec<[f32; 4]> {
        (0..cam.height)
            .flat_map(|j| (0..cam.width).map(move |i| (i, j)))
            .map(|(i, j)| {
                let xd = (i as f64 + 0.5 - cam.cx as f64) / cam.fx as f64;
                let yd = (j as f64 + 0.5 - cam.cy as f64) / cam.fy as f64;
                let (mut x, mut y) = (xd, yd);
                for _ in 0..50 {
                    let (fx, fy) = lens.distort(x, y);
                    let e = 1e-7;
                    let (ax, ay) = lens.distort(x + e, y);
                    let (bx, by) = lens.distort(x, y + e);
                    let (j00, j10, j01, j11) = ((ax - fx) / e, (ay - fy) / e, (bx - fx) / e, (by - fy) / e);
                    let det = j00 * j11 - j01 * j10;
                    let (rx, ry) = (fx - xd, fy - yd);
                    x -= (j11 * rx - j01 * ry) / det;
                    y -= (-j10 * rx + j00 * ry) / det;
                }
                pattern(x, y)
            })
            .collect()
    }

    fn camera() -> Camera {
        Camera {
            name: "t".into(),
            width: 160,
            height: 120,
            fx: 150.0,
            fy: 148.0,
            cx: 81.0,
            cy: 59.5,
            viewmat: glam::Mat4::IDENTITY,
            lens: Lens::Pinhole,
        }
    }

    #[test]
    fn undistortion_recovers_the_pinhole_picture() {
        for lens in [
            Lens::RadialTangential { k: [-0.25, 0.08, 0.0, 0.0], p: [0.002, -0.001] },
            Lens::RadialTangential { k: [0.12, 0.0, 0.0, 0.0], p: [0.0, 0.0] },
            Lens::Fisheye { k: [0.05, -0.01, 0.0, 0.0] },
        ] {
            let cam = Camera { lens, ..camera() };
            let u = Undistort::new(&cam, "test").unwrap();
            let got = u.image(&photo(&lens, &cam));
            let t = &u.target;
            let want: Vec<[f32; 4]> = (0..t.height)
                .flat_map(|j| (0..t.width).map(move |i| (i, j)))
                .map(|(i, j)| {
                    pattern((i as f64 + 0.5 - t.cx as f64) / t.fx as f64, (j as f64 + 0.5 - t.cy as f64) / t.fy as f64)
                })
                .collect();
            let db = crate::util::psnr(&got, &want);
            assert!(db > 40.0, "{lens:?}: {db:.1} dB against the pinhole picture");
            // No blank border: every target pixel maps into the photo, and the focal length is
            // the smallest that does (one percent less leaves a pixel outside).
            assert_eq!(t.width, cam.width);
        }
        // A lens that folds over inside the image is refused.
        let fold = Lens::RadialTangential { k: [-2.0, 0.0, 0.0, 0.0], p: [0.0, 0.0] };
        let e = Undistort::new(&Camera { lens: fold, ..camera() }, "cams.json: frame 3").unwrap_err().to_string();
        assert!(e.contains("frame 3") && e.contains("OPENCV") && e.contains("folds over"), "{e}");
    }

    #[test]
    fn masks_keep_their_ids() {
        let lens = Lens::RadialTangential { k: [-0.2, 0.0, 0.0, 0.0], p: [0.0, 0.0] };
        let cam = Camera { lens, ..camera() };
        let u = Undistort::new(&cam, "test").unwrap();
        let ids: Vec<u16> = (0..cam.width * cam.height).map(|i| (i % 7) as u16).collect();
        assert!(u.ids(&ids).iter().all(|&v| v < 7));
    }
}
