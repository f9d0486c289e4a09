//! Property tests (proptest) of the maths that parsed values feed, over the whole range a reader
//! accepts — what fuzzing the parsers cannot reach: every quaternion `Scene::validate` accepts
//! normalises to a rotation; every accepted Gaussian has a finite, symmetric, positive
//! semi-definite covariance; `Similarity::from_mat4` (scene graphs, `.instgs` transforms) never
//! panics, and what it accepts is the matrix it was given, with an inverse.
use glam::{Mat3, Mat4, Quat, Vec3};
use instgs_vk::math::quat_to_mat;
use instgs_vk::model::instanced::Similarity;
use instgs_vk::model::scene::Scene;
use proptest::prelude::*;

/// Any finite f32 a file may hold, tiny, huge and signed alike (log-uniform magnitudes).
fn any_finite() -> impl Strategy<Value = f32> {
    prop_oneof![
        (-1.0e3f32..1.0e3),
        (-45.0f32..38.0, any::<bool>()).prop_map(|(e, neg)| if neg { -(10f32.powf(e)) } else { 10f32.powf(e) }),
        Just(0.0f32),
        Just(f32::MIN_POSITIVE),
        Just(f32::MAX),
    ]
}

fn one_gaussian(quat: [f32; 4], scales: [f32; 3]) -> Scene {
    Scene {
        sh_degree: 0,
        means: vec![[0.0; 3]],
        scales: vec![scales],
        quats: vec![quat],
        opacities: vec![0.0],
        sh: vec![0.0; 3],
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(20_000))]

    #[test]
    fn accepted_quaternions_normalise_to_rotations(q in [any_finite(), any_finite(), any_finite(), any_finite()]) {
        if one_gaussian(q, [0.0; 3]).validate("q").is_ok() {
            let r = quat_to_mat(q);
            prop_assert!(r.to_cols_array().iter().all(|v| v.is_finite()), "{q:?} -> {r}");
            let err = (r.transpose() * r - Mat3::IDENTITY).to_cols_array().iter().fold(0f32, |e, v| e.max(v.abs()));
            prop_assert!(err < 1e-5, "{q:?}: |RᵀR − I| = {err}");
            prop_assert!((r.determinant() - 1.0).abs() < 1e-5, "{q:?}: det {}", r.determinant());
        }
    }

    #[test]
    fn accepted_gaussians_have_a_covariance(
        q in [any_finite(), any_finite(), any_finite(), any_finite()],
        s in [any_finite(), any_finite(), any_finite()],
    ) {
        if one_gaussian(q, s).validate("g").is_ok() {
            // Σ = R S Sᵀ Rᵀ, S = diag(exp(log-scales)), as the preprocess kernel computes it.
            let m = quat_to_mat(q) * Mat3::from_diagonal(Vec3::from(s).exp());
            let cov = m * m.transpose();
            let c = cov.to_cols_array();
            prop_assert!(c.iter().all(|v| v.is_finite()), "{q:?} {s:?}: Σ = {cov}");
            prop_assert!(cov.abs_diff_eq(cov.transpose(), 1e-6 * c.iter().fold(0f32, |a, v| a.max(v.abs()))));
            prop_assert!(c[0] >= 0.0 && c[4] >= 0.0 && c[8] >= 0.0, "{cov}");
        }
    }

    #[test]
    fn similarity_from_any_finite_matrix_is_checked(rows in proptest::array::uniform4([any_finite(), any_finite(), any_finite(), any_finite()])) {
        let m = Mat4::from_cols_array_2d(&rows).transpose();
        if let Ok(x) = Similarity::from_mat4(m, "m") {
            let back = x.render_mat4();
            let size = m.to_cols_array().iter().fold(0f32, |a, v| a.max(v.abs()));
            prop_assert!(back.abs_diff_eq(m, 1e-2 * size), "{m} -> {back}");
            prop_assert!(x.scale.is_finite() && x.scale > 0.0);
        }
    }

    #[test]
    fn similarities_from_parts_read_back_and_invert(
        axis in [-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0],
        angle in -3.2f32..3.2,
        log_scale in -6.0f32..6.0,
        t in [-1.0e3f32..1.0e3, -1.0e3f32..1.0e3, -1.0e3f32..1.0e3],
    ) {
        let axis = Vec3::from(axis);
        prop_assume!(axis.length() > 1e-3);
        let x = Similarity::from_parts(Quat::from_axis_angle(axis.normalize(), angle), log_scale.exp(), Vec3::from(t));
        let read = Similarity::from_mat4(x.to_mat4(), "x");
        prop_assert!(read.is_ok(), "{:?}", read.err());
        let id = x.render_mat4() * x.inverse().render_mat4();
        let tol = 1e-4 * (1.0 + Vec3::from(t).abs().max_element());
        prop_assert!(id.abs_diff_eq(Mat4::IDENTITY, tol), "{id}");
    }
}
