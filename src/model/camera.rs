//! Pinhole cameras.
//!
//! Internal convention: OpenCV camera (+X right, +Y down, +Z forward), `viewmat` maps world to
//! camera, intrinsics in pixels with pixel (0, 0)'s centre at (0.5, 0.5). NeRF-synthetic
//! `transforms_*.json` store OpenGL/Blender camera-to-world matrices (camera looks down −Z, +Y
//! up); they are converted on load by flipping the camera's Y and Z axes.
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use glam::{Mat4, Vec3, Vec4};

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Name for output files (the frame's `file_path` basename, or `view_000`…).
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// World → camera (OpenCV).
    pub viewmat: Mat4,
    /// The lens's distortion as the camera file gives it. Rendering is pinhole: datasets undistort
    /// their photos on load (`crate::dataset::lens`), and their cameras are pinholes after it.
    pub lens: Lens,
}

/// A lens's distortion of normalised image coordinates (x = (u − cx) / fx, y = (v − cy) / fy):
/// where a ray that a pinhole would image at (x, y) lands in the photo.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Lens {
    #[default]
    Pinhole,
    /// OpenCV's radial-tangential model: r² = x² + y², radial = 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸,
    /// x' = x radial + 2 p1 x y + p2 (r² + 2x²), y' = y radial + p1 (r² + 2y²) + 2 p2 x y.
    /// COLMAP's SIMPLE_RADIAL (k1), RADIAL (k1, k2) and OPENCV (k1, k2, p1, p2); nerfstudio's
    /// OPENCV (k1..k4, p1, p2).
    RadialTangential { k: [f64; 4], p: [f64; 2] },
    /// OpenCV's fisheye (equidistant) model: θ = atan r, θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ +
    /// k4 θ⁸), (x', y') = (θd / r) (x, y). COLMAP's OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE (k1)
    /// and RADIAL_FISHEYE (k1, k2); nerfstudio's OPENCV_FISHEYE.
    Fisheye { k: [f64; 4] },
}

impl Lens {
    /// The distorted point of (x, y).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        match *self {
            Lens::Pinhole => (x, y),
            Lens::RadialTangential { k, p } => {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * (k[2] + r2 * k[3])));
                (
                    x * radial + 2.0 * p[0] * x * y + p[1] * (r2 + 2.0 * x * x),
                    y * radial + p[0] * (r2 + 2.0 * y * y) + 2.0 * p[1] * x * y,
                )
            }
            Lens::Fisheye { k } => {
                let r = x.hypot(y);
                if r < 1e-12 {
                    return (x, y);
                }
                let t = r.atan();
                let t2 = t * t;
                let td = t * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
                (x * td / r, y * td / r)
            }
        }
    }

    /// Whether it distorts at all.
    pub fn is_pinhole(&self) -> bool {
        match self {
            Lens::Pinhole => true,
            Lens::RadialTangential { k, p } => k.iter().chain(p).all(|&v| v == 0.0),
            Lens::Fisheye { .. } => false,
        }
    }

    /// The model's name as OpenCV / COLMAP / nerfstudio call it.
    pub fn name(&self) -> &'static str {
        match self {
            Lens::Pinhole => "PINHOLE",
            Lens::RadialTangential { .. } => "OPENCV",
            Lens::Fisheye { .. } => "OPENCV_FISHEYE",
        }
    }
}

impl Camera {
    /// Camera centre in world space.
    pub fn position(&self) -> Vec3 {
        self.viewmat.inverse().w_axis.truncate()
    }

