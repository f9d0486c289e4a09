//! Similarity transforms (rotation, uniform scale, translation) and Umeyama's closed-form fit.

use nalgebra::{Matrix3, Vector3};

/// x ↦ s·R·x + t.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sim3 {
    pub rotation: Matrix3<f64>,
    pub scale: f64,
    pub translation: Vector3<f64>,
}

impl Sim3 {
    pub fn identity() -> Sim3 {
        Sim3 { rotation: Matrix3::identity(), scale: 1.0, translation: Vector3::zeros() }
    }

    pub fn apply(&self, p: &[f64; 3]) -> [f64; 3] {
        let v = self.rotation * Vector3::from(*p) * self.scale + self.translation;
        [v.x, v.y, v.z]
    }

    /// self ∘ other.
    pub fn compose(&self, other: &Sim3) -> Sim3 {
        Sim3 {
            rotation: self.rotation * other.rotation,
            scale: self.scale * other.scale,
            translation: self.rotation * other.translation * self.scale + self.translation,
        }
    }

    pub fn inverse(&self) -> Sim3 {
        let rt = self.rotation.transpose();
        Sim3 { rotation: rt, scale: 1.0 / self.scale, translation: -(rt * self.translation) / self.scale }
    }

    /// The angle of R·other.Rᵀ, degrees.
    pub fn rotation_error_deg(&self, other: &Sim3) -> f64 {
        let d = self.rotation * other.rotation.transpose();
        ((d.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
    }
}

/// The least-squares similarity (or rigid motion, `with_scale = false`) taking `src[i]` to
/// `dst[i]` (Umeyama 1991). None for fewer than 3 pairs or a degenerate source.
pub fn umeyama(src: &[[f64; 3]], dst: &[[f64; 3]], with_scale: bool) -> Option<Sim3> {
    let n = src.len();
    if n < 3 || dst.len() != n {
        return None;
    }
    let mean = |p: &[[f64; 3]]| p.iter().fold(Vector3::zeros(), |a, x| a + Vector3::from(*x)) / n as f64;
    let (ms, md) = (mean(src), mean(dst));
    let mut cov = Matrix3::zeros();
    let mut var_s = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let (s, d) = (Vector3::from(*s) - ms, Vector3::from(*d) - md);
        cov += d * s.transpose();
        var_s += s.norm_squared();
    }
    cov /= n as f64;
    var_s /= n as f64;
    if var_s <= 1e-300 {
        return None;
    }
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let rotation = u * s * v_t;
    let scale = if with_scale {
        let d = svd.singular_values;
        (d[0] * s[(0, 0)] + d[1] * s[(1, 1)] + d[2] * s[(2, 2)]) / var_s
    } else {
        1.0
    };
    if !scale.is_finite() || scale <= 0.0 {
        return None;
    }
    Some(Sim3 { rotation, scale, translation: md - rotation * ms * scale })
}

/// [`umeyama`] with the scale held inside `range` (`None`: rigid). The rotation of a
/// similarity fit does not depend on its scale, so a clamped scale only moves the translation
/// (to the least-squares one for that scale).
pub fn umeyama_bounded(src: &[[f64; 3]], dst: &[[f64; 3]], range: Option<(f64, f64)>) -> Option<Sim3> {
    let x = umeyama(src, dst, range.is_some())?;
    let Some((lo, hi)) = range else { return Some(x) };
    let scale = x.scale.clamp(lo, hi);
    if scale == x.scale {
        return Some(x);
    }
    let n = src.len() as f64;
    let mean = |p: &[[f64; 3]]| p.iter().fold(Vector3::zeros(), |a, x| a + Vector3::from(*x)) / n;
    Some(Sim3 { scale, translation: mean(dst) - x.rotation * mean(src) * scale, ..x })
}
