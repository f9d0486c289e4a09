//! Quantisation rules shared by the lossy formats: opacity logits of exactly 0 or 1, the
//! "smallest three" quaternion convention, 8-bit unit values, 256-entry codebooks.

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

/// 1D k-means (Lloyd) of `values` into at most `k` centres, ascending; `weights` (one per
/// value, positive) count a value that many times (none: each once).
pub fn codebook_1d(values: &[f32], weights: Option<&[f32]>, k: usize) -> Vec<f32> {
    let mut v: Vec<(f32, f64)> = match weights {
        Some(w) => values.iter().zip(w).map(|(&x, &w)| (x, w as f64)).collect(),
        None => values.iter().map(|&x| (x, 1.0)).collect(),
    };
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n = v.len();
    if n == 0 {
        return vec![0.0; k];
    }
    // Half the starts at quantiles of the weight (where the values are), half evenly over the
    // range (so the rare extremes — the largest splats, the brightest colours — keep entries of
    // their own).
    let mut cumulative = Vec::with_capacity(n);
    let mut total = 0.0f64;
    for &(_, w) in &v {
        total += w;
        cumulative.push(total);
    }
    let (lo, hi) = (v[0].0, v[n - 1].0);
    let mut centres: Vec<f32> = (0..k)
        .map(|i| {
            let t = (i / 2) as f64 / (k / 2).max(1) as f64 + 0.5 / k as f64;
            if i % 2 == 0 {
                v[cumulative.partition_point(|&c| c <= t * total).min(n - 1)].0
            } else {
                lo + (hi - lo) * t as f32
            }
        })
        .collect();
    centres.sort_by(f32::total_cmp);
    for _ in 0..10 {
        centres.dedup();
        // Sorted values: each centre's members are a run between the midpoints.
        let mut sums = vec![(0.0f64, 0.0f64); centres.len()];
        let mut c = 0;
        for &(x, w) in &v {
            while c + 1 < centres.len() && x > 0.5 * (centres[c] + centres[c + 1]) {
                c += 1;
            }
            sums[c].0 += w * x as f64;
            sums[c].1 += w;
        }
        for (centre, (s, m)) in centres.iter_mut().zip(&sums) {
            if *m > 0.0 {
                *centre = (*s / *m) as f32;
            }
        }
        centres.sort_by(f32::total_cmp);
    }
    centres.resize(k, *centres.last().unwrap_or(&0.0));
    centres
}

/// The index of the codebook entry nearest to `x` (the codebook ascending).
pub fn nearest(codebook: &[f32], x: f32) -> u8 {
    let i = codebook.partition_point(|&c| c < x);
    let best = match i {
        0 => 0,
        i if i >= codebook.len() => codebook.len() - 1,
        i => {
            if (x - codebook[i - 1]).abs() <= (codebook[i] - x).abs() {
                i - 1
            } else {
                i
            }
        }
    };
    best as u8
}
