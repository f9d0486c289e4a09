//! Quantisation rules shared by the lossy formats: opacity logits of exactly 0 or 1, the
//! "smallest three" quaternion convention, 8-bit unit values.

/// An opacity logit's bound when the stored opacity is exactly 0 or 1: ln(1019).
pub const OPACITY_LOGIT_LIMIT: f32 = 6.926_577;

/// An opacity in [0, 1] as a logit, 0 and 1 clamped to ±[`OPACITY_LOGIT_LIMIT`].
pub fn opacity_logit(a: f32) -> f32 {
    let limit = 1.0 / (1.0 + OPACITY_LOGIT_LIMIT.exp());
    let a = a.clamp(limit, 1.0 - limit);
    (a / (1.0 - a)).ln()
}

/// A quaternion normalised, with the index of its largest component made positive: what
/// every "smallest three" encoding (compressed PLY, .spz, SOG) stores.
pub fn largest_component(q: [f32; 4]) -> (usize, [f32; 4]) {
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    let q = q.map(|v| v / norm);
    let largest = (0..4).max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs())).unwrap_or(0);
    (largest, if q[largest] < 0.0 { q.map(|v| -v) } else { q })
}

/// A value in [−1, 1] as a normalized signed short (glTF: c / 32 767, at least −1).
pub fn snorm16(v: f32) -> i16 {
    (v.clamp(-1.0, 1.0) * 32767.0).round() as i16
}

pub fn unorm8(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}