    /// The world-space ray (origin, unit direction) through image point (`u`, `v`) in pixels
    /// (pixel (0, 0) spans [0, 1)², as in the module docs).
    pub fn ray(&self, u: f32, v: f32) -> (Vec3, Vec3) {
        let c2w = self.viewmat.inverse();
        let d = Vec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0);
        (c2w.w_axis.truncate(), c2w.transform_vector3(d).normalize())
    }

    /// The image point (`u`, `v`, depth) of world point `p`; None behind the camera.
    pub fn project(&self, p: Vec3) -> Option<[f32; 3]> {
        let c = self.viewmat.transform_point3(p);
        (c.z > 1e-6).then(|| [self.fx * c.x / c.z + self.cx, self.fy * c.y / c.z + self.cy, c.z])
    }

    /// From an OpenGL camera-to-world matrix.
    pub fn from_c2w_opengl(name: &str, c2w: Mat4, width: u32, height: u32, intr: [f32; 4]) -> Camera {
        let flip = Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0));
        Camera {
            name: name.to_string(),
            width,
            height,
            fx: intr[0],
            fy: intr[1],
            cx: intr[2],
            cy: intr[3],
            viewmat: (c2w * flip).inverse(),
            lens: Lens::Pinhole,
        }
    }

    /// The OpenGL camera-to-world matrix (the inverse of [`Camera::from_c2w_opengl`]).
    pub fn c2w_opengl(&self) -> Mat4 {
        self.viewmat.inverse() * Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0))
    }

    /// The same view at another resolution (intrinsics scaled per axis).
    pub fn resized(&self, width: u32, height: u32) -> Camera {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Camera { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, ..self.clone() }
    }

    /// The part of this view `width` × `height` pixels large whose top-left pixel is the
    /// view's (`x0`, `y0`): the same rays, the principal point moved (a crop renders exactly
    /// the pixels of the whole image it covers).
    pub fn cropped(&self, x0: u32, y0: u32, width: u32, height: u32) -> Camera {
        Camera { width, height, cx: self.cx - x0 as f32, cy: self.cy - y0 as f32, ..self.clone() }
    }

    /// Checks the values the rasterizer relies on.
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 {
            bail!("camera '{}': image size {}x{} is empty", self.name, self.width, self.height);
        }
        if !(self.fx > 0.0 && self.fy > 0.0 && self.fx.is_finite() && self.fy.is_finite()) {
            bail!("camera '{}': focal lengths must be positive and finite", self.name);
        }
        if !(self.cx.is_finite() && self.cy.is_finite() && self.viewmat.is_finite()) {
            bail!("camera '{}': non-finite intrinsics or pose", self.name);
        }
        Ok(())
    }
}

#[derive(serde::Deserialize)]
struct TransformsFile {
    camera_angle_x: Option<f32>,
    #[serde(flatten)]
    intrinsics: IntrinsicKeys,
    #[serde(flatten)]
    lens: LensKeys,
    #[serde(default)]
    frames: Vec<Frame>,
}

/// The intrinsics keys (top level, or per frame overriding them): focal lengths and principal
/// point in pixels, image size.
#[derive(serde::Deserialize, Default, Clone, Copy)]
struct IntrinsicKeys {
    fl_x: Option<f32>,
    fl_y: Option<f32>,
    cx: Option<f32>,
    cy: Option<f32>,
    w: Option<f32>,
    h: Option<f32>,
}

impl IntrinsicKeys {
    /// These keys with `frame`'s where it has them.
    fn over(&self, frame: &IntrinsicKeys) -> IntrinsicKeys {
        IntrinsicKeys {
            fl_x: frame.fl_x.or(self.fl_x),
            fl_y: frame.fl_y.or(self.fl_y),
            cx: frame.cx.or(self.cx),
            cy: frame.cy.or(self.cy),
            w: frame.w.or(self.w),
            h: frame.h.or(self.h),
        }
    }
}

/// nerfstudio's lens keys (top level, or per frame overriding them).
#[derive(serde::Deserialize, Default, Clone)]
struct LensKeys {
    camera_model: Option<String>,
    k1: Option<f64>,
    k2: Option<f64>,
    k3: Option<f64>,
    k4: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
}

