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

    /// This similarity applied about `centre` instead of the origin: x ↦ c + s·R·(x − c) + t.
    pub fn about(&self, centre: &Vector3<f64>) -> Sim3 {
        let to = Sim3 { translation: -centre, ..Sim3::identity() };
        let back = Sim3 { translation: *centre, ..Sim3::identity() };
        back.compose(self).compose(&to)
    }

    /// The angle of R·other.Rᵀ, degrees.
    pub fn rotation_error_deg(&self, other: &Sim3) -> f64 {
        let d = self.rotation * other.rotation.transpose();
        ((d.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// The mean of several estimates of one similarity, for points near `at`: the chordal L2
    /// mean rotation (the sum of the rotation matrices projected onto SO(3)), the geometric mean
    /// scale, and the translation that takes `at` to the mean of the estimates' images of it
    /// (so that a rotation's lever arm about the origin does not move the result). None
    /// without estimates or when the rotations cancel out.
    pub fn mean(estimates: &[Sim3], at: &Vector3<f64>) -> Option<Sim3> {
        if estimates.is_empty() {
            return None;
        }
        let n = estimates.len() as f64;
        let sum: Matrix3<f64> = estimates.iter().map(|e| e.rotation).sum();
        let svd = sum.svd(true, true);
        if svd.singular_values.min() <= 1e-9 * svd.singular_values.max() {
            return None;
        }
        let (u, v_t) = (svd.u?, svd.v_t?);
        let mut d = Matrix3::identity();
        if (u * v_t).determinant() < 0.0 {
            d[(2, 2)] = -1.0;
        }
        let rotation = u * d * v_t;
        let scale = (estimates.iter().map(|e| e.scale.ln()).sum::<f64>() / n).exp();
        let p = [at.x, at.y, at.z];
        let image: Vector3<f64> = estimates.iter().map(|e| Vector3::from(e.apply(&p))).sum::<Vector3<f64>>() / n;
        Some(Sim3 { rotation, scale, translation: image - rotation * at * scale })
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Unit};

    fn about(axis: [f64; 3], deg: f64, scale: f64, t: [f64; 3]) -> Sim3 {
        let r = Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), deg.to_radians());
        Sim3 { rotation: *r.matrix(), scale, translation: Vector3::from(t) }
    }

    #[test]
    fn a_similarity_about_a_centre_keeps_the_centre_where_it_was() {
        let r = *nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), 0.7).matrix();
        let c = Vector3::new(1.0, -2.0, 0.5);
        let x = Sim3 { rotation: r, scale: 1.5, translation: Vector3::zeros() }.about(&c);
        let moved = x.apply(&[c.x, c.y, c.z]);
        assert!((Vector3::from(moved) - c).norm() < 1e-12, "{moved:?}");
        let p = [0.3, 0.2, -0.1];
        let expected = c + 1.5 * r * (Vector3::from(p) - c);
        assert!((Vector3::from(x.apply(&p)) - expected).norm() < 1e-12);
    }

    #[test]
    fn the_mean_of_symmetric_perturbations_is_the_centre() {
        let x = about([0.3, 1.0, -0.2], 70.0, 1.3, [2.0, -1.0, 0.5]);
        let at = Vector3::new(1.0, 2.0, 3.0);
        // x turned ±4° about each axis (about `at`) and scaled by 1.02^±1: the mean is x.
        let mut est = Vec::new();
        for axis in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
            for sign in [1.0, -1.0] {
                let d = about(axis, 4.0 * sign, 1.02f64.powf(sign), [0.0; 3]);
                let to = Sim3 { translation: -Vector3::from(x.apply(&[at.x, at.y, at.z])), ..Sim3::identity() };
                let back = to.inverse();
                est.push(back.compose(&d).compose(&to).compose(&x));
            }
        }
        let m = Sim3::mean(&est, &at).unwrap();
        assert!(m.rotation_error_deg(&x) < 1e-6, "{}", m.rotation_error_deg(&x));
        assert!((m.scale - x.scale).abs() < 1e-9);
        let (p, q) = (Vector3::from(m.apply(&[at.x, at.y, at.z])), Vector3::from(x.apply(&[at.x, at.y, at.z])));
        assert!((p - q).norm() < 1e-9, "{p} {q}");
        // One estimate: itself.
        let one = Sim3::mean(&est[..1], &at).unwrap();
        assert!(one.rotation_error_deg(&est[0]) < 1e-6 && (one.translation - est[0].translation).norm() < 1e-9);
        assert!(Sim3::mean(&[], &at).is_none());
        // Opposite half turns cancel: no mean.
        assert!(Sim3::mean(
            &[about([1.0, 0.0, 0.0], 90.0, 1.0, [0.0; 3]), about([1.0, 0.0, 0.0], -90.0, 1.0, [0.0; 3])],
            &at
        )
        .is_none());
    }
}
