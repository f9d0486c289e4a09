//! Camera refinement: the plain stage of a capture learns a small rigid correction of each
//! training camera with the scene (gsplat's `pose_opt`, nerfstudio's camera optimiser), so the
//! few-pixel errors of COLMAP's poses are not blurred into the scene. The corrected camera is
//! `viewmat = E · viewmat₀`, E = [exp(ω) | τ]: a rotation ω (radians, axis × angle) and a
//! translation τ (world units) in the camera's own frame (OpenCV axes). Held-out cameras keep
//! their poses. The later stages train and check on the corrected training cameras
//! (`RUN/cameras.json`, [`apply_cameras`]) and do not refine them again.
//!
//! Gauge: scene and cameras could drift together, and the held-out cameras would then see a
//! moved scene. After every step the corrections' mean motion of the world (each correction read
//! as the world motion V₀⁻¹ E V₀ it equals, to first order) is removed, as the colour transforms
//! keep their mean at the identity.
use anyhow::{bail, Context, Result};
use glam::{DMat3, DVec3};

use crate::dataset::Dataset;
use crate::model::camera::Camera;

/// The file the plain stage writes the corrected training cameras to, beside its scene.
pub const CAMERAS_FILE: &str = "cameras.json";

/// One camera's correction: ω (3, radians) then τ (3, world units), camera frame.
pub type CameraDelta = [f32; 6];

/// The training cameras' corrections with their Adam moments and step counts, and the cameras
/// they correct (set by the run from its dataset, not stored in checkpoints).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraState {
    pub deltas: Vec<CameraDelta>,
    pub exp_avg: Vec<CameraDelta>,
    pub exp_avg_sq: Vec<CameraDelta>,
    pub steps: Vec<u32>,
    #[serde(skip)]
    pub original: Vec<Camera>,
}

fn rotation_of(w: DVec3) -> DMat3 {
    DMat3::from_quat(glam::DQuat::from_scaled_axis(w))
}

/// ω and τ of a correction.
fn split(d: &CameraDelta) -> (DVec3, DVec3) {
    (DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64), DVec3::new(d[3] as f64, d[4] as f64, d[5] as f64))
}

/// A camera's world → camera rotation W and translation t (viewmat = [W | t]), in f64.
fn rotation_translation(c: &Camera) -> (DMat3, DVec3) {
    let v = c.viewmat.as_dmat4();
    (DMat3::from_mat4(v), v.w_axis.truncate())
}

/// `cam` corrected by `d` (see the module docs).
pub fn corrected(cam: &Camera, d: &CameraDelta) -> Camera {
    let (w, tau) = split(d);
    let e = glam::DMat4::from_mat3_translation(rotation_of(w), tau);
    Camera { viewmat: (e * cam.viewmat.as_dmat4()).as_mat4(), ..cam.clone() }
}

fn hat(v: DVec3) -> DMat3 {
    DMat3::from_cols(DVec3::new(0.0, v.z, -v.y), DVec3::new(-v.z, 0.0, v.x), DVec3::new(v.y, -v.x, 0.0))
}

/// The left Jacobian of SO(3) at ω: exp(ω + dω) = exp(J_l(ω) dω) exp(ω) to first order.
fn left_jacobian(w: DVec3) -> DMat3 {
    let t = w.length();
    let k = hat(w);
    let (a, b) = if t < 1e-4 {
        (0.5 - t * t / 24.0, 1.0 / 6.0 - t * t / 120.0)
    } else {
        ((1.0 - t.cos()) / (t * t), (t - t.sin()) / (t * t * t))
    };
    DMat3::IDENTITY + k * a + k * k * b
}