impl LensKeys {
    /// These keys with `frame`'s where it has them.
    fn over(&self, frame: &LensKeys) -> LensKeys {
        LensKeys {
            camera_model: frame.camera_model.clone().or(self.camera_model.clone()),
            k1: frame.k1.or(self.k1),
            k2: frame.k2.or(self.k2),
            k3: frame.k3.or(self.k3),
            k4: frame.k4.or(self.k4),
            p1: frame.p1.or(self.p1),
            p2: frame.p2.or(self.p2),
        }
    }

    /// The lens (nerfstudio's convention: OPENCV unless `camera_model` says otherwise); models
    /// that cannot be undistorted to a pinhole are refused with `what` and the model named.
    fn lens(&self, what: &str) -> Result<Lens> {
        let z = |v: Option<f64>| v.unwrap_or(0.0);
        let k = [z(self.k1), z(self.k2), z(self.k3), z(self.k4)];
        let p = [z(self.p1), z(self.p2)];
        if let Some(v) = k.iter().chain(&p).find(|v| !v.is_finite()) {
            bail!("{what}: distortion parameter {v} is not finite");
        }
        let lens = match self.camera_model.as_deref().unwrap_or("OPENCV") {
            "PINHOLE" | "SIMPLE_PINHOLE" | "OPENCV" | "RADIAL" | "SIMPLE_RADIAL" => Lens::RadialTangential { k, p },
            "OPENCV_FISHEYE" if p == [0.0, 0.0] => Lens::Fisheye { k },
            "OPENCV_FISHEYE" => bail!("{what}: OPENCV_FISHEYE takes k1..k4 only, not p1 or p2"),
            other => bail!(
                "{what}: camera_model {other} cannot be undistorted to a pinhole here (PINHOLE, OPENCV and OPENCV_FISHEYE can); convert its images to a pinhole camera first"
            ),
        };
        Ok(if lens.is_pinhole() && !matches!(lens, Lens::Fisheye { .. }) { Lens::Pinhole } else { lens })
    }
}

/// A frame; its own intrinsics (nerfstudio's per-frame keys) override the file's.
#[derive(serde::Deserialize)]
struct Frame {
    file_path: String,
    transform_matrix: [[f32; 4]; 4],
    #[serde(flatten)]
    intrinsics: IntrinsicKeys,
    #[serde(flatten)]
    lens: LensKeys,
}

/// The camera-to-world matrix of a frame, checked: a rotation (or a rotation times a uniform
/// scale, which is taken out; `scaled` is set) and a translation, last row (0, 0, 0, 1).
fn rigid_c2w(m: Mat4, what: &str, scaled: &mut bool) -> Result<Mat4> {
    let row = m.row(3);
    if (row - Vec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-4 {
        bail!(
            "{what}: transform_matrix's last row is {:?}, not (0, 0, 0, 1): not a camera-to-world matrix",
            row.to_array()
        );
    }
    let r = glam::Mat3::from_mat4(m);
    let det = r.determinant();
    if !(det.is_finite() && det.abs() > 1e-12) {
        bail!("{what}: transform_matrix's rotation part is singular (determinant {det})");
    }
    if det < 0.0 {
        bail!("{what}: transform_matrix's rotation part is a reflection (determinant {det:.3} < 0), not a rotation");
    }
    let s = det.cbrt();
    let rtr = (r.transpose() * r) * (1.0 / (s * s));
    let off = (rtr.x_axis - Vec3::X)
        .abs()
        .max_element()
        .max((rtr.y_axis - Vec3::Y).abs().max_element())
        .max((rtr.z_axis - Vec3::Z).abs().max_element());
    if off > 1e-3 {
        bail!("{what}: transform_matrix's rotation part is sheared or scaled unevenly (RᵀR deviates from a multiple of I by {off:.3}), not a rotation");
    }
    if (s - 1.0).abs() > 1e-4 {
        *scaled = true;
        let r = r * (1.0 / s);
        return Ok(Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), m.w_axis));
    }
    Ok(m)
}

