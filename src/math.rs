//! The maths every stage shares, one copy of each: the real SH basis (Inria's constants and
//! signs, the values `glsl/sh.glsl` uses; a test checks they agree), quaternion → rotation
//! matrix and its vector-Jacobian product, sigmoid / logit, median / percentile, and a k-d tree
//! that tolerates crowded coordinates.
//!
//! Quaternions are (w, x, y, z), as the Inria PLY stores them (`rot_0` = w).
use glam::{DMat3, DVec3, DVec4, Mat3, Vec3};
use kiddo::immutable::float::kdtree::ImmutableKdTree;

/// Real SH constants, degrees 0–3 (f64; [`sh_basis`] rounds them to f32 as the GPU does).
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
pub const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// [`SH_C0`] as f32: colour = SH_C0_F32 · sh0 + 0.5.
pub const SH_C0_F32: f32 = SH_C0 as f32;

/// The SH basis values for a unit direction up to degree `deg` (16 entries, band-major, zero
/// past the degree). One body for f32 ([`sh_basis`]) and f64 ([`sh_basis_grad`]).
macro_rules! sh_basis_values {
    ($t:ty, $x:expr, $y:expr, $z:expr, $deg:expr) => {{
        let (x, y, z, deg): ($t, $t, $t, u32) = ($x, $y, $z, $deg);
        let mut b = [0.0 as $t; 16];
        b[0] = SH_C0 as $t;
        if deg >= 1 {
            let c1 = SH_C1 as $t;
            b[1] = -c1 * y;
            b[2] = c1 * z;
            b[3] = -c1 * x;
        }
        if deg >= 2 {
            let c2 = SH_C2.map(|c| c as $t);
            let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
            b[4] = c2[0] * xy;
            b[5] = c2[1] * yz;
            b[6] = c2[2] * (2.0 * zz - xx - yy);
            b[7] = c2[3] * xz;
            b[8] = c2[4] * (xx - yy);
        }
        if deg >= 3 {
            let c3 = SH_C3.map(|c| c as $t);
            let (xx, yy, zz, xy) = (x * x, y * y, z * z, x * y);
            b[9] = c3[0] * y * (3.0 * xx - yy);
            b[10] = c3[1] * xy * z;
            b[11] = c3[2] * y * (4.0 * zz - xx - yy);
            b[12] = c3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = c3[4] * x * (4.0 * zz - xx - yy);
            b[14] = c3[5] * z * (xx - yy);
            b[15] = c3[6] * x * (xx - 3.0 * yy);
        }
        b
    }};
}