/// dL/d(ω, τ) of camera `cam0` corrected by `d`, from the frame's camera-gradient terms
/// (`Grads::v_camera`, `CAMERA_GRAD_TERMS`: dL/dW column-major and dL/dt of the rendered
/// viewmat = [W | t] with its centre held, then dL/dcampos). The centre c = −Wᵀt is chained here.
pub fn delta_grad(cam0: &Camera, d: &CameraDelta, terms: &[f32]) -> [f64; 6] {
    let g: Vec<f64> = terms.iter().map(|&x| x as f64).collect();
    let (w0, t0) = rotation_translation(cam0);
    let (omega, tau) = split(d);
    let r = rotation_of(omega);
    let (w, t) = (r * w0, r * t0 + tau);
    let g_c = DVec3::new(g[12], g[13], g[14]);
    // c_j = −Σ_i W_ij t_i.
    let outer = |u: DVec3, v: DVec3| DMat3::from_cols(u * v.x, u * v.y, u * v.z);
    let g_w = DMat3::from_cols_array(&g[0..9].try_into().expect("9 terms")) - outer(t, g_c);
    let g_t = DVec3::new(g[9], g[10], g[11]) - w * g_c;
    // W = R W0, t = R t0 + τ; then R ← exp(δ) R: dL/dδ is the axial part of G_R Rᵀ.
    let g_r = g_w * w0.transpose() + outer(g_t, t0);
    let a = g_r * r.transpose();
    let at = |i: usize, j: usize| a.col(j)[i];
    let g_delta = DVec3::new(at(2, 1) - at(1, 2), at(0, 2) - at(2, 0), at(1, 0) - at(0, 1));
    let g_omega = left_jacobian(omega).transpose() * g_delta;
    [g_omega.x, g_omega.y, g_omega.z, g_t.x, g_t.y, g_t.z]
}

impl CameraState {
    /// No correction for each of `cameras`, zero moments.
    pub fn identity(cameras: Vec<Camera>) -> CameraState {
        let n = cameras.len();
        CameraState {
            deltas: vec![[0.0; 6]; n],
            exp_avg: vec![[0.0; 6]; n],
            exp_avg_sq: vec![[0.0; 6]; n],
            steps: vec![0; n],
            original: cameras,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.deltas.is_empty()
    }

    /// Training camera `i` as corrected so far.
    pub fn camera(&self, i: usize) -> Camera {
        corrected(&self.original[i], &self.deltas[i])
    }

    /// One Adam step of camera `i`'s correction on the frame's camera-gradient terms at rates
    /// `lr` (rotation in radians, translation in world units), then the gauge (module docs).
    pub fn step(&mut self, i: usize, terms: &[f32], lr: [f64; 2]) {
        if lr[0] <= 0.0 && lr[1] <= 0.0 {
            return;
        }
        let g = delta_grad(&self.original[i], &self.deltas[i], terms);
        self.steps[i] += 1;
        let f = |a: &CameraDelta| a.map(f64::from);
        let (mut p, mut m, mut v) = (f(&self.deltas[i]), f(&self.exp_avg[i]), f(&self.exp_avg_sq[i]));
        // Adam whose second moment is each group's (rotation, translation) mean square, not
        // each coordinate's: the step follows the gradient's direction, so what a photo hardly
        // constrains (roll, motion along the optical axis) moves little instead of a full step.
        let (beta1, beta2) = (crate::train::optim::BETA1, crate::train::optim::BETA2);
        let step = self.steps[i] as i32;
        let (bc1, bc2) = (1.0 - beta1.powi(step), 1.0 - beta2.powi(step));
        for (range, rate) in [(0..3, lr[0]), (3..6, lr[1])] {
            let g2 = range.clone().map(|k| g[k] * g[k]).sum::<f64>() / 3.0;
            for k in range {
                m[k] += (g[k] - m[k]) * (1.0 - beta1);
                v[k] = beta2 * v[k] + (1.0 - beta2) * g2;
                p[k] -= rate / bc1 * m[k] / (v[k].sqrt() / bc2.sqrt() + crate::train::optim::EPS as f64);
            }
        }
        self.deltas[i] = p.map(|x| x as f32);
        self.exp_avg[i] = m.map(|x| x as f32);
        self.exp_avg_sq[i] = v.map(|x| x as f32);
        self.remove_mean_motion();
    }

    /// Removes the corrections' mean world motion: correction (ω, τ) of a camera with viewmat₀
    /// = [R | t] moves the world by ω_w = Rᵀω, v_w = Rᵀ(ω × t + τ) (first order); the mean
    /// (ω̄_w, v̄_w) is taken back from each camera as ω −= R ω̄_w, τ −= R v̄_w − (R ω̄_w) × t.
    fn remove_mean_motion(&mut self) {
        let n = self.deltas.len() as f64;
        let (mut mw, mut mv) = (DVec3::ZERO, DVec3::ZERO);
        for (c, d) in self.original.iter().zip(&self.deltas) {
            let ((r, t), (w, tau)) = (rotation_translation(c), split(d));
            mw += r.transpose() * w / n;
            mv += r.transpose() * (w.cross(t) + tau) / n;
        }
        for (c, d) in self.original.iter().zip(&mut self.deltas) {
            let ((r, t), (w, tau)) = (rotation_translation(c), split(d));
            let dw = r * mw;
            let (w, tau) = (w - dw, tau - (r * mv - dw.cross(t)));
            *d = [w.x, w.y, w.z, tau.x, tau.y, tau.z].map(|x| x as f32);
        }
    }
}

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    name: String,
    /// ω, radians (axis × angle, camera frame).
    rotation: [f32; 3],
    /// τ, world units (camera frame).
    translation: [f32; 3],
}

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    views: Vec<Entry>,
}