/// The largest image side a camera file may give (pixels).
pub const MAX_IMAGE_SIDE: u32 = 65_536;

/// Loads the cameras of a NeRF-synthetic `transforms_*.json`. The image size comes from `w`/`h`
/// or, when absent, from the first frame's image file next to the JSON.
pub fn load_transforms(path: &Path) -> Result<Vec<Camera>> {
    Ok(load_transforms_with_images(path)?.into_iter().map(|(c, _)| c).collect())
}

/// As [`load_transforms`], with each frame's image path (which need not exist; whoever reads the
/// images confines them to the dataset's folder, `crate::limits::inside`).
pub fn load_transforms_with_images(path: &Path) -> Result<Vec<(Camera, std::path::PathBuf)>> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    transforms_from_str(&text, path.parent().unwrap_or(Path::new(".")), &what)
}

/// [`load_transforms_with_images`] on the text of a transforms JSON; `dir` is its folder (image
/// paths are relative to it), `what` names it in errors.
pub fn transforms_from_str(text: &str, dir: &Path, what: &str) -> Result<Vec<(Camera, std::path::PathBuf)>> {
    let tf: TransformsFile = serde_json::from_str(text).map_err(|e| anyhow!("{what}: not a transforms JSON: {e}"))?;
    if tf.frames.is_empty() {
        bail!("{what}: no frames");
    }
    let (top, first) = (&tf.intrinsics, &tf.frames[0].intrinsics);
    let (w, h) = match (top.w.or(first.w), top.h.or(first.h)) {
        (Some(w), Some(h)) => (w, h),
        _ => {
            // The one image this reader opens: confined to the file's folder.
            crate::limits::relative(what, "frame 0's file_path", &tf.frames[0].file_path, dir)?;
            let img = image_path(dir, &tf.frames[0].file_path);
            let (w, h) = image::image_dimensions(&img)
                .with_context(|| format!("{what}: no w/h given and cannot read image {}", img.display()))?;
            (w as f32, h as f32)
        }
    };
    if !(w >= 1.0 && h >= 1.0) {
        bail!("{what}: image size {w}x{h} is empty");
    }
    let mut cams = Vec::new();
    let mut scaled = false;
    for (k, f) in tf.frames.iter().enumerate() {
        let i = tf.intrinsics.over(&f.intrinsics);
        let (w, h) = (i.w.unwrap_or(w), i.h.unwrap_or(h));
        if !(w >= 1.0 && h >= 1.0) {
            bail!("{what}: frame {k}: image size {w}x{h} is empty");
        }
        for (key, v) in [("w", w), ("h", h)] {
            if v.fract() != 0.0 || v > MAX_IMAGE_SIDE as f32 {
                bail!("{what}: frame {k}: {key} {v} is not an image side (a whole number of pixels, at most {MAX_IMAGE_SIDE})");
            }
        }
        let fx = match (i.fl_x, tf.camera_angle_x) {
            (Some(f), _) => f,
            (None, Some(a)) if a > 0.0 && a < std::f32::consts::PI => 0.5 * w / (0.5 * a).tan(),
            (None, Some(a)) => bail!("{what}: camera_angle_x {a} is not a field of view in (0, π) radians"),
            (None, None) => bail!("{what}: neither fl_x nor camera_angle_x is given"),
        };
        let fy = i.fl_y.unwrap_or(fx);
        let intr = [fx, fy, i.cx.unwrap_or(0.5 * w), i.cy.unwrap_or(0.5 * h)];
        // transform_matrix is row-major.
        let frame = format!("{what}: frame {k} ({})", f.file_path);
        let c2w = rigid_c2w(Mat4::from_cols_array_2d(&f.transform_matrix).transpose(), &frame, &mut scaled)?;
        let lens = tf.lens.over(&f.lens).lens(&frame)?;
        let name = Path::new(&f.file_path)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("frame_{k:03}"));
        let name = [".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"]
            .iter()
            .find_map(|e| name.strip_suffix(e))
            .unwrap_or(&name)
            .to_string();
        // w and h are whole and at most MAX_IMAGE_SIDE (checked above): exact as u32.
        let cam = Camera { lens, ..Camera::from_c2w_opengl(&name, c2w, w as u32, h as u32, intr) };
        cam.validate().with_context(|| format!("{what}: frame {k}"))?;
        cams.push((cam, image_path(dir, &f.file_path)));
    }
    if scaled {
        eprintln!("note: {what}: rotations scaled uniformly in transform_matrix were normalised to rotations");
    }
    Ok(cams)
}