/// The rotation matrix of unit (w, x, y, z) components, column-major: one body for f32 and f64.
macro_rules! rotation_body {
    ($m:ident, $v:ident, $w:expr, $x:expr, $y:expr, $z:expr) => {{
        let (w, x, y, z) = ($w, $x, $y, $z);
        $m::from_cols(
            $v::new(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
            $v::new(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
            $v::new(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
        )
    }};
}

/// SH basis values (f32) for unit direction `d` up to degree `deg`.
pub fn sh_basis(d: Vec3, deg: u32) -> [f32; 16] {
    sh_basis_values!(f32, d.x, d.y, d.z, deg)
}

/// SH basis values (f64) and their derivatives with respect to the direction (treated as
/// unnormalised).
pub fn sh_basis_grad(d: DVec3, deg: u32) -> ([f64; 16], [DVec3; 16]) {
    let b = sh_basis_values!(f64, d.x, d.y, d.z, deg);
    let mut g = [DVec3::ZERO; 16];
    if deg < 1 {
        return (b, g);
    }
    let (x, y, z) = (d.x, d.y, d.z);
    g[1] = DVec3::new(0.0, -SH_C1, 0.0);
    g[2] = DVec3::new(0.0, 0.0, SH_C1);
    g[3] = DVec3::new(-SH_C1, 0.0, 0.0);
    if deg < 2 {
        return (b, g);
    }
    let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
    g[4] = SH_C2[0] * DVec3::new(y, x, 0.0);
    g[5] = SH_C2[1] * DVec3::new(0.0, z, y);
    g[6] = SH_C2[2] * DVec3::new(-2.0 * x, -2.0 * y, 4.0 * z);
    g[7] = SH_C2[3] * DVec3::new(z, 0.0, x);
    g[8] = SH_C2[4] * DVec3::new(2.0 * x, -2.0 * y, 0.0);
    if deg < 3 {
        return (b, g);
    }
    g[9] = SH_C3[0] * DVec3::new(6.0 * xy, 3.0 * xx - 3.0 * yy, 0.0);
    g[10] = SH_C3[1] * DVec3::new(yz, xz, xy);
    g[11] = SH_C3[2] * DVec3::new(-2.0 * xy, 4.0 * zz - xx - 3.0 * yy, 8.0 * yz);
    g[12] = SH_C3[3] * DVec3::new(-6.0 * xz, -6.0 * yz, 6.0 * zz - 3.0 * xx - 3.0 * yy);
    g[13] = SH_C3[4] * DVec3::new(4.0 * zz - 3.0 * xx - yy, -2.0 * xy, 8.0 * xz);
    g[14] = SH_C3[5] * DVec3::new(2.0 * xz, -2.0 * yz, xx - yy);
    g[15] = SH_C3[6] * DVec3::new(3.0 * xx - 3.0 * yy, -6.0 * xy, 0.0);
    (b, g)
}

/// Rotation matrix of a (w, x, y, z) quaternion, normalised first (f32, as the kernels).
pub fn quat_to_mat(q: [f32; 4]) -> Mat3 {
    let q = glam::Vec4::from(q);
    let q = q / q.length();
    let (w, x, y, z) = (q.x, q.y, q.z, q.w);
    rotation_body!(Mat3, Vec3, w, x, y, z)
}

/// Rotation matrix of a unit (w, x, y, z) quaternion.
pub fn rotation(q: DVec4) -> DMat3 {
    let (w, x, y, z) = (q.x, q.y, q.z, q.w);
    rotation_body!(DMat3, DVec3, w, x, y, z)
}

/// Vector-Jacobian product of the rotation matrix of a unit (w, x, y, z) quaternion `q`
/// (`rotation`, without the normalisation): dL/dq from dL/dR.
pub fn rotation_vjp(q: DVec4, v_r: DMat3) -> DVec4 {
    // g[row][col]
    let gm = |row: usize, col: usize| v_r.col(col)[row];
    let (w, x, y, z) = (q.x, q.y, q.z, q.w);
    DVec4::new(
        -z * gm(0, 1) + y * gm(0, 2) + z * gm(1, 0) - x * gm(1, 2) - y * gm(2, 0) + x * gm(2, 1),
        y * gm(0, 1) + z * gm(0, 2) + y * gm(1, 0) - 2.0 * x * gm(1, 1) - w * gm(1, 2) + z * gm(2, 0) + w * gm(2, 1)
            - 2.0 * x * gm(2, 2),
        -2.0 * y * gm(0, 0) + x * gm(0, 1) + w * gm(0, 2) + x * gm(1, 0) + z * gm(1, 2) - w * gm(2, 0) + z * gm(2, 1)
            - 2.0 * y * gm(2, 2),
        -2.0 * z * gm(0, 0) - w * gm(0, 1) + x * gm(0, 2) + w * gm(1, 0) - 2.0 * z * gm(1, 1)
            + y * gm(1, 2)
            + x * gm(2, 0)
            + y * gm(2, 1),
    ) * 2.0
}

/// Logistic sigmoid (opacity from its logit).
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Inverse of [`sigmoid`] for p in (0, 1).
pub fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// The median of `v` (nearest rank; NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    percentile(v, 0.5)
}

/// The `q`-quantile of `v` (nearest rank, q in [0, 1]; NaN when empty).
pub fn percentile(v: &[f64], q: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A neighbour count for the k-d tree's queries (kiddo takes a non-zero one): `n`, at least 1.
pub fn neighbours(n: usize) -> std::num::NonZero<usize> {
    std::num::NonZero::new(n.max(1)).expect("at least one")
}

/// A k-d tree of `points` for nearest-neighbour queries (items = indices). kiddo 5's immutable
/// tree takes any cloud: kiddo 4's panicked where more points than a bucket holds shared a
/// coordinate on one axis (a flat floor, quantised positions) and, as the cafe40 run found, on
/// other clouds too ("mid > len"; sdd-org/kiddo#78, #132, #172, fixed by its version 5 rewrite).
pub fn tree<const K: usize>(points: &[[f64; K]]) -> ImmutableKdTree<f64, u32, K, 32> {
    ImmutableKdTree::new_from_slice(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The float literals of `const float NAME... = ...;` in `glsl/sh.glsl`, in order.
    fn glsl_constants(name: &str) -> Vec<f64> {
        let src = include_str!("../glsl/sh.glsl");
        let start = src.find(&format!("const float {name}")).unwrap_or_else(|| panic!("{name} not in sh.glsl"));
        let decl = &src[start..start + src[start..].find(';').expect("declaration ends")];
        let values = decl.split_once('=').expect("has a value").1;
        let values = values.trim().trim_start_matches(|c: char| c.is_alphanumeric() || c == '[' || c == ']');
        values
            .trim_matches(|c| c == '(' || c == ')' || char::is_whitespace(c))
            .split(',')
            .map(|v| v.trim().parse::<f64>().unwrap_or_else(|e| panic!("{name}: {v:?}: {e}")))
            .collect()
    }

    #[test]
    fn sh_constants_equal_the_shaders() {
        assert_eq!(glsl_constants("SH_C0"), [SH_C0]);
        assert_eq!(glsl_constants("SH_C1"), [SH_C1]);
        assert_eq!(glsl_constants("SH_C2"), SH_C2);
        assert_eq!(glsl_constants("SH_C3"), SH_C3);
    }

    #[test]
    fn f32_and_f64_bodies_agree() {
        let d = DVec3::new(0.3, -0.5, 0.8).normalize();
        let (b64, _) = sh_basis_grad(d, 3);
        let b32 = sh_basis(d.as_vec3(), 3);
        for k in 0..16 {
            assert!((b64[k] - b32[k] as f64).abs() < 1e-6, "basis {k}");
        }
        let q = DVec4::new(0.9, -0.2, 0.3, 0.1);
        let (r64, r32) = (rotation(q / q.length()), quat_to_mat([0.9, -0.2, 0.3, 0.1]));
        assert!((r64 - r32.as_dmat3()).abs().to_cols_array().iter().all(|e| *e < 1e-6));
        assert!((r64 * r64.transpose() - DMat3::IDENTITY).abs().to_cols_array().iter().all(|e| *e < 1e-12));
    }

    #[test]
    fn median_and_percentile_by_nearest_rank() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(percentile(&[1.0, 2.0, 3.0, 4.0, 5.0], 0.9), 5.0);
        assert!(median(&[]).is_nan());
        assert!((sigmoid(logit(0.3)) - 0.3).abs() < 1e-6);
    }
}