/// Writes the training cameras' corrections: `{"views": [{"name", "rotation": [ωx, ωy, ωz],
/// "translation": [τx, τy, τz]}]}` in the dataset's training order (module docs for the model).
pub fn write_cameras(path: &std::path::Path, ds: &Dataset, st: &CameraState) -> Result<()> {
    let views: Vec<Entry> = ds
        .train
        .iter()
        .zip(&st.deltas)
        .map(|(v, d)| Entry {
            name: v.camera.name.clone(),
            rotation: [d[0], d[1], d[2]],
            translation: [d[3], d[4], d[5]],
        })
        .collect();
    crate::util::write_json(path, &serde_json::to_value(File { views })?, true)
}

/// Corrects `ds`'s training cameras by [`write_cameras`]'s file, by name (every training view
/// needs one; each correction finite, under 0.5 rad and under the cameras' extent).
pub fn apply_cameras(path: &std::path::Path, ds: &mut Dataset) -> Result<()> {
    let what = path.display();
    let text = std::fs::read_to_string(path).with_context(|| format!("{what}: cannot read"))?;
    let f: File = serde_json::from_str(&text).with_context(|| format!("{what}: not a camera-correction file"))?;
    let extent = ds.camera_extent();
    let by_name: std::collections::BTreeMap<&str, &Entry> = f.views.iter().map(|e| (e.name.as_str(), e)).collect();
    let mut deltas = Vec::with_capacity(ds.train.len());
    for v in &ds.train {
        let e = by_name
            .get(v.camera.name.as_str())
            .ok_or_else(|| anyhow::anyhow!("{what}: no correction for training view {}", v.camera.name))?;
        let d: CameraDelta =
            [e.rotation[0], e.rotation[1], e.rotation[2], e.translation[0], e.translation[1], e.translation[2]];
        let (w, t) = (glam::Vec3::from_slice(&d[0..3]), glam::Vec3::from_slice(&d[3..6]));
        if !d.iter().all(|x| x.is_finite()) || w.length() > 0.5 || t.length() > extent {
            bail!(
                "{what}: the correction of {} (rotation {:.4} rad, translation {:.4}) is not finite or not small (< 0.5 rad, < the cameras' extent {extent:.3})",
                v.camera.name,
                w.length(),
                t.length()
            );
        }
        deltas.push(d);
    }
    for (v, d) in ds.train.iter_mut().zip(&deltas) {
        v.camera = corrected(&v.camera, d);
    }
    Ok(())
}