/// `cams` as a NeRF-synthetic transforms JSON (OpenGL camera-to-world, row-major) with each
/// frame's intrinsics (`fl_x fl_y cx cy w h`, nerfstudio's per-frame keys; the first camera's
/// also at the top level, with `camera_angle_x`, for readers that take one camera for all) and
/// `file_path` from `images` (the image of each camera).
pub fn transforms_json(cams: &[Camera], images: &[String]) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = cams
        .iter()
        .zip(images)
        .map(|(c, file)| {
            let m = c.c2w_opengl().transpose().to_cols_array_2d();
            let mut f = serde_json::json!({
                "file_path": file, "transform_matrix": m,
                "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
            });
            // nerfstudio's lens keys where the camera has a lens.
            match c.lens {
                Lens::Pinhole => {}
                Lens::RadialTangential { k, p } => {
                    f["camera_model"] = "OPENCV".into();
                    for (key, v) in ["k1", "k2", "k3", "k4", "p1", "p2"].iter().zip(k.iter().chain(&p)) {
                        f[*key] = (*v).into();
                    }
                }
                Lens::Fisheye { k } => {
                    f["camera_model"] = "OPENCV_FISHEYE".into();
                    for (key, v) in ["k1", "k2", "k3", "k4"].iter().zip(&k) {
                        f[*key] = (*v).into();
                    }
                }
            }
            f
        })
        .collect();
    let c = &cams[0];
    serde_json::json!({
        "camera_angle_x": 2.0 * (0.5 * c.width as f32 / c.fx).atan(),
        "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
        "frames": frames,
    })
}

/// The image file of a frame: `file_path` as given, or with `.png` appended.
pub fn image_path(dir: &Path, file_path: &str) -> std::path::PathBuf {
    let p = dir.join(file_path);
    if p.extension().is_some() && p.exists() {
        p
    } else {
        dir.join(format!("{file_path}.png"))
    }
}

/// Which world axis points up, for orbits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum UpAxis {
    /// −Y up: COLMAP / Inria captures (the shared splats).
    #[value(name = "-y")]
    NegY,
    /// +Y up.
    #[value(name = "+y")]
    PosY,
    /// +Z up: Blender / NeRF-synthetic scenes.
    #[value(name = "+z")]
    PosZ,
}

impl UpAxis {
    pub fn vector(self) -> Vec3 {
        match self {
            UpAxis::NegY => -Vec3::Y,
            UpAxis::PosY => Vec3::Y,
            UpAxis::PosZ => Vec3::Z,
        }
    }
}

/// A circle of cameras `elevation_deg` above the horizontal plane, all looking at `center` from
/// `distance` (world units), horizontal field of view `fov_x_deg`.
#[derive(Clone, Copy, Debug)]
pub struct Orbit {
    pub center: Vec3,
    pub distance: f32,
    pub up: UpAxis,
    pub elevation_deg: f32,
    pub fov_x_deg: f32,
}

impl Orbit {
    /// `n` cameras evenly spaced in azimuth, named `view_000`…
    pub fn cameras(&self, n: usize, width: u32, height: u32) -> Vec<Camera> {
        orbit(self, n, width, height)
    }
}

/// Two unit axes spanning the plane orthogonal to `up` (unit), with e1 × e2 = up.
pub fn horizontal_axes(up: Vec3) -> (Vec3, Vec3) {
    let a = if up.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let e1 = (a - up * a.dot(up)).normalize();
    (e1, up.cross(e1))
}

/// A level camera (no roll about `up`) at `eye` looking along `forward` (unit), square pixels,
/// centred principal point, horizontal field of view `fov_x` (radians). OpenCV axes: z forward,
/// x right, y down.
pub fn level_camera(name: String, eye: Vec3, forward: Vec3, up: Vec3, width: u32, height: u32, fov_x: f32) -> Camera {
    let z = forward;
    let x = z.cross(up).normalize();
    let y = z.cross(x);
    let c2w = Mat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), eye.extend(1.0));
    let fx = 0.5 * width as f32 / (0.5 * fov_x).tan();
    Camera {
        name,
        width,
        height,
        fx,
        fy: fx,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
        viewmat: c2w.inverse(),
        lens: Lens::Pinhole,
    }
}

fn orbit(o: &Orbit, n: usize, width: u32, height: u32) -> Vec<Camera> {
    let Orbit { center, distance, up, elevation_deg, fov_x_deg } = *o;
    let upv = up.vector();
    let (e1, e2) = horizontal_axes(upv);
    let el = elevation_deg.to_radians();
    (0..n)
        .map(|k| {
            let az = std::f32::consts::TAU * k as f32 / n.max(1) as f32;
            let dir = (e1 * az.cos() + e2 * az.sin()) * el.cos() + upv * el.sin();
            let eye = center + dir * distance;
            let forward = (center - eye).normalize();
            level_camera(format!("view_{k:03}"), eye, forward, upv, width, height, fov_x_deg.to_radians())
        })
        .collect()
}

/// An orbit framing the scene's robust bounds (2nd–98th percentile of the means).
pub fn orbit_around(scene: &crate::model::scene::Scene, n: usize, up: UpAxis, width: u32, height: u32) -> Vec<Camera> {
    orbit_around_points(&scene.means, n, up, width, height)
}

/// [`orbit_around_points`] for a scene read from `what`, refused with the scene named when its
/// robust bounds are too far out to frame (a camera there would not be finite).
pub fn scene_orbit(
    means: &[[f32; 3]],
    n: usize,
    up: UpAxis,
    width: u32,
    height: u32,
    what: &str,
) -> Result<Vec<Camera>> {
    let cams = orbit_around_points(means, n, up, width, height);
    if cams.iter().any(|c| c.validate().is_err()) {
        let (lo, hi) = crate::model::scene::robust_bounds(means, 0.02);
        bail!(
            "{what}: the scene's extent ({lo:?} .. {hi:?}, 2nd–98th percentile of its Gaussians' means) is too large to frame a camera around: are some positions wrong?"
        );
    }
    Ok(cams)
}

/// [`orbit_around`] for splat means.
pub fn orbit_around_points(means: &[[f32; 3]], n: usize, up: UpAxis, width: u32, height: u32) -> Vec<Camera> {
    let (lo, hi) = crate::model::scene::robust_bounds(means, 0.02);
    let center = 0.5 * (lo + hi);
    let radius = (0.5 * (hi - lo).length()).max(1e-3);
    let fov_x = 50.0f32;
    // Fit the bounding sphere into the narrower field of view.
    let fov_min = if height <= width {
        2.0 * ((0.5 * fov_x.to_radians()).tan() * height as f32 / width as f32).atan()
    } else {
        fov_x.to_radians()
    };
    let distance = radius / (0.5 * fov_min).sin() * 1.05;
    Orbit { center, distance, up, elevation_deg: 25.0, fov_x_deg: fov_x }.cameras(n, width, height)
}
